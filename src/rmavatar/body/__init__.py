"""Body models driven by SMPL-format parameters: user-supplied SMPL files and the free Anny body.

``load_body_model("anny" | "anny:PRESET" | "smpl:PATH", gender=None, offsets=None) -> BodyModel``; see
:class:`rmavatar.body.base.BodyModel` for the interface and ``docs/body.md`` for the user guide.
"""

from __future__ import annotations

from rmavatar.body.base import SMPL_JOINT_NAMES, SMPL_PARENTS, BodyModel, BodyOutput
from rmavatar.body.corrections import (CORRECTION_DIM, apply_pose_corrections, joint_angle_errors, pose_error,
                                      smooth_poses)
from rmavatar.body.lbs import axis_angle_to_matrix, global_rotations, lbs
from rmavatar.body.motion import Motion, load_motion, motion_to_sequence
from rmavatar.body.poses import PoseSequence, posed_vertices, rest_pose
from rmavatar.utils import UserError

__all__ = [
    "BodyModel", "BodyOutput", "CORRECTION_DIM", "Motion", "PoseSequence", "SMPL_JOINT_NAMES", "SMPL_PARENTS",
    "apply_pose_corrections", "axis_angle_to_matrix", "global_rotations", "joint_angle_errors", "lbs", "load_body_model", "load_motion", "motion_to_sequence",
    "pose_error", "posed_vertices", "rest_pose", "smooth_poses",
]  # fmt: skip

_GENDERS = ("neutral", "male", "female")


def load_body_model(spec: str, gender: str | None = None, offsets=None) -> BodyModel:
    """Build a body from a spec string (the CLI's ``--body``); ``offsets`` [V] (Anny only): body offsets,
    metres along the rest normals (a shape fitted to a person, ``AnnyBody``).

    - ``"anny"``: the Anny body; the preset follows ``gender`` (``male``/``female``, else ``neutral``).
    - ``"anny:PRESET"``: a named Anny phenotype (``neutral``, ``male``, ``female``, ``child``).
    - ``"smpl:PATH"``: an SMPL, SMPL-H or SMPL-X ``.pkl``/``.npz`` file (the kind is read from the file),
      or a folder holding ``SMPL_{NEUTRAL,MALE,FEMALE}`` files, else ``SMPLX_*`` or ``SMPLH_*`` ones
      (``gender`` picks one; neutral when None).
    """
    if gender is not None and gender not in _GENDERS:
        raise UserError(f"gender must be one of {', '.join(_GENDERS)} or None, got {gender!r}")
    kind, _, arg = spec.partition(":")
    if kind == "anny":
        from rmavatar.body.anny import AnnyBody

        return AnnyBody(arg or (gender if gender in ("male", "female") else "neutral"), offsets)
    if offsets is not None:
        raise UserError(f"body offsets are for the Anny body; {spec!r} takes its shape from its betas")
    if kind == "smpl":
        if not arg:
            raise UserError("--body smpl needs a path: smpl:PATH (an SMPL .pkl/.npz file or a folder)")
        from rmavatar.body.smpl import SmplBody

        return SmplBody.from_path(arg, gender)
    raise UserError(f"unknown body {spec!r}: use 'anny', 'anny:PRESET' or 'smpl:PATH'")
