"""Test-time pose fitting (``rmavatar eval --fit-poses``): each evaluated frame's pose fitted to its image.

The avatar stays frozen (its parameters are not changed and nothing is written); only a correction per
frame (24 joint rotations composed on the left and a translation, :mod:`rmavatar.body.corrections`,
starting at zero) is optimised with Adam against the frame's image and mask, for a fixed number of
steps, several frames at a time. The loss is the mean absolute RGB error to the ground truth composited
over the evaluation's background plus the mean absolute error of the rendered alpha to the mask (the
silhouette, which pulls limbs back into place even where the colours are flat), compared coarse to
fine (averaged over 4x4, then 2x2 pixel blocks, then per pixel), so that a limb several pixels off
still feels the pull. The rectifier sees the corrected pose but sends no gradient into it, as in
training; its output and the view-dependent colours are re-evaluated every ``refresh`` steps and held in
between, so a step costs only the mesh embedding and the rasterizer. Every frame is drawn through
:func:`rmavatar.avatar.frame.render_frame` and its target made with :func:`rmavatar.render.composite`,
as in training and evaluation. What the fit gains and costs, measured: docs/evaluate.md ("Test-time pose
fitting").

This is the protocol InstantAvatar and GART report PeopleSnapshot numbers with; the evaluation's JSON
states it (``protocol.fit_poses``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from rmavatar.avatar.frame import render_frame
from rmavatar.avatar.model import drawable_copy
from rmavatar.body import CORRECTION_DIM, PoseSequence, apply_pose_corrections
from rmavatar.body.corrections import NUM_JOINTS, correction_adam_step, pose_corrections
from rmavatar.render.camera import CameraTensors
from rmavatar.render.composite import composite
from rmavatar.utils import UserError
from rmavatar.utils.config import check_fields, whole_number


def pixel_blocks(value, name: str) -> tuple[int, ...]:
    """``value`` (a pose fit's coarse-to-fine ``scales``) as a tuple of pixel-block sizes, each a whole
    number >= 1; UserError naming the setting ``name`` otherwise."""
    blocks = [whole_number(k, 1) for k in value] if isinstance(value, (list, tuple)) else []
    if not blocks or None in blocks:
        raise UserError(f"{name} must be a list of whole numbers of pixels >= 1, got {value!r}")
    return tuple(blocks)


@dataclass
class PoseFitConfig:
    """How evaluation fits poses: Adam ``steps`` per frame, ``batch`` frames optimised together, the
    learning rates (radians / metres per step) decaying linearly to ``final_scale`` of themselves."""

    steps: int = 100  # Adam steps per frame
    batch: int = 8  # frames optimised together (one loss, one backward)
    lr_rotation: float = 2e-2  # learning rate of the joint rotations, radians per step
    lr_translation: float = 5e-4  # learning rate of the translation, metres per step
    final_scale: float = 0.1  # both learning rates decay linearly to this fraction of themselves
    silhouette: float = 1.0  # weight of the |alpha - mask| term beside the RGB term
    # Weight of sum_j |delta_j|^2 (rad^2) per frame, pulling each joint's rotation back to where it
    # started (or to fit_poses's anchor): Adam scales every joint's step to the learning rate however
    # faint its gradient, so the joints the image hardly sees (feet, hands) would wander without it.
    prior: float = 0.01
    # Coarse to fine: the images are compared averaged over k x k pixel blocks, each k for an equal share
    # of the steps, so that a limb several pixels off still gets a gradient from the coarse ones.
    scales: tuple[int, ...] = (4, 2, 1)
    refresh: int = 10  # steps between re-running the rectifier and the view-dependent colours (held between)
    # Frames (+-) the split's given poses are first averaged over (body.smooth_poses; tracker jitter is
    # frame-to-frame); 0 = fit from the poses as given.
    smooth: int = 2

    def validate(self) -> "PoseFitConfig":
        # the settings `rmavatar eval` has flags for, in the flags' words
        if self.steps < 1:
            raise UserError(f"--fit-poses needs at least 1 step, got {self.steps}")
        if self.batch < 1:
            raise UserError(f"the pose-fitting batch (--fit-batch) must be >= 1 frame, got {self.batch}")
        if not isinstance(self.smooth, int) or isinstance(self.smooth, bool) or self.smooth < 0:
            raise UserError(f"the pose fit's smoothing (--fit-smooth) must be a whole number of frames >= 0, "
                            f"got {self.smooth!r}")
        # the rest: finite numbers of their types, and in range
        check_fields(self, "fit", at_least_one=("refresh",),
                     nonnegative=("lr_rotation", "lr_translation", "silhouette", "prior"), positive=("final_scale",))
        self.scales = pixel_blocks(self.scales, "fit.scales")
        return self

    def protocol(self) -> dict:
        return {"steps": self.steps, "batch": self.batch, "smooth_frames": self.smooth,
                "lr_rotation": self.lr_rotation,
                "lr_translation": self.lr_translation, "final_scale": self.final_scale,
                "loss": f"mean |render - ground truth| (RGB) + {self.silhouette} x mean |alpha - mask|, on "
                        f"{' then '.join(f'{k}x{k}' for k in self.scales)} pixel blocks (equal shares of the steps), + "
                        f"{self.prior} x sum of the squared joint corrections (rad^2)",
                "optimiser": "Adam, one second moment per joint; rectifier and view-dependent colours held "
                             f"for {self.refresh} steps at a time",
                "optimised": "per frame: 24 joint rotations (composed on the left) and the translation; "
                             "avatar frozen"}  # fmt: skip


def fit_poses(avatar, body, poses: PoseSequence, betas, frames: Sequence, background: torch.Tensor,
              cfg: PoseFitConfig | None = None, progress: bool = False,
              anchor: PoseSequence | None = None) -> PoseSequence:
    """The poses of ``frames`` (a sequence of Frame objects: image, mask, camera; indexed one batch at a
    time) fitted to their images.

    avatar, body: the Avatar and its body model (frozen: their parameters never change; training's
    pose sweeps call this with the avatar being trained); poses: the frames' starting poses; betas
    [n,nb] or None: their body shapes; background [3] on the avatar's device; anchor: the poses whose
    joint rotations ``cfg.prior`` pulls the fitted ones toward (None: the starting poses). Returns the
    fitted poses (on the CPU).
    """
    from tqdm import tqdm

    cfg = (cfg or PoseFitConfig()).validate()
    n = len(poses)
    if len(frames) != n:
        raise ValueError(f"{n} poses for {len(frames)} frames")
    dev = background.device
    frozen = [(p, p.requires_grad) for p in list(avatar.parameters()) + list(body.parameters())]
    for p, _ in frozen:
        p.requires_grad_(False)
    was_training = avatar.training
    avatar.eval()
    # the Gaussians too faint to draw add nothing to the images the fit compares: posed without them,
    # a fitting step costs a fifth to a quarter less (docs/evaluate.md)
    visible = drawable_copy(avatar)
    out = []
    try:
        bar = tqdm(total=n, desc="fit poses", unit="frame", disable=not progress, dynamic_ncols=True, leave=False)
        for start in range(0, n, cfg.batch):
            rows = slice(start, min(n, start + cfg.batch))
            start_poses = poses.select(rows).to(dev)
            toward = None if anchor is None else pose_corrections(start_poses, anchor.select(rows).to(dev)).float()
            out.append(_fit_batch(visible, body, start_poses,
                                  None if betas is None else torch.as_tensor(betas[rows]).float().to(dev),
                                  [frames[i] for i in range(n)[rows]], background, cfg, toward))  # fmt: skip
            bar.update(rows.stop - rows.start)
        bar.close()
    finally:
        for p, flag in frozen:
            p.requires_grad_(flag)
        avatar.train(was_training)
    fitted = (torch.cat([getattr(p, k) for p in out]) for k in ("global_orient", "body_pose", "transl"))
    return PoseSequence(*fitted, poses.hand_pose)  # the fingers are not fitted


def _fit_batch(avatar, body, poses: PoseSequence, betas, frames, background, cfg: PoseFitConfig,
               toward: torch.Tensor | None) -> PoseSequence:
    """``poses`` fitted; ``toward`` [b,75] or None (zero): the corrections the prior pulls toward."""
    dev = background.device
    b = len(poses)
    delta = torch.zeros(b, CORRECTION_DIM, device=dev, requires_grad=True)
    exp_avg = torch.zeros_like(delta)
    exp_avg_sq = torch.zeros(b, NUM_JOINTS + 1, device=dev)
    counts = torch.zeros(b, dtype=torch.long, device=dev)
    lr = torch.full((CORRECTION_DIM,), cfg.lr_rotation, device=dev)
    lr[-3:] = cfg.lr_translation
    targets, masks, cams = _targets(frames, background)
    rectified: list = [None] * b
    colors: list = [None] * b
    pooled = {}  # the targets and masks at the current scale: pooled once per scale, not every step
    for step in range(cfg.steps):
        scale = 1.0 - (1.0 - cfg.final_scale) * step / max(cfg.steps - 1, 1)
        pool = cfg.scales[step * len(cfg.scales) // cfg.steps]
        if pooled.get("k") != pool:
            pooled = {"k": pool, "targets": [_pooled(t, pool) for t in targets],
                      "masks": [_pooled(m, pool) for m in masks]}
        fitted = apply_pose_corrections(poses, delta)
        vertices = body(betas, fitted.global_orient, fitted.body_pose, fitted.transl,
                        hand_pose=fitted.hand_pose).vertices.float()
        loss = 0.0
        for k in range(b):
            # The rectifier's output and the view-dependent colours send no gradient to the pose; held
            # fixed between refreshes, a step costs the mesh embedding and the rasterizer only.
            refresh = step % cfg.refresh == 0
            pose = avatar.pose_input(fitted.body_pose[k], fitted.hand(k))
            if refresh and avatar.rectifier is not None:
                with torch.no_grad():
                    rectified[k] = avatar.rectify(vertices[k], pose)
            table = avatar.face_table(vertices[k], kernels=True)  # the CPU kernels, where they apply
            drawn = render_frame(avatar, None, pose, cams[k], background, table=table, rectified=rectified[k],
                                 colors=None if refresh else colors[k], hold_colors=True)
            colors[k] = drawn.colors
            loss = loss + (_pooled(drawn.image, pool) - pooled["targets"][k]).abs().mean() \
                + cfg.silhouette * (_pooled(drawn.alpha, pool) - pooled["masks"][k]).abs().mean()
        off = delta if toward is None else delta - toward
        loss = loss + cfg.prior * off[:, : NUM_JOINTS * 3].square().sum()
        (grad,) = torch.autograd.grad(loss, delta)
        correction_adam_step(delta, grad, exp_avg, exp_avg_sq, counts, slice(0, b), lr * scale)
    with torch.no_grad():
        fitted = apply_pose_corrections(poses, delta)
    return fitted.to("cpu")


def _targets(frames, background: torch.Tensor) -> tuple[list, list, list]:
    """Each frame's ground truth composited over ``background`` [H,W,3], its mask [H,W,1] and its
    camera (CameraTensors), on the background's device."""
    dev = background.device
    targets, masks, cams = [], [], []
    for f in frames:
        m = torch.tensor(f.mask, dtype=torch.float32, device=dev)[..., None]
        targets.append(composite(torch.tensor(f.image, dtype=torch.float32, device=dev), m, background))
        masks.append(m)
        c = f.camera
        cams.append(CameraTensors(torch.tensor(c.viewmat, dtype=torch.float32, device=dev),
                                  torch.tensor(c.K, dtype=torch.float32, device=dev), c.width, c.height))
    return targets, masks, cams


def _pooled(image: torch.Tensor, k: int) -> torch.Tensor:
    """image [H,W,C] averaged over k x k blocks (k = 1: itself)."""
    return image if k == 1 else F.avg_pool2d(image.permute(2, 0, 1), k, ceil_mode=True)
