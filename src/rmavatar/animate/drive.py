"""Posing a trained avatar and rendering it: the shared core of ``animate``, ``export``, ``view`` and
``render --turntable``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from rmavatar.animate.motion import PoseSequence, rest_pose
from rmavatar.utils import UserError


@dataclass
class Poser:
    """A trained avatar with the body shape it was trained on.

    ``avatar(vertices [V,3], body_pose [69]) -> GaussianSet``; ``body`` the BodyModel;
    ``betas`` [1,nb] or None (the body's default shape).
    """

    avatar: Any
    body: Any
    betas: torch.Tensor | None = None
    data_spec: str | None = None  # the training data, for the 'train' rest pose

    @classmethod
    def from_run(cls, run) -> "Poser":
        """From a ``LoadedRun``; the shape is the run's (``run.betas``, else the training data's)."""
        return cls(run.avatar, run.body, run_betas(run), getattr(run, "data_spec", None))

    def rest_pose(self, kind: str = "tpose") -> PoseSequence:
        """A one-frame standing pose at the origin: 'tpose' (zero pose), 'apose' (arms down 45 degrees)
        or 'train' (the median body pose of the training frames, facing +z)."""
        if kind != "train":
            go, pose = rest_pose(kind)
        else:
            if not self.data_spec:
                raise UserError("--pose train needs the run's training data, and this run names none")
            from rmavatar.data import load_dataset

            try:
                poses = np.asarray(load_dataset(self.data_spec).params("train")["body_pose"], np.float32)
            except UserError as exc:
                raise UserError(f"--pose train reads the run's training data {self.data_spec!r}, which "
                                f"cannot be read: {exc}") from None
            go, pose = torch.zeros(3), torch.from_numpy(np.median(poses, axis=0))
        return PoseSequence(go[None], pose[None], torch.zeros(1, 3))

    @property
    def device(self) -> torch.device:
        return self.body.v_template.device

    @torch.no_grad()
    def vertices(self, seq: PoseSequence, chunk: int = 32) -> torch.Tensor:
        """Posed body vertices [n,V,3] for every pose of ``seq``."""
        out = []
        seq = seq.to(self.device)
        betas = None if self.betas is None else self.betas.to(self.device)
        for s in range(0, len(seq), chunk):
            part = seq.select(slice(s, s + chunk))
            res = self.body(betas, part.global_orient, part.body_pose, part.transl)
            out.append(res.vertices.float())
        return torch.cat(out, 0)

    @torch.no_grad()
    def root_rest(self) -> torch.Tensor:
        """The root joint [3] in the rest pose with this shape (where SMPL's transl is measured from)."""
        zero = torch.zeros(1, 3, device=self.device)
        betas = None if self.betas is None else self.betas.to(self.device)
        return self.body(betas, zero, torch.zeros(1, 69, device=self.device), zero).joints[0, 0].float().cpu()

    @torch.no_grad()
    def gaussians(self, vertices: torch.Tensor, body_pose: torch.Tensor):
        """The avatar's world-space GaussianSet on posed ``vertices`` [V,3], rectified for ``body_pose`` [69]
        (evaluation mode, every stored SH band)."""
        return self.avatar.world_gaussians(vertices.to(self.device), body_pose.reshape(69).to(self.device))

    @torch.no_grad()
    def pose(self, seq: PoseSequence, i: int):
        """GaussianSet of frame ``i`` of ``seq``."""
        one = seq.select(slice(i, i + 1))
        return self.gaussians(self.vertices(one)[0], one.body_pose[0])


def run_betas(run) -> torch.Tensor | None:
    """The body shape a run was trained with, [1,nb], or None when it used the default shape.

    Read from the run (``betas``) or its avatar; failing that, the mean betas of the training split
    of the run's dataset (every frame of a subject carries the same shape).
    """
    if getattr(getattr(run, "body", None), "num_betas", None) == 0:
        return None  # a body without shape parameters (Anny presets): nothing to look up
    for owner in (run, getattr(run, "avatar", None)):
        betas = getattr(owner, "betas", None)
        if betas is not None:
            return torch.as_tensor(betas, dtype=torch.float32).reshape(1, -1)
    spec = getattr(run, "data_spec", None)
    if not spec:
        return None
    from rmavatar.data import load_dataset

    try:
        params = load_dataset(spec).params("train")
    except UserError as exc:
        raise UserError(f"the run's body shape comes from its training data {spec!r}, which cannot be "
                        f"read: {exc}") from None
    return torch.as_tensor(np.asarray(params["betas"], np.float32).mean(0, keepdims=True))


def render_image(gs, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int,
                 background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """Render a GaussianSet-like object (means, quats, scales, opacities, sh, sh_degree) -> image [H,W,3]."""
    from rmavatar.render import rasterize

    with torch.no_grad():
        bg = None if background is None else torch.as_tensor(background, dtype=gs.means.dtype,
                                                             device=gs.means.device)
        viewmat = viewmat.to(gs.means)
        image, _, _ = rasterize(gs.means, gs.quats, gs.scales, gs.opacities, gs.colors(viewmat), viewmat,
                                K.to(gs.means), width, height, background=bg)
    return image


def parse_background(text: str) -> tuple[float, float, float]:
    """'white', 'black', or 'R,G,B' in 0..1 -> RGB."""
    named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5)}
    if text in named:
        return named[text]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise UserError(f"--bg must be white, black, gray or R,G,B with values in 0..1, got {text!r}")
    return rgb


def even_size(size: int, aspect: float = 1.0) -> tuple[int, int]:
    """(width, height) of an image ``size`` pixels high, rounded up to even numbers (H.264 needs them)."""
    if size < 2:
        raise UserError(f"--size must be at least 2, got {size}")
    height = size + size % 2
    width = int(round(size * aspect))
    return width + width % 2, height
