"""Fitting the Anny body's shape to the person's outline: body offsets d [V] (metres along each rest
vertex's normal, :class:`rmavatar.body.anny.AnnyBody`), one for the clip, with the fitted poses held.

Anny's phenotype moves its surface by 2-3 cm at most, so a clothed person's mask is wider than the
preset body posed in it, and an avatar's Gaussians would start inside the person. Skinning is linear
in the rest vertices, so with the poses held the posed body is P0 + d x D per frame (``offset_directions``)
and the fit needs no body forward per step. The objective, on a few frames spread over the clip:

- silhouette and outline: the body fit's own mask terms (:mod:`rmavatar.capture.fit`), the surface
  inside the mask and the mask's outline drawn to the surface;
- smooth: the squared uniform mesh Laplacian of d (a constant offset costs nothing, a bump does), so
  the sparsely sampled surface moves as a whole and a hair or a bag cannot pull one vertex out;
- prior: a weak pull of d towards zero, so that the silhouette's evidence decides.

d is zero on the hands (MediaPipe's mask blurs the fingers), on Anny's interior parts (eyes, mouth
cavity, tongue), and is clamped to [min_offset, max_offset] (head: head_max_offset, where the mask
holds hair); by default 0..10 cm: the body does not shrink (docs/capture.md, "The body's shape").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from rmavatar.capture.fit import (Observations, geman_mcclure, nearest_points, outline_term, project,
                                  sample_map, surface_points)

FIXED_PARTS = ("hand.L", "hand.R", "eye_back.L", "eye_back.R", "eye_front.L", "eye_front.R", "eye_cavity.L",
               "eye_cavity.R", "mouth_cavity", "tongue")


@dataclass
class ShapeFitConfig:
    """Weights and schedule of the shape fit (see the module docstring for the terms)."""

    frames: int = 24  # frames spread over the clip that the shape is fitted to (each costs a body forward)
    iters: int = 100  # Adam steps (100, 150 and 300 fitted the same IoU to 0.001, docs/capture.md)
    lr: float = 0.003  # Adam's learning rate, metres per step at the start (cosine decay to 5% of it)
    # weight of the surface-inside-the-mask term. 5 (the body fit's is 20): on cam04 and the synthetic turn
    # 2-10 fitted about the same IoU, 20 a little less, 60-600 shrank the body into its pose errors
    silhouette: float = 5.0
    sigma: float = 0.03  # its Geman-McClure scale, fraction of the person's height (as the body fit's)
    outline: float = 1.0  # weight of the outline-to-surface term (as the body fit's)
    outline_sigma: float = 0.01  # its Geman-McClure scale, fraction of the person's height
    outline_every: int = 10  # steps between searches for each outline pixel's nearest surface point
    smooth: float = 1.0  # weight of the squared Laplacian of d, in centimetres
    prior: float = 0.001  # weight of the squared d, in centimetres
    # metres: the most the body may shrink. 0: with -1 or -3 cm allowed the fit shrank heads, feet and
    # limbs where the held poses project outside the mask, and fitted a lower IoU on both measured clips
    min_offset: float = 0.0
    max_offset: float = 0.10  # metres: loose clothes beyond this are the avatar's to learn, not the body's
    head_max_offset: float = 0.03  # metres, on the head (hair fills its mask)
    point_spacing: float = 0.02  # metres between the surface points the mask terms see (1.5 cm: the same IoU)

    def check(self) -> None:
        from rmavatar.body.anny import MAX_OFFSET
        from rmavatar.utils import UserError

        bounds = -MAX_OFFSET <= self.min_offset <= 0 <= self.max_offset <= MAX_OFFSET and self.head_max_offset >= 0
        if self.frames < 1 or self.iters < 0 or not bounds:
            raise UserError(f"shape fit: need frames >= 1, iters >= 0, -{MAX_OFFSET} <= min_offset <= 0 <= "
                            f"max_offset <= {MAX_OFFSET}, head_max_offset >= 0; got {self}")


@dataclass
class ShapeFitResult:
    """offsets [V] float32 metres; free [V] bool, the vertices that may move; the frames (of the fit's T)
    it saw; final loss terms; seconds."""

    offsets: np.ndarray
    free: np.ndarray
    frames: list[int]
    losses: dict
    seconds: float

    def summary(self) -> dict:
        """Mean (over the vertices that may move) and extremes of the offsets, millimetres."""
        d = self.offsets[self.free]
        return {"mean_mm": round(float(d.mean()) * 1000, 1), "max_mm": round(float(self.offsets.max()) * 1000, 1),
                "min_mm": round(float(self.offsets.min()) * 1000, 1), "frames": len(self.frames),
                "seconds": round(self.seconds, 3), "losses": self.losses}


def can_fit_shape(body) -> bool:
    """Whether ``body``'s shape is fitted by offsets (Anny); SMPL bodies fit their betas instead."""
    return hasattr(body, "offset_directions") and hasattr(body, "rest_normals")


def free_vertices(body) -> tuple[torch.Tensor, torch.Tensor]:
    """Which vertices may move [V] bool (none of their faces on FIXED_PARTS), and which lie on the head
    [V] bool."""
    V = body.rest_vertices.shape[0]
    dev = body.faces.device
    fixed_ids = [body.part_names.index(n) for n in FIXED_PARTS if n in body.part_names]
    fixed_face = torch.isin(body.face_part, torch.tensor(fixed_ids, device=dev))
    fixed = torch.zeros(V, dtype=torch.bool, device=dev)
    fixed[body.faces[fixed_face].reshape(-1)] = True
    head = torch.zeros(V, dtype=torch.bool, device=dev)
    head[body.faces[body.face_part == body.part_names.index("head")].reshape(-1)] = True
    return ~fixed, head & ~fixed


def edges(faces: torch.Tensor) -> torch.Tensor:
    """The mesh's edges [E,2], each once, from faces [F,3]."""
    e = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return torch.unique(torch.sort(e, dim=1).values, dim=0)


def laplacian(d: torch.Tensor, edges: torch.Tensor, degree: torch.Tensor) -> torch.Tensor:
    """The uniform mesh Laplacian of per-vertex values d [V]: each value less its neighbours' mean [V]
    (``edges`` [E,2], ``degree`` [V] neighbours per vertex). Two scatters: a sparse matrix product (and
    its backward) was most of the fit's time on the CPU."""
    a, b = edges[:, 0], edges[:, 1]
    total = torch.zeros_like(d).index_add(0, a, d[b]).index_add(0, b, d[a])
    return d - total / degree


def spread_frames(T: int, count: int) -> list[int]:
    """At most ``count`` frame indices spread evenly over 0..T-1."""
    return sorted(set(np.linspace(0, T - 1, min(count, T)).round().astype(int).tolist()))


def _posed(body, params: dict, frames: list[int], points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The held poses' surface points without offsets P0 [F,P,3] (camera frame) and their offset
    directions D [F,P,3], for the rows ``frames`` of ``params`` and the vertex ids ``points`` [P]."""
    dev = body.faces.device
    t = lambda k: torch.as_tensor(np.asarray(params[k])[frames], dtype=torch.float32, device=dev)  # noqa: E731
    hand = t("hand_pose") if params.get("hand_pose") is not None else None
    with torch.no_grad():
        go, bp = t("global_orient"), t("body_pose")
        P0 = body(None, go, bp, t("transl"), hand_pose=hand).vertices[:, points]
        D = body.offset_directions(go, bp, hand)[:, points]
    return P0, D


def _bounds(body, cfg: ShapeFitConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The vertices that may move [V] bool, and each vertex's lowest and highest offset [V] (0 and 0
    where it may not)."""
    free, head = free_vertices(body)
    dev = free.device
    hi = torch.where(head, min(cfg.head_max_offset, cfg.max_offset), cfg.max_offset).to(dev) * free
    return free, torch.full(free.shape, cfg.min_offset, device=dev) * free, hi


def _mask_terms(uv: torch.Tensor, seen: Observations, cfg: ShapeFitConfig, nearest,
                step: int) -> tuple[dict, torch.Tensor | None]:
    """The silhouette and outline terms of the projected points uv [F,P,2] against the F frames' masks
    in ``seen``, and the outline's correspondences [F,B] (searched again every cfg.outline_every steps)."""
    dist = sample_map(seen.outside, uv, seen.size) / seen.height_px
    terms = {"silhouette": cfg.silhouette * geman_mcclure(dist * dist, cfg.sigma).mean()}
    if seen.outline is not None and cfg.outline:
        if nearest is None or step % max(cfg.outline_every, 1) == 0:
            nearest = nearest_points(seen.outline, uv)
        terms["outline"] = cfg.outline * outline_term(uv, seen.outline, seen.outline_weight, nearest,
                                                      seen.height_px, cfg.outline_sigma)
    return terms, nearest


def fit_body_offsets(body, params: dict, obs: Observations, cfg: ShapeFitConfig | None = None) -> ShapeFitResult:
    """Fit the offsets of the Anny ``body`` (built without offsets) to the masks in ``obs`` (its
    ``outside`` maps, outline, K, size and height_px; T frames), the poses held at ``params``
    (global_orient [T,3], body_pose [T,69], transl [T,3], optional hand_pose [T,90]); see the module
    docstring. Returns the offsets [V] with what the fit saw and its final terms."""
    cfg = cfg or ShapeFitConfig()
    cfg.check()
    start = time.perf_counter()
    dev = body.faces.device
    V = body.rest_vertices.shape[0]
    T = int(np.asarray(params["global_orient"]).shape[0])
    frames = spread_frames(T, cfg.frames)
    free, lo, hi = _bounds(body, cfg)
    points = surface_points(body, cfg.point_spacing).to(dev)
    P0, D = _posed(body, params, frames, points)
    seen = replace(obs, outside=obs.outside[frames], outline=None if obs.outline is None else obs.outline[frames],
                   outline_weight=None if obs.outline is None else obs.outline_weight[frames])
    e = edges(body.faces)
    degree = torch.bincount(e.reshape(-1), minlength=V).clamp_min(1).float()
    d = torch.zeros(V, device=dev, requires_grad=True)
    opt = torch.optim.Adam([d], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(cfg.iters, 1), eta_min=cfg.lr * 0.05)
    nearest, terms = None, {}
    for step in range(cfg.iters):
        opt.zero_grad(set_to_none=True)
        uv = project(P0 + d[points][None, :, None] * D, obs.K)
        terms, nearest = _mask_terms(uv, seen, cfg, nearest, step)
        cm = d * 100
        terms["smooth"] = cfg.smooth * laplacian(cm, e, degree).pow(2).mean()
        terms["prior"] = cfg.prior * cm.pow(2).mean()
        sum(terms.values()).backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            d.copy_(torch.maximum(torch.minimum(d, hi), lo))
    offsets = d.detach().cpu().numpy().astype(np.float32)
    losses = {k: float(v.detach()) for k, v in terms.items()}
    return ShapeFitResult(offsets=offsets, free=free.cpu().numpy(), frames=frames, losses=losses,
                          seconds=time.perf_counter() - start)


__all__ = ["ShapeFitConfig", "ShapeFitResult", "can_fit_shape", "fit_body_offsets"]
