"""End to end on a small trained run: ``rmavatar export / animate / render --turntable / view``.

The run is trained once per session (a tiny synthetic subject, 32x32, a few iterations) by the
``trained_run`` fixture (conftest.py). Set RMAVATAR_KEEP_OUTPUTS=DIR to keep the videos and PLYs.
"""

import math
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
import roma
import torch

from rmavatar.commands import main


def keep(path: Path) -> None:
    target = os.environ.get("RMAVATAR_KEEP_OUTPUTS")
    if target:
        Path(target).mkdir(parents=True, exist_ok=True)
        dst = Path(target) / path.name
        if path.is_dir():
            shutil.copytree(path, dst, dirs_exist_ok=True)
        else:
            shutil.copy(path, dst)


def write_amass_like(path: Path, n: int = 8) -> Path:
    """An AMASS-layout motion (poses (N,156) SMPL-H, z-up world, 120 fps) walking 2 m while waving."""
    t = np.arange(n) / n
    body = np.zeros((n, 72))
    body[:, 16 * 3 + 2] = -1.0 + 0.9 * np.sin(2 * np.pi * t)  # left arm waves
    body[:, 1 * 3] = 0.5 * np.sin(2 * np.pi * t)  # hips swing
    body[:, 2 * 3] = -0.5 * np.sin(2 * np.pi * t)
    z_from_y = roma.rotvec_to_rotmat(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=torch.float64))
    turn = roma.rotvec_to_rotmat(torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64))
    body[:, :3] = roma.rotmat_to_rotvec((z_from_y @ turn).expand(n, 3, 3)).numpy()
    poses = np.concatenate([body[:, :66], np.zeros((n, 90))], 1)
    trans = np.stack([2 * t, -1.5 * t, 0.95 + 0 * t], 1)  # z-up: height is z
    np.savez(path, poses=poses.astype(np.float32), trans=trans.astype(np.float32),
             betas=np.zeros(16, np.float32), mocap_framerate=np.float64(120.0))
    return path


def read_video(path: Path) -> list[np.ndarray]:
    reader = imageio.get_reader(str(path), "ffmpeg")
    frames = [f for f in reader]
    reader.close()
    return frames


def mask(img: np.ndarray, bg: int = 255) -> np.ndarray:
    return np.abs(img.astype(int) - bg).max(-1) > 12


# ----------------------------------------------------------------------------------------------- export
def test_export_trained_run(trained_run, tmp_path, capsys):
    plyfile = pytest.importorskip("plyfile")
    from rmavatar.animate.camera import intrinsics, look_at
    from rmavatar.avatar import load_trained
    from rmavatar.export import read_ply
    from rmavatar.render import render_gaussians

    def render_image(gs, view, K, width, height):
        with torch.no_grad():
            return render_gaussians(gs, view, K, width, height, torch.ones(3))[0]

    out = tmp_path / "avatar.ply"
    assert main(["export", str(trained_run), "--ply", str(out)]) == 0
    assert "Gaussians" in capsys.readouterr().out
    keep(out)
    run = load_trained(trained_run)
    ply = plyfile.PlyData.read(str(out))
    assert ply["vertex"].count == run.avatar.num_gaussians
    assert "f_rest_8" in ply["vertex"].data.dtype.names and "f_rest_9" not in ply["vertex"].data.dtype.names
    # the avatar's own render (its forward in the zero pose) against the PLY as a static scene
    zero = torch.zeros(1, 3)
    verts = run.body(run.betas, zero, torch.zeros(1, 69), zero).vertices[0]
    run.avatar.active_sh_degree.fill_(run.avatar.config.sh_degree)
    with torch.no_grad():
        gs = run.avatar(verts, torch.zeros(69))
    back = read_ply(out)
    K = intrinsics(64, 64, 40.0)
    for eye in ([0.0, 0.0, 3.5], [-3.0, 1.0, -1.0]):
        view = look_at(eye, [0.0, -0.2, 0.0])
        ref = render_image(gs, view, K, 64, 64)
        assert mask((ref.numpy() * 255).astype(np.uint8)).mean() > 0.05
        assert float((render_image(back, view, K, 64, 64) - ref).abs().max()) < 1e-5

    motion = write_amass_like(tmp_path / "walk.npz")
    assert main(["export", str(trained_run), "--ply", str(tmp_path / "f3.ply"), "--motion", str(motion),
                 "--frame", "3"]) == 0
    assert not torch.allclose(read_ply(tmp_path / "f3.ply").means, back.means, atol=1e-3)
    assert main(["export", str(trained_run), "--ply", str(tmp_path / "f9.ply"), "--motion", str(motion),
                 "--frame", "9"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["avatar.ply", "f3.ply", "walk.npz"]


# ----------------------------------------------------------------------------------------------- animate
def test_animate_trained_run_mp4(trained_run, tmp_path, capsys):
    motion = write_amass_like(tmp_path / "walk.npz")
    out = tmp_path / "walk.mp4"
    # 120 fps motion shown at 30 fps: every 4th frame -> 2 of 8
    assert main(["animate", str(trained_run), "--motion", str(motion), "--out", str(out), "--size", "48",
                 "--fps", "30"]) == 0
    assert "wrote 2 frames at 30 fps" in capsys.readouterr().out
    assert main(["animate", str(trained_run), "--motion", str(motion), "--out", str(out), "--size", "47",
                 "--frames", "1:5"]) == 0
    keep(out)
    meta = imageio.get_reader(str(out), "ffmpeg").get_meta_data()
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p") and meta["fps"] == 120
    frames = read_video(out)
    assert len(frames) == 4 and frames[0].shape == (48, 48, 3)  # 47 made even
    for f in frames:
        m = mask(f)
        ys, xs = np.nonzero(m)
        assert 0.03 < m.mean() < 0.6 and abs(xs.mean() - 24) < 8 and abs(ys.mean() - 24) < 10
        assert (f[:2, :2] > 240).all()  # white background
    assert np.abs(frames[0].astype(int) - frames[3]).mean() > 0.5  # the arm waves
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.mp4", "walk.npz"]


def test_animate_trained_run_png_orbit(trained_run, tmp_path):
    motion = write_amass_like(tmp_path / "walk.npz")
    out = tmp_path / "frames"
    assert main(["animate", str(trained_run), "--motion", str(motion), "--out", f"{out}/", "--size", "32",
                 "--camera", "orbit", "--frames", "2:6", "--bg", "black"]) == 0
    keep(out)
    names = sorted(p.name for p in out.iterdir() if p.name != ".rmavatar")  # the folder's output marker
    assert names == [f"frame_{i:05d}.png" for i in range(4)]
    assert (out / ".rmavatar").is_file()
    imgs = [imageio.imread(out / n) for n in names]
    assert all(mask(i, bg=0).mean() > 0.03 for i in imgs) and (imgs[0][:2, :2] < 15).all()


def test_animate_and_export_play_the_finger_poses(trained_run, tmp_path):
    """An AMASS SMPL-H motion standing still in the T-pose while both hands close into fists: the fingers,
    and only they, move in ``animate``'s frames and in ``export --motion``'s Gaussians."""
    from rmavatar.avatar import load_trained
    from rmavatar.body.hands import hand_axes, hand_pose_from_angles
    from rmavatar.export import read_ply

    bend = torch.linspace(0.0, 1.2, 3)[:, None, None, None].expand(3, 2, 5, 3)
    poses = np.zeros((3, 156))
    poses[:, 0] = math.pi / 2  # the body's up along +z, as in AMASS
    poses[:, 66:] = hand_pose_from_angles(bend, torch.zeros(3, 2, 5), hand_axes(load_trained(trained_run).body))
    motion = tmp_path / "fists.npz"
    np.savez(motion, poses=poses, trans=np.zeros((3, 3)), mocap_framerate=np.array(30.0))
    out = tmp_path / "frames"
    assert main(["animate", str(trained_run), "--motion", str(motion), "--out", f"{out}/", "--size", "64"]) == 0
    keep(out)
    flat, fists = (imageio.imread(out / f"frame_{i:05d}.png").astype(int) for i in (0, 2))
    changed = np.abs(flat - fists).max(-1) > 30
    columns = np.nonzero(changed.any(0))[0]
    assert changed[:, :32].any() and changed[:, 32:].any() and ((columns < 16) | (columns >= 48)).all()
    for k in (0, 2):
        assert main(["export", str(trained_run), "--ply", str(tmp_path / f"f{k}.ply"), "--motion", str(motion),
                     "--frame", str(k)]) == 0
    flat, fists = (read_ply(tmp_path / f"f{k}.ply").means for k in (0, 2))
    moved = (fists - flat).norm(dim=-1)
    torso = flat[:, 0].abs() < 0.3  # the hands are far out on the sides
    assert float(moved.max()) > 0.03 and int(torso.sum()) > 1000 and float(moved[torso].max()) < 1e-5


def test_animate_bad_inputs_with_trained_run(trained_run, tmp_path, capsys):
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((4, 60), np.float32))
    assert main(["animate", str(trained_run), "--motion", str(bad), "--out", str(tmp_path / "v.mp4")]) == 2
    assert "poses must have shape" in capsys.readouterr().err
    good = write_amass_like(tmp_path / "walk.npz")
    ro = tmp_path / "blocker"
    ro.write_text("a file, not a folder")
    assert main(["animate", str(trained_run), "--motion", str(good), "--out", str(ro / "v.mp4")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main(["animate", str(trained_run), "--motion", str(good), "--out", str(tmp_path / "v.gif")]) == 2
    assert main(["animate", str(trained_run), "--motion", str(good), "--out", str(tmp_path / "v.mp4"),
                 "--frames", "9:12"]) == 2
    assert "selects no frames" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npy", "blocker", "walk.npz"]


# ----------------------------------------------------------------------------------------------- turntable
def test_turntable_trained_run(trained_run, tmp_path):
    out = tmp_path / "turn.mp4"
    code = main(["render", str(trained_run), "--turntable", "--out", str(out), "--size", "48", "--frames", "12",
                 "--pose", "train"])
    assert code == 0
    keep(out)
    frames = read_video(out)
    assert len(frames) == 12 and frames[0].shape == (48, 48, 3)
    front, back = mask(frames[0]), mask(frames[6])
    assert front.mean() > 0.03
    iou = (front & np.fliplr(back)).sum() / (front | np.fliplr(back)).sum()
    assert iou > 0.6  # the back view mirrors the front silhouette


# ----------------------------------------------------------------------------------------------- view
def test_view_command_serves_the_page(trained_run, tmp_path):
    """``rmavatar view`` starts and serves viser's page (the browser test is in test_viewer.py)."""
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    motion = write_amass_like(tmp_path / "walk.npz")
    proc = subprocess.Popen([sys.executable, "-m", "rmavatar", "view", str(trained_run), "--motion", str(motion),
                             "--port", str(port)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 120
        lines = [""]
        while "viewer running at" not in lines[-1]:
            lines.append(proc.stdout.readline())
            assert lines[-1] or proc.poll() is None, "rmavatar view exited early:\n" + "".join(lines)
            assert time.monotonic() < deadline, "rmavatar view did not start:\n" + "".join(lines)
        served = int(lines[-1].split("http://localhost:")[1].split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{served}/", timeout=30) as resp:
            assert resp.status == 200 and b"<html" in resp.read().lower()
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_training_pose_is_the_subjects_a_pose(trained_run):
    from rmavatar.avatar import load_trained
    from rmavatar.data.synth.motion import A_POSE_DEG

    pose = load_trained(trained_run).rest_pose("train").body_pose[0]
    # the synthetic subject turns in an A-pose: shoulders (SMPL joints 16/17) lowered by A_POSE_DEG
    assert abs(float(pose[15 * 3 + 2]) + math.radians(A_POSE_DEG)) < math.radians(10)
    assert abs(float(pose[16 * 3 + 2]) - math.radians(A_POSE_DEG)) < math.radians(10)
