"""Export a trained avatar as a standard 3D Gaussian Splatting PLY; read such PLYs back.

``write_ply(path, means, quats, scales, opacities, sh)``, ``read_ply(path) -> GaussianSet`` (world axes).
"""

from rmavatar.export.ply import read_ply, write_ply

__all__ = ["read_ply", "write_ply"]
