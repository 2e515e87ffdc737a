"""A small mesh picture renderer (painter's algorithm with PIL, flat shading) for looking at bodies.

Not for training: it exists so a person can check a posed body (``rmavatar body show``).
"""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

# view name -> rotation applied to the body before an orthographic look along -z (y up, x right)
_VIEWS = {
    "front": np.eye(3),
    "side": np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),  # the body's left side
    "back": np.diag([-1.0, 1.0, -1.0]),
}


def render_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    size: int = 512,
    views: tuple[str, ...] = ("front", "side"),
    face_colors: np.ndarray | None = None,
    points: np.ndarray | None = None,
    bounds: tuple[np.ndarray, float] | None = None,
) -> Image.Image:
    """Render ``vertices [V,3]`` / ``faces [F,3]`` (y up) side by side from each view.

    ``face_colors [F,3]`` in 0..1 (grey if None); ``points [P,3]`` are drawn as red dots (e.g. joints)
    over the mesh. ``bounds`` = (centre [3], half extent) fixes the framing (default: fit the mesh).
    """
    if views and any(v not in _VIEWS for v in views):
        raise ValueError(f"views must be among {', '.join(_VIEWS)}, got {views}")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if bounds is None:
        lo, hi = vertices.min(0), vertices.max(0)
        centre, half = (lo + hi) / 2, float((hi - lo).max()) / 2 * 1.08
    else:
        centre, half = bounds
    base = np.full((len(faces), 3), 0.8) if face_colors is None else np.asarray(face_colors)
    image = Image.new("RGB", (size * len(views), size), (255, 255, 255))
    draw = ImageDraw.Draw(image)
    light = np.array([0.3, 0.4, 1.0]) / np.linalg.norm([0.3, 0.4, 1.0])
    for k, view in enumerate(views):
        R = _VIEWS[view]
        v = (vertices - centre) @ R.T
        tri = v[faces]  # [F,3,3]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
        shade = 0.25 + 0.75 * np.abs(normal @ light)  # two-sided: inner faces still readable
        colors = np.clip(base * shade[:, None] * 255, 0, 255).astype(np.uint8)
        px = (tri[..., 0] / half * 0.5 + 0.5) * size + k * size
        py = (0.5 - tri[..., 1] / half * 0.5) * size
        order = np.argsort(tri[..., 2].mean(1))  # far (small z) first
        for f in order:
            draw.polygon(
                [(px[f, 0], py[f, 0]), (px[f, 1], py[f, 1]), (px[f, 2], py[f, 2])],
                fill=tuple(int(c) for c in colors[f]),
            )
        if points is not None:
            p = (np.asarray(points, dtype=np.float64) - centre) @ R.T
            for x, y in zip((p[:, 0] / half * 0.5 + 0.5) * size + k * size, (0.5 - p[:, 1] / half * 0.5) * size):
                draw.ellipse([x - 3, y - 3, x + 3, y + 3], fill=(220, 30, 30))
    return image
