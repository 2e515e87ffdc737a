"""``rmavatar capture``: from a video of one person to a native dataset with estimated poses, offline.

MediaPipe (optional extra ``rmavatar[capture]``) finds the person's mask and landmarks in each frame;
the body (Anny by default, or SMPL) is fitted to all frames at once, then Anny's shape to the person's
outline (body offsets, :mod:`rmavatar.capture.shape`); the result is a dataset
``rmavatar train`` reads, with a contact sheet of the fit. See docs/capture.md.
"""

from rmavatar.capture.pipeline import CaptureConfig, capture, intrinsics
from rmavatar.capture.shape import ShapeFitConfig

__all__ = ["CaptureConfig", "ShapeFitConfig", "capture", "intrinsics"]
