"""Training configuration: typed, nested dataclasses with the paper's defaults, read from and written to YAML.

Defaults are RMAvatar's (paper §4.2, SPEC §2) for a 50,000-iteration run; iteration-based schedules
(density control, opacity resets) are given at that length and scaled to the actual run length by
:func:`rmavatar.train.density` 's schedule helper, so a short CPU run keeps the paper's proportions.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rmavatar.utils import UserError, atomic_path

BACKGROUNDS = ("white", "black", "random")


@dataclass
class DataConfig:
    """Which frames to train on."""

    path: str = ""  # dataset spec as given to rmavatar.data.load_dataset (stored absolute)
    size: int | None = None  # square image size the frames are resampled to; None = native
    split: str = "train"


@dataclass
class ModelConfig:
    """The avatar: body model and Gaussian/rectifier options (see rmavatar.avatar.AvatarConfig)."""

    body: str | None = None  # "anny", "anny:PRESET", "smpl:PATH"; None = the dataset's own preset/gender
    gender: str | None = None  # None = the dataset's gender
    sh_degree: int = 3
    rectifier: bool = True  # False = the paper's "w/o GauRec" ablation
    coarse_to_fine: bool = True  # ramp the rectifier's encoding frequencies in over training
    rectifier_precision: str = "float32"  # "bfloat16": faster hidden layers on CPUs with bf16 dot products
    placement: str = "face"  # "face": one Gaussian per binding face (the paper); "area": num_gaussians by area
    num_gaussians: int | None = None  # total for placement "area" (at least one per face)
    init_opacity: float = 0.1


@dataclass
class LossConfig:
    """Loss weights: L = rgb L1 + ssim (1-SSIM) + lpips LPIPS + pos L_pos + scaling L_scaling + offset L_offset."""

    rgb: float = 1.5
    ssim: float = 0.2
    lpips: float = 0.05
    pos: float = 0.01
    scaling: float = 1.0
    offset: float = 1.0
    eps_pos: float = 1.0  # L_pos threshold on |mu| (triangle-local units)
    eps_scaling: float = 0.6  # L_scaling threshold on the local (pre-w) scale


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


@dataclass
class DensityConfig:
    """Mesh-bound density control on the paper's schedule, stated for `reference_iters` iterations."""

    enabled: bool = True
    reference_iters: int = 50_000  # the schedule below is scaled by iters / reference_iters
    start: int = 10_000
    every: int = 500
    stop: int = 35_000
    reset_every: int = 5_000
    reset_start: int = 10_000
    grad_threshold: float = 2e-4  # view-space position-gradient norm (3DGS rule)
    prune_opacity: float = 0.005
    percent_dense: float = 0.01  # clone if largest rest-pose scale <= this x the body's extent, else split
    max_gaussians: int = 0  # 0 = unlimited


@dataclass
class LogConfig:
    """How often to report, preview and checkpoint (iterations)."""

    progress_every: int = 10
    tensorboard_every: int = 10
    preview_every: int = 500
    checkpoint_every: int = 1000
    max_bad_steps: int = 20  # stop after this many consecutive non-finite losses/gradients
    tensorboard: bool = True


@dataclass
class TrainConfig:
    """Everything a run needs; written to RUN/config.yaml and stored in every checkpoint."""

    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    density: DensityConfig = field(default_factory=DensityConfig)
    log: LogConfig = field(default_factory=LogConfig)
    seed: int = 0
    background: str = "white"
    threads: int = 0  # torch CPU threads; 0 = leave torch's default
    device: str = "auto"  # "auto" (CUDA when available), "cpu", "cuda", "cuda:N"

    def validate(self) -> "TrainConfig":
        """Raise UserError for values no run can use; returns self."""
        if self.background not in BACKGROUNDS:
            raise UserError(f"background must be one of {', '.join(BACKGROUNDS)}, not {self.background!r}")
        if self.optim.iters < 1:
            raise UserError(f"iters must be >= 1, got {self.optim.iters}")
        if self.data.size is not None and self.data.size < 8:
            raise UserError(f"size must be >= 8 pixels, got {self.data.size}")
        if self.model.placement not in ("face", "area"):
            raise UserError(f"model.placement must be 'face' or 'area', not {self.model.placement!r}")
        if self.model.placement == "area" and not self.model.num_gaussians:
            raise UserError("model.placement 'area' needs model.num_gaussians")
        if not 0 <= self.model.sh_degree <= 3:
            raise UserError(f"model.sh_degree must be 0..3, got {self.model.sh_degree}")
        for name in ("progress_every", "tensorboard_every", "preview_every", "checkpoint_every", "max_bad_steps"):
            if getattr(self.log, name) < 1:
                raise UserError(f"log.{name} must be >= 1, got {getattr(self.log, name)}")
        for f in dataclasses.fields(self.loss):
            if getattr(self.loss, f.name) < 0:
                raise UserError(f"loss.{f.name} must be >= 0, got {getattr(self.loss, f.name)}")
        if self.optim.lr_position_final <= 0 or self.optim.lr_position <= 0:
            raise UserError("optim.lr_position and optim.lr_position_final must be > 0")
        return self


def to_dict(cfg: Any) -> dict:
    """A config dataclass as plain nested dicts (YAML/pickle-safe)."""
    return dataclasses.asdict(cfg)


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check/convert a YAML value against a dataclass field type; errors name the key."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        last = None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except UserError as exc:
                last = exc
        raise last or UserError(f"{where}: bad value {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise UserError(f"{where}: expected a mapping, got {value!r}")
        return from_dict(tp, value, where)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise UserError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise UserError(f"{where}: expected an integer, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):  # PyYAML reads "1e-5" (no dot) as a string
            try:
                return float(value)
            except ValueError:
                pass
        raise UserError(f"{where}: expected a number, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise UserError(f"{where}: expected a string, got {value!r}")
    return value


def from_dict(cls: type, data: dict, where: str = "config") -> Any:
    """Build dataclass ``cls`` from nested dicts; missing keys keep their defaults, unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise UserError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in data.items()}
    return cls(**kwargs)


def load_config(path: str | os.PathLike) -> TrainConfig:
    """Read a YAML config (a full or partial TrainConfig); unknown keys and bad types raise UserError."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise UserError(f"config file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise UserError(f"config file {path} is not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise UserError(f"config file {path}: expected a mapping at the top level")
    return from_dict(TrainConfig, data, where=str(path)).validate()


def save_config(cfg: TrainConfig, path: str | os.PathLike) -> None:
    """Write ``cfg`` as YAML atomically."""
    import yaml

    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))


# The paper's ablations (§4.4) as dotted overrides: each flips exactly one switch of the full model.
ABLATIONS: dict[str, dict[str, Any]] = {
    "full": {},
    "no_rectifier": {"model.rectifier": False},  # "w/o GauRec": Gaussians fixed to their faces
    "no_offset_loss": {"loss.offset": 0.0},  # "w/o OffsetLoss"
    "no_scaling_loss": {"loss.scaling": 0.0},  # "w/o ScalingLoss"
}


def flatten(values: dict, prefix: str = "") -> dict[str, Any]:
    """Nested mappings -> dotted keys: {"optim": {"iters": 5}} -> {"optim.iters": 5}."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def apply_overrides(cfg: TrainConfig, overrides: dict[str, Any], where: str = "overrides") -> TrainConfig:
    """A copy of ``cfg`` with dotted keys set (``{"optim.iters": 1000, "model.rectifier": False}``;
    nested mappings work too), type-checked like a config file: errors name ``where`` and the key."""
    merged = to_dict(cfg)
    sections = sorted(k for k, v in merged.items() if isinstance(v, dict))
    for key, value in flatten(overrides).items():
        *path, leaf = str(key).split(".")
        node = merged
        for depth, part in enumerate(path):
            if not isinstance(node.get(part), dict):
                head = ".".join(path[: depth + 1])
                raise UserError(f"{where}: unknown key {key!r} ({head!r} is not a config section; sections: "
                                f"{', '.join(sections)}; top-level keys: "
                                f"{', '.join(k for k in merged if k not in sections)})")
            node = node[part]
        if isinstance(node.get(leaf), dict):
            raise UserError(f"{where}: {key!r} is a config section, give one of its keys ({key}.KEY)")
        node[leaf] = value
    return from_dict(TrainConfig, merged, where=where)
