"""How well ``rmavatar capture`` finds the fingers: a synthetic clip whose finger poses are known, captured,
and the captured finger joints scored against the truth.

    PYTHONPATH=src python scripts/measure_hand_capture.py OUT.json [--work DIR] [--frames 48] [--size 1080]

Renders the synthetic subject (``rmavatar synth``'s neutral Anny in its tunic, seed 0) standing in front of
the camera, whole body in view, forearms raised in front of the chest, swaying left and right while the
wrists turn and both hands go through open, fist, open, pointing and spread
(:func:`rmavatar.data.synth.motion.finger_motion`, 8 frames from one shape to the next, the right hand half
a shape behind), ``--size`` pixels square, as a folder of frames (30 frames/s). Then captures it twice with
the true field of view, the real ``capture`` path: with hand capture (the defaults) and without (the
baseline: the body's relaxed hands, the body fit's wrists).

Scores per finger (thumb, index, middle, ring, pinky) and overall, over the frames where capture found
the hand and over all frames: the joints' angle error (the geodesic angle of R_true^T R_est of each of
the 15 joints' local rotations, degrees; a finger's first joint with SMPL's hand joint, which turns the
four fingers too) and the bones' direction error (the angle between the true and
the captured direction of each finger's three bones in the camera's frame, wrist and body fit included);
the share of frames that found each hand; the seconds per frame of the hand step. Writes the JSON to
OUT.json.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

FPS = 30.0


def clip_poses(n: int, axes, seed: int = 0) -> dict[str, np.ndarray]:
    """World-frame poses of the clip: body facing the camera, yaw swaying +-25 degrees, forearms raised
    (hands in front of the shoulders), the wrists turning; the fingers through finger_motion's shapes."""
    from rmavatar.data.synth.motion import finger_motion

    rng = np.random.default_rng(seed)
    t = np.arange(n) / FPS
    pose = np.zeros((n, 69))

    def joint(j, x=0.0, y=0.0, z=0.0):  # body_pose holds SMPL joints 1..23
        pose[:, 3 * (j - 1):3 * j] = np.stack(np.broadcast_arrays(x, y, z), 1)

    wave = lambda amp, period, phase=0.0: amp * np.sin(2 * math.pi * t / period + phase)  # noqa: E731
    joint(16, z=-1.2 + wave(0.1, 1.7))
    joint(17, z=1.2 + wave(0.1, 1.9, 1.0))
    joint(18, y=-2.0 + wave(0.15, 1.3))
    joint(19, y=2.0 + wave(0.15, 1.1, 2.0))
    joint(20, x=wave(0.5, 1.6), z=wave(0.3, 2.3))  # the wrists turn the palms in and out, up and down
    joint(21, x=wave(0.5, 1.4, 1.0), z=wave(0.3, 2.1, 0.5))
    yaw = wave(math.radians(25), 3.2)
    go = np.stack([np.zeros(n), yaw, np.zeros(n)], 1)
    hands = finger_motion(n, axes, rng, frames_per_shape=8.0)
    return {"global_orient": go, "body_pose": pose, "transl": np.zeros((n, 3)), "hand_pose": hands}


def render_clip(folder: Path, n: int, size: int) -> tuple[dict, np.ndarray, np.ndarray, float]:
    """Frames 00000.png ... into ``folder``; returns the true poses, K, viewmat and the horizontal fov."""
    from PIL import Image
    from scipy.spatial.transform import Rotation

    from rmavatar.body import PoseSequence, load_body_model, posed_vertices
    from rmavatar.body.hands import hand_axes
    from rmavatar.data.synth.motion import look_at
    from rmavatar.data.synth.render import render
    from rmavatar.data.synth.subject import build_subject, garment_state

    body = load_body_model("anny")
    subject = build_subject(body, 0)
    truth = clip_poses(n, hand_axes(body))
    verts = posed_vertices(body, PoseSequence.from_arrays(**truth)).numpy()
    ys = body.v_template[:, 1]
    lo, hi = float(ys.min()), float(ys.max())
    distance = 3.0
    f = size * 0.9 * distance / (1.15 * (hi - lo))  # synth's framing: the whole body with room to spare
    K = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.5 * (lo + hi), 0.0])
    viewmat = look_at(target + np.array([0.0, 0.1, distance]), target)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        image, _ = render(subject, verts[i], Rotation.from_rotvec(truth["global_orient"][i]).as_matrix(),
                          garment_state(truth["body_pose"][i]), K, viewmat, size, size, ss=2)
        Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)).save(folder / f"{i:05d}.png")
    fov = math.degrees(2 * math.atan(size / 2 / f))
    return truth, K, viewmat, fov


def finger_rotations(params: dict) -> torch.Tensor:
    """[T,2,15,3,3]: each finger joint's rotation relative to its parent, the four fingers' first joints
    composed with SMPL's hand joint (22 / 23), which turns them too: a finger's base relative to the wrist,
    whichever of the two joints holds the turn."""
    import roma

    from rmavatar.body.base import HAND_JOINT_NAMES

    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    R = roma.rotvec_to_rotmat(t(params["hand_pose"]).reshape(-1, 2, 15, 3))
    hand = roma.rotvec_to_rotmat(t(np.asarray(params["body_pose"])[:, 63:69]).reshape(-1, 2, 3))
    bases = [k for k, name in enumerate(HAND_JOINT_NAMES) if name.endswith("1") and not name.startswith("thumb")]
    R[:, :, bases] = hand[:, :, None] @ R[:, :, bases]
    return R


def joint_errors(truth: dict, est: dict) -> np.ndarray:
    """[T,2,15] degrees: the geodesic angle between true and captured rotations of each joint."""
    import roma

    a, b = finger_rotations(truth), finger_rotations(est)
    return torch.rad2deg(roma.rotmat_to_rotvec(a.transpose(-1, -2) @ b).norm(dim=-1)).numpy()


def bone_errors(body, truth: dict, viewmat: np.ndarray, est: dict) -> np.ndarray:
    """[T,2,5,3] degrees: per hand and finger the angle between the true and captured directions of its
    three bones (joint 1 -> 2 -> 3 -> tip) in the camera's frame."""
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        true_pts = body(None, *(t(truth[k]) for k in ("global_orient", "body_pose", "transl")),
                        hand_pose=t(truth["hand_pose"])).hand_points.double().numpy()
        est_pts = body(None, *(t(est[k]) for k in ("global_orient", "body_pose", "transl")),
                       hand_pose=t(est["hand_pose"])).hand_points.double().numpy()
    true_pts = true_pts @ viewmat[:3, :3].T  # directions only: the rotation into the camera's frame

    def bones(p):
        chain = p.reshape(-1, 2, 21, 3)[:, :, 1:].reshape(-1, 2, 5, 4, 3)
        d = chain[:, :, :, 1:] - chain[:, :, :, :-1]
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    cos = np.clip((bones(true_pts) * bones(est_pts)).sum(-1), -1, 1)
    return np.degrees(np.arccos(cos))


def summarise(joint_err: np.ndarray, bone_err: np.ndarray, found: np.ndarray) -> dict:
    """Means per finger and overall, over the frames that found the hand and over all frames."""
    from rmavatar.body.base import FINGERS, HAND_JOINT_NAMES

    def mean(a: np.ndarray) -> float | None:
        return round(float(a.mean()), 2) if a.size else None

    out = {}
    for name, mask in (("found", found), ("all", np.ones_like(found))):
        per = {}
        for f, finger in enumerate(FINGERS):
            cols = [k for k, j in enumerate(HAND_JOINT_NAMES) if j.startswith(finger)]
            per[finger] = {"joint_deg": mean(joint_err[:, :, cols][mask]), "bone_deg": mean(bone_err[:, :, f][mask])}
        per["overall"] = {"joint_deg": mean(joint_err[mask]), "bone_deg": mean(bone_err[mask])}
        out[name] = per
    return out


def run_capture(frames: Path, out: Path, fov: float, hands: bool) -> tuple[dict, dict]:
    from rmavatar.capture import CaptureConfig, capture

    cfg = CaptureConfig(fov=fov, device="cpu", test_fraction=0.1)
    if not hands:
        cfg.hands = None
    summary = capture(frames, out, cfg, progress=False, overwrite=True)
    with np.load(out / "smpl.npz") as d:
        params = {k: d[k] for k in d.files}
    with np.load(out / "capture.npz") as d:
        params["source_index"] = d["source_index"]
    return summary, params


def main() -> int:
    from rmavatar.body import load_body_model

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("json", type=Path, help="where to write the result")
    ap.add_argument("--work", type=Path, default=None,
                    help="folder for the frames and datasets (kept; frames rendered there before are reused)")
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--size", type=int, default=1080)
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="hand_capture_"))
    start = time.perf_counter()
    saved = work / "truth.npz"
    reused = saved.is_file()
    if reused:  # rendered by an earlier run with --work
        with np.load(saved) as d:
            truth = {k: d[k] for k in ("global_orient", "body_pose", "transl", "hand_pose")}
            K, viewmat, fov = d["K"], d["viewmat"], float(d["fov"])
        if len(truth["hand_pose"]) != args.frames or int(K[0, 2] * 2) != args.size:
            raise SystemExit(f"{work} holds another clip; give another --work")
    else:
        truth, K, viewmat, fov = render_clip(work / "frames", args.frames, args.size)
        np.savez(saved, K=K, viewmat=viewmat, fov=fov, **truth)
    rendered = time.perf_counter() - start
    body = load_body_model("anny")
    report = {"clip": {"frames": args.frames, "size": args.size, "fov_deg": round(fov, 3), "fps": FPS,
                       "render_seconds": None if reused else round(rendered, 1)}}
    relaxed = body.relaxed_hand_pose.numpy()
    seen = np.zeros((args.frames, 2), bool)  # per source frame: the captured run found the hand
    for name, hands in (("captured", True), ("baseline_relaxed", False)):
        summary, est = run_capture(work / "frames", work / name, fov, hands)
        idx = est["source_index"]
        sel = {k: v[idx] for k, v in truth.items()}
        if hands:
            seen[idx] = est["hand_found"]
        else:
            est["hand_pose"] = np.broadcast_to(relaxed, (len(idx), 90)).copy()
        n = summary["decoded"]
        # the baseline is scored on the frames where the captured run found each hand, as the capture
        report[name] = {
            **summarise(joint_errors(sel, est), bone_errors(body, sel, viewmat, est), seen[idx]),
            "frames_with_person": int(len(idx)),
            "seconds_per_frame": {k: round(v / n, 4) for k, v in summary["seconds"].items()},
            "total_seconds_per_frame": round(summary["total_seconds"] / n, 4),
        }
        if hands:
            report[name]["found_share"] = {"left": round(float(seen[idx, 0].mean()), 4),
                                           "right": round(float(seen[idx, 1].mean()), 4)}
            # the hand step's own seconds per frame: MediaPipe's hand landmarks and the hand fit
            report[name]["hand_seconds_per_frame"] = {
                "landmarks": round(summary["hands"]["landmark_seconds"] / n, 4),
                "fit": round(summary["hands"]["fit_seconds"] / n, 4)}
    print(json.dumps(report, indent=2))
    args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
