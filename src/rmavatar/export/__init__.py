"""Export a trained avatar as a standard 3D Gaussian Splatting PLY; read such PLYs back.

``write_ply(path, means, quats, scales, opacities, sh, up="-y")`` (y-up Gaussians in; the file is y down, as
stock 3DGS viewers expect, unless ``up="y"``), ``read_ply(path) -> GaussianSet`` (back in the y-up world,
whichever way the file was written), ``ply_up(path)`` (the file's convention).
"""

from rmavatar.export.ply import ply_up, read_ply, write_ply

__all__ = ["ply_up", "read_ply", "write_ply"]
