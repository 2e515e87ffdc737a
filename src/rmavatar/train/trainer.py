"""The training loop: one frame per step, Adam with the paper's learning rates, density control on the
paper's (run-length-scaled) schedule, atomic checkpoints, exact resume, Ctrl-C and NaN safety.

:class:`Trainer` owns stepping and scheduling only; its parts each do one job: the frames
(:class:`rmavatar.train.frames.FrameCache`), the density controller, pose refinement (a strategy with
hooks, :mod:`rmavatar.train.pose_refine`), the reporter and the non-finite guard
(:mod:`rmavatar.train.report`). Code that drives steps itself (benchmarks, tests) calls ``setup()``, then
``step()`` as often as wanted, and ``save()``. ``rmavatar.train.train`` (:mod:`rmavatar.train.pipeline`)
runs whole trainings, fresh or resumed, in one pass or two.

A step makes no host synchronisation: the finiteness guard stays on the device, the fused Adam skips its
update when told a value was non-finite (``found_inf``, as under ``torch.amp.GradScaler``), and the
density statistics leave such a step out; the step's values are read once per logging interval.
Density control itself may sync (it is rare).
"""

from __future__ import annotations

import functools
import random
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from rmavatar.avatar.model import Avatar
from rmavatar.avatar.run import Checkpoint, RunFolder, body_info, load_saved_body, training_betas
from rmavatar.body import PoseSequence, smooth_poses
from rmavatar.data import Dataset
from rmavatar.render import rasterize
from rmavatar.train.checkpoint import capture_rng, restore_rng, save_checkpoint
from rmavatar.train.config import TrainConfig, to_dict
from rmavatar.train.density import live_optimizer_state
from rmavatar.train.frames import FRAME_CACHE_BYTES, FrameCache, FrameSampler, background_color, open_dataset
from rmavatar.train.graphs import StepGraphs
from rmavatar.train.pose_refine import PoseFiles, load_pose_state
from rmavatar.train.poses import pose_corrected
from rmavatar.train.report import NonFiniteGuard, Reporter, finite_flag
from rmavatar.utils import resolve_device
from rmavatar.utils.device import keep_freed_memory, set_threads


@dataclass
class TrainResult:
    iteration: int  # the last completed iteration
    interrupted: bool  # stopped by Ctrl-C (a checkpoint was written)
    run_dir: Path  # the run folder
    history: list[dict]  # one entry per progress report: iteration, loss, psnr, gaussians


class Trainer:
    """One training pass into ``run`` (a RunFolder). ``checkpoint``: a :class:`Checkpoint` to resume
    from, or None; ``on_iteration(iteration, total)`` is called after every iteration, once any
    checkpoint of it is written. After :meth:`setup`: ``dataset``, ``body``, ``avatar`` (training mode),
    ``optimizer``, ``density``, ``frames`` (FrameCache), ``sampler``, ``poses`` (the pose refinement
    strategy, or None), ``device``, ``iteration`` (steps done)."""

    def __init__(self, cfg: TrainConfig, run: RunFolder | str | Path, checkpoint: Checkpoint | None = None,
                 progress: bool = True, on_iteration: Callable[[int, int], None] | None = None,
                 dataset: Dataset | None = None):
        self.run_folder = run if isinstance(run, RunFolder) else RunFolder(run)
        self.cfg, self.ckpt, self.progress = cfg, checkpoint, progress
        self.on_iteration, self.dataset = on_iteration, dataset

    def setup(self) -> None:
        cfg, ckpt, where = self.cfg, self.ckpt, str(self.run_folder.checkpoint)
        if cfg.threads > 0:
            set_threads(cfg.threads)
        keep_freed_memory()
        self.dataset = self.dataset or open_dataset(cfg.data)
        split, estimated = cfg.data.split, self.dataset.poses_estimated
        params = self.dataset.params(split)
        self.device = resolve_device(cfg.device)
        self.body, self.body_info = load_body(cfg, self.dataset, ckpt, where)
        self.body.to(self.device)
        self.betas = training_betas(params) if self.body.num_betas > 0 else None  # the shape a trained avatar keeps
        poses = PoseSequence.from_params(params)
        if not cfg.data.hand_pose:
            poses.hand_pose = None
        if cfg.poses.refines(estimated):  # refinement starts from the smoothed poses
            poses = smooth_poses(poses, params["index"], cfg.poses.smooth)
        self.frames = FrameCache(self.dataset, split, self.body, self.device)
        self.pose_files = PoseFiles(self.dataset, split)
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        random.seed(cfg.seed)
        self.bg_generator = torch.Generator().manual_seed(cfg.seed + 1)
        self.sampler = FrameSampler(len(self.frames), cfg.seed)
        self.avatar = Avatar.from_state(self.body, ckpt.avatar, where) if ckpt else cfg.model.build(self.body, cfg.seed)
        self.avatar.to(self.device).train()
        self.optimizer = cfg.optim.build(self.avatar)
        self.density = cfg.density.build(self.avatar, self.optimizer, cfg.optim.iters, seed=cfg.seed)
        self.guard = NonFiniteGuard(self.device, cfg.log.max_bad_steps)
        self.graphs = StepGraphs(self.avatar, cfg.loss, cfg.cuda_graphs)
        self._pose_corrected = functools.partial(pose_corrected, self.body, self.avatar.pose_input)
        self.poses = None
        if cfg.poses.refines(estimated):
            held = cfg.poses.first_pass_iters(cfg.optim.iters, estimated) > 0  # the second of two passes
            self.poses = cfg.poses.build(poses, params["betas"] if self.body.num_betas > 0 else None, params["index"],
                                         cfg.optim.iters, self.device, held,
                                         self.density.schedule if cfg.density.enabled else None, self.progress)
        self.iteration = 0
        if ckpt is not None:
            self.optimizer.load_state_dict(ckpt.optimizer)
            self.density.load_state_dict(ckpt.density)
            self.sampler.load_state_dict(ckpt.sampler)
            restore_rng(ckpt.rng, self.bg_generator)
            load_pose_state(self.poses, ckpt.poses, where)
            self.iteration = int(ckpt.iteration)
            print(f"resuming {self.run_folder.path} from iteration {self.iteration} of {cfg.optim.iters}", flush=True)
        if cfg.density.enabled and (self.graphs.enabled if cfg.density.capacity is None else cfg.density.capacity):
            self.density.use_capacity()  # fixed shapes between density events: graphs stay captured
        if self.poses is not None:
            poses = self.poses.start_poses(poses, self.run_folder.pose_pass, split, ckpt is not None)
        self.frames.hold(poses, self.avatar.pose_input)
        self.ckpt = None  # free the loaded tensors
        self.frames.fill(self.avatar, cfg.background, bool(cfg.loss.lpips), self.bg_generator, FRAME_CACHE_BYTES,
                         cfg.loss.lpips_region, masks=bool(cfg.loss.mask))
        # A kill during a checkpoint write leaves only its temporary file behind (the old last.pt is intact).
        for stale in self.run_folder.checkpoint.parent.glob(".last.*.tmp.pt"):
            stale.unlink(missing_ok=True)

    def save(self) -> None:
        """The checkpoint (atomic) and, with refinement, RUN/poses.npz; for a synthetic subject with true
        poses, RUN/pose_error.json."""
        cfg, run = self.cfg, self.run_folder
        save_checkpoint(run.checkpoint, Checkpoint(
            iteration=self.iteration, config=to_dict(cfg), data_spec=cfg.data.path, body=self.body_info,
            betas=self.betas, avatar=self.avatar.checkpoint_state(),
            optimizer=live_optimizer_state(self.optimizer, self.avatar),
            density=self.density.state_dict(), sampler=self.sampler.state_dict(), rng=capture_rng(self.bg_generator),
            poses=None if self.poses is None else self.poses.state_dict(), saved_at=time.time()))
        self.pose_error = self.pose_files.write(run, self.iteration, self.poses)

    def step(self) -> dict:
        """One iteration, without a host sync (module docstring). Returns its values as tensors on the
        device: "ok" (bool: the loss and all gradients were finite, so the step was applied), "loss", each
        loss term, "image", "target"; and "frame", "lr_position", "events" (density control) as Python
        values. Does not advance ``iteration`` (the loop does: a skipped step still moves the schedules)."""
        cfg, it = self.cfg, self.iteration + 1
        lr = cfg.optim.position_lr(it - 1)
        for group in self.optimizer.param_groups:
            if group.get("name") == "position":
                group["lr"] = lr
        self.avatar.set_progress(it, cfg.optim.iters)
        i = self.sampler.next()
        bg = background_color(cfg.background, self.bg_generator, self.device)
        target = self.frames.target(i, bg)
        cam = self.frames.cameras[i]
        refined = None if self.poses is None else self.poses.frame_inputs(i, it)
        if refined is not None:  # the corrected body, posed in the same graph as the avatar
            posed = self.graphs.pose_body(self._pose_corrected, refined, cam.viewmat)
        else:
            posed = self.graphs.pose(*self.frames.held(i), cam.viewmat)  # rasterized eagerly in between
        image, alpha, info = rasterize(posed.means, posed.quats, posed.scales, posed.opacities, posed.colors,
                                       cam.viewmat, cam.K, cam.width, cam.height, background=bg, check=False)
        coverage = (alpha, self.frames.mask(i)) if cfg.loss.mask else None
        loss, parts = self.graphs.losses(image, target, posed, self.frames.lpips_units(i, bg),
                                         self.frames.lpips_window(i), coverage)
        loss.backward()
        grads = [p.grad for g in self.optimizer.param_groups for p in g["params"] if p.grad is not None]
        grads += [] if self.poses is None else self.poses.gradients()
        # checked on the device in one reduction with the loss and every gradient
        ok, bad = finite_flag(*posed[:5], loss, *grads)
        if self.optimizer.defaults.get("fused"):  # skips on the device, no sync
            self.optimizer.grad_scale, self.optimizer.found_inf = None, bad
            self.optimizer.step()
        elif bool(ok):  # an optimiser without device-side skipping: one sync
            self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if self.poses is not None:
            self.poses.after_step(i, it, ok)
        events = self.density.after_step(it, info, self.frames.width, self.frames.height, valid=ok)
        self.guard.update(bad)
        return {"ok": ok, "loss": loss.detach(), **parts, "frame": i, "lr_position": lr, "events": events,
                "image": image.detach(), "target": target}

    def frame_body(self, i: int, iteration: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Vertices [V,3], body_pose [69] and face table (or None: to be computed) of training frame ``i``
        at step ``iteration``: the held ones, or the pose refinement's corrected body."""
        corrected = None if self.poses is None else self.poses.frame_body(self._pose_corrected, i, iteration)
        return corrected or self.frames.held(i)

    def run(self) -> TrainResult:
        """Set up, train to ``cfg.optim.iters`` (saving on the way and at the end), return the result."""
        self.setup()
        cfg, total, started, start = self.cfg, self.cfg.optim.iters, time.perf_counter(), self.iteration
        headline = (f"training on {len(self.frames)} frames of {cfg.data.path} ({cfg.data.split}) at {self.frames.width}x"
                    f"{self.frames.height}, body {self.body_info['spec']}, {self.avatar.num_gaussians} Gaussians, "
                    f"{self.device}, {torch.get_num_threads()} threads -> {self.run_folder.path}")
        interrupted = False
        with Reporter(cfg.log, self.run_folder, total, start, self.progress, headline) as report, _Interrupt() as stop:
            while self.iteration < total:
                if self.poses is not None:  # after that iteration's checkpoint: a resume redoes it
                    held = self.poses.before_step(self.iteration, self.avatar, self.body, self.frames.frames(),
                                                  self.frames.fit_background(cfg.background))
                    if held is not None:
                        self.frames.hold(held, self.avatar.pose_input)
                out = self.step()
                self.iteration += 1
                report.step(self.iteration, out, self.avatar.num_gaussians, self.guard, self.save)
                if self.iteration % cfg.log.checkpoint_every == 0 and self.iteration < total:
                    self.save()
                if self.on_iteration:
                    self.on_iteration(self.iteration, total)
                if stop.requested:
                    interrupted = True
                    break
            self.save()
        if interrupted:
            print(f"interrupted at iteration {self.iteration}; checkpoint saved to {self.run_folder.checkpoint} "
                  f"(continue with --resume)")
        else:
            report.summary(self.iteration - start, time.perf_counter() - started, self.avatar.num_gaussians,
                           self.pose_error)
            if self.progress and self.device.type == "cuda":
                g = self.graphs
                failed = f", {len(g.failures)} failed to capture (first: {g.failures[0][1]})" if g.failures else ""
                print(f"CUDA graphs: {g.captures} captured in {g.capture_s:.1f} s{failed}" if g.enabled
                      else f"CUDA graphs off: {g.off_reason}")
        return TrainResult(self.iteration, interrupted, self.run_folder.path, report.history)


def load_body(cfg: TrainConfig, dataset, ckpt: Checkpoint | None, where: str):
    """(body model, what checkpoints keep of it): the checkpoint's, or the config's, else the dataset's
    preset and gender, else Anny; with the dataset's body offsets (a captured shape) where the body is
    the one the dataset names."""
    if ckpt is not None:
        return load_saved_body(ckpt.body, where, faces=ckpt.faces), ckpt.body
    gender = cfg.model.gender or dataset.gender
    body = dataset.body_model(cfg.model.body, gender)
    return body, body_info(body, gender)


class _Interrupt:
    """SIGINT (Ctrl-C) and SIGTERM set a flag the loop checks after each step, so the run saves and
    stops cleanly; a second signal raises KeyboardInterrupt as usual."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self):
        self.requested = False
        self._previous: dict = {}

    def __enter__(self):
        for sig in self.SIGNALS:
            try:
                self._previous[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not the main thread: leave signals alone
                pass
        return self

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc):
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        return False
