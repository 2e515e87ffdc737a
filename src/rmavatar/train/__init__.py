"""Training: config, the loop, checkpoints, and ``load_run`` for the commands that use a trained avatar."""

from rmavatar.train.checkpoint import LoadedRun, load_run
from rmavatar.train.config import TrainConfig, load_config, save_config

__all__ = ["LoadedRun", "TrainConfig", "load_config", "load_run", "save_config", "train"]


def train(*args, **kwargs):
    """See :func:`rmavatar.train.trainer.train` (imported lazily: it pulls in the renderer)."""
    from rmavatar.train.trainer import train as _train

    return _train(*args, **kwargs)
