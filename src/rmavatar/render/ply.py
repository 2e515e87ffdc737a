"""Read a standard 3D Gaussian Splatting PLY (the format of the 3DGS reference code and viewers)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from rmavatar.utils import UserError

_PLY_TYPES = {
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
    "char": "i1", "int8": "i1", "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
}


def read_gaussian_ply(path: str | Path) -> dict:
    """Gaussians from a binary little-endian 3DGS PLY: means [N,3], quats [N,4] wxyz, scales [N,3]
    (exp of the stored log-scales), opacities [N] (sigmoid of the stored logits), colors SH [N,K,3],
    sh_degree. Raises UserError naming what is missing."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise UserError(f"{path}: not a PLY file")
        fmt, count, props, in_vertex = None, None, [], False
        while True:
            line = f.readline()
            if not line:
                raise UserError(f"{path}: PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                in_vertex = words[1] == "vertex"
                if in_vertex:
                    count = int(words[2])
            elif words[0] == "property" and in_vertex:
                if words[1] == "list":
                    raise UserError(f"{path}: list properties in the vertex element are not supported")
                if words[1] not in _PLY_TYPES:
                    raise UserError(f"{path}: unknown PLY type {words[1]!r}")
                props.append((words[2], "<" + _PLY_TYPES[words[1]]))
            elif words[0] == "end_header":
                break
        if fmt != "binary_little_endian":
            raise UserError(f"{path}: only binary_little_endian PLY is supported, got {fmt}")
        if count is None:
            raise UserError(f"{path}: no vertex element")
        dtype = np.dtype(props)
        data = np.frombuffer(f.read(dtype.itemsize * count), dtype=dtype, count=count)
    names = set(dtype.names)
    need = ["x", "y", "z", "opacity", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"scale_{i}" for i in range(3)] + [
        f"rot_{i}" for i in range(4)]
    missing = [n for n in need if n not in names]
    if missing:
        raise UserError(f"{path}: not a 3DGS PLY, missing properties {missing}")

    def cols(keys):
        return torch.from_numpy(np.stack([data[k].astype(np.float32) for k in keys], -1))

    n_rest = sum(1 for n in names if n.startswith("f_rest_"))
    k = 1 + n_rest // 3
    degree = int(round(k**0.5)) - 1
    if (degree + 1) ** 2 != k:
        raise UserError(f"{path}: {n_rest} f_rest properties do not form whole SH bands")
    dc = cols([f"f_dc_{i}" for i in range(3)])[:, None, :]
    if n_rest:
        # Stored channel-major: f_rest_{c * (K-1) + j}.
        rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(-1, 3, k - 1).transpose(1, 2)
        sh = torch.cat([dc, rest], 1)
    else:
        sh = dc
    return {
        "means": cols(["x", "y", "z"]),
        "quats": cols([f"rot_{i}" for i in range(4)]),
        "scales": torch.exp(cols([f"scale_{i}" for i in range(3)])),
        "opacities": torch.sigmoid(cols(["opacity"])[:, 0]),
        "colors": sh.contiguous(),
        "sh_degree": degree,
    }
