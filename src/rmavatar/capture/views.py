"""Other calibrated cameras of the same clip: a ``novel_view`` split with real ground truth.

A rig's calibration places every camera in one world; the captured dataset's world is the main camera's
frame, so another camera's viewmat there is ``T_other inv(T_main)``. Each training instant's frame of
the other video becomes a ``novel_view`` frame: its image (resized to the dataset's frame size, its
intrinsics scaled alike), the body parameters of the same instant, and its own mask. The mask is
MediaPipe's (image mode) on a crop around the fitted body as that camera sees it, so bystanders
elsewhere in a lab's view are not taken for the person, then snapped to the frame's colour edges as the
main camera's are (:func:`rmavatar.capture.matte.refine_mask`).

The videos are synchronised by their content: of the frame offsets within SYNC_SECONDS, the one at
which MediaPipe's landmarks in the two videos, triangulated with the calibration, reproject best
(the mean of each landmark's reprojection error in both views, capped at SYNC_CAP of the frame's longer
side, over SYNC_INSTANTS instants spread over the clip). Pose2Sim's demo rig, for one, starts its
cameras up to a few frames apart.

Nothing of these frames reaches the fit or training; evaluation poses them as the run posed the same
instants (meta.yaml's ``same_instant``), so the score is of the avatar seen from a view it never saw.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rmavatar.data.calibration import CalibratedCamera, pick_camera
from rmavatar.utils import UserError

SPLIT = "novel_view"
CROP_MARGIN = 0.15  # the crop around the projected body grows by this share of its larger side
CROP_HEIGHT = 640  # MediaPipe sees the crop scaled to this height (as the main video's person, WORK_HEIGHT)
SYNC_SECONDS = 0.15  # offsets tried: up to this long either way
SYNC_INSTANTS = 8  # instants the offsets are tried at
SYNC_CAP = 0.015  # a landmark's reprojection error counts at most this share of the longer side
SYNC_VISIBLE = 0.8  # landmarks MediaPipe is at least this sure of, in both views
IOU_SIDE = 512  # the body-mask check is made at this many pixels on the longer side (as bench capture's)


@dataclass
class NovelView:
    """A synchronised video of the clip by another calibrated camera."""

    video: Path
    camera: CalibratedCamera


def parse_views(specs: list[str], cameras: dict[str, CalibratedCamera], calibration: Path) -> list[NovelView]:
    """``VIDEO`` (its camera named like its file, as Pose2Sim names them) or ``VIDEO@CAMERA`` -> NovelView,
    each video checked to exist."""
    views = []
    for spec in specs:
        video, _, name = spec.rpartition("@") if "@" in spec else (spec, "", "")
        path = Path(video).expanduser()
        if not path.is_file():
            raise UserError(f"--novel-view {spec}: the video {path} does not exist")
        views.append(NovelView(path, pick_camera(cameras, name or None, path, calibration,
                                                 option=f"--novel-view {path}@CAMERA")))
    return views


@dataclass
class ViewFrames:
    """What the views added to a dataset: per frame K [M,3,3] and viewmat [M,4,4] (float32), the dataset
    frame of the same instant by the main camera (``same_instant`` [M]), the camera's name per frame,
    each camera's synchronising offset, and how well the fitted body covers each frame's mask (``body_iou`` [M]: intersection over union of
    the body's silhouette and the mask > 0.5; a check of calibration, synchronisation and mask)."""

    K: list[np.ndarray] = field(default_factory=list)
    viewmat: list[np.ndarray] = field(default_factory=list)
    same_instant: list[int] = field(default_factory=list)
    cameras: list[str] = field(default_factory=list)
    body_iou: list[float] = field(default_factory=list)
    offsets: dict[str, int] = field(default_factory=dict)  # per camera: its video's frame - the main video's

    def summary(self) -> dict:
        """Per camera: its frames, the offset it was synchronised at and the body's mean IoU with its masks."""
        per_camera = {}
        for name in dict.fromkeys(self.cameras):
            ious = [v for c, v in zip(self.cameras, self.body_iou) if c == name]
            per_camera[name] = {"frames": len(ious), "offset": self.offsets.get(name, 0),
                                "body_iou": round(float(np.mean(ious)), 4)}
        return per_camera


def _crop_box(points: np.ndarray, width: int, height: int) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right) around the projected points [P,2] grown by CROP_MARGIN, inside the
    frame; None when the body is out of view."""
    inside = (points[:, 0] > 0) & (points[:, 0] < width) & (points[:, 1] > 0) & (points[:, 1] < height)
    if inside.mean() < 0.5:
        return None
    (x0, y0), (x1, y1) = points.min(0), points.max(0)
    grow = CROP_MARGIN * max(x1 - x0, y1 - y0)
    return (max(int(y0 - grow), 0), min(int(y1 + grow) + 1, height),
            max(int(x0 - grow), 0), min(int(x1 + grow) + 1, width))


def look_in_box(detect, image: np.ndarray, box: tuple[int, int, int, int]):
    """MediaPipe (image mode) on the crop ``box`` of ``image`` (uint8 [H,W,3]), scaled so the crop is
    CROP_HEIGHT tall: (keypoints [33,2] in the frame's pixels, visibility [33], mask [H,W] float32 zero
    outside the crop), or None when it finds no one."""
    from rmavatar.capture.frames import shrink
    from rmavatar.data.io import resample

    top, bottom, left, right = box
    crop = image[top:bottom, left:right]
    scale = min(1.0, CROP_HEIGHT / crop.shape[0])
    small = shrink(crop, max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
    det = detect.look(small)
    if det is None:
        return None
    mask = np.zeros(image.shape[:2], np.float32)
    mask[top:bottom, left:right] = resample(det.mask, crop.shape[1], crop.shape[0])
    keypoints = det.keypoints * np.array([crop.shape[1] / small.shape[1], crop.shape[0] / small.shape[0]],
                                         np.float32) + np.array([left, top], np.float32)
    return keypoints, det.visibility, mask


def reprojection_error(K0: np.ndarray, K1: np.ndarray, viewmat1: np.ndarray, x0: np.ndarray, x1: np.ndarray,
                       cap: float) -> np.ndarray:
    """Each point seen at x0 [P,2] by camera 0 (K0, at the world's origin) and x1 [P,2] by camera 1 (K1,
    viewmat1 [4,4]) triangulated (linear, DLT) and reprojected: the mean of its two pixel errors, at most
    ``cap`` [P]."""
    P0 = K0 @ np.eye(3, 4)
    P1 = K1 @ viewmat1[:3]
    out = np.empty(len(x0))
    for k, (a, b) in enumerate(zip(x0, x1)):
        A = np.stack([a[0] * P0[2] - P0[0], a[1] * P0[2] - P0[1], b[0] * P1[2] - P1[0], b[1] * P1[2] - P1[1]])
        X = np.linalg.svd(A)[2][-1]
        errors = [np.linalg.norm((P @ X)[:2] / (P @ X)[2] - x) for P, x in ((P0, a), (P1, b))]
        out[k] = min(0.5 * sum(errors), cap)
    return out


def _body_iou(vertices_cam: np.ndarray, faces: np.ndarray, K: np.ndarray, mask: np.ndarray) -> float:
    """Intersection over union of the body's silhouette (camera-frame vertices [V,3]) and ``mask`` > 0.5,
    both at IOU_SIDE pixels on the longer side."""
    from rmavatar.capture.sheet import body_silhouette
    from rmavatar.data.dataset import target_size
    from rmavatar.data.io import resample

    h, w = mask.shape
    sw, sh = target_size(w, h, IOU_SIDE)
    body = body_silhouette(vertices_cam, faces, np.diag([sw / w, sh / h, 1.0]) @ K, sw, sh)
    seen = resample(mask, sw, sh) > 0.5
    union = (body | seen).sum()
    return float((body & seen).sum() / union) if union else 0.0


@dataclass
class MainView:
    """The main camera's side of a capture, as the views need it: K [3,3] of the dataset's frames,
    ``size`` (W, H), each dataset frame's video frame (``source_frames``) and MediaPipe's ``keypoints``
    [T,33,2] / ``visibility`` [T,33] in them; the training frames' positions and the fitted body there
    (``vertices`` [len(positions),V,3] in the camera's frame; ``faces`` [F,3])."""

    K: np.ndarray
    size: tuple[int, int]
    source_frames: list[int]
    keypoints: np.ndarray
    visibility: np.ndarray
    positions: list[int]
    vertices: np.ndarray
    faces: np.ndarray


class _ViewVideo:
    """One view's video, its camera placed in the main camera's frame, and its frames' crops around the
    fitted body."""

    def __init__(self, view: NovelView, calibrated_main: CalibratedCamera, main: MainView):
        from rmavatar.capture.frames import open_source

        self.view, self.main = view, main
        self.source = open_source(view.video)
        self.K = view.camera.scaled_K(*main.size)
        self.viewmat = view.camera.relative_to(calibrated_main)

    def frames(self, indices: list[int]) -> dict[int, np.ndarray]:
        """Video frames ``indices`` (those inside the clip) at the dataset's frame size."""
        from rmavatar.capture.frames import frames_at, shrink

        wanted = sorted({i for i in indices if i >= 0})
        return {i: shrink(image, *self.main.size) for i, image in frames_at(self.source, wanted)}

    def body(self, k: int) -> tuple[np.ndarray, tuple[int, int, int, int]]:
        """The fitted body of training frame ``k`` (of main.positions) in this camera's frame [V,3], and
        the crop around it; a UserError when it is out of view."""
        cam = self.main.vertices[k] @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        projected = cam @ self.K.T
        box = _crop_box(projected[:, :2] / projected[:, 2:3], *self.main.size)
        if box is None:
            raise UserError(f"--novel-view {self.view.video}: the fitted body is out of camera "
                            f"{self.view.camera.name}'s view; is it the right camera?")
        return cam, box

    def offset(self, detect, fps: float) -> int:
        """The frame offset (this video's frame = the main video's + offset) at which the landmarks of
        both triangulate best (module docstring)."""
        main = self.main
        reach = max(1, round(SYNC_SECONDS * fps))
        picks = np.unique(np.linspace(0, len(main.positions) - 1, min(SYNC_INSTANTS, len(main.positions))).round()
                          ).astype(int)
        wanted = [main.source_frames[main.positions[k]] + d for k in picks for d in range(-reach, reach + 1)]
        images = self.frames(wanted)
        cap = SYNC_CAP * max(main.size)
        errors = {}
        for k in picks:
            p = main.positions[k]
            _, box = self.body(k)
            for d in range(-reach, reach + 1):
                image = images.get(main.source_frames[p] + d)
                seen = None if image is None else look_in_box(detect, image, box)
                if seen is None:
                    continue
                both = (main.visibility[p] > SYNC_VISIBLE) & (seen[1] > SYNC_VISIBLE)
                if both.any():
                    e = reprojection_error(main.K, self.K, self.viewmat, main.keypoints[p][both], seen[0][both], cap)
                    errors.setdefault(d, []).extend(e.tolist())
        if not errors:
            raise UserError(f"--novel-view {self.view.video}: MediaPipe finds the person in none of its frames "
                            f"near the clip's instants; is it a video of the same clip?")
        best = min(errors, key=lambda d: (np.mean(errors[d]), abs(d)))
        return int(best)


def capture_views(views: list[NovelView], calibrated_main: CalibratedCamera, main: MainView, fps: float,
                  first: int, write) -> ViewFrames:
    """Each view's frames at the instants of the training frames (``main.positions``; those its video
    holds), synchronised (:meth:`_ViewVideo.offset`), written by ``write(n, image, mask)`` as dataset
    frames ``first``, ``first + 1``, ...; ``fps``: the videos' frame rate. A view without any of those
    frames, or in which MediaPipe finds no one, is a UserError naming it."""
    from rmavatar.capture.detect import Detector
    from rmavatar.capture.matte import refine_mask
    from rmavatar.data.io import to_uint8

    out = ViewFrames()
    for view in views:
        video = _ViewVideo(view, calibrated_main, main)
        with Detector() as detect:
            offset = video.offset(detect, fps)
            wanted = [main.source_frames[p] + offset for p in main.positions]
            images = video.frames(wanted)
            if not images:
                raise UserError(f"--novel-view {view.video}: the video has none of the training instants' frames "
                                f"(it is {offset:+d} frames from the main video's)")
            for k, (p, frame) in enumerate(zip(main.positions, wanted)):
                if frame not in images:  # the other video starts later or ends earlier: instants it lacks
                    continue
                cam, box = video.body(k)
                seen = look_in_box(detect, images[frame], box)
                mask = refine_mask(images[frame], seen[2] if seen is not None else np.zeros(images[frame].shape[:2],
                                                                                            np.float32))
                out.body_iou.append(_body_iou(cam, main.faces, video.K, mask))
                write(first + len(out.K), images[frame], to_uint8(mask, f"mask of {view.video} frame {frame}"))
                out.K.append(video.K.astype(np.float32))
                out.viewmat.append(video.viewmat.astype(np.float32))
                out.same_instant.append(p)
                out.cameras.append(view.camera.name)
        out.offsets[view.camera.name] = offset
    return out


@dataclass
class MainClip:
    """The main video as capture detected it: each dataset frame's video frame (``source_frames``) and
    MediaPipe's ``keypoints`` [T,33,2] / ``visibility`` [T,33] in it."""

    source_frames: list[int]
    keypoints: np.ndarray
    visibility: np.ndarray


@dataclass
class Rig:
    """A calibrated rig: the input's camera (``main``) and the other cameras' videos (``views``)."""

    main: CalibratedCamera
    views: list[NovelView]

    def capture(self, body, params: dict, train: list[int], clip: MainClip, K: np.ndarray, size: tuple[int, int],
                fps: float, write) -> ViewFrames:
        """The other cameras' frames at the training frames' instants (:func:`capture_views`) of a clip
        fitted with ``body`` and ``params`` (the dataset's SMPL-style parameters), its frames of ``size``
        seen by K; ``write(n, image, mask)`` writes dataset frame n."""
        import torch

        from rmavatar.body import PoseSequence, posed_vertices

        poses = PoseSequence.from_params(params).select(torch.as_tensor(train))
        betas = np.asarray(params["betas"]).reshape(-1)[:min(10, int(getattr(body, "num_betas", 0)))]
        with torch.no_grad():
            vertices = posed_vertices(body, poses, torch.as_tensor(betas)[None] if len(betas) else None)
        main = MainView(K=K, size=size, source_frames=clip.source_frames, keypoints=clip.keypoints,
                        visibility=clip.visibility, positions=train, vertices=vertices.cpu().numpy(),
                        faces=body.faces.cpu().numpy())
        return capture_views(self.views, self.main, main, fps, len(clip.source_frames), write)


def open_rig(calibration: str | None, camera: str | None, videos: list[str], video: Path) -> Rig | None:
    """The calibration's cameras for a capture of ``video`` (its camera ``camera``, else the one named like
    it) with the other ``videos`` (``VIDEO[@CAMERA]``), or None without a calibration."""
    if calibration is None:
        return None
    from rmavatar.data.calibration import read_calibration

    cameras = read_calibration(calibration)
    main = pick_camera(cameras, camera, video, calibration)
    views = parse_views(videos, cameras, Path(calibration))
    same = [v.video for v in views if v.camera.name == main.name]
    if same:
        raise UserError(f"--novel-view {same[0]} is camera {main.name}, the input's own: a novel view needs another camera")
    return Rig(main, views)


PER_FRAME = ("global_orient", "body_pose", "transl", "hand_pose", "hand_found")  # params with a row per frame


def with_views(params: dict, views: ViewFrames, K: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray]:
    """The dataset's params, K [N+M,3,3] and viewmat [N+M,4,4] with the views' M frames after the clip's
    N: each view frame takes the parameters of its instant's frame."""
    rows = np.asarray(views.same_instant)
    out = {k: (np.concatenate([v, np.asarray(v)[rows]]) if k in PER_FRAME else v) for k, v in params.items()}
    n = len(params["global_orient"])
    Ks = np.concatenate([np.broadcast_to(K, (n, 3, 3)), np.stack(views.K)]).astype(np.float32)
    viewmats = np.concatenate([np.broadcast_to(np.eye(4), (n, 4, 4)), np.stack(views.viewmat)]).astype(np.float32)
    return out, Ks, viewmats


def clip_params(params: dict, n: int) -> dict:
    """``params`` of the clip's first ``n`` frames (without the other cameras' frames)."""
    return {k: (np.asarray(v)[:n] if k in PER_FRAME else v) for k, v in params.items()}

