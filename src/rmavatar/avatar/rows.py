"""What each Gaussian row of an avatar gathers from its face: the face's slot among the binding faces,
its row of a posed mesh's face table, and the rest-mesh constants the local rectifier reads.

The gathers that depend only on which face a row sits on are made once and reused by every step
(:class:`RowGathers`): density control replaces ``face_ids`` (they are made anew), capacity buffers
rewrite rows in place (:meth:`RowGathers.refresh` recomputes them into the same memory, where a captured
CUDA graph reads them), ``.to()`` replaces the buffers they come from (made anew).
"""

from __future__ import annotations

import torch

from rmavatar.avatar.geometry import FaceTable


def face_slots(face_ids: torch.Tensor, binding_faces: torch.Tensor, num_faces: int) -> torch.Tensor:
    """Index of every row's face ``face_ids`` [N] in ``binding_faces`` [Fb] of a mesh of ``num_faces``
    faces: [N]. Checks that every face is a binding face (a host sync)."""
    dev = face_ids.device
    lookup = torch.full((num_faces,), -1, dtype=torch.long, device=dev)
    lookup[binding_faces] = torch.arange(binding_faces.shape[0], device=dev)
    slot = lookup[face_ids]
    if bool((slot < 0).any()):
        raise ValueError("some Gaussians are attached to faces outside binding_faces")
    return slot


def posed_rows(table: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
    """Every row's row [N,W] of a posed mesh's face table [Fb,W] (``slot`` [N]: from :func:`face_slots`).
    index_select: its backward (pose refinement, fitting) is an index_add, faster on the CPU than
    indexing's (docs/model.md, "Measured choices")."""
    return table.index_select(0, slot)


def frame_points(wR: torch.Tensor, M: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
    """w R mu + M [N,3]: face-local positions ``means`` [N,3] placed by per-row frames w R [N,3,3] and
    origins M [N,3] (the posed mu* on a posed mesh's rows, the rest-mesh position on the rest frames)."""
    return torch.baddbmm(M.unsqueeze(-1), wR, means.unsqueeze(-1)).squeeze(-1)


def posed_means(g: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
    """mu* = w R mu + M [N,3] alone, from the rows ``g`` [N,W] of a posed mesh's face table (:func:`posed_rows`)
    and the face-local ``means`` [N,3] (the paper's rectifier reads it)."""
    return frame_points(g[:, FaceTable.wR].unflatten(-1, (3, 3)), g[:, FaceTable.M], means)


def _refill(old: torch.Tensor | None, new: torch.Tensor | None) -> torch.Tensor | None:
    """``new``'s values in ``old``'s memory where the shapes agree (else ``new``)."""
    if old is None or new is None or old.shape != new.shape:
        return new
    return old.copy_(new)


def _same(a, b) -> bool:
    return a is b if torch.is_tensor(a) else a == b


class RowGathers:
    """An avatar's per-row gathers, each kept with the identities (and in-place versions) of the tensors
    it was gathered from and made again when one of them changed; hold one per avatar (a copy of an
    avatar with other rows needs its own)."""

    def __init__(self):
        self._slot = None  # (key, slot [N])
        self._local = None  # (key, (wR [N,3,3], M [N,3], group [N] or None))

    def slot(self, avatar) -> torch.Tensor:
        """Every row's index into ``avatar.binding_faces`` [N]: checked (a host sync) once per
        ``face_ids`` tensor."""
        key = (avatar.face_ids, avatar.face_ids._version, avatar.binding_faces, avatar.binding_faces._version)
        if self._slot is not None and all(_same(a, b) for a, b in zip(self._slot[0], key)):
            return self._slot[1]
        slot = face_slots(avatar.face_ids, avatar.binding_faces, avatar.faces.shape[0])
        if self._slot is not None and self._slot[0][0] is avatar.face_ids:  # rows rewritten in place: so is the slot
            slot = _refill(self._slot[1], slot)
        self._slot = (key, slot)
        return slot

    def local(self, avatar) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The local rectifier's per-row constants: the rest frames as w R [N,3,3], the rest centroids
        [N,3] and the pose-mask groups [N] (None without pose masks)."""
        slot = self.slot(avatar)
        groups = getattr(avatar, "face_pose_group", None)
        key = (slot, slot._version, avatar.rest_frames, avatar.rest_scales, avatar.rest_centroids, groups)
        if self._local is None or not all(_same(a, b) for a, b in zip(self._local[0], key)):
            values = (avatar.rest_scales[slot, None, None] * avatar.rest_frames[slot], avatar.rest_centroids[slot],
                      None if groups is None else groups[avatar.face_ids])
            if self._local is not None and self._local[0][0] is slot:  # rows rewritten in place: so are these
                values = tuple(_refill(old, new) for old, new in zip(self._local[1], values))
            self._local = (key, values)
        return self._local[1]

    def refresh(self, avatar) -> None:
        """Recompute every gather after the rows were rewritten in place, into the same tensors."""
        self.local(avatar)
