"""Standard 3D Gaussian Splatting PLY files: write an avatar's world-space Gaussians, read them back.

The layout is the one the 3DGS reference release writes and every stock viewer reads: one ``vertex``
element, binary little endian, float32 properties

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3*(K-1)-1)  opacity  scale_0..2  rot_0..3

with ``opacity`` a logit, ``scale_*`` natural-log world scales, ``rot_*`` a normalised wxyz world
quaternion, ``f_dc`` the degree-0 SH coefficient per colour channel and ``f_rest`` the higher SH
coefficients in channel-major order (all of red's K-1 coefficients, then green's, then blue's).
Colour is ``SH(dir) + 0.5``, the convention of 3DGS and gsplat. Normals are written as zeros, as 3DGS does.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from rmavatar.render.gaussians import GaussianSet
from rmavatar.utils import UserError
from rmavatar.utils.outputs import output_file

# Opacities are clamped away from 0 and 1 so that their logits stay finite in float32.
_OPACITY_EPS = 1e-6

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def ply_property_names(num_sh: int) -> list[str]:
    """The 3DGS property names, in file order, for ``num_sh`` = K SH coefficients per channel."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (num_sh - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def gaussians_to_ply_table(means, quats, scales, opacities, sh) -> np.ndarray:
    """The PLY's property table [N, P] float32 (columns as :func:`ply_property_names`).

    means [N,3] world, quats [N,4] wxyz (any norm), scales [N,3] linear world,
    opacities [N] in [0,1], sh [N,K,3] (or colours are not accepted: pass SH).
    """
    means = _np(means)
    quats = _np(quats)
    scales = _np(scales)
    opacities = _np(opacities).reshape(-1)
    sh = _np(sh)
    n = means.shape[0]
    if sh.ndim != 3 or sh.shape[2] != 3 or sh.shape[0] != n:
        raise ValueError(f"sh must be [N,K,3] with N={n}, got {tuple(sh.shape)}")
    num_sh = sh.shape[1]
    if math.isqrt(num_sh) ** 2 != num_sh:
        raise ValueError(f"sh must have (degree+1)^2 coefficients, got K={num_sh}")
    for name, arr, shape in (("means", means, (n, 3)), ("quats", quats, (n, 4)),
                             ("scales", scales, (n, 3)), ("opacities", opacities, (n,))):
        if arr.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    quats = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    op = np.clip(opacities, _OPACITY_EPS, 1.0 - _OPACITY_EPS)
    cols = [
        means,
        np.zeros((n, 3), np.float64),
        sh[:, 0, :],
        # channel-major: [N,K-1,3] -> [N,3,K-1] -> flat
        sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1),
        (np.log(op) - np.log1p(-op))[:, None],
        np.log(np.maximum(scales, 1e-30)),
        quats,
    ]
    return np.concatenate(cols, axis=1).astype(np.float32)


def write_ply(path: str | os.PathLike, means, quats, scales, opacities, sh, *, overwrite: bool = False) -> Path:
    """Write Gaussians to a 3DGS PLY at ``path`` atomically (see the module docstring for units); an existing
    file is replaced only when rmavatar wrote it, or with ``overwrite`` (see :mod:`rmavatar.utils.outputs`).

    means [N,3], quats [N,4] wxyz, scales [N,3] linear, opacities [N] in [0,1], sh [N,K,3].
    """
    table = gaussians_to_ply_table(means, quats, scales, opacities, sh)
    names = ply_property_names(_np(sh).shape[1])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {table.shape[0]}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    path = Path(path)
    try:
        with output_file(path, option="--ply", overwrite=overwrite) as tmp:
            with open(tmp, "wb") as f:
                f.write(("\n".join(header) + "\n").encode("ascii"))
                f.write(np.ascontiguousarray(table, dtype="<f4").tobytes())
    except OSError as exc:  # disk full, read-only file system, a folder in the way, ...
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
    return path


def read_ply(path: str | os.PathLike) -> GaussianSet:
    """Read a 3DGS PLY (ours or any 3DGS-layout file: binary either endianness, or ascii)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"PLY file {path} does not exist")
    with open(path, "rb") as f:
        fmt, elements = _read_header(f, path)
        data = _read_vertices(f, path, fmt, elements)
    names = data.dtype.names
    need = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in need if n not in names]
    if missing:
        raise UserError(f"{path} is not a 3D Gaussian Splatting PLY: vertex properties {missing} missing")
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[len("f_rest_"):]))
    num_sh = len(rest) // 3 + 1
    degree = math.isqrt(num_sh) - 1
    if len(rest) % 3 or (degree + 1) ** 2 != num_sh or rest != [f"f_rest_{i}" for i in range(len(rest))]:
        raise UserError(f"{path}: {len(rest)} f_rest_* properties is not a full SH degree "
                        "(need 0, 9, 24 or 45 numbered from f_rest_0)")

    def cols(keys):
        return np.stack([np.asarray(data[k], np.float64) for k in keys], axis=1) if keys else \
            np.zeros((len(data), 0))

    n = len(data)
    sh = np.empty((n, num_sh, 3))
    sh[:, 0, :] = cols(["f_dc_0", "f_dc_1", "f_dc_2"])
    sh[:, 1:, :] = cols(rest).reshape(n, 3, num_sh - 1).transpose(0, 2, 1)
    quats = cols(["rot_0", "rot_1", "rot_2", "rot_3"])
    quats /= np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    logit = np.asarray(data["opacity"], np.float64)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return GaussianSet(
        means=t(cols(["x", "y", "z"])),
        quats=t(quats),
        scales=t(np.exp(cols(["scale_0", "scale_1", "scale_2"]))),
        opacities=t(1.0 / (1.0 + np.exp(-logit))),
        sh=t(sh),
        sh_degree=degree,
    )


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _read_header(f, path: Path):
    first = f.readline()
    if first.strip() != b"ply":
        raise UserError(f"{path} is not a PLY file (it does not start with 'ply')")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
    while True:
        line = f.readline()
        if not line:
            raise UserError(f"{path}: PLY header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise UserError(f"{path}: PLY property before any element")
            if words[1] == "list":
                elements[-1][2].append((words[4], None))
            else:
                if words[1] not in _PLY_TYPES:
                    raise UserError(f"{path}: unknown PLY property type {words[1]!r}")
                elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise UserError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements


def _read_vertices(f, path: Path, fmt: str, elements) -> np.ndarray:
    end = "<" if fmt == "binary_little_endian" else ">"
    for name, count, props in elements:
        if any(t is None for _, t in props):
            if name == "vertex":
                raise UserError(f"{path}: list properties in the vertex element are not supported")
            raise UserError(f"{path}: element {name!r} with list properties precedes the vertices")
        dtype = np.dtype([(p, end + t) for p, t in props])
        if fmt == "ascii":
            rows = [f.readline().split() for _ in range(count)]
            if name != "vertex":
                continue
            arr = np.array(rows, dtype=np.float64).reshape(count, len(props))
            out = np.empty(count, dtype=[(p, "f8") for p, _ in props])
            for i, (p, _) in enumerate(props):
                out[p] = arr[:, i]
            return out
        raw = f.read(dtype.itemsize * count)
        if len(raw) != dtype.itemsize * count:
            raise UserError(f"{path}: file is truncated (element {name!r} needs {dtype.itemsize * count} bytes)")
        if name == "vertex":
            return np.frombuffer(raw, dtype=dtype, count=count)
    raise UserError(f"{path}: PLY has no 'vertex' element")
