"""Measure the offsets between MediaPipe's pose landmarks and the Anny body's joints
(rmavatar.capture.landmarks.OFFSETS) on synthetic subjects whose true poses are known.

    PYTHONPATH=src python scripts/calibrate_capture_landmarks.py [--work /tmp/calib]

Renders two synthetic subjects (male seed 1 at 256 px, female seed 2 at 384 px; never the default
evaluation subject, neutral seed 0), runs MediaPipe on all their frames, and fits each landmark's
offset (metres, in the canonical frame of its segment) by robust least squares of the 2D reprojection
against MediaPipe's landmarks, weighted by visibility. Prints the OFFSETS table to paste into
landmarks.py and the landmark errors (% of body height) before and after.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from rmavatar.body import load_body_model
from rmavatar.capture.detect import Detector
from rmavatar.capture.landmarks import LANDMARKS, USED, body_landmarks, joint_rotations
from rmavatar.data.io import read_image
from rmavatar.data.synth import SynthConfig, synthesize

SUBJECTS = (("male", 1, 256), ("female", 2, 384))


def observations(root: Path, preset: str):
    """Per frame: MediaPipe keypoints [K,2], visibility [K], the true joints and rotations in camera
    coordinates, K, and the body's height in pixels."""
    true = np.load(root / "smpl_true.npz")
    cams = np.load(root / "cameras.npz")
    body = load_body_model(f"anny:{preset}")
    go, bp, tr = (torch.tensor(true[k]) for k in ("global_orient", "body_pose", "transl"))
    with torch.no_grad():
        out = body(None, go, bp, tr)
        G = joint_rotations(go, bp)
    R = torch.tensor(cams["viewmat"][:, :3, :3])
    t = torch.tensor(cams["viewmat"][:, :3, 3])
    joints = torch.einsum("nij,nkj->nki", R, out.joints) + t[:, None]
    rot = R[:, None] @ G
    verts = torch.einsum("nij,nkj->nki", R, out.vertices) + t[:, None]
    Ks = torch.tensor(cams["K"])
    uv = verts[..., :2] / verts[..., 2:] * Ks[:, None, [0, 1], [0, 1]] + Ks[:, None, :2, 2]
    height = uv[..., 1].amax(1) - uv[..., 1].amin(1)
    n = len(go)
    kp = np.zeros((n, len(USED), 2), np.float32)
    vis = np.zeros((n, len(USED)), np.float32)
    with Detector() as detect:
        for i in range(n):
            image = (read_image(root / "images" / f"{i:05d}.png") * 255 + 0.5).astype(np.uint8)
            det = detect(image)
            if det is not None:
                kp[i] = det.keypoints[list(USED)]
                vis[i] = det.visibility[list(USED)]
    return torch.tensor(kp), torch.tensor(vis), joints, rot, Ks, height


def project(X, Ks):
    return X[..., :2] / X[..., 2:] * Ks[:, None, [0, 1], [0, 1]] + Ks[:, None, :2, 2]


def errors(obs, offsets):
    kp, vis, joints, rot, Ks, height = obs
    uv = project(body_landmarks(joints, rot, offsets), Ks)
    return (uv - kp).norm(dim=-1) / height[:, None] * 100, vis


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="/tmp/rmavatar-calib", help="folder for the synthetic subjects")
    args = parser.parse_args()
    work = Path(args.work)
    obs = []
    for preset, seed, size in SUBJECTS:
        root = work / f"{preset}{seed}_{size}"
        if not (root / "meta.yaml").exists():
            synthesize(root, SynthConfig(size=size, seed=seed, preset=preset), progress=True)
        obs.append(observations(root, preset))
    # Left and right landmarks share one offset, mirrored in x (the body's left).
    names = [LANDMARKS[k][0] for k in USED]
    owner = [names.index(n.replace("right_", "left_")) for n in names]
    sign = torch.tensor([[-1.0 if n.startswith("right_") else 1.0, 1.0, 1.0] for n in names])
    free = torch.zeros(len(USED), 3, requires_grad=True)
    opt = torch.optim.Adam([free], lr=2e-3)
    sigma = 3.0  # % of body height: Geman-McClure scale
    for it in range(1500):
        opt.zero_grad()
        offsets = free[owner] * sign
        loss = 0.0
        for o in obs:
            e, vis = errors(o, offsets)
            w = (vis > 0.5).float() * vis
            loss = loss + (w * e**2 / (e**2 + sigma**2)).sum() / w.sum()
        loss.backward()
        opt.step()
    offsets = (free[owner] * sign).detach()
    zero = torch.zeros(len(USED), 3)
    print("landmark          median error % of height: zero offsets -> fitted")
    with torch.no_grad():
        for j, k in enumerate(USED):
            before = torch.cat([errors(o, zero)[0][:, j][o[1][:, j] > 0.5] for o in obs])
            after = torch.cat([errors(o, offsets)[0][:, j][o[1][:, j] > 0.5] for o in obs])
            print(f"  {LANDMARKS[k][0]:<18} {before.median():5.2f} -> {after.median():5.2f}")
    print("OFFSETS: dict[int, tuple[float, float, float]] = {")
    for j, k in enumerate(USED):
        x, y, z = (round(float(v), 3) for v in offsets[j])
        print(f"    {k}: ({x}, {y}, {z}),  # {LANDMARKS[k][0]}")
    print("}")


if __name__ == "__main__":
    main()
