"""The training loop: one frame per step, Adam with the paper's learning rates, density control on the
paper's (run-length-scaled) schedule, atomic checkpoints, exact resume, Ctrl-C and NaN safety.

``train(cfg, run_dir)`` runs it; :class:`Trainer` is the loop itself, for code that drives steps
(benchmarks, tests): ``setup()``, then ``step()`` as often as wanted, ``target(i, bg)`` for a frame's
ground truth, ``save()``.

The posed body of every training frame is computed once, up front, in batches, and so are (while they
fit in ``FRAME_CACHE_BYTES``) each frame's face table (the mesh half of posing the Gaussians) and, with a
fixed background, its composited target and the target's LPIPS features; a step then only runs
avatar -> rasterizer -> losses. With pose refinement (``optim.refine_poses``, :mod:`rmavatar.train.poses`)
a step past its warm-up poses its frame's corrected body instead, through :meth:`Trainer.frame_body`.
"""

from __future__ import annotations

import json
import math
import random
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from rmavatar.avatar.model import FACE_TABLE, Avatar
from rmavatar.avatar.trained import (
    body_signature,
    check_body,
    checkpoint_path,
    read_checkpoint,
    training_betas,
)
from rmavatar.body import PoseSequence, load_body_model, posed_vertices, smooth_poses
from rmavatar.data import Dataset, load_dataset
from rmavatar.data.registry import parse_spec
from rmavatar.render.gaussians import render_gaussians
from rmavatar.train.checkpoint import (
    capture_rng,
    prepare_run_dir,
    restore_rng,
    save_checkpoint,
)
from rmavatar.train.config import TrainConfig, config_differences, from_dict, save_config, to_dict
from rmavatar.train.losses import lpips_units, total_loss
from rmavatar.train.poses import PoseRefiner, read_poses, write_poses
from rmavatar.data.checks import check_files
from rmavatar.utils import UserError, atomic_path, check_writable_folder, resolve_device
from rmavatar.utils.config import read_yaml
from rmavatar.utils.device import constant


# ----------------------------------------------------------------------------------------------- small parts
def normalize_data_spec(spec: str) -> str:
    """The dataset spec with its path made absolute, so a run remembers its data from any folder."""
    kind, path, options = parse_spec(str(spec))
    query = "&".join(f"{k}={v}" for k, v in options.items())
    return f"{kind + ':' if kind else ''}{path.resolve()}{'?' + query if query else ''}"


class FrameSampler:
    """Seeded shuffling, one frame per step: epoch e visits permutation(seed, e) in order.

    Its whole state is (epoch, position), so a checkpoint can store and restore it exactly.
    """

    def __init__(self, num_frames: int, seed: int):
        if num_frames < 1:
            raise UserError("the training split has no frames")
        self.num_frames = num_frames
        self.seed = seed
        self.epoch = 0
        self.position = 0
        self._perm = self._permutation(0)

    def _permutation(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(self.num_frames)

    def next(self) -> int:
        if self.position >= self.num_frames:
            self.epoch += 1
            self.position = 0
            self._perm = self._permutation(self.epoch)
        i = int(self._perm[self.position])
        self.position += 1
        return i

    def state_dict(self) -> dict:
        return {"epoch": self.epoch, "position": self.position, "num_frames": self.num_frames, "seed": self.seed}

    def load_state_dict(self, state: dict) -> None:
        if state["num_frames"] != self.num_frames:
            raise UserError(f"the checkpoint was trained on {state['num_frames']} frames, "
                            f"the dataset now has {self.num_frames}")
        self.seed = state["seed"]
        self.epoch = state["epoch"]
        self.position = state["position"]
        self._perm = self._permutation(self.epoch)


def background_color(kind: str, generator: torch.Generator, device: torch.device | str = "cpu") -> torch.Tensor:
    """Background [3] on ``device`` for one step: white, black (shared read-only constants, not made and
    uploaded every step), or a random colour per step (drawn from ``generator``, on the CPU)."""
    if kind == "white":
        return constant((1.0, 1.0, 1.0), torch.float32, device)
    if kind == "black":
        return constant((0.0, 0.0, 0.0), torch.float32, device)
    return torch.rand(3, generator=generator).to(device, non_blocking=True)


def composite_target(image: torch.Tensor, mask: torch.Tensor, bg: torch.Tensor) -> torch.Tensor:
    """target = image * mask + bg * (1 - mask); image [H,W,3], mask [H,W], bg [3] -> [H,W,3].

    As one lerp (bg + mask (image - bg), exact where the mask is 0 or 1) rather than four operations."""
    return torch.lerp(bg, image, mask.unsqueeze(-1))


def resolve_body(cfg: TrainConfig, dataset) -> tuple[str, str | None]:
    """(body spec, gender): the config's choice, else the dataset's preset, else anny with its gender."""
    spec = cfg.model.body or getattr(dataset, "body", None) or "anny"
    gender = cfg.model.gender or getattr(dataset, "gender", None)
    return spec, gender


def set_threads(n: int) -> None:
    """Use ``n`` CPU threads in torch and in the Numba rasterizer kernels."""
    import numba

    torch.set_num_threads(n)
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


def keep_freed_memory() -> None:
    """Let glibc keep freed heap memory for reuse instead of returning it to the OS.

    A CPU step allocates and frees tens of MB of tensors; by default glibc serves the large ones with
    fresh mmaps and trims the heap after frees, so every step pays page faults that zero the memory
    again. Measured at 64x64: 5.8 s of 31 s in the kernel, 19 s instead of 27 s per 60 iterations with
    this (peak RSS +7%). No-op where glibc's mallopt is not available.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    mallopt(M_MMAP_THRESHOLD, 32 * 2**20)  # glibc's largest allowed value on 64-bit
    mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    mallopt(M_TOP_PAD, 256 * 2**20)


# ----------------------------------------------------------------------------------------------- training
@dataclass
class TrainResult:
    iteration: int  # the last completed iteration
    interrupted: bool  # stopped by Ctrl-C (a checkpoint was written)
    run_dir: Path
    history: list[dict]  # one entry per progress report: iteration, loss, psnr, gaussians


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


# A resumed run whose config lacks a setting was trained without it: these values keep it that way.
_BEFORE_THE_SETTING = {"optim": {"smooth_poses": 0, "pose_sweeps": (), "pose_pass": 0.0, "pose_refits": (),
                                 "pose_fit_mask": 1.0}}


def _as_trained(saved: dict) -> dict:
    """A run's saved config (a checkpoint's or RUN/config.yaml's, as a dict) with each setting newer than
    the run filled in with the value that reproduces how it was trained (``_BEFORE_THE_SETTING``)."""
    for section, values in _BEFORE_THE_SETTING.items():
        old = {k: v for k, v in values.items() if k not in saved.get(section, {})}
        saved = {**saved, section: {**saved.get(section, {}), **old}}
    return saved


# The first pass of a two-pass run (optim.pose_pass) is a run of its own in this folder of RUN.
POSE_PASS = "pose_pass"


def train(
    cfg: TrainConfig | None,
    run_dir: str | Path,
    *,
    resume: bool = False,
    data: str | None = None,
    overrides: list | None = None,
    progress: bool = True,
    on_iteration: Callable[[int, int], None] | None = None,
) -> TrainResult:
    """Train an avatar into ``run_dir``.

    Fresh run: ``cfg`` is the full config. Resume: ``cfg`` is None, the run's checkpoint supplies the
    config; ``data`` (if given) must name the same dataset; ``overrides`` [(value, section, key)] may
    change only the run length, logging, threads and device, anything else that differs is an error.
    ``on_iteration(iteration, total)`` is called after every iteration, once any checkpoint of that
    iteration is written (``rmavatar batch`` reports progress with it).
    """
    return _train(cfg, Path(run_dir), resume, data, overrides, progress, on_iteration)


def _train(cfg: TrainConfig | None, run_dir: Path, resume: bool, data: str | None, overrides: list | None,
           progress: bool, on_iteration, dataset: Dataset | None = None, ckpt: dict | None = None) -> TrainResult:
    """:func:`train`; a two-pass run's first pass is given the second's opened ``dataset`` (the same
    data, its frames already read and checked) and, resumed, its checkpoint ``ckpt`` as read already."""
    check_writable_folder(run_dir / "config.yaml", f"--out {run_dir}", create=True)
    in_pose_pass = (resume and not checkpoint_path(run_dir).is_file()
                    and checkpoint_path(run_dir / POSE_PASS).is_file())
    if in_pose_pass:  # stopped in the first pass of two: that pass resumes, then the second starts
        path = run_dir / "config.yaml"
        ckpt, cfg = None, from_dict(TrainConfig, _as_trained(read_yaml(path)), where=str(path))
        _check_resume_data(run_dir, data, cfg.data.path)
        _apply_resume_overrides(cfg, overrides or [])
        cfg.validate()
    elif resume:
        ckpt = ckpt or _resume_payload(run_dir, data)
        cfg = from_dict(TrainConfig, _as_trained(ckpt["config"]), where=f"{checkpoint_path(run_dir)}:config")
        _apply_resume_overrides(cfg, overrides or [])
        cfg.validate()
        if cfg.optim.iters < int(ckpt["iteration"]):
            raise UserError(f"--iters {cfg.optim.iters} is below the {ckpt['iteration']} iterations {run_dir} has "
                            "done: give more to continue it (or start a new run)")
    else:
        if cfg is None:
            raise ValueError("train() needs a config for a fresh run")
        cfg = from_dict(TrainConfig, to_dict(cfg)).validate()  # a private copy
        if not cfg.data.path:
            raise UserError("no dataset given (data.path is empty)")
        cfg.data.path = normalize_data_spec(cfg.data.path)
    # Open the dataset and read every training frame's files before RUN is touched, so a wrong path or a
    # broken frame leaves nothing behind and is not found hours in.
    if dataset is None:
        dataset = _open_dataset(cfg)
        check_files(dataset, [cfg.data.split], progress=progress)
    first, first_ckpt = _first_pass(cfg, run_dir, dataset.poses_estimated) if ckpt is None else (None, None)
    done = 0 if first_ckpt is None else int(first_ckpt["iteration"])
    prepare_run_dir(run_dir, cfg.data.path, resume and not in_pose_pass)
    save_config(cfg, run_dir / "config.yaml")
    if first is not None and done < first.optim.iters:
        where = run_dir / POSE_PASS
        if progress:
            print(f"pose pass: {first.optim.iters} iterations refine the training poses ({where}), then the "
                  f"avatar is trained afresh on them for {cfg.optim.iters}", flush=True)
        if done:
            keep = [o for o in overrides or [] if (o[1], o[2]) != ("optim", "iters")]  # its length is its own
            result = _train(None, where, True, None, keep, progress, on_iteration, dataset, first_ckpt)
        else:
            result = _train(first, where, False, None, None, progress, on_iteration, dataset)
        if result.interrupted:
            return result
    return Trainer(cfg, run_dir, ckpt, progress, on_iteration, dataset=dataset).run()


def _open_dataset(cfg: TrainConfig) -> Dataset:
    """The training dataset, keeping every decoded training frame (image + mask, float32) in memory
    when that fits in 6 GB: re-reading large PNGs each step would cost more than a GPU step."""
    dataset = load_dataset(cfg.data.path, size=cfg.data.size)
    w, h = dataset.image_size
    dataset.reserve_cache(min(dataset.num_frames(cfg.data.split) * w * h * 16 / 2**20 + 64, 6144))
    return dataset


def _first_pass(cfg: TrainConfig, run_dir: Path, poses_estimated: bool) -> tuple[TrainConfig | None, dict | None]:
    """The config of the first pass of a two-pass run (``optim.pose_pass``; None: one pass) and its
    checkpoint (None: not begun): a run of its own in RUN/pose_pass that refines the training poses (with
    the sweeps); the second pass trains the avatar afresh on the poses it leaves in RUN/pose_pass/poses.npz.
    A first pass already there (stopped, or done) must have been trained with the same settings; its
    length is its own."""
    iters = cfg.optim.pose_pass_iters(poses_estimated)
    if not iters:
        return None, None
    first = from_dict(TrainConfig, to_dict(cfg))
    first.optim.iters, first.optim.pose_pass, first.optim.pose_refits = iters, 0.0, ()
    where = checkpoint_path(run_dir / POSE_PASS)
    if not where.is_file():
        return first, None
    payload = read_checkpoint(where)
    saved = _as_trained(payload["config"])
    differ = config_differences(saved, first, ignore=("optim.pose_refits", "optim.pose_refit_lr",
                                                          "optim.pose_refit_steps"))  # not the first's
    if differ:
        raise UserError(f"{run_dir / POSE_PASS} holds a first pass trained with other settings than this "
                        f"run's ({', '.join(differ[:6])}); choose another folder")
    first.optim.iters = int(saved["optim"]["iters"])
    return first, payload


def _resume_payload(run_dir: Path, data: str | None) -> dict:
    path = checkpoint_path(run_dir)
    if not path.is_file():
        raise UserError(f"--resume: {run_dir} has no checkpoint ({path} missing)")
    payload = read_checkpoint(path)
    _check_resume_data(run_dir, data, payload["data_spec"])
    return payload


def _check_resume_data(run_dir: Path, data: str | None, trained_on: str) -> None:
    """``--data`` given with ``--resume`` must name the dataset the run was trained on."""
    if data is not None and normalize_data_spec(data) != trained_on:
        raise UserError(f"--resume: {run_dir} is a run of {trained_on!r}, not of {normalize_data_spec(data)!r}")


# Per-frame constants kept on the device for the whole run, while all of them together fit in this many
# bytes (filled in this order, each kind for every frame or not at all): face tables, composited targets,
# the targets' LPIPS features. Each saves a step dozens of tensor operations (GPU kernel launches).
FRAME_CACHE_BYTES = 2 * 2**30

_RESUME_CHANGEABLE = {("optim", "iters"), ("log", "checkpoint_every"), (None, "threads"), (None, "device")}


def _apply_resume_overrides(cfg: TrainConfig, overrides: list) -> None:
    for value, section, key in overrides:
        target = getattr(cfg, section) if section else cfg
        if (section, key) in _RESUME_CHANGEABLE:
            setattr(target, key, value)
        elif getattr(target, key) != value:
            name = f"{section}.{key}" if section else key
            raise UserError(f"--resume keeps the run's config: {name} is {getattr(target, key)!r} there, "
                            f"cannot change it to {value!r} (start a new run instead)")


class Trainer:
    """One training run. ``checkpoint``: a payload from :func:`read_checkpoint` to resume from, or None;
    ``on_iteration(iteration, total)`` is called after every iteration, once any checkpoint of it is written.

    After :meth:`setup`: ``dataset``, ``body``, ``avatar`` (training mode), ``optimizer``, ``density``,
    ``vertices`` [n,V,3] / ``body_pose`` [n,69] / ``viewmats`` [n,4,4] / ``Ks`` [n,3,3] of the training
    frames (on ``device``), ``width``/``height``, ``iteration`` (steps done).
    """

    def __init__(self, cfg: TrainConfig, run_dir: Path, checkpoint: dict | None = None, progress: bool = True,
                 on_iteration: Callable[[int, int], None] | None = None, dataset: Dataset | None = None):
        self.cfg = cfg
        self.dataset = dataset
        self.run_dir = run_dir
        self.ckpt = checkpoint
        self.progress = progress
        self.on_iteration = on_iteration

    # --- setup --------------------------------------------------------------------------------
    def setup(self) -> None:
        cfg = self.cfg
        if cfg.threads > 0:
            set_threads(cfg.threads)
        keep_freed_memory()
        if self.dataset is None:
            self.dataset = _open_dataset(cfg)
        split = cfg.data.split
        n = self.dataset.num_frames(split)
        params = self.dataset.params(split)
        spec, gender = resolve_body(cfg, self.dataset)
        if self.ckpt is not None:
            saved = self.ckpt["body"]
            spec, gender = saved["spec"], saved.get("gender")
        self.body = load_body_model(spec, gender=gender)
        if self.ckpt is not None:
            check_body(self.ckpt["body"], self.body, str(checkpoint_path(self.run_dir)))
        self.body_info = {**body_signature(self.body), "gender": gender}
        self.betas = training_betas(params) if self.body.num_betas > 0 else None  # the shape a trained avatar keeps
        self.device = resolve_device(cfg.device)
        dev = self.device
        self.body.to(dev)
        poses = PoseSequence.from_arrays(params["global_orient"], params["body_pose"], params["transl"])
        if cfg.optim.refines_poses(self.dataset.poses_estimated):  # refinement starts from the smoothed poses
            poses = smooth_poses(poses, params["index"], cfg.optim.smooth_poses)
        cams = [self.dataset.camera(split, i) for i in range(n)]
        self.viewmats = torch.as_tensor(np.stack([c.viewmat for c in cams]), dtype=torch.float32, device=dev)
        self.Ks = torch.as_tensor(np.stack([c.K for c in cams]), dtype=torch.float32, device=dev)
        self.width, self.height = cams[0].width, cams[0].height
        self._setup_poses(params, poses)

        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed % 2**32)
        random.seed(cfg.seed)
        self.bg_generator = torch.Generator().manual_seed(cfg.seed + 1)
        self.sampler = FrameSampler(n, cfg.seed)

        if self.ckpt is not None:
            self.avatar = Avatar.from_state(self.body, self.ckpt["avatar"], where=str(checkpoint_path(self.run_dir)))
        else:
            self.avatar = cfg.model.build(self.body, seed=cfg.seed)
        self.avatar.to(dev)
        self.avatar.train()
        self.optimizer = cfg.optim.build(self.avatar)
        self.density = cfg.density.build(self.avatar, self.optimizer, cfg.optim.iters, seed=cfg.seed)
        self._guard = _NonFiniteGuard(dev, cfg.log.max_bad_steps)
        self.iteration = 0
        if self.ckpt is not None:
            self.optimizer.load_state_dict(self.ckpt["optimizer"])
            self.density.load_state_dict(self.ckpt["density"])
            self.sampler.load_state_dict(self.ckpt["sampler"])
            restore_rng(self.ckpt["rng"], self.bg_generator)
            self._resume_poses(self.ckpt["poses"])
            self.iteration = int(self.ckpt["iteration"])
            print(f"resuming {self.run_dir} from iteration {self.iteration} of {cfg.optim.iters}", flush=True)
        elif self.poses is not None and self.poses.frozen:  # the second pass starts from the first's poses
            self.poses.set_poses(read_poses(self.run_dir / POSE_PASS / "poses.npz", params["index"], split))
        self._hold_poses(poses if self.poses is None or not self.poses.frozen else self.poses.poses())
        self.ckpt = None  # free the loaded tensors
        self._cache_frames(FRAME_CACHE_BYTES)
        # A kill during a checkpoint write leaves only its temporary file behind (the old last.pt is intact).
        for stale in checkpoint_path(self.run_dir).parent.glob(".last.*.tmp.pt"):
            stale.unlink(missing_ok=True)

    def _hold_poses(self, poses: PoseSequence) -> None:
        """Pose the training frames' bodies once: ``vertices`` [n,V,3] and ``body_pose`` [n,69], what
        every step without per-step refinement uses, until a refit poses them again."""
        betas = self.dataset.params(self.cfg.data.split)["betas"]
        self.vertices = posed_vertices(self.body, poses, betas).to(self.device)
        self.body_pose = poses.body_pose.to(self.device)

    def _cache_frames(self, budget: int) -> None:
        """Fill ``face_tables`` [n,Fb,38], ``targets`` [n,H,W,3] and ``target_units`` (LPIPS, per frame)
        within ``budget`` bytes; a kind that does not fit stays None and is computed at each step."""
        n = self.vertices.shape[0]
        self.face_tables = self.targets = self.target_units = None
        self._cached_bg = None
        need = n * self.avatar.binding_faces.shape[0] * FACE_TABLE * self.vertices.element_size()
        if need <= budget:
            self.face_tables = self._face_tables()
            budget -= need
        if self.cfg.background not in ("white", "black"):
            return  # a new random background every step: nothing fixed to keep
        bg = background_color(self.cfg.background, self.bg_generator, self.device)
        need = n * self.height * self.width * 3 * 4
        if need > budget:
            return
        self.targets = torch.stack([self.target(i, bg) for i in range(n)])
        self._cached_bg = bg
        budget -= need
        if self.cfg.loss.lpips:
            first = lpips_units(self.targets[0])
            if n * sum(u.numel() * u.element_size() for u in first) <= budget:
                self.target_units = [first] + [lpips_units(t) for t in self.targets[1:]]

    @torch.no_grad()
    def _face_tables(self) -> torch.Tensor:
        """The held bodies' face tables [n,Fb,38], one frame at a time: the same arithmetic, to the bit,
        as an uncached step's."""
        return torch.stack([self.avatar.face_table(v) for v in self.vertices])

    def target_lpips_units(self, i: int, bg: torch.Tensor) -> list[torch.Tensor] | None:
        """The cached LPIPS features of ``target(i, bg)`` (for ``total_loss(lpips_units=)``), or None."""
        return self.target_units[i] if self.target_units is not None and bg is self._cached_bg else None

    def target(self, i: int, bg: torch.Tensor) -> torch.Tensor:
        """Frame ``i``'s image composited over the background ``bg`` [3]: [H,W,3] on the device."""
        if self.targets is not None and bg is self._cached_bg:
            return self.targets[i]
        frame = self.dataset.frame(self.cfg.data.split, i)
        image = torch.from_numpy(np.array(frame.image, dtype=np.float32)).to(self.device)
        mask = torch.from_numpy(np.array(frame.mask, dtype=np.float32)).to(self.device)
        return composite_target(image, mask, bg)

    # --- checkpoints ------------------------------------------------------------------------------
    def save(self) -> None:
        save_checkpoint(checkpoint_path(self.run_dir), {
            "iteration": self.iteration,
            "config": to_dict(self.cfg),
            "data_spec": self.cfg.data.path,
            "body": self.body_info,
            "betas": self.betas,
            "avatar": self.avatar.checkpoint_state(),
            "optimizer": self.optimizer.state_dict(),
            "density": self.density.state_dict(),
            "sampler": self.sampler.state_dict(),
            "rng": capture_rng(self.bg_generator),
            "poses": None if self.poses is None else self.poses.state_dict(),
            "saved_at": time.time(),
        })
        self._write_pose_files()

    # --- one step ---------------------------------------------------------------------------------
    def step(self) -> dict:
        """One iteration. Returns its values as tensors on the device (reading them is the caller's
        choice: the loop does so once per logging interval): "ok" (bool: the loss and all gradients
        were finite, so the step was applied; otherwise nothing was changed), "loss", each loss term,
        "image", "target"; and "frame", "lr_position", "events" (density control) as Python values.
        Does not advance ``iteration`` (the loop does, so a skipped step still moves the schedules on).

        No host synchronisation: the finiteness guard stays on the device. The fused Adam skips its
        update when told a value was non-finite (``found_inf``, as under ``torch.amp.GradScaler``), and
        the density statistics leave such a step out. Density control itself may sync (it is rare)."""
        cfg = self.cfg
        it = self.iteration + 1
        lr = cfg.optim.position_lr(it - 1)
        for group in self.optimizer.param_groups:
            if group.get("name") == "position":
                group["lr"] = lr
        self.avatar.set_progress(it, cfg.optim.iters)
        i = self.sampler.next()
        bg = background_color(cfg.background, self.bg_generator, self.device)
        target = self.target(i, bg)
        vertices, body_pose, table = self.frame_body(i, it)
        gs = self.avatar(vertices, body_pose, table=table)
        image, _, info = render_gaussians(gs, self.viewmats[i], self.Ks[i], self.width, self.height,
                                          background=bg, check=False)
        loss, parts = total_loss(image, target, gs, cfg.loss, lpips_units=self.target_lpips_units(i, bg))
        loss.backward()
        grads = [p.grad for g in self.optimizer.param_groups for p in g["params"] if p.grad is not None]
        if self.poses is not None and self.poses.delta.grad is not None:
            grads.append(self.poses.delta.grad)
        # Checked on the device, in one reduction: the Gaussians (the rasterizer culls non-finite ones
        # instead of refusing them), the loss and every gradient.
        # bad: 1.0 for a skipped step, the optimiser's found_inf and the guard's count
        ok, bad = _finite_flag(gs.means, gs.quats, gs.scales, gs.opacities, gs.sh, loss, *grads)
        self._optimizer_step(ok, bad)
        self.optimizer.zero_grad(set_to_none=True)
        if self.poses is not None:
            self.poses.step(i, it, ok)
        events = self.density.after_step(it, info, self.width, self.height, valid=ok)
        self._guard.update(bad)
        return {"ok": ok, "loss": loss.detach(), **parts, "frame": i, "lr_position": lr, "events": events,
                "image": image.detach(), "target": target}

    def _optimizer_step(self, ok: torch.Tensor, bad: torch.Tensor) -> None:
        if self.optimizer.defaults.get("fused"):
            self.optimizer.grad_scale = None
            self.optimizer.found_inf = bad
            self.optimizer.step()
        elif bool(ok):  # an optimiser without device-side skipping: one sync
            self.optimizer.step()

    # --- loop ---------------------------------------------------------------------------------
    def run(self) -> TrainResult:
        """Set up, train to ``cfg.optim.iters`` (saving on the way and at the end), return the result."""
        self.setup()
        cfg = self.cfg
        total = cfg.optim.iters
        started = time.perf_counter()
        start_iteration = self.iteration
        if self.progress:
            print(f"training on {self.vertices.shape[0]} frames of {cfg.data.path} ({cfg.data.split}) at "
                  f"{self.width}x{self.height}, body {self.body_info['spec']}, {self.avatar.num_gaussians} "
                  f"Gaussians, {self.device}, {torch.get_num_threads()} threads -> {self.run_dir}", flush=True)
        writer = _tensorboard(self.run_dir) if cfg.log.tensorboard else None
        history: list[dict] = []
        interrupted = False
        from tqdm import tqdm

        bar = tqdm(total=total, initial=self.iteration, disable=not self.progress, unit="it",
                   dynamic_ncols=True, desc="train")
        try:
            with _Interrupt() as stop:
                schedule = self.density.schedule if cfg.density.enabled else None
                if self.poses is None:
                    sweeps = set()
                elif self.poses.frozen:  # the second pass: its refits
                    sweeps = cfg.optim.pose_sweep_iterations(schedule, cfg.optim.pose_refits)
                else:
                    sweeps = cfg.optim.pose_sweep_iterations(schedule)
                while self.iteration < total:
                    if self.iteration in sweeps:  # after that iteration's checkpoint: a resume redoes it
                        self.sweep_poses()
                    out = self.step()
                    self.iteration += 1
                    self._report(out, writer, history, bar)
                    if self.iteration % cfg.log.checkpoint_every == 0 and self.iteration < total:
                        self.save()
                    if self.on_iteration:
                        self.on_iteration(self.iteration, total)
                    if stop.requested:
                        interrupted = True
                        break
                self.save()
        finally:
            bar.close()
            if writer:
                writer.close()
        if interrupted:
            print(f"interrupted at iteration {self.iteration}; checkpoint saved to {checkpoint_path(self.run_dir)} "
                  f"(continue with --resume)")
        elif self.progress:
            done = self.iteration - start_iteration
            seconds = time.perf_counter() - started
            last = f", last training PSNR {history[-1]['psnr']:.2f} dB" if history else ""
            print(f"done: {done} iterations in {seconds:.0f} s ({done / max(seconds, 1e-9):.2f} it/s), "
                  f"{self.avatar.num_gaussians} Gaussians{last}; checkpoint {checkpoint_path(self.run_dir)}")
            if self.pose_error is not None:
                e = self.pose_error
                refined = "" if e["refined"] is None else f", refined {e['refined']['joint_angle_deg']:.2f}"
                print(f"training pose error vs the true poses (mean per-joint angle, deg): given "
                      f"{e['given']['joint_angle_deg']:.2f}{refined} -> {self.run_dir / 'pose_error.json'}")
        return TrainResult(self.iteration, interrupted, self.run_dir, history)

    # --- pose refinement --------------------------------------------------------------------------
    def _setup_poses(self, params: dict, poses: PoseSequence) -> None:
        """``poses``: a PoseRefiner of the training frames, or None without pose refinement (auto: on for
        datasets with estimated poses); frozen in the second pass of a two-pass run (``optim.pose_pass``),
        which holds the first pass's poses; ``true_poses``: the noise-free poses of a synthetic subject."""
        from rmavatar.data.synth import true_poses

        self.pose_index = params["index"]
        self.poses = None
        if self.cfg.optim.refines_poses(self.dataset.poses_estimated):
            betas = params["betas"] if self.body.num_betas > 0 else None
            frozen = self.cfg.optim.pose_pass_iters(self.dataset.poses_estimated) > 0  # the second pass
            self.poses = PoseRefiner(poses, betas, self.cfg.optim, self.device, frozen=frozen)
        self.true_poses = true_poses(self.dataset, self.cfg.data.split)
        self.pose_error = None

    def _resume_poses(self, state: dict | None) -> None:
        where = str(checkpoint_path(self.run_dir))
        if (state is None) != (self.poses is None):
            now = "refines" if self.poses is not None else "does not refine"
            raise UserError(f"{where}: the run was trained {'without' if state is None else 'with'} pose "
                            f"refinement, but its config now {now} the poses (did the dataset's meta.yaml "
                            f"'poses:' change?); start a new run")
        if state is not None:
            self.poses.load_state_dict(state, where)

    def sweep_poses(self) -> None:
        """A pose sweep (``optim.pose_sweeps``; in the second pass, a refit, ``optim.pose_refits``): every
        training frame's corrected pose fitted to its image and mask (weighed ``optim.pose_fit_mask``) with
        the avatar held still (:func:`rmavatar.evaluate.fit.fit_poses`, ``optim.pose_sweep_steps`` steps;
        a refit ``optim.pose_refit_steps``), then made the frame's
        new corrected pose; held poses are posed again."""
        from rmavatar.evaluate.fit import FitConfig, fit_poses

        split, n = self.cfg.data.split, len(self.poses)
        optim = self.cfg.optim
        steps = optim.pose_refit_steps if self.poses.frozen else optim.pose_sweep_steps
        # Any fixed background does: the targets are composited with their masks over the same one.
        bg = background_color("black" if self.cfg.background == "black" else "white", self.bg_generator, self.device)
        if self.progress:
            what = "pose refit" if self.poses.frozen else "pose sweep"
            print(f"{what} after iteration {self.iteration}: fitting the {n} training poses "
                  f"({steps} steps each)", flush=True)
        fit = FitConfig(steps=steps, silhouette=optim.pose_fit_mask)
        if self.poses.frozen:
            fit.lr_rotation, fit.lr_translation = optim.pose_refit_lr, optim.pose_refit_lr / 40
        fitted = fit_poses(self.avatar, self.body, self.poses.poses(), self.poses.betas,
                           self.dataset.frames(split, n), bg, fit, progress=self.progress)
        self.poses.set_poses(fitted)
        if self.poses.frozen:
            self._hold_poses(self.poses.poses())
            if self.face_tables is not None:
                self.face_tables = self._face_tables()

    def frame_body(self, i: int, iteration: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Posed vertices [V,3], body_pose [69] and face table (``Avatar.face_table``, or None: to be
        computed) of training frame ``i`` at step ``iteration``: the cached ones, or with pose refinement
        past its warm-up the corrected pose through the body."""
        if self.poses is None or not self.poses.active(iteration):
            return self.vertices[i], self.body_pose[i], None if self.face_tables is None else self.face_tables[i]
        return (*self.poses.posed(self.body, i), None)

    def _write_pose_files(self) -> None:
        """RUN/poses.npz (the refined training poses) and, for a subject with true poses,
        RUN/pose_error.json (the given and the refined poses' errors); both atomic."""
        from rmavatar.body import pose_error

        refined = None if self.poses is None else self.poses.poses()
        if refined is not None:
            write_poses(self.run_dir / "poses.npz", refined, self.pose_index, self.cfg.data.split)
        if self.true_poses is None:
            return
        params = self.dataset.params(self.cfg.data.split)
        given = PoseSequence.from_arrays(params["global_orient"], params["body_pose"], params["transl"])
        self.pose_error = {
            "iteration": self.iteration, "split": self.cfg.data.split,
            "measure": "mean over frames and the 24 joints (global orientation + 23 body joints) of the "
                       "geodesic angle to the true rotation; translation: mean distance",
            "given": pose_error(given, self.true_poses),
            "refined": None if refined is None else pose_error(refined, self.true_poses),
        }  # fmt: skip
        with atomic_path(self.run_dir / "pose_error.json") as tmp:
            tmp.write_text(json.dumps(self.pose_error, indent=2) + "\n")

    def _report(self, out: dict, writer, history: list, bar) -> None:
        """Progress, TensorBoard and previews. The step's tensors are read (one host sync for all of
        them) only at a logging iteration; so are the non-finite-step counters, which stop the run
        after ``max_bad_steps`` consecutive skipped steps."""
        cfg = self.cfg
        it = self.iteration
        n = self.avatar.num_gaussians
        bar.update(1)
        last = it == cfg.optim.iters
        log_progress = it % cfg.log.progress_every == 0 or last
        log_tb = writer is not None and it % cfg.log.tensorboard_every == 0
        if writer:
            for k, v in out["events"].items():  # density control: cloned / split / pruned counts, resets
                writer.add_scalar(f"density/{k}", float(v), it)
        if not (log_progress or log_tb):
            return
        names = [k for k, v in out.items() if torch.is_tensor(v) and v.dim() == 0 and k != "ok"]
        psnr = -10.0 * torch.log10(torch.mean((out["image"] - out["target"]) ** 2).clamp_min(1e-12))
        values = torch.stack([out[k].float() for k in names] + [psnr.float(), out["ok"].float(),
                                                                *self._guard.counters()])
        *scalars, psnr_v, ok_v, skipped, longest = values.tolist()
        scalars = dict(zip(names, scalars), psnr=psnr_v, lr_position=out["lr_position"])
        self._guard.check(int(skipped), int(longest), it, bar, writer, self)
        if log_progress and ok_v:
            history.append({"iteration": it, "loss": scalars["loss"], "psnr": psnr_v, "gaussians": n})
            bar.set_postfix(loss=f"{scalars['loss']:.4f}", psnr=f"{psnr_v:.2f}", N=n, refresh=False)
        if log_tb and ok_v:
            for k, v in scalars.items():
                writer.add_scalar(f"train/{k}", v, it)
            writer.add_scalar("train/gaussians", n, it)
        if it % cfg.log.preview_every == 0 or last:
            self._preview(out["image"], out["target"], it, writer)

    def _preview(self, image: torch.Tensor, target: torch.Tensor, it: int, writer) -> None:
        from PIL import Image

        pair = torch.cat((image, target), dim=1).clamp(0, 1)
        arr = (pair.cpu().numpy() * 255.0 + 0.5).astype(np.uint8)  # numpy and PIL need host memory
        folder = self.run_dir / "previews"
        folder.mkdir(exist_ok=True)
        with atomic_path(folder / f"iter_{it:06d}.png") as tmp:
            Image.fromarray(arr).save(tmp, format="PNG")
        if writer:
            writer.add_image("preview/render_target", arr, it, dataformats="HWC")


def _finite_flag(*tensors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(ok, bad) on the tensors' device: ok (bool) = every element of every tensor is finite; bad is
    the float32 1.0 - ok. No host sync.

    The sum of the L1 norms is NaN or +Inf when any element is (or when finite values overflow: also
    worth skipping), so this is one fused reduction over all tensors, their sum, and one comparison:
    a sum of norms is never negative, and NaN < Inf is false (isfinite + all would take five)."""
    if not tensors:
        ok = torch.ones((), dtype=torch.bool)
    else:
        ok = torch.stack(torch._foreach_norm([t.detach() for t in tensors], 1)).sum() < math.inf
    dev = ok.device
    return ok, torch.where(ok, constant(0.0, torch.float32, dev), constant(1.0, torch.float32, dev))


class _NonFiniteGuard:
    """Counts skipped (non-finite) steps on the device; :meth:`check` reads them at logging time and
    stops the run after ``max_bad_steps`` consecutive ones (the model is untouched by skipped steps)."""

    def __init__(self, device: torch.device, max_bad_steps: int):
        self.max_bad_steps = max_bad_steps
        self.skipped = torch.zeros((), device=device)  # since the last check
        self.run = torch.zeros((), device=device)  # current streak
        self.longest = torch.zeros((), device=device)  # longest streak since the last check

    def update(self, bad: torch.Tensor) -> None:
        """``bad``: 1.0 for a skipped step, 0.0 for an applied one (a float tensor on the device)."""
        bad = bad.to(self.run.dtype)
        self.skipped += bad
        torch.addcmul(bad, self.run, bad, out=self.run)  # (run + 1) * bad, as bad is 0 or 1
        torch.maximum(self.longest, self.run, out=self.longest)

    def counters(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.skipped, self.longest

    def check(self, skipped: int, longest: int, it: int, bar, writer, trainer) -> None:
        if skipped:
            bar.write(f"iteration {it}: {skipped} step(s) since the last report skipped (non-finite loss or "
                      f"gradient; longest streak {longest})")
            if writer:
                writer.add_scalar("train/skipped_steps", skipped, it)
        self.skipped.zero_()
        self.longest.copy_(self.run)
        if longest >= self.max_bad_steps:
            trainer.save()
            raise UserError(
                f"training stopped at iteration {it}: {longest} consecutive steps had a non-finite loss or "
                f"gradient (log.max_bad_steps is {self.max_bad_steps}, checked at each progress report); "
                f"the last good model is saved in {checkpoint_path(trainer.run_dir)} (try a lower "
                f"learning rate or check the data)")


def _tensorboard(run_dir: Path):
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(run_dir / "tb"))
