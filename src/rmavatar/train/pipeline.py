"""``train()``: a whole training, fresh or resumed, in one pass or two.

One pass is one :class:`rmavatar.train.trainer.Trainer` run. A run that refines estimated poses in two
passes (``poses.first_pass``) is two ordinary passes: the first, a run folder of its own in RUN/pose_pass,
refines the poses (its config: the run's, shorter, one pass, no held fits); the second trains the avatar
afresh in RUN on the poses the first left, held. Everything that can be checked (the config, the dataset
and every training frame's files, a first pass already there) is checked before RUN is written to.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Callable

from rmavatar.avatar.run import Checkpoint, RunFolder
from rmavatar.data.checks import check_files
from rmavatar.data.registry import normalize_spec, same_dataset
from rmavatar.train.config import (
    TrainConfig,
    apply_overrides,
    config_differences,
    config_from_dict,
    flatten,
    load_config,
    save_config,
    to_dict,
)
from rmavatar.train.frames import open_dataset
from rmavatar.train.trainer import Trainer, TrainResult
from rmavatar.utils import UserError, check_writable_folder

# What a resumed run may change (dotted keys; "log." every reporting setting): its length, where and how
# fast it runs, what it reports. Anything else (the model, the losses, the schedules' shape) is the run's.
RESUME_CHANGEABLE = ("optim.iters", "threads", "device", "cuda_graphs", "density.capacity", "log.")
# The second pass's settings, which its first pass does not use.
HELD_FIT_KEYS = ("poses.held_fits", "poses.held_fit_steps", "poses.held_fit_lr_rotation",
                 "poses.held_fit_lr_translation", "poses.smooth_held", "poses.held_fit_scales",
                 "poses.held_fit_prior", "poses.held_fit_anchor")


def train(cfg: TrainConfig | None, run_dir: str | Path, *, resume: bool = False, data: str | None = None,
          overrides: dict[str, Any] | None = None, progress: bool = True,
          on_iteration: Callable[[int, int], None] | None = None) -> TrainResult:
    """Train an avatar into ``run_dir``.

    Fresh run: ``cfg`` is the full config. Resume: ``cfg`` is None, the run's checkpoint supplies the
    config (with RUN/config.yaml's edits since, where they may change mid-run); ``data`` (if given) must
    name the same dataset; ``overrides`` (dotted keys, ``{"optim.iters": 8000}``) may change only
    :data:`RESUME_CHANGEABLE`, anything else that differs is an error. One process at a time trains into
    a run folder (RunFolder.writer_lock).
    ``on_iteration(iteration, total)`` is called after every iteration, once any checkpoint of that
    iteration is written (``rmavatar batch`` reports progress with it).
    """
    run, overrides = RunFolder(run_dir), dict(overrides or {})
    check_writable_folder(run.config, f"--out {run.path}", create=True)
    with run.writer_lock():  # one writer per run folder, from before anything is written
        return _train(cfg, run, resume, data, overrides, progress, on_iteration)


def _train(cfg: TrainConfig | None, run: RunFolder, resume: bool, data: str | None, overrides: dict[str, Any],
           progress: bool, on_iteration) -> TrainResult:
    """:func:`train` with the run's writer lock held."""
    in_first_pass = resume and not run.has_checkpoint() and run.pose_pass.has_checkpoint()
    ckpt = None
    if in_first_pass:  # stopped in the first pass of two: that pass resumes, then the second starts
        cfg = load_config(run.config, as_trained=True)
        _check_resume_data(run, data, cfg.data.path)
        cfg = _resume_overrides(cfg, overrides)
    elif resume:
        ckpt = _resume_checkpoint(run, data)
        cfg = config_from_dict(ckpt.config, where=f"{run.checkpoint}:config")
        cfg = _resume_overrides(_with_config_edits(cfg, run), overrides)
        if cfg.optim.iters < ckpt.iteration:
            raise UserError(f"--iters {cfg.optim.iters} is below the {ckpt.iteration} iterations {run.path} has "
                            "done: give more to continue it (or start a new run)")
    else:
        if cfg is None:
            raise ValueError("train() needs a config for a fresh run")
        cfg = copy.deepcopy(cfg).validate()
        if not cfg.data.path:
            raise UserError("no dataset given (data.path is empty)")
        cfg.data.path = normalize_spec(cfg.data.path)
    # Open the dataset and read every training frame's files before anything is written to RUN (only its
    # lock is held), so a wrong path or a broken frame leaves nothing behind and is not found hours in.
    dataset = open_dataset(cfg.data)
    check_files(dataset, [cfg.data.split], progress=progress)
    first, first_ckpt = (None, None) if ckpt is not None else first_pass_config(cfg, run, dataset)
    _start(cfg, run, ckpt is not None)
    if first is not None and (first_ckpt is None or first_ckpt.iteration < first.optim.iters):
        if progress:
            held = cfg.poses.held_fit_fractions(cfg.optim.iters, dataset.num_frames(cfg.data.split))
            print(f"pose pass: {first.optim.iters} iterations refine the training poses ({run.pose_pass.path}), "
                  f"then the avatar is trained afresh on them for {cfg.optim.iters}, fitting them again "
                  f"{len(held)} times", flush=True)
        _start(first, run.pose_pass, first_ckpt is not None)
        # a first pass at a smaller size (poses.first_pass_scale) reads the frames at its own size
        own = dataset if first.data.size == cfg.data.size else None
        result = Trainer(first, run.pose_pass, first_ckpt, progress, on_iteration, own).run()
        if result.interrupted:
            return result
    return Trainer(cfg, run, ckpt, progress, on_iteration, dataset).run()


def _start(cfg: TrainConfig, run: RunFolder, resume: bool) -> None:
    """Create or check the pass's folder and write its config.yaml."""
    run.prepare(cfg.data.path, resume)
    save_config(cfg, run.config)


def first_pass_config(cfg: TrainConfig, run: RunFolder, dataset) -> tuple[TrainConfig | None, Checkpoint | None]:
    """The config of the first pass of a two-pass run on ``dataset`` (opened at the run's size; None: one
    pass) and its checkpoint (None: not begun). A first pass already there (stopped, or done) must have
    been trained with the same settings; its length is its own."""
    iters = cfg.poses.first_pass_iters(cfg.optim.iters, dataset.poses_estimated)
    if not iters:
        return None, None
    first = copy.deepcopy(cfg)
    first.optim.iters, first.poses.first_pass, first.poses.held_fits, first.poses.smooth_held = iters, 0.0, (), False
    first.data.size = cfg.poses.first_pass_size(dataset.image_size) or cfg.data.size
    if not run.pose_pass.has_checkpoint():
        return first, None
    ckpt = run.pose_pass.read_checkpoint()
    differ = config_differences(ckpt.config, first, ignore=HELD_FIT_KEYS)
    if differ:
        raise UserError(f"{run.pose_pass.path} holds a first pass trained with other settings than this run's "
                        f"({', '.join(differ[:6])}); choose another folder")
    first.optim.iters = int(ckpt.config["optim"]["iters"])
    return first, ckpt


def _resume_checkpoint(run: RunFolder, data: str | None) -> Checkpoint:
    if not run.has_checkpoint():
        raise UserError(f"--resume: {run.path} has no checkpoint ({run.checkpoint} missing)")
    ckpt = run.read_checkpoint()
    _check_resume_data(run, data, ckpt.data_spec)
    return ckpt


def _check_resume_data(run: RunFolder, data: str | None, trained_on: str) -> None:
    """``--data`` given with ``--resume`` must name the dataset the run was trained on."""
    if data is not None and not same_dataset(data, trained_on):
        raise UserError(f"--resume: {run.path} is a run of {trained_on!r}, not of {normalize_spec(data)!r}")


def _changeable(key: str) -> bool:
    return any(key == k or (k.endswith(".") and key.startswith(k)) for k in RESUME_CHANGEABLE)


def _with_config_edits(cfg: TrainConfig, run: RunFolder) -> TrainConfig:
    """``cfg`` (the checkpoint's) with the edits the user made to RUN/config.yaml since: applied where a
    running training may change (:data:`RESUME_CHANGEABLE`), else refused, naming the keys; never
    silently dropped (the resumed run writes its config back)."""
    if not run.config.is_file():
        return cfg
    saved, edited = flatten(to_dict(cfg)), flatten(to_dict(load_config(run.config, as_trained=True)))
    changed = sorted(k for k in set(saved) | set(edited) if saved.get(k) != edited.get(k))
    fixed = [f"{k}: {saved.get(k)!r} -> {edited.get(k)!r}" for k in changed if not _changeable(k)]
    if fixed:
        raise UserError(f"{run.config} was edited since its checkpoint ({'; '.join(fixed[:6])}): these settings "
                        f"cannot change in the middle of a run (only {', '.join(RESUME_CHANGEABLE)}* can); undo "
                        f"the edit, or start a new run with it: rmavatar train DATA --out NEW --config {run.config}")
    return apply_overrides(cfg, {k: edited[k] for k in changed}, where=str(run.config)) if changed else cfg


def _resume_overrides(cfg: TrainConfig, overrides: dict[str, Any]) -> TrainConfig:
    """``cfg`` with the changeable ``overrides`` applied, validated; any other override must equal the
    run's own value."""
    current = flatten(to_dict(cfg))
    for key, value in overrides.items():
        now = current.get(key)
        if not _changeable(key) and now != value:
            raise UserError(f"--resume keeps the run's config: {key} is {now!r} there, cannot change it to "
                            f"{value!r} (start a new run instead)")
    changeable = {k: v for k, v in overrides.items() if _changeable(k)}
    return (apply_overrides(cfg, changeable, where="--resume") if changeable else cfg).validate()
