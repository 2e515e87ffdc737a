"""Writing runs: the run folder's ownership checks, atomic checkpoints and the RNG states resuming needs.

The run folder's layout and the checkpoint's content and format version are described, and read, in
:mod:`rmavatar.avatar.trained`.
"""

from __future__ import annotations

import json
import os
import random
from pathlib import Path

import numpy as np
import torch

from rmavatar.avatar.trained import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    MARKER,
    checkpoint_path,
    read_marker,
)
from rmavatar.utils import UserError, atomic_path


# ----------------------------------------------------------------------------------------------- run folder
def _write_marker(run_dir: Path, data_spec: str) -> None:
    with atomic_path(run_dir / MARKER) as tmp:
        tmp.write_text(json.dumps({"format": "rmavatar-run", "version": 1, "data": data_spec}, indent=2))


def prepare_run_dir(run_dir: str | os.PathLike, data_spec: str, resume: bool) -> None:
    """Create or check RUN before training writes anything into it.

    A fresh run needs RUN absent, empty, or our own run without a checkpoint yet (a failed start); a
    folder with other files is someone else's and is never written into, and a trained run (of this or
    another dataset) is only continued with ``resume``. ``--resume`` needs our run
    of the same dataset with a checkpoint.
    """
    run_dir = Path(run_dir)
    if run_dir.exists() and not run_dir.is_dir():
        raise UserError(f"--out {run_dir} exists and is not a folder")
    marker = read_marker(run_dir) if run_dir.is_dir() else None
    if marker is None:
        if run_dir.is_dir() and any(run_dir.iterdir()):
            raise UserError(
                f"--out {run_dir} is not empty and holds no rmavatar run ({MARKER} missing): "
                "refusing to write into someone else's folder; choose an empty or new folder"
            )
        if resume:
            raise UserError(f"--resume: {run_dir} holds no run to resume")
        run_dir.mkdir(parents=True, exist_ok=True)
        _write_marker(run_dir, data_spec)
        return
    has_ckpt = checkpoint_path(run_dir).is_file()
    if marker.get("data") != data_spec:
        if has_ckpt or resume:
            raise UserError(
                f"--out {run_dir} holds a run of another dataset ({marker.get('data')!r}, not {data_spec!r}); "
                "choose another folder"
            )
        # A start that failed before its first checkpoint (e.g. a wrong body path): nothing to keep.
        _write_marker(run_dir, data_spec)
    if resume and not has_ckpt:
        raise UserError(f"--resume: {run_dir} has no checkpoint yet ({checkpoint_path(run_dir)} missing)")
    if not resume and has_ckpt:
        raise UserError(
            f"--out {run_dir} already holds a trained run (checkpoint at {checkpoint_path(run_dir)}); "
            "pass --resume to continue it, or choose another folder"
        )


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
def save_checkpoint(path: str | os.PathLike, payload: dict) -> None:
    """Write ``payload`` (plain containers and tensors) atomically: a kill never leaves a torn file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **payload}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            torch.save(payload, fh)
            fh.flush()
            os.fsync(fh.fileno())
