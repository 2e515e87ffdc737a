"""Run folders and checkpoints: atomic writes, ownership checks, and ``load_run`` for the other commands.

A run folder holds::

    RUN/rmavatar-run.json        marker: this folder is an rmavatar run, and of which dataset
    RUN/config.yaml              the full training config (accepted back with --config)
    RUN/checkpoints/last.pt      the latest checkpoint (torch.save of plain containers and tensors)
    RUN/previews/*.png           render | target previews
    RUN/tb/                      TensorBoard event files

A checkpoint stores the config, the iteration, the body model's spec and a signature of its topology,
the avatar's state (including the Gaussian count and parent-face ids), the optimiser state, the RNG
states of torch / numpy / python and the background generator, and the frame sampler's position, so
``--resume`` continues exactly where the checkpoint was taken.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rmavatar.utils import UserError, atomic_path

MARKER = "rmavatar-run.json"
CHECKPOINT_FORMAT = "rmavatar-checkpoint"
CHECKPOINT_VERSION = 1


def checkpoint_path(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / "checkpoints" / "last.pt"


# ----------------------------------------------------------------------------------------------- run folder
def read_marker(run_dir: str | os.PathLike) -> dict | None:
    """The run marker's content, or None when the folder has none."""
    path = Path(run_dir) / MARKER
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise UserError(f"{path} is not a readable rmavatar run marker: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != "rmavatar-run":
        raise UserError(f"{path} is not an rmavatar run marker")
    return data


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


# ----------------------------------------------------------------------------------------------- body identity
def body_signature(body: Any) -> dict:
    """What makes a checkpoint usable with a body model: its spec and a hash of its topology."""
    faces = body.faces.detach().cpu().to(torch.int64).contiguous().numpy()
    return {
        "spec": str(body.spec),
        "num_vertices": int(body.v_template.shape[0]),
        "num_faces": int(faces.shape[0]),
        "faces_sha1": hashlib.sha1(faces.tobytes()).hexdigest(),
    }


def check_body(saved: dict, body: Any, where: str) -> None:
    """Raise UserError when ``body`` cannot carry the avatar saved with signature ``saved``."""
    now = body_signature(body)
    if (saved["num_vertices"], saved["num_faces"], saved["faces_sha1"]) != (
        now["num_vertices"], now["num_faces"], now["faces_sha1"]
    ):
        raise UserError(
            f"{where} was trained with body model {saved['spec']!r} ({saved['num_vertices']} vertices, "
            f"{saved['num_faces']} faces), which is incompatible with {now['spec']!r} "
            f"({now['num_vertices']} vertices, {now['num_faces']} faces)"
        )


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


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Load a checkpoint written by :func:`save_checkpoint`; anything else raises UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means "not our checkpoint"
        raise UserError(f"{path} is not a readable rmavatar checkpoint: {exc}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path} is not an rmavatar checkpoint")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise UserError(f"{path} has checkpoint version {payload.get('version')}, this rmavatar reads {CHECKPOINT_VERSION}")
    return payload


# ----------------------------------------------------------------------------------------------- load_run
@dataclass
class LoadedRun:
    """A trained avatar ready to render: ``avatar(vertices [V,3], body_pose [69]) -> GaussianSet``."""

    avatar: Any  # rmavatar.avatar.Avatar, in eval mode
    body: Any  # rmavatar.body.BodyModel the avatar is bound to
    config: Any  # rmavatar.train.config.TrainConfig
    iteration: int
    data_spec: str  # the dataset it was trained on, as accepted by rmavatar.data.load_dataset


def load_run(run_dir: str | os.PathLike, device: str | torch.device = "cpu") -> LoadedRun:
    """Load RUN/checkpoints/last.pt: the avatar, its body model, the config and the iteration."""
    from rmavatar.body import load_body_model
    from rmavatar.train.config import TrainConfig, from_dict

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"run folder {run_dir} does not exist")
    if read_marker(run_dir) is None:
        raise UserError(f"{run_dir} is not an rmavatar run ({MARKER} missing)")
    path = checkpoint_path(run_dir)
    if not path.is_file():
        raise UserError(f"{run_dir} has no checkpoint yet ({path} missing): train it first")
    payload = read_checkpoint(path)
    config = from_dict(TrainConfig, payload["config"], where=f"{path}:config")
    body = load_body_model(payload["body"]["spec"], gender=payload["body"].get("gender"))
    check_body(payload["body"], body, str(path))
    from rmavatar.train.trainer import build_avatar

    avatar = build_avatar(body, config, state=payload["avatar"])
    avatar.eval()
    return LoadedRun(
        avatar=avatar.to(device), body=body.to(device), config=config,
        iteration=int(payload["iteration"]), data_spec=str(payload["data_spec"]),
    )
