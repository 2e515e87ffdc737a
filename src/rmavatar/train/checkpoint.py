"""Writing checkpoints (only training does) and the RNG states resuming needs.

The run folder's layout and the checkpoint's content, format version and migrations are in
:mod:`rmavatar.avatar.run`.
"""

from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch

from rmavatar.avatar.run import Checkpoint
from rmavatar.utils import atomic_path


# ----------------------------------------------------------------------------------------------- RNG states
def capture_rng(background: torch.Generator | None = None) -> dict:
    """RNG states of torch, numpy (legacy global), python and the background generator."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "python": random.getstate(),
    }
    if background is not None:
        state["background"] = background.get_state()
    return state


def restore_rng(state: dict, background: torch.Generator | None = None) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    py = state["python"]
    random.setstate((py[0], tuple(py[1]), py[2]))
    if background is not None and "background" in state:
        background.set_state(state["background"])


# ----------------------------------------------------------------------------------------------- checkpoint io
def save_checkpoint(path: str | os.PathLike, checkpoint: Checkpoint) -> None:
    """Write ``checkpoint`` atomically: a kill never leaves a torn file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            torch.save(checkpoint.to_payload(), fh)
            fh.flush()
            os.fsync(fh.fileno())
