"""Adam with the paper's learning rates: ``OptimConfig.build(avatar)``, and the position lr schedule."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from rmavatar.utils import UserError
from rmavatar.utils.config import check_fields


def position_lr(iteration: int, total: int, lr_start: float, lr_end: float) -> float:
    """3DGS's log-linear decay: lr_start at iteration 0, lr_end at iteration ``total``."""
    t = min(max(iteration / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(lr_start) * (1.0 - t) + math.log(lr_end) * t)


@dataclass
class OptimConfig:
    """Adam learning rates (positions in triangle-local units) and the run length."""

    iters: int = 50_000
    lr_position: float = 0.008
    lr_position_final: float = 1e-5  # reached log-linearly at the last iteration
    lr_scaling: float = 0.017
    lr_rotation: float = 0.001
    lr_opacity: float = 0.05
    lr_color: float = 0.0025  # SH band 0; higher bands use lr_color / sh_rest_divisor
    sh_rest_divisor: float = 20.0
    lr_rectifier: float = 1e-4
    adam_eps: float = 1e-15
    # Pose refinement (docs/train.md): per-frame corrections of the training poses. None = auto: on when
    # the dataset says its poses are estimated (rmavatar capture), off otherwise (the paper's protocol).
    refine_poses: bool | None = None
    lr_pose: float = 2e-2  # a frame's rotation corrections move at most this far (radians) per step
    lr_pose_transl: float = 5e-4  # translation corrections, metres per Adam step
    lr_pose_final_scale: float = 0.1  # both decay log-linearly to this fraction at the last iteration
    pose_warmup: float = 0.1  # fraction of the run with frozen corrections (the avatar takes shape first)
    # With refinement, the estimated poses are first averaged over +-this many frames of their video
    # (body.smooth_poses: tracker jitter is frame-to-frame); 0 = off.
    smooth_poses: int = 2
    # Pose sweeps: at these fractions of the run every training frame's pose is fitted to its image with
    # the avatar held still (the evaluation's fitting, pose_sweep_steps Adam steps per frame), then
    # training goes on from the fitted poses. Why: a frame's correction otherwise moves only on the ~1 in
    # n steps that sample it; 1,000 steps over 100 frames left the corrections nearly where the
    # smoothing put them. Two early sweeps beat one late one (128 px proxy, fitted test frames: [0.75]
    # 27.50 dB, [0.45, 0.75] 28.22, [0.2, 0.45] 28.39, true poses 28.94; docs/train.md), plausibly
    # because the avatar then has most of the run, at a position lr not yet decayed, to sharpen on the
    # fitted poses. A sweep on an opacity reset runs one step earlier (pose_sweep_iterations). Each
    # sweep is a fixed cost (every training frame x pose_sweep_steps): large against the demo's 1,000
    # steps, small against the paper's 50,000. Empty = no sweeps.
    pose_sweeps: tuple[float, ...] = (0.2, 0.45)
    pose_sweep_steps: int = 30
    # Two passes: with refinement, a first run of this fraction of iters (with the sweeps above) refines
    # the poses into RUN/pose_pass, then the avatar is trained afresh on those poses, held, for iters.
    # Why: an avatar that trained on poses still wrong for part of its run stays blurred after they are
    # fixed; one trained from the start on the refined poses is sharper (D = 3 at the demo's size, fitted
    # test / novel_pose: 33.24 / 30.98 dB against 33.06 / 30.65 in one pass; true poses 34.33 / 31.73;
    # +29% training time; docs/train.md). 0 = one pass: the avatar that refined the poses is the result.
    pose_pass: float = 0.5
    # Refits in the second pass: at these fractions of it the avatar being trained fits every held
    # training pose again (pose_refit_steps steps, rotations at pose_refit_lr, translations at 1/40 of
    # it), then trains on from them. Why: the first pass's poses are only as exact as its avatar, which
    # trained on poses that were moving; the second pass's avatar is sharper and aligns them better (D = 3
    # at the demo's size, fitted test: none 33.24 dB, [0.5] 33.46, [0.4, 0.7] 33.56; true poses 34.33;
    # the captured turn of docs/capture.md, with pose_fit_mask 0: 32.82 -> 32.98 dB fitted from its
    # captured test poses; docs/train.md). A lower lr than the first pass's sweeps: from poses already
    # nearly right, 30 steps at 2e-2 overshoot (16 frames 0.56 px off in the image: 0.61 px after, 0.49 at
    # 5e-3). Each refit costs as much as a sweep: a few percent of a run at the default iters, 27-81% more
    # training at the demo's 1,000. Empty = none (the second pass trains on the first pass's poses, held).
    pose_refits: tuple[float, ...] = (0.4, 0.7)
    pose_refit_lr: float = 5e-3
    # Fitting steps per frame in a refit. 100 fit closer than 30 (D = 3, three refits, test fitted for
    # 300 steps: 33.87 dB against 33.72; true poses 34.33), the second pass taking 2.6x as long at 1,000
    # iterations (docs/evaluate.md).
    pose_refit_steps: int = 30
    # Weight of the alpha-vs-mask term in the sweeps' and refits' fitting (rmavatar.evaluate.fit's
    # FitConfig.silhouette); 0 = the images only. Why 0: estimated masks mislead the fit (the synthetic
    # turn captured by rmavatar capture, MediaPipe's masks: the first pass's avatar fits 16 training
    # frames to 0.62 px without the term, 0.69 at 1, 0.79 at 3; fitted from the captured test poses:
    # 32.63 dB at 1, 32.82 at 0, 32.98 at 0 with refits on training seed 0, 32.99 on seed 1; the
    # true-pose avatars 33.47 and 33.42), and exact ones do not need it (D = 3 with refits: 33.61 dB
    # fitted on test at 0 against 33.50-33.56 at 1, training poses 1.90 against 1.97-2.00 degrees).
    pose_fit_mask: float = 0.0

    def validate(self) -> "OptimConfig":
        check_fields(self, "optim", positive=("adam_eps", "sh_rest_divisor", "pose_refit_lr"),
                     nonnegative=("lr_scaling", "lr_rotation", "lr_opacity", "lr_color", "lr_rectifier",
                                  "smooth_poses", "pose_fit_mask"),
                     at_least_one=("pose_sweep_steps", "pose_refit_steps"))
        if self.iters < 1:
            raise UserError(f"iters must be >= 1, got {self.iters}")
        if self.lr_position_final <= 0 or self.lr_position <= 0:
            raise UserError("optim.lr_position and optim.lr_position_final must be > 0")
        if self.lr_pose < 0 or self.lr_pose_transl < 0:
            raise UserError("optim.lr_pose and optim.lr_pose_transl must be >= 0")
        if not 0 < self.lr_pose_final_scale <= 1:
            raise UserError(f"optim.lr_pose_final_scale must be in (0, 1], got {self.lr_pose_final_scale}")
        if not 0 <= self.pose_warmup < 1:
            raise UserError(f"optim.pose_warmup must be in [0, 1), got {self.pose_warmup}")
        for name in ("pose_sweeps", "pose_refits"):
            value = getattr(self, name)
            bad = not isinstance(value, (list, tuple)) or any(
                isinstance(f, bool) or not isinstance(f, (int, float)) for f in value)
            if bad or any(not 0 < f < 1 for f in value):
                raise UserError(f"optim.{name} must be fractions of the run in (0, 1), got {value!r}")
            setattr(self, name, tuple(float(f) for f in value))
        f = self.pose_pass
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 <= f <= 1:
            raise UserError(f"optim.pose_pass must be a fraction of iters in [0, 1], got {self.pose_pass!r}")
        return self

    def refines_poses(self, poses_estimated: bool) -> bool:
        """Whether this run refines its training poses, for a dataset whose poses are (not) estimated."""
        return bool(poses_estimated) if self.refine_poses is None else self.refine_poses

    def pose_pass_iters(self, poses_estimated: bool) -> int:
        """Iterations of the pose pass that comes before this run (``pose_pass``); 0 = none."""
        if not self.refines_poses(poses_estimated) or self.pose_pass == 0:
            return 0
        return max(1, round(self.pose_pass * self.iters))

    def pose_warmup_steps(self) -> int:
        """Steps with frozen pose corrections; refinement starts at step ``pose_warmup_steps() + 1``."""
        return round(self.pose_warmup * self.iters)

    def pose_sweep_iterations(self, schedule=None, fractions: tuple[float, ...] | None = None) -> set[int]:
        """The iteration counts after which the training poses are fitted (before the next step): at the
        ``fractions`` of the run (default ``pose_sweeps``; the second pass: ``pose_refits``), each one that
        falls on an opacity reset of ``schedule`` (a density DensitySchedule; None: no density control)
        moved one earlier. Why: right after a reset every opacity is at most
        ``density.reset_opacity_to`` (0.01) and the avatar is nearly invisible, so fitting the poses to
        its renders learns little (measured at 128 px, 500 steps, 3 degrees of pose noise: sweeps at 0.3
        and 0.6 of the run, both on resets, scored 0.54 dB below the same sweeps one step earlier on
        fitted test frames, and 2.1 dB below on the avatar's own training frames; docs/train.md)."""
        on_reset = (lambda s: False) if schedule is None else schedule.reset_at
        planned = (max(1, round(f * self.iters)) for f in (self.pose_sweeps if fractions is None else fractions))
        return {s - 1 if s > 1 and on_reset(s) else s for s in planned}

    def pose_lr_scale(self, iteration: int) -> float:
        """The pose corrections' lr factor before step ``iteration + 1``: 0 during the warm-up, then a
        log-linear decay from 1 to ``lr_pose_final_scale`` at the last iteration."""
        start = self.pose_warmup_steps()
        if iteration < start:
            return 0.0
        return position_lr(iteration - start, self.iters - start, 1.0, self.lr_pose_final_scale)

    def build(self, avatar) -> torch.optim.Adam:
        """Adam over named parameter groups (eps ``adam_eps``).

        Group order and names are fixed, so a checkpoint's optimiser state loads into a rebuilt one; the
        "position" group's lr follows :meth:`position_lr`, set every step by the trainer.
        """
        groups = [
            {"name": "position", "params": [avatar.means], "lr": self.lr_position},
            {"name": "rotation", "params": [avatar.quats], "lr": self.lr_rotation},
            {"name": "scaling", "params": [avatar.log_scales], "lr": self.lr_scaling},
            {"name": "opacity", "params": [avatar.opacity_logits], "lr": self.lr_opacity},
            {"name": "sh_dc", "params": [avatar.sh_dc], "lr": self.lr_color},
            {"name": "sh_rest", "params": [avatar.sh_rest], "lr": self.lr_color / self.sh_rest_divisor},
        ]
        if avatar.rectifier is not None:
            groups.append({"name": "rectifier", "params": list(avatar.rectifier.parameters()), "lr": self.lr_rectifier})
        # Fused Adam (CPU and CUDA) skips a step on the device (``found_inf``), which the trainer's NaN
        # guard relies on; OneLaunchAdam runs it over all groups at once. Elsewhere: plain Adam.
        if avatar.means.device.type in ("cpu", "cuda"):
            return OneLaunchAdam(groups, lr=self.lr_position, eps=self.adam_eps)
        return torch.optim.Adam(groups, lr=self.lr_position, eps=self.adam_eps)

    def position_lr(self, iteration: int) -> float:
        """The position group's lr before step ``iteration + 1`` (0-based count of steps done)."""
        return position_lr(iteration, self.iters, self.lr_position, self.lr_position_final)


class OneLaunchAdam(torch.optim.Adam):
    """``torch.optim.Adam(fused=True)`` whose step is six tensor operations for all its groups together,
    not three per group; same results up to float rounding, same state (``step``, ``exp_avg``,
    ``exp_avg_sq`` per parameter), so its state_dict is a torch Adam's and loads into one.

    One fused Adam kernel needs one lr, so it runs with lr 1 on update buffers U (zeroed first, standing
    in for the parameters); then U *= each parameter's group lr and params += U. ``found_inf`` (a 0-d
    float tensor, 1.0 = skip, as set by ``torch.amp.GradScaler`` or the trainer) makes the kernel write
    nothing, so U stays zero and the step counts are put back: the step changes nothing, without a host
    sync. Groups that differ in betas, eps, amsgrad or maximize get one kernel each. Weight decay is
    not supported (the kernel would decay U, not the parameter); lr must be a number.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 amsgrad: bool = False, maximize: bool = False):
        super().__init__(params, lr=lr, betas=betas, eps=eps, amsgrad=amsgrad, maximize=maximize, fused=True)
        self._updates: dict = {}  # parameter -> its U buffer (not state: recreated after density surgery)

    def add_param_group(self, param_group: dict) -> None:
        if param_group.get("weight_decay") or param_group.get("decoupled_weight_decay"):
            raise ValueError("OneLaunchAdam does not support weight decay")
        super().add_param_group(param_group)

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        buckets: dict = {}
        for group in self.param_groups:
            if torch.is_tensor(group["lr"]):
                raise ValueError("OneLaunchAdam needs a number as lr, not a tensor")
            params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps = [], [], [], [], [], []
            self._init_group(group, params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps)
            for i, p in enumerate(params):
                key = (p.device, p.dtype, *group["betas"], group["eps"], group["amsgrad"], group["maximize"])
                lists = buckets.setdefault(key, ([], [], [], [], [], [], []))
                lists[6].append(group["lr"])
                for dst, src in zip(lists, (params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps)):
                    if src:
                        dst.append(src[i])
        updates: dict = {}
        grad_scale = getattr(self, "grad_scale", None)
        found_inf = getattr(self, "found_inf", None)
        for (device, dtype, beta1, beta2, eps, amsgrad, maximize), lists in buckets.items():
            params, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, lrs = lists
            u = []
            for p in params:
                buf = self._updates.get(p)
                u.append(buf if buf is not None and buf.shape == p.shape else torch.empty_like(p))
                updates[p] = u[-1]
            skip = None if found_inf is None else found_inf.to(device)
            torch._foreach_zero_(u)
            torch._foreach_add_(steps, 1)
            torch._fused_adam_(u, grads, exp_avgs, exp_avg_sqs, max_exp_avg_sqs, steps, lr=1.0, beta1=beta1,
                               beta2=beta2, weight_decay=0.0, eps=eps, amsgrad=amsgrad, maximize=maximize,
                               grad_scale=None if grad_scale is None else grad_scale.to(device), found_inf=skip)
            if skip is not None:  # a list of the one tensor: a tensor scalar would be read on the host
                torch._foreach_sub_(steps, [skip] * len(steps))
            torch._foreach_mul_(u, lrs)
            torch._foreach_add_(params, u)
        self._updates = updates
        return loss
