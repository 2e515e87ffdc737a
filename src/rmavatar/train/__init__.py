"""Training: config, the loop, checkpoints, and ``load_run`` for the commands that use a trained avatar.

Names are imported lazily, so ``rmavatar train`` can configure threading before torch loads.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "LoadedRun": "rmavatar.train.checkpoint",
    "load_run": "rmavatar.train.checkpoint",
    "TrainConfig": "rmavatar.train.config",
    "load_config": "rmavatar.train.config",
    "save_config": "rmavatar.train.config",
    "train": "rmavatar.train.trainer",
    "TrainResult": "rmavatar.train.trainer",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'rmavatar.train' has no attribute {name!r}")
