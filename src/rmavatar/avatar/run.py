"""The run folder's contract: its layout (:class:`RunFolder`), the checkpoint (:class:`Checkpoint`) and one
versioned migration chain that brings an older run's checkpoint and config up to today's.

A run folder holds::

    RUN/rmavatar-run.json        marker: this folder is an rmavatar run, and of which dataset
    RUN/config.yaml              the full training config, stamped with its layout version (accepted back with --config)
    RUN/checkpoints/last.pt      the latest checkpoint (torch.save of plain containers and tensors)
    RUN/poses.npz                the refined training poses (runs with pose refinement)
    RUN/pose_pass/               the first pass of a run that refines its poses (a run folder itself)
    RUN/pose_error.json          the training poses' error vs the true ones (synthetic subjects)
    RUN/previews/*.png           render | target previews
    RUN/tb/                      TensorBoard event files
    RUN/.rmavatar-run.lock       held (flock) by the one process training into RUN, naming it

Only training writes checkpoints (``rmavatar.train.checkpoint``); everything reads them here.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import time
import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from rmavatar.utils import UserError, atomic_path
from rmavatar.utils.errors import load_error

MARKER = "rmavatar-run.json"
LOCK = ".rmavatar-run.lock"
CHECKPOINT_FORMAT = "rmavatar-checkpoint"
# The version of the checkpoint and of the training config's layout, raised together (the history is
# in MIGRATIONS below).
CHECKPOINT_VERSION = 9


class RunFolder:
    """Where everything of one run lives (the layout above); reading its marker and checkpoint."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    marker = property(lambda self: self.path / MARKER)
    config = property(lambda self: self.path / "config.yaml")
    checkpoint = property(lambda self: self.path / "checkpoints" / "last.pt")
    poses = property(lambda self: self.path / "poses.npz")
    pose_error = property(lambda self: self.path / "pose_error.json")
    previews = property(lambda self: self.path / "previews")
    tensorboard = property(lambda self: self.path / "tb")

    @property
    def pose_pass(self) -> "RunFolder":
        """The first pass of a two-pass run: a run folder of its own inside this one."""
        return RunFolder(self.path / "pose_pass")

    def has_checkpoint(self) -> bool:
        return self.checkpoint.is_file()

    def read_marker(self) -> dict | None:
        """The marker's content, or None when the folder has none."""
        if not self.marker.is_file():
            return None
        try:
            data = json.loads(self.marker.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise UserError(f"{self.marker} is not a readable rmavatar run marker: {exc}") from None
        if not isinstance(data, dict) or data.get("format") != "rmavatar-run":
            raise UserError(f"{self.marker} is not an rmavatar run marker")
        return data

    def write_marker(self, data_spec: str) -> None:
        with atomic_path(self.marker) as tmp:
            tmp.write_text(json.dumps({"format": "rmavatar-run", "version": 1, "data": data_spec}, indent=2))

    def read_checkpoint(self) -> "Checkpoint":
        return read_checkpoint(self.checkpoint)

    def check_trained(self) -> None:
        """Raise UserError unless this is a run with a checkpoint (what every reader of an avatar needs)."""
        if not self.path.is_dir():
            raise UserError(f"run folder {self.path} does not exist")
        if self.read_marker() is None:
            raise UserError(f"{self.path} is not an rmavatar run ({MARKER} missing)")
        if not self.has_checkpoint():
            if os.path.lexists(self.checkpoint):  # a folder, a broken link: not "missing"
                raise UserError(f"{self.checkpoint} is not a checkpoint file (a folder or a broken link)")
            raise UserError(f"{self.path} has no checkpoint yet ({self.checkpoint} missing): train it first")

    def refuse_foreign(self) -> None:
        """Raise UserError when the folder exists and is not ours to write into: not a folder, or a folder
        holding files without our marker (someone else's)."""
        if self.path.exists() and not self.path.is_dir():
            raise UserError(f"--out {self.path} exists and is not a folder")
        if self.path.is_dir() and self.read_marker() is None and any(p.name != LOCK for p in self.path.iterdir()):
            raise UserError(f"--out {self.path} is not empty and holds no rmavatar run ({MARKER} missing): "
                            "refusing to write into someone else's folder; choose an empty or new folder")

    @contextlib.contextmanager
    def writer_lock(self) -> Iterator[None]:
        """Hold the run's lock while training writes into it: a second writer (another ``rmavatar train``
        of the same folder, a batch worker) is refused with a message naming the process that holds it.
        An exclusive ``flock`` on RUN/.rmavatar-run.lock: the kernel releases it when its process dies, so
        a killed run's lock is taken over by the next one. A folder this made, and left as empty as it
        found it, is removed again."""
        import fcntl

        self.refuse_foreign()
        created = not self.path.exists()
        self.path.mkdir(parents=True, exist_ok=True)
        path = self.path / LOCK
        while True:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise UserError(f"--out {self.path} is being trained by {self._holder(path)}: wait for it to "
                                "finish or stop it, or choose another folder") from None
            if os.path.exists(path) and os.stat(path).st_ino == os.fstat(fd).st_ino:
                break  # the lock file is still the one at the path (not unlinked by its last holder)
            os.close(fd)
        try:
            holder = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
            os.ftruncate(fd, 0)
            os.write(fd, json.dumps(holder).encode())
            yield
        finally:
            os.unlink(path)
            os.close(fd)
            if created and not any(self.path.iterdir()):
                self.path.rmdir()

    @staticmethod
    def _holder(path: Path) -> str:
        try:
            h = json.loads(path.read_text())
            return f"process {h['pid']} on {h['host']} (since {h['since']})"
        except (OSError, ValueError, KeyError, TypeError):
            return f"another process ({path} is locked)"

    def prepare(self, data_spec: str, resume: bool) -> None:
        """Create or check the folder before training writes anything into it.

        A fresh run needs it absent, empty, or our own run without a checkpoint yet (a failed start); a
        folder with other files is someone else's and is never written into, and a trained run (of this
        or another dataset) is only continued with ``resume``, which needs our run of the same dataset
        with a checkpoint."""
        run_dir = self.path
        self.refuse_foreign()
        marker = self.read_marker() if run_dir.is_dir() else None
        if marker is None:
            if resume:
                raise UserError(f"--resume: {run_dir} holds no run to resume")
            run_dir.mkdir(parents=True, exist_ok=True)
            self.write_marker(data_spec)
            return
        has_ckpt = self.has_checkpoint()
        if marker.get("data") != data_spec:
            if has_ckpt or resume:
                raise UserError(f"--out {run_dir} holds a run of another dataset ({marker.get('data')!r}, not "
                                f"{data_spec!r}); choose another folder")
            self.write_marker(data_spec)  # a start that failed before its first checkpoint: nothing to keep
        if resume and not has_ckpt:
            raise UserError(f"--resume: {run_dir} has no checkpoint yet ({self.checkpoint} missing)")
        if not resume and has_ckpt:
            raise UserError(f"--out {run_dir} already holds a trained run (checkpoint at {self.checkpoint}); "
                            "pass --resume to continue it, or choose another folder")


@dataclass
class Checkpoint:
    """What a checkpoint holds (the training config in today's layout, however old the file)."""

    iteration: int  # training iterations done
    config: dict  # the TrainConfig as plain containers
    data_spec: str  # the dataset it trains on (absolute spec)
    body: dict  # the body model's spec, gender and topology signature (body_signature)
    betas: torch.Tensor | None  # [1,nb] the body shape the avatar keeps (None: read from the data, v1 runs)
    avatar: dict  # Avatar.checkpoint_state(): its config and state_dict
    optimizer: dict  # the Adam state
    density: dict  # the density controller's statistics
    sampler: dict  # the frame sampler's position
    rng: dict  # torch / numpy / python / background RNG states
    poses: dict | None  # the pose corrections (PoseRefiner.state_dict) of a run that refines its poses
    saved_at: float  # time.time() when written

    @property
    def num_gaussians(self) -> int:
        return int(self.avatar["state_dict"]["means"].shape[0])

    @property
    def faces(self) -> torch.Tensor | None:
        """The triangulation [F,3] the avatar was trained on (None where its state holds none)."""
        state = self.avatar.get("state_dict") if isinstance(self.avatar, dict) else None
        return state.get("faces") if isinstance(state, dict) else None

    def to_payload(self) -> dict:
        """Plain containers for torch.save (a dataclass would not load with ``weights_only``)."""
        return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
                **{f.name: getattr(self, f.name) for f in fields(self)}}


# ----------------------------------------------------------------------------------------------- migrations
# The pose-refinement settings that moved from "optim" to their own section "poses" in version 5, each
# with the value that reproduces a run trained before the setting existed (saved configs of version 4
# lack the settings added after version 4 was introduced).
POSE_KEYS_V4 = {  # optim.<old> -> poses.<new>
    "refine_poses": "refine", "smooth_poses": "smooth", "pose_pass": "first_pass", "pose_warmup": "warmup",
    "lr_pose": "lr_rotation", "lr_pose_transl": "lr_translation", "lr_pose_final_scale": "lr_final_scale",
    "pose_sweeps": "fits", "pose_sweep_steps": "fit_steps", "pose_fit_mask": "fit_mask",
    "pose_refits": "held_fits", "pose_refit_steps": "held_fit_steps",
}
_BEFORE_THE_SETTING = {"smooth_poses": 0, "pose_sweeps": (), "pose_pass": 0.0, "pose_refits": (),
                       "pose_fit_mask": 1.0}


def _config_v4(config: dict, as_trained: bool) -> dict:
    """Version 4's config kept pose refinement in "optim"; ``as_trained``: a run's own saved config, whose
    missing settings are those added after it was written (filled with how it was trained)."""
    optim = dict(config.get("optim") or {})
    if as_trained:
        optim = {**{k: v for k, v in _BEFORE_THE_SETTING.items() if k not in optim}, **optim}
    poses = {new: optim.pop(old) for old, new in POSE_KEYS_V4.items() if old in optim}
    if poses:  # the sweeps fitted at the test-time fit's learning rates then, unwritten
        poses["fit_lr_rotation"], poses["fit_lr_translation"] = 2e-2, 5e-4
    if "pose_refit_lr" in optim:  # the refits' translation lr was 1/40 of their rotation lr, unwritten
        lr = optim.pop("pose_refit_lr")
        poses["held_fit_lr_rotation"], poses["held_fit_lr_translation"] = lr, lr / 40
    out = {**config, "optim": optim}
    if poses:
        out["poses"] = {**poses, **(config.get("poses") or {})}
    return out


# The defaults a run of a version was trained with, for the settings a later version added or changed
# (docs/train.md): version -> (the config section, {setting: value}). Version 5 had no
# loss.lpips_region (LPIPS on the whole frame); version 6's pose-refinement defaults, which version 7
# changed; version 7's three held fits in every run, which version 8 made depend on the run's length;
# version 8's held fits pulled toward their start at the fit's own prior, version 9 toward the neighbours.
POSE_DEFAULTS_V6 = {"first_pass": 0.5, "fits": (0.2, 0.45), "fit_steps": 30, "held_fits": (0.4, 0.7),
                    "held_fit_steps": 30, "held_fit_scales": (4, 2, 1), "smooth_held": False}
POSE_DEFAULTS_V7 = {"held_fits": (0.25, 0.6, 0.85)}
POSE_DEFAULTS_V8 = {"held_fit_prior": 0.01, "held_fit_anchor": "start"}
TRAINED_DEFAULTS = {5: ("loss", {"lpips_region": "frame"}), 6: ("poses", POSE_DEFAULTS_V6),
                    7: ("poses", POSE_DEFAULTS_V7), 8: ("poses", POSE_DEFAULTS_V8)}


def _trained_defaults(config: dict, version: int, as_trained: bool) -> dict:
    """``config`` of ``version`` (a key of :data:`TRAINED_DEFAULTS`) read as the next version: when
    ``as_trained`` (a run's own config) the section's missing settings take the values its run was
    trained with; otherwise, or when the section is not a mapping (left for validation to refuse),
    unchanged: today's defaults apply."""
    name, defaults = TRAINED_DEFAULTS[version]
    section = config.get(name)
    if not as_trained or not (section is None or isinstance(section, dict)):
        return config
    return {**config, name: {**defaults, **(section or {})}}


def _v1(payload: dict) -> dict:
    """Version 1 (rmavatar 0.1.0): the avatar's config carried the run's seed (for area placement, which
    a stored avatar no longer needs); the training config's "model" section was a subset of the avatar's
    config (still readable as one); no body shape was stored (None: read from the training data)."""
    avatar = dict(payload["avatar"])
    avatar["config"] = {k: v for k, v in avatar["config"].items() if k != "seed"}
    return {**payload, "avatar": avatar, "betas": None}


def _named_rectifier(section: dict) -> dict:
    return {**section, "rectifier": "paper"} if section.get("rectifier") is True else section


def _config_v2(config: dict) -> dict:
    """Version 2's config: ``model.rectifier`` was true/false; true was the paper's design, the only one then."""
    return {**config, "model": _named_rectifier(config["model"])} if isinstance(config.get("model"), dict) else config


def _v2(payload: dict) -> dict:
    """Version 2: the rectifier's switch, in the training config and the avatar's own (``_config_v2``)."""
    avatar = {**payload["avatar"], "config": _named_rectifier(payload["avatar"]["config"])}
    return {**payload, "avatar": avatar, "config": _config_v2(payload["config"])}


def _v3(payload: dict) -> dict:
    """Version 3: no pose refinement existed; the training poses were the dataset's."""
    return {**payload, "poses": None}


def _v4(payload: dict) -> dict:
    """Version 4: pose refinement's settings lived in the config's "optim" section."""
    return {**payload, "config": _config_v4(payload["config"], as_trained=True)}


def _trained_defaults_step(version: int):
    """The checkpoint migration of a version of :data:`TRAINED_DEFAULTS`: its config as trained."""
    return lambda payload: {**payload, "config": _trained_defaults(payload["config"], version, as_trained=True)}


MIGRATIONS = {1: _v1, 2: _v2, 3: _v3, 4: _v4,  # version -> the step to version + 1
              **{version: _trained_defaults_step(version) for version in TRAINED_DEFAULTS}}


def migrate_config(config: dict, version: int | None, as_trained: bool) -> dict:
    """A training config (plain containers) of layout ``version`` in today's layout. ``version`` None:
    unknown (a hand-written file, or RUN/config.yaml written before configs were stamped): read as the
    oldest layout whose keys it has (version 2's rectifier switch, version 4's pose settings in "optim"),
    as version 4 when ``as_trained`` (a run's own file), else as today's. ``as_trained``: settings newer
    than the file take the value that reproduces how its run was trained (:data:`TRAINED_DEFAULTS`)."""
    if version is None:
        switch = (config.get("model") or {}).get("rectifier") is True
        old = any(k in (config.get("optim") or {}) for k in (*POSE_KEYS_V4, "pose_refit_lr"))
        version = 2 if switch else 4 if old or as_trained else CHECKPOINT_VERSION
    if version <= 2:
        config, version = _config_v2(config), 4  # version 3's config is version 4's
    if version == 4:
        config, version = _config_v4(config, as_trained), 5
    while version in TRAINED_DEFAULTS:
        config, version = _trained_defaults(config, version, as_trained), version + 1
    if version != CHECKPOINT_VERSION:
        raise UserError(f"config layout version {version}; this rmavatar reads versions up to "
                        f"{CHECKPOINT_VERSION} (a newer rmavatar wrote it)")
    return config


def read_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Load a checkpoint (of this or an older format version, migrated); anything else raises UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint {path} does not exist")
    try:
        with warnings.catch_warnings():
            # torch's weights-only unpickler warns about a pickle's protocol before refusing it: the refusal
            # below says what is wrong, in words that do not recommend unsafe loading
            warnings.filterwarnings("ignore", module="torch._weights_only_unpickler")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means "not our checkpoint"
        raise UserError(f"{path} is not a readable rmavatar checkpoint: {load_error(exc)}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise UserError(f"{path} is not an rmavatar checkpoint")
    version = payload.get("version")
    while version in MIGRATIONS:
        payload, version = MIGRATIONS[version](payload), version + 1
    if version != CHECKPOINT_VERSION:
        raise UserError(f"{path} has checkpoint version {payload.get('version')}; this rmavatar reads versions "
                        f"up to {CHECKPOINT_VERSION} (a newer rmavatar wrote it)")
    try:
        return Checkpoint(**{f.name: payload[f.name] for f in fields(Checkpoint)})
    except KeyError as exc:
        raise UserError(f"{path} is an incomplete rmavatar checkpoint (no {exc})") from None


# ----------------------------------------------------------------------------------------------- the body
def body_signature(body: Any) -> dict:
    """What makes a checkpoint usable with a body model: its spec, a hash of its topology and one of its
    body offsets (None without)."""
    faces = body.faces.detach().cpu().to(torch.int64).contiguous().numpy()
    offsets = getattr(body, "offsets", None)
    return {
        "spec": str(body.spec),
        "num_vertices": int(body.v_template.shape[0]),
        "num_faces": int(faces.shape[0]),
        "faces_sha1": hashlib.sha1(faces.tobytes()).hexdigest(),
        "offsets_sha1": None if offsets is None else hashlib.sha1(offsets.cpu().numpy().tobytes()).hexdigest(),
    }


def body_info(body: Any, gender: str | None) -> dict:
    """What a checkpoint keeps of its body (``Checkpoint.body``): the signature, the gender and the body
    offsets [V] (None without), from which :func:`load_saved_body` builds it again."""
    offsets = getattr(body, "offsets", None)
    return {**body_signature(body), "gender": gender, "offsets": None if offsets is None else offsets.cpu().clone()}


def load_saved_body(saved: dict, where: str, faces=None):
    """The body model a checkpoint's ``body`` (:func:`body_info`) describes, checked against it and, when
    given, the triangulation the checkpoint's avatar holds (``faces`` [F,3], as :func:`check_body`)."""
    from rmavatar.body import load_body_model

    body = load_body_model(saved["spec"], gender=saved.get("gender"), offsets=saved.get("offsets"))
    check_body(saved, body, where, faces)
    return body


def check_body(saved: dict, body: Any, where: str, faces=None) -> None:
    """Raise UserError when ``body`` cannot carry the avatar saved with signature ``saved``. ``faces``
    [F,3]: the avatar's own triangulation; a body that splits some of the same quads along their other
    diagonal (:func:`rmavatar.avatar.geometry.same_quads`: Anny built on a machine that rounds otherwise)
    carries it too, the avatar keeping its own."""
    from rmavatar.avatar.geometry import same_quads

    now = body_signature(body)
    counts = (saved["num_vertices"], saved["num_faces"]) == (now["num_vertices"], now["num_faces"])
    if not counts or (saved["faces_sha1"] != now["faces_sha1"] and (faces is None or not same_quads(faces, body.faces))):
        raise UserError(
            f"{where} was trained with body model {saved['spec']!r} ({saved['num_vertices']} vertices, "
            f"{saved['num_faces']} faces), which is incompatible with {now['spec']!r} "
            f"({now['num_vertices']} vertices, {now['num_faces']} faces)"
        )
    if saved.get("offsets_sha1") != now["offsets_sha1"]:
        raise UserError(f"{where} was trained on {saved['spec']!r} "
                        f"{'with' if saved.get('offsets_sha1') else 'without'} body offsets (a fitted shape); "
                        f"the body given has {'other' if now['offsets_sha1'] else 'no'} offsets")


def training_betas(params: dict) -> torch.Tensor:
    """The body shape [1,nb] a subject is trained with: the mean over its training frames' betas
    (every frame of a subject carries the same shape)."""
    return torch.as_tensor(np.asarray(params["betas"], np.float32).mean(0, keepdims=True))
