"""A trained avatar: a run folder read back as something that poses and renders (``load_trained``).

A run folder holds::

    RUN/rmavatar-run.json        marker: this folder is an rmavatar run, and of which dataset
    RUN/config.yaml              the full training config (accepted back with --config)
    RUN/checkpoints/last.pt      the latest checkpoint (torch.save of plain containers and tensors)
    RUN/poses.npz                the refined training poses (runs with pose refinement)
    RUN/pose_pass/               the first pass of a run that refines its poses (a run folder itself)
    RUN/pose_error.json          the training poses' error vs the true ones (synthetic subjects)
    RUN/previews/*.png           render | target previews
    RUN/tb/                      TensorBoard event files

A checkpoint stores the training config, the iteration, the body model's spec and a signature of its
topology, the body shape it was trained with, the avatar's state (Gaussian count and parent faces
included), the pose corrections of runs that refine their training poses (with the poses they correct)
and what resuming needs (optimiser, density statistics, frame sampler, RNG states). Its
format is versioned: older checkpoints are migrated when read (:func:`read_checkpoint`).

Everything that uses a trained avatar (eval, animate, render, export, view, bench, the demo) goes through
:class:`TrainedAvatar`; only training writes checkpoints (``rmavatar.train.checkpoint``).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rmavatar.avatar.model import Avatar
from rmavatar.body import PoseSequence, apply_pose_corrections, load_body_model, posed_vertices, rest_pose
from rmavatar.render.gaussians import GaussianSet, render_gaussians
from rmavatar.utils import UserError
from rmavatar.utils.errors import load_error

MARKER = "rmavatar-run.json"
CHECKPOINT_FORMAT = "rmavatar-checkpoint"
# 2: TrainConfig.model is the avatar's own config (AvatarConfig, without its seed); the body shape is stored.
# 3: model.rectifier names the rectifier's design ("paper", "local") or is false (none).
# 4: "poses": the training poses' corrections (rmavatar.train.poses.PoseRefiner.state_dict) or None.
CHECKPOINT_VERSION = 4


def checkpoint_path(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / "checkpoints" / "last.pt"


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


# ----------------------------------------------------------------------------------------------- checkpoints
def _migrate_v1(payload: dict) -> dict:
    """Version 1 (rmavatar 0.1.0): the avatar's config carried the run's seed (for area placement, which
    a stored avatar no longer needs); the training config's "model" section was a subset of the avatar's
    config (still readable as one); no body shape was stored (None: read from the training data)."""
    avatar = dict(payload["avatar"])
    avatar["config"] = {k: v for k, v in avatar["config"].items() if k != "seed"}
    return {**payload, "avatar": avatar, "betas": None, "version": 2}


def _migrate_v2(payload: dict) -> dict:
    """Version 2: ``rectifier`` was true/false; true was the paper's design, the only one then."""

    def named(section):
        return {**section, "rectifier": "paper"} if section.get("rectifier") is True else section

    avatar = {**payload["avatar"], "config": named(payload["avatar"]["config"])}
    config = payload["config"]
    if isinstance(config.get("model"), dict):
        config = {**config, "model": named(config["model"])}
    return {**payload, "avatar": avatar, "config": config, "version": 3}


def _migrate_v3(payload: dict) -> dict:
    """Version 3: no pose refinement existed; the training poses were the dataset's."""
    return {**payload, "poses": None, "version": 4}


_MIGRATIONS = {1: _migrate_v1, 2: _migrate_v2, 3: _migrate_v3}


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Load a checkpoint (of this or an older format version, migrated); anything else raises UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means "not our checkpoint"
        raise UserError(f"{path} is not a readable rmavatar checkpoint: {load_error(exc)}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path} is not an rmavatar checkpoint")
    version = payload.get("version")
    while version in _MIGRATIONS:
        payload = _MIGRATIONS[version](payload)
        version = payload["version"]
    if version != CHECKPOINT_VERSION:
        raise UserError(f"{path} has checkpoint version {payload.get('version')}; this rmavatar reads versions "
                        f"up to {CHECKPOINT_VERSION} (a newer rmavatar wrote it)")
    return payload


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


def training_betas(params: dict) -> torch.Tensor:
    """The body shape [1,nb] a subject is trained with: the mean over its training frames' betas
    (every frame of a subject carries the same shape)."""
    return torch.as_tensor(np.asarray(params["betas"], np.float32).mean(0, keepdims=True))


# ----------------------------------------------------------------------------------------------- the avatar
@dataclass
class TrainedAvatar:
    """A trained avatar bound to its body model, in evaluation mode.

    avatar: the :class:`Avatar` (``avatar(vertices [V,3], body_pose [69]) -> GaussianSet``); body: the
    BodyModel; betas [1,nb] the body shape it was trained with (None: the body's own shape);
    iteration: training iterations done; data_spec: the dataset it was trained on; size: the image size
    it was trained at (None: the dataset's own); config: the training config as plain dicts;
    training_poses: the refined poses of the training frames (a PoseSequence in the order of the
    training split) when the run refined them, else None.
    """

    avatar: Avatar
    body: Any
    betas: torch.Tensor | None
    iteration: int
    data_spec: str
    size: int | None
    config: dict
    betas_error: str | None = None  # why the shape could not be read (raised when posing needs it)
    training_poses: PoseSequence | None = None

    @property
    def training_split(self) -> str:
        return str(self.config.get("data", {}).get("split", "train"))

    @property
    def device(self) -> torch.device:
        return self.body.v_template.device

    def rest_pose(self, kind: str = "tpose") -> PoseSequence:
        """A one-frame standing pose at the origin: 'tpose' (zero pose), 'apose' (arms down 45 degrees)
        or 'train' (the median body pose of the training frames, refined where the run refined them,
        facing +z)."""
        if kind != "train":
            return rest_pose(kind)
        if self.training_poses is not None:
            median = torch.median(self.training_poses.body_pose.cpu(), dim=0).values
            return PoseSequence(torch.zeros(1, 3), median[None], torch.zeros(1, 3))
        from rmavatar.data import load_dataset

        try:
            poses = np.asarray(load_dataset(self.data_spec).params("train")["body_pose"], np.float32)
        except UserError as exc:
            raise UserError(f"--pose train reads the run's training data {self.data_spec!r}, which "
                            f"cannot be read: {exc}") from None
        return PoseSequence(torch.zeros(1, 3), torch.from_numpy(np.median(poses, axis=0))[None], torch.zeros(1, 3))

    def _shape(self) -> torch.Tensor | None:
        if self.betas_error:
            raise UserError(self.betas_error)
        return self.betas

    def vertices(self, poses: PoseSequence, chunk: int = 32) -> torch.Tensor:
        """Posed body vertices [n,V,3] for every pose of ``poses``, with the avatar's body shape."""
        return posed_vertices(self.body, poses, self._shape(), chunk)

    @torch.no_grad()
    def root_rest(self) -> torch.Tensor:
        """The root joint [3] in the rest pose with this shape (where SMPL's transl is measured from)."""
        self._shape()
        zero = torch.zeros(1, 3, device=self.device)
        betas = None if self.betas is None else self.betas.to(self.device)
        return self.body(betas, zero, torch.zeros(1, 69, device=self.device), zero).joints[0, 0].float().cpu()

    @torch.no_grad()
    def gaussians(self, vertices: torch.Tensor, body_pose: torch.Tensor) -> GaussianSet:
        """World-space Gaussians on posed ``vertices`` [V,3], rectified for ``body_pose`` [69]
        (every stored SH band)."""
        return self.avatar.world_gaussians(vertices.to(self.device), body_pose.reshape(69).to(self.device))

    def pose(self, poses: PoseSequence, i: int) -> GaussianSet:
        """The GaussianSet of frame ``i`` of ``poses``."""
        one = poses.select(slice(i, i + 1))
        return self.gaussians(self.vertices(one)[0], one.body_pose[0])

    @torch.no_grad()
    def render(self, gs: GaussianSet, camera, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
        """``gs`` seen by ``camera`` (anything with viewmat [4,4], K [3,3], width, height) over
        ``background`` (RGB in 0..1, or None for transparent black) -> image [H,W,3]."""
        image, _, _ = render_gaussians(gs, camera.viewmat, camera.K, camera.width, camera.height, background)
        return image


def load_trained(run_dir: str | os.PathLike, device: str | torch.device = "cpu") -> TrainedAvatar:
    """Read RUN/checkpoints/last.pt: the avatar on its body model, its shape, the config and the iteration."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise UserError(f"run folder {run_dir} does not exist")
    if read_marker(run_dir) is None:
        raise UserError(f"{run_dir} is not an rmavatar run ({MARKER} missing)")
    path = checkpoint_path(run_dir)
    if not path.is_file():
        raise UserError(f"{run_dir} has no checkpoint yet ({path} missing): train it first")
    payload = read_checkpoint(path)
    body = load_body_model(payload["body"]["spec"], gender=payload["body"].get("gender"))
    check_body(payload["body"], body, str(path))
    avatar = Avatar.from_state(body, payload["avatar"], where=str(path))
    avatar.eval()
    config = payload["config"]
    betas, betas_error = payload["betas"], None
    if betas is None and body.num_betas > 0:  # an old checkpoint: the shape is its training data's
        from rmavatar.data import load_dataset

        spec = payload["data_spec"]
        try:
            betas = training_betas(load_dataset(spec).params("train"))
        except UserError as exc:
            betas_error = f"the run's body shape comes from its training data {spec!r}, which cannot be read: {exc}"
    training_poses = None
    if payload["poses"] is not None:
        base = payload["poses"]["base"]
        training_poses = apply_pose_corrections(
            PoseSequence(base["global_orient"], base["body_pose"], base["transl"]), payload["poses"]["delta"])
    return TrainedAvatar(
        avatar=avatar.to(device), body=body.to(device),
        betas=None if betas is None else torch.as_tensor(betas, dtype=torch.float32).to(device),
        iteration=int(payload["iteration"]), data_spec=str(payload["data_spec"]),
        size=config["data"]["size"], config=config, betas_error=betas_error, training_poses=training_poses,
    )
