"""A trained avatar: a run folder read back as something that poses and renders (``load_trained``).

The run folder's layout, its checkpoint and their migrations are in :mod:`rmavatar.avatar.run`.
Everything that uses a trained avatar (eval, animate, render, export, view, bench, the demo) goes through
:class:`TrainedAvatar`; only training writes checkpoints (``rmavatar.train.checkpoint``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from rmavatar.avatar.model import Avatar, drawable_copy
from rmavatar.avatar.run import RunFolder, load_saved_body, training_betas
from rmavatar.body import PoseSequence, apply_pose_corrections, posed_vertices, rest_pose
from rmavatar.body.poses import hands_given
from rmavatar.render.gaussians import GaussianSet, render_gaussians
from rmavatar.utils import UserError
from rmavatar.utils.graphs import Replay


# ----------------------------------------------------------------------------------------------- the avatar
@dataclass
class TrainedAvatar:
    """A trained avatar bound to its body model, in evaluation mode.

    avatar: the :class:`Avatar` (``avatar(vertices [V,3], pose_input) -> GaussianSet``); body: the
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
    cuda_graphs: bool = True  # pose() replays body + avatar as one CUDA graph on a GPU (False: eagerly)
    _poser: Replay | None = field(default=None, repr=False)  # pose()'s replayed graph, made at its first call
    _checked: PoseSequence | None = field(default=None, repr=False)  # the sequence pose() last checked

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
    def gaussians(self, vertices: torch.Tensor, body_pose: torch.Tensor,
                  hand_pose: torch.Tensor | None = None) -> GaussianSet:
        """World-space Gaussians on posed ``vertices`` [V,3], rectified for ``body_pose`` [69] and
        ``hand_pose`` [90] (None: relaxed hands; read only by an avatar whose rectifier sees the hands),
        every stored SH band."""
        hands = None if hand_pose is None else hand_pose.reshape(90).to(self.device)
        pose = self.avatar.pose_input(body_pose.reshape(69).to(self.device), hands)
        return self.avatar.world_gaussians(vertices.to(self.device), pose)

    def pose(self, poses: PoseSequence, i: int, keep: bool = True) -> GaussianSet:
        """The GaussianSet of frame ``i`` of ``poses``: body, mesh embedding and rectifier, replayed as one
        CUDA graph on a GPU. ``keep=False``: the tensors are the graph's output buffers, valid until the
        next call (a render loop that draws each frame at once saves their copies)."""
        if self._checked is not poses:  # checked once per sequence: the graph itself reads nothing back
            for name in ("global_orient", "body_pose", "transl", "hand_pose"):
                if getattr(poses, name) is not None and not bool(torch.isfinite(getattr(poses, name)).all()):
                    raise UserError(f"the poses' {name} contains NaN or infinite values")
            self._checked = poses
        one = poses.select(slice(i, i + 1)).to(self.device)
        shape = self._shape()
        if self._poser is None:
            self._poser = Replay(self._pose_one, enabled=self.cuda_graphs)
        out = self._poser(one.global_orient, one.body_pose, one.transl, one.hand_rows(),
                          *(() if shape is None else (shape,)))
        means, quats, scales, opacities, sh, *frames = (t.clone() for t in out) if keep else out
        return GaussianSet(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh,
                           sh_degree=self.avatar.config.sh_degree, frames=frames[0] if frames else None)

    @property
    def posing_graph(self) -> Replay | None:
        """:meth:`pose`'s Replay (whether it captured, why not), once pose() has run."""
        return self._poser

    def _pose_one(self, global_orient, body_pose, transl, hand_pose, betas=None) -> tuple[torch.Tensor, ...]:
        """:meth:`pose` as a function of tensors ([1,3], [1,69], [1,3], [1,90] or [1,0] for no hand pose,
        [1,nb]) for :class:`Replay`."""
        hands = hands_given(hand_pose)
        vertices = self.body(betas, global_orient, body_pose, transl, check_values=False,
                             hand_pose=hands).vertices.float()[0]
        gs = self.avatar.world_gaussians(vertices, self.avatar.pose_input(body_pose.reshape(69),
                                                                            None if hands is None else hands[0]))
        return (gs.means, gs.quats, gs.scales, gs.opacities, gs.sh) + (() if gs.frames is None else (gs.frames,))

    @torch.no_grad()
    def render(self, gs: GaussianSet, camera, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
        """``gs`` seen by ``camera`` (anything with viewmat [4,4], K [3,3], width, height) over
        ``background`` (RGB in 0..1, or None for transparent black) -> image [H,W,3]."""
        image, _, _ = render_gaussians(gs, camera.viewmat, camera.K, camera.width, camera.height, background)
        return image


def load_trained(run_dir: str | os.PathLike, device: str | torch.device = "cpu",
                 every_gaussian: bool = False) -> TrainedAvatar:
    """Read RUN/checkpoints/last.pt: the avatar on its body model, its shape, the config and the iteration.

    The avatar holds only the Gaussians a rasterizer can draw (:func:`rmavatar.avatar.model.drawable_copy`):
    the others (opacity under 1/255) change no pixel but cost their posing in every frame, and trained
    avatars hold many (docs/model.md, "Measured choices"). ``every_gaussian``: keep them all, as trained."""
    run = RunFolder(run_dir)
    run.check_trained()
    path = run.checkpoint
    ckpt = run.read_checkpoint()
    body = load_saved_body(ckpt.body, str(path), faces=ckpt.faces)
    avatar = Avatar.from_state(body, ckpt.avatar, where=str(path))
    avatar.eval()
    if not every_gaussian:
        avatar = drawable_copy(avatar)
    config = ckpt.config
    betas, betas_error = ckpt.betas, None
    if betas is None and body.num_betas > 0:  # a version-1 checkpoint: the shape is its training data's
        from rmavatar.data import load_dataset

        spec = ckpt.data_spec
        try:
            betas = training_betas(load_dataset(spec).params("train"))
        except UserError as exc:
            betas_error = f"the run's body shape comes from its training data {spec!r}, which cannot be read: {exc}"
    training_poses = None
    if ckpt.poses is not None:
        base = ckpt.poses["base"]
        training_poses = apply_pose_corrections(
            PoseSequence(base["global_orient"], base["body_pose"], base["transl"], base.get("hand_pose")),
            ckpt.poses["delta"])
    return TrainedAvatar(
        avatar=avatar.to(device), body=body.to(device),
        betas=None if betas is None else torch.as_tensor(betas, dtype=torch.float32).to(device),
        iteration=int(ckpt.iteration), data_spec=str(ckpt.data_spec),
        size=config["data"]["size"], config=config, betas_error=betas_error, training_poses=training_poses,
    )
