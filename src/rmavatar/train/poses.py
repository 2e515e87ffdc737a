"""Pose refinement while training: learnable per-frame corrections of the training poses.

Every training frame gets a correction [75] (24 joint rotations composed on the left, a translation; see
:mod:`rmavatar.body.corrections`), zero at the start. A step poses the body with its frame's corrected
pose, so the mesh, the Gaussians on it and the rectifier's pose input all see it, and the image loss
reaches the correction through the body model.

The corrections have their own Adam, kept per frame: a frame's moments and step count change only on
the steps that train that frame. A shared dense Adam would keep moving every frame visited before on
stale momentum; ``torch.optim.SparseAdam`` bias-corrects with the global step count, so a frame's first
update would be a fraction of the intended size. Learning rates and their schedule (frozen during a
warm-up, then a log-linear decay) are in :class:`rmavatar.train.pose_refine.PoseConfig`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from rmavatar.body import CORRECTION_DIM, PoseSequence, apply_pose_corrections
from rmavatar.body.corrections import correction_adam_step, pose_corrections
from rmavatar.body.poses import hands_given
from rmavatar.utils import UserError, atomic_path


class PoseRefiner:
    """Corrections ``delta`` [n,75] of ``base`` (the dataset's poses of the n training frames) with
    per-frame Adam state; ``betas`` [n,nb] or None is each frame's body shape; ``cfg`` (a
    :class:`rmavatar.train.pose_refine.PoseConfig`) gives the learning rates and their schedule over a
    pass of ``iters``. ``frozen``: the corrections are held as set (:meth:`set_poses`; the second pass of
    ``poses.first_pass``)."""

    def __init__(self, base: PoseSequence, betas: torch.Tensor | None, cfg, iters: int, device: torch.device,
                 frozen: bool = False):
        self.cfg = cfg
        self.iters = iters
        self.frozen = frozen
        self.base = base.to(device)
        self.betas = None if betas is None else torch.as_tensor(betas, dtype=torch.float32).to(device)
        n = len(base)
        self.delta = torch.zeros(n, CORRECTION_DIM, device=device, requires_grad=True)
        self.exp_avg = torch.zeros(n, CORRECTION_DIM, device=device)
        self.exp_avg_sq = torch.zeros(n, device=device)
        self.steps = torch.zeros(n, dtype=torch.long, device=device)
        lr = torch.full((CORRECTION_DIM,), cfg.lr_rotation, dtype=torch.float32)
        lr[-3:] = cfg.lr_translation
        self.lr = lr.to(device)

    def __len__(self) -> int:
        return len(self.base)

    def active(self, iteration: int) -> bool:
        """Whether step ``iteration`` (1-based) trains the corrections (after the frozen warm-up)."""
        return not self.frozen and iteration > self.cfg.warmup_steps(self.iters)

    def frame_inputs(self, i: int) -> tuple[torch.Tensor, ...]:
        """What :func:`pose_corrected` takes for frame ``i``: its correction row [1,75] (a view of
        ``delta``, so gradients reach it), its base global_orient [1,3], body_pose [1,69], transl [1,3],
        hand_pose [1,90] ([1,0] without finger poses), and its betas [1,nb] when the body has a shape."""
        base = self.base.select(slice(i, i + 1))
        rows = (self.delta[i : i + 1], base.global_orient, base.body_pose, base.transl, base.hand_rows())
        return rows if self.betas is None else (*rows, self.betas[i : i + 1])

    def zero_grad(self) -> None:
        self.delta.grad = None

    @torch.no_grad()
    def step(self, i: int, iteration: int, ok: torch.Tensor) -> None:
        """Adam on frame ``i``'s correction with the lr of step ``iteration`` (1-based); clears the gradient.
        ``ok`` (a bool tensor on the device) false leaves the frame's correction and Adam state as they
        were, decided on the device so that a skipped step costs no host synchronisation."""
        grad = self.delta.grad
        self.delta.grad = None
        if grad is None:
            return
        rows = slice(i, i + 1)
        state = (self.delta, self.exp_avg, self.exp_avg_sq, self.steps)
        before = [t[rows].clone() for t in state]
        lr = self.lr * self.cfg.lr_scale(iteration - 1, self.iters)
        correction_adam_step(self.delta, torch.nan_to_num(grad[rows]), self.exp_avg, self.exp_avg_sq, self.steps,
                             rows, lr)
        for t, old in zip(state, before):
            t[rows] = torch.where(ok, t[rows], old)

    @torch.no_grad()
    def set_poses(self, poses: PoseSequence) -> None:
        """Make ``poses`` (all n frames; a pose sweep's fitted ones) the corrected poses. Every frame's Adam
        state starts afresh: its momentum pointed from the old pose."""
        self.delta.copy_(pose_corrections(self.base, poses.to(self.delta.device)))
        for t in (self.exp_avg, self.exp_avg_sq, self.steps):
            t.zero_()

    @torch.no_grad()
    def poses(self) -> PoseSequence:
        """The corrected poses of every training frame (on the CPU)."""
        return apply_pose_corrections(self.base, self.delta.detach()).to("cpu")

    # --- checkpoints ----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Tensors on the CPU: the base poses (so a trained avatar has its refined poses without the
        dataset), the corrections and the Adam state."""
        cpu = lambda t: t.detach().cpu().clone()  # noqa: E731
        return {
            "base": {"global_orient": cpu(self.base.global_orient), "body_pose": cpu(self.base.body_pose),
                     "transl": cpu(self.base.transl),
                     **({} if self.base.hand_pose is None else {"hand_pose": cpu(self.base.hand_pose)})},
            "delta": cpu(self.delta), "exp_avg": cpu(self.exp_avg), "exp_avg_sq": cpu(self.exp_avg_sq),
            "steps": cpu(self.steps),
        }  # fmt: skip

    @torch.no_grad()
    def load_state_dict(self, state: dict, where: str) -> None:
        base = state["base"]
        if base["body_pose"].shape[0] != len(self):
            raise UserError(f"{where}: its pose corrections are for {base['body_pose'].shape[0]} training frames, "
                            f"the dataset now has {len(self)}")
        mine = (self.base.global_orient, self.base.body_pose, self.base.transl)
        theirs = (base["global_orient"], base["body_pose"], base["transl"])
        if not all(torch.equal(a.cpu(), b) for a, b in zip(mine, theirs)):
            raise UserError(f"{where}: the dataset's training poses changed since this run refined them; "
                            "start a new run")
        dev = self.delta.device
        self.delta.copy_(state["delta"].to(dev))
        self.exp_avg.copy_(state["exp_avg"].to(dev))
        self.exp_avg_sq.copy_(state["exp_avg_sq"].to(dev))
        self.steps.copy_(state["steps"].to(dev))


def write_poses(path, poses: PoseSequence, index: np.ndarray, split: str) -> None:
    """The refined training poses as ``RUN/poses.npz`` (written atomically): global_orient [n,3],
    body_pose [n,69], transl [n,3], hand_pose [n,90] (where the data has finger poses; not refined),
    index [n] (the dataset's frame numbers), split."""
    hands = {} if poses.hand_pose is None else {"hand_pose": poses.hand_pose.numpy()}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, global_orient=poses.global_orient.numpy(), body_pose=poses.body_pose.numpy(),
                     transl=poses.transl.numpy(), index=np.asarray(index, np.int64), split=np.array(split),
                     **hands)


def read_poses(path: Path, index: np.ndarray, split: str) -> PoseSequence:
    """The poses of :func:`write_poses` at ``path``, checked to be of the frames ``index`` of ``split``."""
    if not path.is_file():
        raise UserError(f"{path} is missing: the poses this run trains on (start a new run)")
    with np.load(path) as f:
        if str(f["split"]) != split or not np.array_equal(f["index"], index):
            raise UserError(f"{path} holds the poses of other frames than this run's {len(index)} {split!r} frames")
        return PoseSequence.from_params(f)


def pose_corrected(body, pose_input: Callable, delta: torch.Tensor, global_orient: torch.Tensor,
                   body_pose: torch.Tensor, transl: torch.Tensor, hand_pose: torch.Tensor,
                   betas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One frame's body posed with its correction ``delta`` [1,75] applied to its base pose
    (global_orient [1,3], body_pose [1,69], transl [1,3]; hand_pose [1,90], or [1,0] for none, is not
    corrected): vertices [V,3], differentiable in ``delta``, and the rectifier's pose input
    (``pose_input(body_pose [69], hand_pose [90] | None)``, the avatar's ``pose_input``) of the corrected
    pose, without gradient: the corrections are to align the body with the image, not to suit the MLP.
    Tensor operations only: a CUDA step replays it in a graph with the avatar's posing."""
    one = apply_pose_corrections(PoseSequence(global_orient, body_pose, transl), delta)
    hands = hands_given(hand_pose)
    # NaN/inf are caught by the trainer's one device-side check (the Gaussians and every gradient)
    vertices = body(betas, one.global_orient, one.body_pose, one.transl, check_values=False,
                    hand_pose=hands).vertices[0].float()
    return vertices, pose_input(one.body_pose[0].detach(), None if hands is None else hands[0])

