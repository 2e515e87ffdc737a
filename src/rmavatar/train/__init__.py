"""Training: the run's config, ``train`` (the pipeline of one or two passes), the loop (``Trainer``) and its
parts (frames, density control, pose refinement, losses, the reporter), writing checkpoints.

Names are imported lazily, so ``rmavatar train`` can configure threading before torch loads.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "TrainConfig": "rmavatar.train.config",
    "load_config": "rmavatar.train.config",
    "save_config": "rmavatar.train.config",
    "train": "rmavatar.train.pipeline",
    "Trainer": "rmavatar.train.trainer",
    "TrainResult": "rmavatar.train.trainer",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'rmavatar.train' has no attribute {name!r}")
