"""Export a trained avatar as a standard 3D Gaussian Splatting PLY; read such PLYs back.

``write_ply(path, means, quats, scales, opacities, sh)``, ``read_ply(path) -> PlyGaussians``.
"""

from rmavatar.export.ply import PlyGaussians, read_ply, write_ply

__all__ = ["PlyGaussians", "read_ply", "write_ply"]
