"""Standard 3D Gaussian Splatting PLY files: write an avatar's world-space Gaussians, read them back.

The layout is the one the 3DGS reference release writes and every stock viewer reads: one ``vertex``
element, binary little endian, float32 properties

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3*(K-1)-1)  opacity  scale_0..2  rot_0..3

with ``opacity`` a logit, ``scale_*`` natural-log world scales, ``rot_*`` a normalised wxyz world
quaternion, ``f_dc`` the degree-0 SH coefficient per colour channel and ``f_rest`` the higher SH
coefficients in channel-major order (all of red's K-1 coefficients, then green's, then blue's).
Colour is ``SH(dir) + 0.5``, the convention of 3DGS and gsplat. Normals are written as zeros, as 3DGS does.

World axes ("up"). rmavatar works in SMPL's world: y up, the body faces +z. Stock 3DGS files follow the
COLMAP / OpenCV convention instead, y down (and z forward, away from the first camera), and viewers made
for them (PlayCanvas SuperSplat and the viewer of its splat-transform tool turn every file 180 degrees
about z) show a y-up file upside down. So :func:`write_ply` writes ``up="-y"`` by default: the Gaussians
turned 180 degrees about the x axis (y -> -y, z -> -z; the avatar then faces -z, as a person filmed by
an OpenCV camera looking down +z faces it), rotations and SH turned with them; ``up="y"`` keeps SMPL's
axes for tools that draw the file's axes as they are in a y-up world. The file says which in a header
comment, ``comment rmavatar up -y`` or ``comment rmavatar up y``, which other readers ignore.
:func:`read_ply` brings either back to y up; a PLY without that comment (any other 3DGS file) is taken
to be y down.
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path

import numpy as np
import torch

from rmavatar.render.gaussians import GaussianSet
from rmavatar.render.project import sh_rotation_matrices
from rmavatar.utils import UserError
from rmavatar.utils.outputs import output_file

# Opacities are clamped away from 0 and 1 so that their logits stay finite in float32.
_OPACITY_EPS = 1e-6

# The PLY's world convention: "-y" (y down: 3DGS / COLMAP / OpenCV, what stock viewers expect) or "y" (y up).
UP_AXES = ("-y", "y")
DEFAULT_UP = "-y"
UP_COMMENT = "rmavatar up"  # header comment: "comment rmavatar up -y" / "comment rmavatar up y"
_UP_MEANING = {
    "-y": "y down, the avatar facing -z: the 3DGS / COLMAP / OpenCV convention",
    "y": "y up, the avatar facing +z: SMPL's world",
}

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def check_up(up: str, option: str = "up") -> str:
    """``up`` if it is one of :data:`UP_AXES`, else a UserError naming ``option``."""
    if up not in UP_AXES:
        raise UserError(f"{option} must be -y (y down, the 3DGS / COLMAP convention stock viewers expect) or y "
                        f"(y up), got {up!r}")
    return up


def flip_up(means, quats, sh, to: str = "-y") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians turned 180 degrees about the x axis (y -> -y, z -> -z): from y up to y down (``to="-y"``)
    or back (``to="y"``).

    means [N,3], quats [N,4] wxyz, sh [N,K,3] in world axes -> float64 arrays. The turn is exact:
    positions and quaternions only change signs and places (the quaternion is left-multiplied by the
    turn's (0, 1, 0, 0), or by its inverse (0, -1, 0, 0) on the way back, so a round trip gives the very
    same quaternion, not its negative), and every real SH basis function is even or odd under the turn,
    so each SH coefficient is kept or negated (:func:`_flip_sh_signs`)."""
    check_up(to)
    means, quats, sh = _np(means), _np(quats), _np(sh)
    w, x, y, z = quats.T
    if to == "-y":
        turned_q = np.stack([-x, w, -z, y], axis=1)  # (0, 1, 0, 0) * (w, x, y, z)
    else:
        turned_q = np.stack([x, -w, z, -y], axis=1)  # (0, -1, 0, 0) * (w, x, y, z)
    signs = _flip_sh_signs(math.isqrt(sh.shape[1]) - 1)
    return means * np.array([1.0, -1.0, -1.0]), turned_q, sh * signs[None, :, None]


@functools.lru_cache(maxsize=None)
def _flip_sh_signs(degree: int) -> np.ndarray:
    """[(degree+1)^2] +-1: the SH coefficients of a Gaussian turned 180 degrees about x (band matrices of
    :func:`sh_rotation_matrices`, which for this turn are diagonal +-1 up to rounding; rounded here so the
    turn loses nothing)."""
    signs = [1.0]
    if degree > 0:
        turn = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))[None]
        for band in sh_rotation_matrices(turn, degree):
            m = band[0].numpy()
            exact = np.round(m)
            assert np.abs(m - exact).max() < 1e-9 and np.count_nonzero(exact) == len(m), m
            signs += list(np.diag(exact))
    return np.array(signs)


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


def write_ply(path: str | os.PathLike, means, quats, scales, opacities, sh, *, up: str = DEFAULT_UP,
              overwrite: bool = False) -> Path:
    """Write Gaussians to a 3DGS PLY at ``path`` atomically (see the module docstring for units); an existing
    file is replaced only when rmavatar wrote it, or with ``overwrite`` (see :mod:`rmavatar.utils.outputs`).

    means [N,3], quats [N,4] wxyz, scales [N,3] linear, opacities [N] in [0,1], sh [N,K,3], all in
    rmavatar's y-up world. ``up``: the file's convention, "-y" (default: turned 180 degrees about x into
    the y-down convention of stock 3DGS viewers) or "y" (as given); recorded in a header comment.
    """
    check_up(up)
    if up == "-y":
        means, quats, sh = flip_up(means, quats, sh, to="-y")
    table = gaussians_to_ply_table(means, quats, scales, opacities, sh)
    names = ply_property_names(_np(sh).shape[1])
    header = ["ply", "format binary_little_endian 1.0",
              f"comment {UP_COMMENT} {up}", f"comment ({_UP_MEANING[up]}; written by rmavatar)",
              f"element vertex {table.shape[0]}"]
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


def read_ply(path: str | os.PathLike, up: str | None = "y") -> GaussianSet:
    """Read a 3DGS PLY (ours or any 3DGS-layout file: binary either endianness, or ascii).

    ``up``: the axes to return the Gaussians in: "y" (default, rmavatar's y-up world), "-y" (the y-down
    3DGS / COLMAP convention) or None (as stored). The file's own convention is its ``rmavatar up``
    header comment (see the module docstring); a file without one is y down, as 3DGS files are.
    """
    if up is not None:
        check_up(up)
    path = Path(path)
    if not path.is_file():
        raise UserError(f"PLY file {path} does not exist")
    with open(path, "rb") as f:
        fmt, elements, comments = _read_header(f, path)
        data = _read_vertices(f, path, fmt, elements)
    stored = _stored_up(comments, path)
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
    means = cols(["x", "y", "z"])
    if up is not None and up != stored:
        means, quats, sh = flip_up(means, quats, sh, to=up)
    logit = np.asarray(data["opacity"], np.float64)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return GaussianSet(
        means=t(means),
        quats=t(quats),
        scales=t(np.exp(cols(["scale_0", "scale_1", "scale_2"]))),
        opacities=t(1.0 / (1.0 + np.exp(-logit))),
        sh=t(sh),
        sh_degree=degree,
    )


def ply_up(path: str | os.PathLike) -> str:
    """The world convention a 3DGS PLY is stored in: "y" or "-y" (its ``rmavatar up`` header comment;
    "-y", the 3DGS convention, when it has none)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"PLY file {path} does not exist")
    with open(path, "rb") as f:
        _, _, comments = _read_header(f, path)
    return _stored_up(comments, path)


def _stored_up(comments: list[str], path: Path) -> str:
    found = [c.split()[2:] for c in comments if c.split()[:2] == UP_COMMENT.split()]
    if not found:
        return DEFAULT_UP
    if len(found[0]) != 1 or found[0][0] not in UP_AXES:
        raise UserError(f"{path}: unknown world convention in its header comment {UP_COMMENT!r}: "
                        f"{' '.join(found[0])!r} (rmavatar writes -y or y)")
    return found[0][0]


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
    comments: list[str] = []
    while True:
        line = f.readline()
        if not line:
            raise UserError(f"{path}: PLY header has no end_header")
        words = line.decode("ascii", errors="replace").split()
        if words and words[0] == "comment":
            comments.append(" ".join(words[1:]))
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
    return fmt, elements, comments


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
