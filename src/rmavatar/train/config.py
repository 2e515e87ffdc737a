"""A training run's configuration: the components' own configs nested in one ``TrainConfig``, with the
paper's defaults, read from and written to YAML (``RUN/config.yaml``).

Each section is the config of the component it builds: ``model`` (:class:`rmavatar.avatar.AvatarConfig`)
builds the avatar, ``optim`` the optimiser, ``density`` the density controller (which scales the paper's
50,000-iteration schedule to the run's length), ``poses`` the pose refinement strategy, ``loss`` weighs the
loss terms. The settings people tune come first in each section; those below its ``--- advanced ---``
line are for experiments (docs/train.md lists them all, with the measurements behind the defaults).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

from rmavatar.avatar.model import AvatarConfig
from rmavatar.avatar.run import CHECKPOINT_VERSION, migrate_config
from rmavatar.train.density import DensityConfig
from rmavatar.train.losses import LossConfig
from rmavatar.train.optim import OptimConfig
from rmavatar.train.pose_refine import PoseConfig
from rmavatar.utils import UserError
from rmavatar.utils.config import (
    apply_overrides,
    check_fields,
    flatten,
    from_dict,
    read_yaml,
    to_dict,
    write_yaml,
)

BACKGROUNDS = ("white", "black", "random")

__all__ = ["ABLATIONS", "AvatarConfig", "DataConfig", "DensityConfig", "LogConfig", "LossConfig", "OptimConfig",
           "PoseConfig", "TrainConfig", "apply_overrides", "config_from_dict", "flatten", "from_dict", "load_config",
           "save_config", "to_dict"]


@dataclass
class DataConfig:
    """Which frames to train on."""

    path: str = ""  # dataset spec as given to rmavatar.data.load_dataset (stored absolute)
    size: int | None = None  # square image size the frames are resampled to; None = native
    split: str = "train"  # the dataset split to train on
    # pose the fingers with the dataset's hand poses where it has them (false: relaxed hands, as before
    # hand poses existed; evaluation on the run's data follows the same choice)
    hand_pose: bool = True

    def validate(self) -> "DataConfig":
        check_fields(self, "data")
        if self.size is not None and not 8 <= self.size <= 8192:
            raise UserError(f"data.size (--size) must be in 8..8192 pixels, got {self.size}")
        return self


@dataclass
class LogConfig:
    """How often to report, preview and checkpoint (iterations)."""

    checkpoint_every: int = 1000  # write checkpoints/last.pt every this many iterations (and at the end)
    tensorboard: bool = True  # write TensorBoard event files to RUN/tb
    # --- advanced ---
    progress_every: int = 10  # update the progress bar's loss / PSNR every this many iterations
    tensorboard_every: int = 10  # TensorBoard scalars every this many iterations
    preview_every: int = 500  # a render | target preview PNG every this many iterations
    max_bad_steps: int = 20  # stop after this many consecutive non-finite losses/gradients

    def validate(self) -> "LogConfig":
        check_fields(self, "log")
        for name in ("progress_every", "tensorboard_every", "preview_every", "checkpoint_every", "max_bad_steps"):
            if getattr(self, name) < 1:
                raise UserError(f"log.{name} must be >= 1, got {getattr(self, name)}")
        return self


@dataclass
class TrainConfig:
    """Everything a run needs; written to RUN/config.yaml and stored in every checkpoint."""

    data: DataConfig = field(default_factory=DataConfig)  # which frames, at which size
    model: AvatarConfig = field(default_factory=AvatarConfig)  # the avatar: body model, rectifier, SH degree
    optim: OptimConfig = field(default_factory=OptimConfig)  # iterations and learning rates
    poses: PoseConfig = field(default_factory=PoseConfig)  # pose refinement (estimated poses)
    density: DensityConfig = field(default_factory=DensityConfig)  # densify / prune; the Gaussian cap
    loss: LossConfig = field(default_factory=LossConfig)  # the loss terms' weights
    log: LogConfig = field(default_factory=LogConfig)  # progress, previews, checkpoints
    background: str = "white"  # the background renders and targets are composited over: white, black, random
    seed: int = 0  # seeds every random choice of the run (frame order, initialisation, random backgrounds)
    threads: int = 0  # torch CPU threads; 0 = leave torch's default
    device: str = "auto"  # "auto" (CUDA when available), "cpu", "cuda", "cuda:N"
    cuda_graphs: bool = True  # on CUDA, replay the step's posing and losses as CUDA graphs (same results, faster)

    def validate(self) -> "TrainConfig":
        """Raise UserError for values no run can use; returns self."""
        if self.background not in BACKGROUNDS:
            raise UserError(f"background must be one of {', '.join(BACKGROUNDS)}, not {self.background!r}")
        for section in (self.data, self.model, self.loss, self.optim, self.poses, self.density, self.log):
            section.validate()
        check_fields(self, "", nonnegative=("seed", "threads"))
        return self


def load_config(path: str | os.PathLike, as_trained: bool = False) -> TrainConfig:
    """Read a YAML config (a full or partial TrainConfig, of this or an older layout: migrated); unknown
    keys and bad types raise UserError. ``as_trained``: a run's own RUN/config.yaml, whose missing settings
    are those added after it was written (:func:`rmavatar.avatar.run.migrate_config`)."""
    data = read_yaml(path)
    version = data.pop("version", None) if isinstance(data, dict) else None
    return config_from_dict(migrate_config(data, version, as_trained), where=str(path))


def config_from_dict(data: dict, where: str = "config") -> TrainConfig:
    """A validated TrainConfig from plain containers in today's layout (a checkpoint's ``config``)."""
    return from_dict(TrainConfig, data, where=where).validate()


def save_config(cfg: TrainConfig, path: str | os.PathLike) -> None:
    """Write ``cfg`` as YAML atomically, stamped with its layout version (``version:``, first)."""
    write_yaml(cfg, path, header={"version": CHECKPOINT_VERSION})


def config_differences(saved: dict, cfg: TrainConfig, ignore: tuple[str, ...] = ()) -> list[str]:
    """The settings in which a run's saved config (a checkpoint's ``config``) differs from ``cfg``, as
    "key: saved -> now", leaving out what may change between the parts of one run (its length,
    threads, device, logging) and the dotted keys ``ignore``. A setting the saved config lacks (added since
    it was written) counts as its default: a new setting's default is how runs trained before it, and the
    migrations (rmavatar.avatar.run) fill in those whose later default is not."""
    a, b = flatten(to_dict(config_from_dict(saved, where="the saved config"))), flatten(to_dict(cfg))
    skip = ("optim.iters", "threads", "device", *ignore)
    keys = sorted(k for k in set(a) | set(b) if not k.startswith("log.") and k not in skip and a.get(k) != b.get(k))
    return [f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in keys]


# The paper's ablations (§4.4) and our variants as dotted overrides, each one switch away from the paper's
# full model (its rectifier design, "paper"; our default is "local").
ABLATIONS: dict[str, dict[str, Any]] = {
    "full": {"model.rectifier": "paper"},  # the paper's full model
    "no_rectifier": {"model.rectifier": False},  # "w/o GauRec": Gaussians fixed to their faces
    "no_offset_loss": {"model.rectifier": "paper", "loss.offset": 0.0},  # "w/o OffsetLoss"
    "no_scaling_loss": {"model.rectifier": "paper", "loss.scaling": 0.0},  # "w/o ScalingLoss"
    "local_rectifier": {"model.rectifier": "local"},  # ours, the default: docs/model.md "The local rectifier"
}
