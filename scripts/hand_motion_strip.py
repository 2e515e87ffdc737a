"""A frame strip of the Anny body driven by a motion file with finger poses, to look at the fingers.

    python scripts/hand_motion_strip.py OUT.png [--motion-out hands.npz] [--body-motion aist_demo.npz] [--run RUN]

Writes an AMASS-style SMPL-H motion (``poses [N,156]``, z-up, ``mocap_framerate``) in which both hands go
open -> fist -> pointing index -> open, reads it back with ``rmavatar.body.load_motion`` (as ``animate``,
``export --motion`` and ``view`` do), turns it upright and facing the camera as ``animate`` and ``view``
do, and draws six frames of the posed Anny mesh: the whole body from the front, then each hand close up
from the front (the fingers seen bending in profile) and from below (the palm side when standing). The
body stands with its arms lowered, or moves as the body poses of ``--body-motion``. With ``--run`` the
same pictures show a trained avatar (posed and rendered as ``animate`` does) instead of the bare mesh.

The fist is written in MANO's convention, not read off Anny: at the T-pose the left hand's fingers point
along +x with the palm down (-y), so bending them towards the palm (tips towards -y) is a turn about -z;
the right hand's fingers point along -x and bend about +z. The thumbs point forward and out, along
(+-1, 0, 1), and bend across the palm about (1, 0, -1) / sqrt(2) (left) and (1, 0, 1) / sqrt(2) (right).
A wrong finger mapping in the body shows here as fingers bending backwards.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw
from scipy.spatial.transform import Rotation

from rmavatar.animate.motion import recenter_motion
from rmavatar.body import load_body_model, load_motion, motion_to_sequence, posed_vertices
from rmavatar.body.base import SMPL_REST_JOINTS
from rmavatar.body.render import render_mesh

FPS = 30.0
# The left hand's flexion axis per MANO joint (index, middle, pinky, ring: 3 joints each, then the thumb);
# the right hand's is its mirror image in x, an axial vector: (x, -y, -z).
LEFT_AXES = np.array([[0.0, 0.0, -1.0]] * 12 + [[2**-0.5, 0.0, -(2**-0.5)]] * 3)
AXES = np.stack([LEFT_AXES, LEFT_AXES * [1.0, -1.0, -1.0]])  # [2 hands, 15 joints, 3]
# Bend in radians per joint from the palm out, for a fist: the knuckles and middle joints bend most.
FINGER_FIST = (1.4, 1.6, 1.0)
THUMB_FIST = (0.4, 0.6, 0.8)
# Keyframes (time in s, how far each finger is closed: index, middle, pinky, ring, thumb).
KEYS = [
    (0.0, (0, 0, 0, 0, 0)),  # open: the flat hand
    (1.0, (1, 1, 1, 1, 1)),  # fist
    (1.6, (1, 1, 1, 1, 1)),
    (2.4, (0, 1, 1, 1, 1)),  # pointing with the index
    (3.0, (0, 1, 1, 1, 1)),
    (4.0, (0, 0, 0, 0, 0)),  # open again
]
SHOWN = [(0.0, "open"), (0.5, "closing"), (1.3, "fist"), (2.7, "pointing"), (3.5, "opening"), (4.0, "open")]


def hand_poses(times: np.ndarray) -> np.ndarray:
    """[N,90]: both hands through :data:`KEYS` at ``times`` (s), eased between keyframes."""
    key_t = np.array([t for t, _ in KEYS])
    key_c = np.array([c for _, c in KEYS], np.float64)  # [K,5]
    closed = np.stack([np.interp(times, key_t, key_c[:, f]) for f in range(5)], 1)
    closed = closed * closed * (3 - 2 * closed)  # smoothstep (keys are 0 or 1): eases in and out of each key
    bend = np.concatenate([(closed[:, :4, None] * FINGER_FIST).reshape(-1, 12), closed[:, 4:5] * THUMB_FIST], 1)
    return (bend[:, None, :, None] * AXES[None]).reshape(len(times), 90)


def standing_body(n: int) -> tuple[np.ndarray, np.ndarray]:
    """y-up poses [n,72] and trans [n,3]: standing, arms lowered 30 degrees, elbows a little bent."""
    poses = np.zeros((n, 72))
    poses[:, 16 * 3 + 2], poses[:, 17 * 3 + 2] = -0.5, 0.5  # shoulders (the left arm points along +x)
    poses[:, 18 * 3 + 1], poses[:, 19 * 3 + 1] = -0.3, 0.3  # elbows: forearms forward
    return poses, np.zeros((n, 3))


def borrowed_body(path: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """y-up poses [n,72] and trans [n,3]: the first ``n`` frames of ``path``'s body motion."""
    m = load_motion(path)
    if len(m) < n:
        raise SystemExit(f"{path} has {len(m)} frames, the strip needs {n}")
    return np.concatenate([m.global_orient, m.body_pose], 1)[:n], m.transl[:n]


def write_smplh(path: Path, poses: np.ndarray, trans: np.ndarray, hands: np.ndarray) -> None:
    """An AMASS SMPL-H file of the y-up ``poses [N,72]`` / ``trans`` and ``hands [N,90]``: turned z-up as
    AMASS is (load_motion turns it back), SMPL's two hand joints dropped."""
    up = Rotation.from_euler("x", 90, degrees=True)  # y-up -> z-up; SMPL rotates about its rest root
    orient = (up * Rotation.from_rotvec(poses[:, :3])).as_rotvec()
    J0 = SMPL_REST_JOINTS[0]
    smplh = np.concatenate([orient, poses[:, 3:66], hands], 1)
    np.savez(path, poses=smplh, trans=up.apply(trans + J0) - J0, betas=np.zeros(16),
             mocap_framerate=np.array(FPS), gender="neutral")


def hand_views(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray, half: float, size: int) -> list:
    """Close-ups from the front and from below (the palm side when standing) of the box of half side
    ``half`` around ``centre``."""
    near = (np.abs(vertices[faces] - centre) < 1.5 * half).all(-1).all(-1)  # only the hand: fast, unhidden
    below = Rotation.from_euler("x", -90, degrees=True).as_matrix()  # -y (under the palm) to the camera
    front = render_mesh(vertices, faces[near], size, views=("front",), bounds=(centre, half))
    under = render_mesh(vertices @ below.T, faces[near], size, views=("front",), bounds=(below @ centre, half))
    return [front, under]


def camera_at(centre: np.ndarray, half: float, size: int, view: str, distance: float = 2.0):
    """A camera of ``size`` pixels whose picture spans the box of half side ``half`` around ``centre``,
    looking from the front (+z) or from below (-y)."""
    from rmavatar.data.synth.motion import look_at
    from rmavatar.render.camera import Camera

    offset, up = ((0.0, 0.0, distance), (0.0, 1.0, 0.0)) if view == "front" else ((0.0, -distance, 0.0), (0.0, 0.0, 1.0))
    f = size / 2 * distance / half
    K = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(centre + np.array(offset), centre, up=up), size, size)


def avatar_pictures(trained, seq, k: int, whole, hands: np.ndarray, size: int) -> list:
    """Frame ``k`` of ``seq`` on the trained avatar: the whole body, then each hand from the front and
    from below (as :func:`hand_views` frames the mesh)."""
    gs = trained.pose(seq, k)
    views = [camera_at(whole[0], whole[1], size, "front")]
    for hand in hands:
        centre = (hand.min(0) + hand.max(0)) / 2
        views += [camera_at(centre, 0.12, size, "front"), camera_at(centre, 0.12, size, "below")]
    return [Image.fromarray((trained.render(gs, cam).clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8))
            for cam in views]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="the strip, a PNG")
    parser.add_argument("--motion-out", type=Path, default=None,
                        help="where to keep the SMPL-H motion (default: OUT with .npz)")
    parser.add_argument("--body-motion", type=Path, default=None,
                        help="take the body poses from this motion file (e.g. aist_demo.npz) instead of standing")
    parser.add_argument("--size", type=int, default=240, help="pixels per picture (default 240)")
    parser.add_argument("--run", type=Path, default=None,
                        help="draw this trained avatar (a run folder on an Anny body) instead of the bare mesh")
    args = parser.parse_args()

    times = np.arange(round(KEYS[-1][0] * FPS) + 1) / FPS
    body_poses, trans = (standing_body(len(times)) if args.body_motion is None
                         else borrowed_body(args.body_motion, len(times)))
    motion_path = args.motion_out or args.out.with_suffix(".npz")
    write_smplh(motion_path, body_poses, trans, hand_poses(times))

    trained = None
    if args.run is not None:
        from rmavatar.avatar import load_trained

        trained = load_trained(args.run)
    body = load_body_model("anny") if trained is None else trained.body
    seq = motion_to_sequence(load_motion(motion_path), source=str(motion_path))
    with torch.no_grad():
        zero = torch.zeros(1, 3)
        root_rest = body(None, zero, torch.zeros(1, 69), zero).joints[0, 0]
    seq = recenter_motion(seq, root_rest)  # upright and facing the camera, as animate and view show it
    frames = [round(t * FPS) for t, _ in SHOWN]
    seq = seq.select(frames)
    vertices = posed_vertices(body, seq).numpy()
    with torch.no_grad():
        points = body(None, seq.global_orient, seq.body_pose, seq.transl, hand_pose=seq.hand_pose).hand_points
    points = points.numpy().reshape(len(frames), 2, 21, 3)
    faces = body.faces.numpy()
    lo, hi = vertices.reshape(-1, 3).min(0), vertices.reshape(-1, 3).max(0)
    whole = ((lo + hi) / 2, float((hi - lo).max()) / 2 * 1.05)  # one framing: the body does not jump about

    label_h = 22
    rows = ["whole body", "left hand, front", "left hand, from below", "right hand, front", "right hand, from below"]
    strip = Image.new("RGB", (args.size * len(frames), label_h + args.size * len(rows)), (255, 255, 255))
    draw = ImageDraw.Draw(strip)
    for k, ((t, name), verts) in enumerate(zip(SHOWN, vertices)):
        if trained is not None:
            pictures = avatar_pictures(trained, seq, k, whole, points[k], args.size)
        else:
            pictures = [render_mesh(verts, faces, args.size, views=("front",), bounds=whole)]
            for hand in points[k]:  # left, right
                pictures += hand_views(verts, faces, (hand.min(0) + hand.max(0)) / 2, 0.12, args.size)
        for r, picture in enumerate(pictures):
            strip.paste(picture, (k * args.size, label_h + r * args.size))
        draw.text((k * args.size + 6, 5), f"frame {frames[k]} ({t:.1f} s): {name}", fill=(0, 0, 0))
    for r, name in enumerate(rows):
        draw.text((6, label_h + r * args.size + 4), name, fill=(90, 90, 90))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    strip.save(args.out)
    print(f"wrote {args.out} ({len(frames)} frames of {motion_path})")


if __name__ == "__main__":
    main()
