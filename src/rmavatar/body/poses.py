"""Sequences of SMPL-format poses and the posed body they give.

``PoseSequence`` holds global_orient [N,3], body_pose [N,69], transl [N,3] (float32 tensors, SMPL's
conventions) and, where the source has them, hand_pose [N,90] (MANO's 15 joints per hand, left then
right: :data:`rmavatar.body.base.HAND_JOINT_NAMES`); :func:`posed_vertices` runs a body model over it
in chunks; :func:`rest_pose` gives the canonical standing poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from rmavatar.utils import UserError


@dataclass
class PoseSequence:
    """SMPL-convention poses: global_orient [N,3], body_pose [N,69], transl [N,3] (float32 tensors);
    hand_pose [N,90] or None (no finger data: each body shows its relaxed hands)."""

    global_orient: torch.Tensor
    body_pose: torch.Tensor
    transl: torch.Tensor
    hand_pose: torch.Tensor | None = None

    @classmethod
    def from_arrays(cls, global_orient, body_pose, transl, hand_pose=None) -> "PoseSequence":
        """From numpy arrays or tensors (e.g. a dataset split's ``params``), as float32 tensors."""
        t = lambda a: torch.as_tensor(np.asarray(a, np.float32) if not torch.is_tensor(a) else a,  # noqa: E731
                                      dtype=torch.float32)
        return cls(t(global_orient), t(body_pose), t(transl), None if hand_pose is None else t(hand_pose))

    @classmethod
    def from_params(cls, params) -> "PoseSequence":
        """From a dataset split's ``params`` (``Dataset.params``): its hand poses where it has them."""
        return cls.from_arrays(params["global_orient"], params["body_pose"], params["transl"], params.get("hand_pose"))

    def __len__(self) -> int:
        return int(self.global_orient.shape[0])

    def select(self, index) -> "PoseSequence":
        hands = None if self.hand_pose is None else self.hand_pose[index]
        return PoseSequence(self.global_orient[index], self.body_pose[index], self.transl[index], hands)

    def hand(self, i: int) -> torch.Tensor | None:
        """Frame ``i``'s hand pose [90], or None without finger poses."""
        return None if self.hand_pose is None else self.hand_pose[i]

    def hand_rows(self) -> torch.Tensor:
        """``hand_pose``, or an empty [N,0] tensor without finger poses: always a tensor, so a function
        replayed as a CUDA graph keeps one argument layout (:func:`hands_given` reads it back)."""
        return self.hand_pose if self.hand_pose is not None else self.transl.new_zeros(len(self), 0)

    def to(self, device) -> "PoseSequence":
        hands = None if self.hand_pose is None else self.hand_pose.to(device)
        return PoseSequence(self.global_orient.to(device), self.body_pose.to(device), self.transl.to(device), hands)

    def joint_rotvecs(self) -> torch.Tensor:
        """[N,24,3]: the global orientation, then the 23 body joints, as axis-angle vectors."""
        return torch.cat((self.global_orient, self.body_pose), 1).reshape(len(self), 24, 3)


def hands_given(hand_rows: torch.Tensor) -> torch.Tensor | None:
    """:meth:`PoseSequence.hand_rows`' tensor back as a hand pose: None where it is empty."""
    return hand_rows if hand_rows.shape[-1] else None


def rest_pose(kind: str = "tpose") -> PoseSequence:
    """A one-frame canonical pose at the origin: 'tpose' (all zero) or 'apose' (arms lowered 45 degrees
    at the shoulders, as many avatar methods train in)."""
    go = torch.zeros(3)
    pose = torch.zeros(69)
    if kind == "apose":
        # body_pose holds joints 1..23; SMPL joints 16/17 are the left/right shoulders.
        # The body's left arm points along +x, so lowering it is a negative turn about z.
        pose[(16 - 1) * 3 + 2] = -np.pi / 4
        pose[(17 - 1) * 3 + 2] = np.pi / 4
    elif kind != "tpose":
        raise UserError(f"unknown rest pose {kind!r} (choose tpose or apose)")
    return PoseSequence(go[None], pose[None], torch.zeros(1, 3))


@torch.no_grad()
def posed_vertices(body, poses: PoseSequence, betas: torch.Tensor | None = None, chunk: int = 32) -> torch.Tensor:
    """Posed vertices [n,V,3] (float32, on the body's device) of every pose of ``poses``.

    ``betas``: None (the body's default shape), [1,nb] (one shape for all frames) or [n,nb] (per frame).
    Runs ``chunk`` frames per body forward to bound memory.
    """
    device = body.v_template.device
    poses = poses.to(device)
    if betas is not None:
        betas = torch.as_tensor(betas, dtype=torch.float32).to(device)
    out = []
    for s in range(0, len(poses), chunk):
        part = poses.select(slice(s, s + chunk))
        b = betas[s:s + chunk] if betas is not None and betas.shape[0] > 1 else betas
        out.append(body(b, part.global_orient, part.body_pose, part.transl, hand_pose=part.hand_pose).vertices.float())
    return torch.cat(out, 0)
