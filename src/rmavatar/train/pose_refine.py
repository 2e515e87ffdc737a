"""Pose refinement as a strategy the trainer calls through a few hooks (docs/train.md, "Pose refinement").

Estimated training poses (``rmavatar capture``'s) are off by a few degrees; an avatar trained on them is
blurred. With ``poses.refine`` every training frame gets a learnable correction
(:class:`rmavatar.train.poses.PoseRefiner`): a step poses its frame's corrected body, so the image loss
reaches the correction through the body model. At the fractions ``poses.fits`` of the run every training
pose is *fitted* to its image with the avatar held still (:func:`rmavatar.evaluate.fit.fit_poses`), since
a frame's correction otherwise moves only on the ~1 in n steps that sample it.

Two passes (``poses.first_pass``): a first run of that fraction of the iterations refines the poses (in
RUN/pose_pass, a run folder of its own); then the avatar is trained afresh on those poses, *held*
(``held=True``: no per-step corrections; with ``poses.smooth_held`` first averaged over neighbouring
frames, as the given poses are), fitting them again at ``poses.held_fits`` of the second pass (by
default three fits, five in a run long enough that they cost little: :meth:`PoseConfig.held_fit_fractions`),
each fit's prior pulling every joint toward its neighbouring frames' average (``poses.held_fit_anchor``).

The trainer's hooks, in the order it calls them: :meth:`PoseRefinement.start_poses` (the poses the held
bodies start from), :meth:`before_step` (a pose fit when one is due; returns poses to hold),
:meth:`frame_body` (a step's corrected body, or None: the held one), :meth:`gradients` (for the
finiteness guard), :meth:`after_step` (the corrections' Adam), :meth:`state_dict` /
:meth:`load_state_dict`; :class:`PoseFiles` writes RUN/poses.npz with each checkpoint.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import torch

from rmavatar.avatar.run import RunFolder
from rmavatar.body import PoseSequence, pose_error, smooth_poses
from rmavatar.evaluate.fit import PoseFitConfig, fit_poses, pixel_blocks
from rmavatar.train.optim import position_lr
from rmavatar.train.poses import PoseRefiner, read_poses, write_poses
from rmavatar.utils import UserError, atomic_path
from rmavatar.utils.config import check_fields


# The held fits by default (``poses.held_fits: null``): three, or five where the run is long enough that
# five cost at most 5/3 fitting frame-steps per training iteration (docs/train.md, "The defaults of
# version 8"): the later fits close part of the gap to the true-pose avatar that grows with the run.
SHORT_HELD_FITS = (0.25, 0.6, 0.85)
LONG_HELD_FITS = (0.2, 0.4, 0.6, 0.8, 0.95)
LONG_RUN_ITERS_PER_FIT_STEP = 3  # a run is long from this many iterations per frame-step of one held fit
HELD_FIT_ANCHORS = ("neighbours", "start")  # what a held fit's prior pulls the joint rotations toward


@dataclass
class PoseConfig:
    """Pose refinement (``TrainConfig.poses``): per-frame corrections of the training poses.
    ``build`` makes the :class:`PoseRefinement` strategy; the measurements behind each default are in
    docs/train.md."""

    refine: bool | None = None  # refine the training poses; None = when the dataset's poses are estimated
    first_pass: float = 0.1  # a first pass of this fraction of optim.iters refines the poses; 0 = one pass
    # --- advanced ---
    first_pass_scale: float = 1.0  # the first pass trains and fits at this fraction of the image size (>= 32 px)
    smooth: int = 2  # first average the given poses over +-this many video frames (tracker jitter); 0 = off
    smooth_held: bool = True  # the second pass starts from the first pass's poses averaged the same way
    warmup: float = 0.1  # fraction of a refining pass with frozen corrections (the avatar takes shape first)
    lr_rotation: float = 2e-2  # per-step corrections: radians per Adam step
    lr_translation: float = 5e-4  # per-step corrections: metres per Adam step
    lr_final_scale: float = 0.1  # both decay log-linearly to this fraction at the pass's last iteration
    fits: tuple[float, ...] = (0.9,)  # fractions of a refining pass at which every training pose is fitted
    fit_steps: int = 20  # Adam steps per frame in those fits
    fit_lr_rotation: float = 2e-2  # their rotation learning rate (radians per step)
    fit_lr_translation: float = 5e-4  # their translation learning rate (metres per step)
    fit_mask: float = 0.0  # weight of the alpha-vs-mask term in every pose fit; 0 = the images only
    held_fits: tuple[float, ...] | None = None  # fractions of the second pass (poses held) at which they are refitted; None: 3 or 5 by length
    held_fit_steps: int = 20  # Adam steps per frame in those fits
    held_fit_lr_rotation: float = 5e-3  # their rotation learning rate: lower, the poses are nearly right
    held_fit_lr_translation: float = 1.25e-4  # their translation learning rate
    held_fit_scales: tuple[int, ...] = (1,)  # their coarse-to-fine pixel blocks (PoseFitConfig.scales)
    held_fit_prior: float = 0.1  # their prior: weight (per rad^2) of each joint rotation's pull toward the anchor
    held_fit_anchor: str = "neighbours"  # the anchor: the fit's start averaged over +-smooth frames, or "start"

    def validate(self) -> "PoseConfig":
        check_fields(self, "poses", positive=("lr_final_scale", "held_fit_lr_rotation"),
                     nonnegative=("smooth", "lr_rotation", "lr_translation", "fit_lr_rotation",
                                  "fit_lr_translation", "fit_mask", "held_fit_lr_translation", "held_fit_prior"),
                     at_least_one=("fit_steps", "held_fit_steps"))
        if self.lr_final_scale > 1:
            raise UserError(f"poses.lr_final_scale must be in (0, 1], got {self.lr_final_scale}")
        if not 0 <= self.warmup < 1:
            raise UserError(f"poses.warmup must be in [0, 1), got {self.warmup}")
        for name in ("fits", "held_fits"):
            value = getattr(self, name)
            if value is None and name == "held_fits":
                continue
            bad = not isinstance(value, (list, tuple)) or any(
                isinstance(f, bool) or not isinstance(f, (int, float)) for f in value)
            if bad or any(not 0 < f < 1 for f in value):
                raise UserError(f"poses.{name} must be fractions of the run in (0, 1), got {value!r}")
            setattr(self, name, tuple(float(f) for f in value))
        self.held_fit_scales = pixel_blocks(self.held_fit_scales, "poses.held_fit_scales")
        if self.held_fit_anchor not in HELD_FIT_ANCHORS:
            raise UserError(f"poses.held_fit_anchor must be one of {', '.join(HELD_FIT_ANCHORS)}, "
                            f"got {self.held_fit_anchor!r}")
        scale = self.first_pass_scale
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 < scale <= 1:
            raise UserError(f"poses.first_pass_scale must be a fraction of the image size in (0, 1], got {scale!r}")
        f = self.first_pass
        if isinstance(f, bool) or not isinstance(f, (int, float)) or not 0 <= f <= 1:
            raise UserError(f"poses.first_pass must be a fraction of optim.iters in [0, 1], got {f!r}")
        return self

    def refines(self, poses_estimated: bool) -> bool:
        """Whether a run refines its training poses, for a dataset whose poses are (not) estimated."""
        return bool(poses_estimated) if self.refine is None else self.refine

    def first_pass_iters(self, iters: int, poses_estimated: bool) -> int:
        """Iterations of the first pass that comes before a run of ``iters``; 0 = none (one pass)."""
        if not self.refines(poses_estimated) or self.first_pass == 0:
            return 0
        return max(1, round(self.first_pass * iters))

    def first_pass_size(self, image_size: tuple[int, int]) -> int | None:
        """The first pass's ``data.size`` (its longer side, at least 32 px, LPIPS's least) for frames of
        ``image_size`` (width, height) at the run's size; None: the run's own size."""
        if self.first_pass_scale == 1:
            return None
        return min(max(image_size), max(32, round(self.first_pass_scale * max(image_size))))

    def warmup_steps(self, iters: int) -> int:
        """Steps with frozen corrections; refinement starts at step ``warmup_steps(iters) + 1``."""
        return round(self.warmup * iters)

    def lr_scale(self, iteration: int, iters: int) -> float:
        """The corrections' lr factor before step ``iteration + 1`` of ``iters``: 0 during the warm-up,
        then a log-linear decay from 1 to ``lr_final_scale`` at the last iteration."""
        start = self.warmup_steps(iters)
        if iteration < start:
            return 0.0
        return position_lr(iteration - start, iters - start, 1.0, self.lr_final_scale)

    def held_fit_fractions(self, iters: int, frames: int) -> tuple[float, ...]:
        """The fractions of a second pass of ``iters`` over ``frames`` training frames at which its poses
        are refitted: ``held_fits``, or where that is None :data:`LONG_HELD_FITS` when ``iters`` is at
        least ``LONG_RUN_ITERS_PER_FIT_STEP * held_fit_steps * frames`` (6,000 for 100 frames at 20
        steps), else :data:`SHORT_HELD_FITS`."""
        if self.held_fits is not None:
            return self.held_fits
        long = iters >= LONG_RUN_ITERS_PER_FIT_STEP * self.held_fit_steps * frames
        return LONG_HELD_FITS if long else SHORT_HELD_FITS

    def fit_iterations(self, iters: int, frames: int, schedule=None, held: bool = False) -> set[int]:
        """The iteration counts after which the ``frames`` training poses are fitted (before the next
        step): at ``fits`` (:meth:`held_fit_fractions` when ``held``) of a run of ``iters`` (at most
        ``iters - 1``, the last before which a fit can run), each that falls on an opacity reset of
        ``schedule`` (a density DensitySchedule; None: no density control) one earlier: right after a
        reset the avatar is nearly invisible and fitting to its renders learns little (docs/train.md)."""
        on_reset = (lambda s: False) if schedule is None else schedule.reset_at
        fractions = self.held_fit_fractions(iters, frames) if held else self.fits
        # a fit comes before a step, so one that rounds to the last iteration runs before it instead
        planned = (min(max(1, round(f * iters)), max(1, iters - 1)) for f in fractions)
        return {s - 1 if s > 1 and on_reset(s) else s for s in planned}

    def fit_config(self, held: bool):
        """The :class:`rmavatar.evaluate.fit.PoseFitConfig` of this pass's pose fits."""
        if held:
            return PoseFitConfig(steps=self.held_fit_steps, silhouette=self.fit_mask, scales=self.held_fit_scales,
                                 lr_rotation=self.held_fit_lr_rotation, lr_translation=self.held_fit_lr_translation,
                                 prior=self.held_fit_prior)
        return PoseFitConfig(steps=self.fit_steps, silhouette=self.fit_mask, lr_rotation=self.fit_lr_rotation,
                             lr_translation=self.fit_lr_translation)

    def held_anchor(self, poses: PoseSequence, frame_ids) -> PoseSequence | None:
        """What a held fit starting from ``poses`` (frame numbers ``frame_ids``) pulls the joints toward:
        their average over +-``smooth`` frames, or None (their start) with ``held_fit_anchor`` "start"."""
        return smooth_poses(poses, frame_ids, self.smooth) if self.held_fit_anchor == "neighbours" else None

    def build(self, poses: PoseSequence, betas, frame_ids, iters: int, device, held: bool, schedule=None,
              progress: bool = True) -> "PoseRefinement":
        """The strategy for a pass of ``iters`` over the training ``poses`` (betas [n,nb] or None;
        frame_ids [n]: each pose's frame number in its video, for the averages over neighbours);
        ``held``: the second of two passes; ``schedule``: the density schedule (fits avoid its resets)."""
        return PoseRefinement(self, PoseRefiner(poses, betas, self, iters, device, frozen=held), frame_ids,
                              self.fit_iterations(iters, len(poses), schedule, held), progress)


class PoseRefinement:
    """The strategy :meth:`PoseConfig.build` makes; ``refiner`` holds the corrections and their Adam."""

    def __init__(self, cfg: PoseConfig, refiner: PoseRefiner, frame_ids, fit_at: set[int], progress: bool):
        self.cfg, self.refiner, self.frame_ids, self.fit_at, self.progress = cfg, refiner, frame_ids, fit_at, progress

    @property
    def held(self) -> bool:
        return self.refiner.frozen

    def start_poses(self, given: PoseSequence, first_pass: RunFolder, split: str, resumed: bool) -> PoseSequence:
        """The poses the held bodies start from: a fresh second pass takes the first pass's result
        (averaged over +-``smooth`` frames with ``smooth_held``)."""
        if self.held and not resumed:
            poses = read_poses(first_pass.poses, self.frame_ids, split)
            if self.cfg.smooth_held:
                poses = smooth_poses(poses, self.frame_ids, self.cfg.smooth)
            self.refiner.set_poses(poses)
        return self.refiner.poses() if self.held else given

    def before_step(self, iteration: int, avatar, body, frames, background: torch.Tensor) -> PoseSequence | None:
        """A pose fit when one is due after ``iteration``: every training frame's corrected pose fitted to
        its image (``frames``, composited over ``background``) with the avatar held, then made its new
        corrected pose. Returns the poses to hold (second pass), else None."""
        if iteration not in self.fit_at:
            return None
        n = len(self.refiner)
        if self.progress:
            what = "held pose fit" if self.held else "pose fit"
            steps = self.cfg.held_fit_steps if self.held else self.cfg.fit_steps
            print(f"{what} after iteration {iteration}: fitting the {n} training poses ({steps} steps each)",
                  flush=True)
        poses = self.refiner.poses()
        anchor = self.cfg.held_anchor(poses, self.frame_ids) if self.held else None
        fitted = fit_poses(avatar, body, poses, self.refiner.betas, frames, background,
                           self.cfg.fit_config(self.held), progress=self.progress, anchor=anchor)
        self.refiner.set_poses(fitted)
        return self.refiner.poses() if self.held else None

    def frame_body(self, posed_body, i: int, iteration: int):
        """Frame ``i``'s corrected body (vertices [V,3], the rectifier's pose input, None) at step
        ``iteration``, or None while the corrections are not trained (warm-up, second pass): then the held
        body is used. ``posed_body``: :func:`rmavatar.train.poses.pose_corrected` with its body and the
        avatar's pose input bound."""
        if not self.refiner.active(iteration):
            return None
        return (*posed_body(*self.refiner.frame_inputs(i)), None)

    def frame_inputs(self, i: int, iteration: int) -> tuple[torch.Tensor, ...] | None:
        """What :func:`rmavatar.train.poses.pose_corrected` takes to pose frame ``i``'s corrected body at
        step ``iteration`` (a training step runs it in one graph with the avatar's posing), or None as
        :meth:`frame_body`."""
        return self.refiner.frame_inputs(i) if self.refiner.active(iteration) else None

    def gradients(self) -> list[torch.Tensor]:
        grad = self.refiner.delta.grad
        return [] if grad is None else [grad]

    def after_step(self, i: int, iteration: int, ok: torch.Tensor) -> None:
        self.refiner.step(i, iteration, ok)

    def state_dict(self) -> dict:
        return self.refiner.state_dict()

    def load_state_dict(self, state: dict | None, where: str) -> None:
        if state is None:
            raise UserError(f"{where}: the run was trained without pose refinement, but its config now refines "
                            "the poses (did the dataset's meta.yaml 'poses:' change?); start a new run")
        self.refiner.load_state_dict(state, where)

    def poses(self) -> PoseSequence:
        """The corrected poses of every training frame (on the CPU)."""
        return self.refiner.poses()


def load_pose_state(refinement: PoseRefinement | None, state: dict | None, where: str) -> None:
    """Resume ``refinement`` (None: the run does not refine) from a checkpoint's pose ``state``."""
    if refinement is not None:
        refinement.load_state_dict(state, where)
    elif state is not None:
        raise UserError(f"{where}: the run was trained with pose refinement, but its config now does not refine "
                        "the poses (did the dataset's meta.yaml 'poses:' change?); start a new run")


class PoseFiles:
    """The pose files a run writes with each checkpoint: RUN/poses.npz (the refined training poses) and,
    for a synthetic subject with true poses, RUN/pose_error.json (the given and the refined poses'
    errors). The true poses are read once, when made, so a broken file is found before training."""

    def __init__(self, dataset, split: str):
        from rmavatar.data.synth import true_poses

        params = dataset.params(split)
        self.split, self.index = split, params["index"]
        self.given = PoseSequence.from_params(params)
        self.true = true_poses(dataset, split)

    def write(self, run: RunFolder, iteration: int, refinement: PoseRefinement | None) -> dict | None:
        """Both files (atomic) as of ``iteration``; returns what pose_error.json holds (None: not written)."""
        refined = None if refinement is None else refinement.poses()
        if refined is not None:
            write_poses(run.poses, refined, self.index, self.split)
        if self.true is None:
            return None
        report = {
            "iteration": iteration, "split": self.split,
            "measure": "mean over frames and the 24 joints (global orientation + 23 body joints) of the "
                       "geodesic angle to the true rotation; translation: mean distance",
            "given": pose_error(self.given, self.true),
            "refined": None if refined is None else pose_error(refined, self.true),
        }  # fmt: skip
        with atomic_path(run.pose_error) as tmp:
            tmp.write_text(json.dumps(report, indent=2) + "\n")
        return report
