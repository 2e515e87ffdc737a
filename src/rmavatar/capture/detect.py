"""Person mask and 2D/3D landmarks per frame with MediaPipe 0.10.21 (its pose landmarker with person
segmentation ships inside the wheel and runs offline through the legacy ``mediapipe.solutions`` API).

MediaPipe is an optional dependency (``rmavatar[capture]``); :func:`require_mediapipe` says exactly
what to install when it is missing.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import warnings
from dataclasses import dataclass

import numpy as np

from rmavatar.utils import UserError

MEDIAPIPE_VERSION = "0.10.21"
INSTALL_HINT = (
    "rmavatar capture needs MediaPipe 0.10.21 (the last release that ships its pose model inside the "
    "package). Install it with:\n"
    "    pip install 'rmavatar[capture]'\n"
    f"    pip install --no-deps mediapipe=={MEDIAPIPE_VERSION}\n"
    "(--no-deps: MediaPipe declares numpy<2, jax and a GUI OpenCV it does not need for this; the "
    "'capture' extra installs what it does need: protobuf<7, opencv-python-headless, matplotlib, attrs)"
)


@contextlib.contextmanager
def quiet_native_stderr():
    """Hide what MediaPipe's C++ side prints on file descriptor 2 while loading (TFLite and absl
    banners); it is printed after all if the block fails with an error, not when it is interrupted
    (Ctrl-C: the banners would bury the one line that says so)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        except Exception:
            os.dup2(saved, 2)
            sink.seek(0)
            sys.stderr.write(sink.read().decode(errors="replace"))
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)


@contextlib.contextmanager
def protobuf_prototypes():
    """While MediaPipe's bindings load, give protobuf's MessageFactory the ``GetPrototype`` method that
    protobuf 5 removed (it was the class of a descriptor's messages, ``GetMessageClass`` since).

    Why: MediaPipe 0.10.21's C++ bindings (pybind11_protobuf) look the method up once, when they load;
    without it they print ``AttributeError: 'MessageFactory' object has no attribute 'GetPrototype'``
    and go on without their protobuf conversions (capture does not use them). The line was hidden while
    loading and shown when a capture was interrupted there; with the method there is no line, and the
    bindings load as on protobuf 4. The method is removed again after the import; an older protobuf
    that has it is left alone, and any other error while importing is raised as before."""
    try:
        from google.protobuf import message_factory
    except ImportError:
        yield
        return
    factory = message_factory.MessageFactory
    if hasattr(factory, "GetPrototype") or not hasattr(message_factory, "GetMessageClass"):
        yield
        return

    def GetPrototype(self, descriptor):  # noqa: N802 (protobuf's name)
        return message_factory.GetMessageClass(descriptor)

    factory.GetPrototype = GetPrototype
    try:
        yield
    finally:
        del factory.GetPrototype


def require_mediapipe():
    """Import MediaPipe's pose solution, or raise UserError with the install lines. Returns
    (the pose module, MediaPipe's version)."""
    try:
        with quiet_native_stderr(), protobuf_prototypes():
            import mediapipe
            from mediapipe.python.solutions import pose
    except ImportError as exc:
        raise UserError(f"{INSTALL_HINT}\n(import failed: {exc})") from None
    except (AttributeError, TypeError) as exc:  # e.g. a protobuf too new for this MediaPipe
        raise UserError(f"MediaPipe could not load ({exc}).\n{INSTALL_HINT}") from None
    version = getattr(mediapipe, "__version__", "?")
    if version != MEDIAPIPE_VERSION:
        raise UserError(f"MediaPipe {version} is installed; rmavatar capture needs {MEDIAPIPE_VERSION} "
                        f"(later releases no longer ship the pose model).\n{INSTALL_HINT}")
    return pose, version


@dataclass
class FrameDetection:
    """MediaPipe's result for one frame with a person.

    keypoints [33,2] pixels (pixel-centre convention of rmavatar: MediaPipe's normalised x * width);
    visibility [33] in 0..1; world [33,3] metres, hip-centred, camera-aligned axes (x right, y down,
    z away from the camera); mask [H,W] float32 0..1, the person's segmentation.
    """

    keypoints: np.ndarray
    visibility: np.ndarray
    world: np.ndarray
    mask: np.ndarray


class Detector:
    """MediaPipe pose in video mode (landmarks tracked and smoothed from frame to frame) with its person
    segmentation; a second, per-image pose instance looks for another person once the first is erased."""

    def __init__(self):
        pose, _ = require_mediapipe()
        try:
            with quiet_native_stderr(), warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)  # protobuf 6 on MediaPipe's graph setup
                self._pose = pose.Pose(static_image_mode=False, model_complexity=1, enable_segmentation=True,
                                       smooth_landmarks=True, smooth_segmentation=True)
                self._single = pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True)
        except AttributeError as exc:  # protobuf 7 removed what MediaPipe's graph setup reads
            raise UserError(f"MediaPipe could not start its pose graph ({exc}).\n{INSTALL_HINT}") from None
        with quiet_native_stderr():
            blank = np.zeros((64, 64, 3), np.uint8)  # the first call starts the graphs, which log
            self._pose.process(blank)
            self._single.process(blank)

    def close(self) -> None:
        self._pose.close()
        self._single.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __call__(self, image: np.ndarray) -> FrameDetection | None:
        """uint8 RGB [H,W,3], the clip's next frame -> the person's landmarks and mask, or None when no
        person is found. Video mode: the person is tracked from the previous frame's landmarks (the
        person detector runs only when the track is lost), and landmarks and mask are smoothed."""
        return self._process(self._pose, image)

    def look(self, image: np.ndarray) -> FrameDetection | None:
        """The same for a frame on its own (image mode: the person detector runs on it), for frames
        looked at out of order."""
        return self._process(self._single, image)

    @staticmethod
    def _process(graph, image: np.ndarray) -> FrameDetection | None:
        image = np.ascontiguousarray(image)
        h, w = image.shape[:2]
        with quiet_native_stderr():  # a one-off notice about non-square frames
            r = graph.process(image)
        if r.pose_landmarks is None or r.segmentation_mask is None:
            return None
        lm = r.pose_landmarks.landmark
        keypoints = np.array([(p.x * w, p.y * h) for p in lm], dtype=np.float32)
        visibility = np.array([p.visibility for p in lm], dtype=np.float32)
        world = np.array([(p.x, p.y, p.z) for p in r.pose_world_landmarks.landmark], dtype=np.float32)
        mask = np.clip(np.asarray(r.segmentation_mask, dtype=np.float32), 0.0, 1.0)
        return FrameDetection(keypoints, visibility, world, mask)

    def another_person(self, image: np.ndarray, person: FrameDetection) -> bool:
        """Whether the frame shows a second person: ``person`` (its mask grown by 3% of the frame) is
        painted over with the background's colour (the median of the frame's border) and MediaPipe
        looks again; a confident pose (torso visibility > 0.5) with a mask at least a third of the
        first person's, lying outside the painted region, is another person. ``person`` is MediaPipe's
        result on this very ``image`` (its mask has the image's size)."""
        from scipy import ndimage

        mine = person.mask > 0.5
        grow = max(2, round(0.03 * max(mine.shape)))
        # grown by `grow` steps of 4-connected dilation: the pixels within that city-block distance (one
        # pass, where iterated dilation took `grow` passes over the frame)
        region = ndimage.distance_transform_cdt(~mine, metric="taxicab") <= grow if mine.any() else mine
        border = np.concatenate([image[0], image[-1], image[:, 0], image[:, -1]])
        erased = np.array(image, copy=True)
        erased[region] = np.median(border, 0).astype(np.uint8)
        with quiet_native_stderr():
            r = self._single.process(erased)
        if r.pose_landmarks is None or r.segmentation_mask is None:
            return False
        torso = np.mean([r.pose_landmarks.landmark[k].visibility for k in (11, 12, 23, 24)])
        other = np.asarray(r.segmentation_mask) > 0.5
        apart = (other & ~region).sum()
        return bool(torso > 0.5 and apart >= max(mine.sum(), 1) / 3)
