"""Pieces of ``animate`` that need no avatar: cameras, motion re-centring, frame ranges, video writing."""

import math
import os

import imageio.v2 as imageio
import numpy as np
import pytest
import roma
import torch

from rmavatar.animate.camera import intrinsics, look_at, orbit_viewmats, preset_viewmat
from rmavatar.animate.motion import (
    parse_frame_range,
    recenter_motion,
    upright_rotation,
)
from rmavatar.animate.video import check_output, frame_writer
from rmavatar.body import Motion, PoseSequence, motion_to_sequence, rest_pose
from rmavatar.utils import UserError


def project(view, K, p):
    c = view[:3, :3].double() @ torch.as_tensor(p, dtype=torch.float64) + view[:3, 3].double()
    uv = K.double() @ (c / c[2])
    return uv[:2], c[2]


# ----------------------------------------------------------------------------------------------- cameras
def test_look_at_centres_target_and_keeps_up_up():
    view = look_at([0.4, 1.5, 3.0], [0.1, 0.9, -0.2])
    K = intrinsics(64, 48, 40.0)
    uv, z = project(view, K, [0.1, 0.9, -0.2])
    assert z > 0
    torch.testing.assert_close(uv, torch.tensor([32.0, 24.0], dtype=torch.float64), atol=1e-4, rtol=0)
    # a point above the target appears higher in the image (smaller v)
    uv_up, _ = project(view, K, [0.1, 1.2, -0.2])
    assert uv_up[1] < uv[1] - 1
    R = view[:3, :3].double()
    torch.testing.assert_close(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert torch.det(R) > 0


def test_intrinsics_field_of_view():
    K = intrinsics(100, 80, 60.0)
    assert math.isclose(2 * math.degrees(math.atan(40 / float(K[1, 1]))), 60.0, rel_tol=1e-6)


def test_orbit_and_presets():
    center = torch.tensor([0.0, 1.0, 0.5])
    views = orbit_viewmats(center, 2.5, 8)
    eyes = torch.stack([-(v[:3, :3].T @ v[:3, 3]) for v in views])
    torch.testing.assert_close((eyes - center).norm(dim=1), torch.full((8,), 2.5), atol=1e-5, rtol=0)
    assert torch.allclose(eyes[:, 1], center[1].expand(8), atol=1e-5)
    # distinct views covering the circle, first one in front (+z)
    assert eyes[0, 2] > center[2] + 2.4 and eyes[4, 2] < center[2] - 2.4
    front = preset_viewmat("front", center, 2.0)
    torch.testing.assert_close(front, look_at(center + torch.tensor([0, 0, 2.0]), center))
    side = preset_viewmat("side", center, 2.0)
    eye_side = -(side[:3, :3].T @ side[:3, 3])
    torch.testing.assert_close(eye_side, center + torch.tensor([2.0, 0, 0]), atol=1e-5, rtol=0)


# ----------------------------------------------------------------------------------------------- motion
J0 = torch.tensor([0.01, -0.2, 0.03], dtype=torch.float64)


def rigid_body(points, seq: PoseSequence):
    """A one-bone body with SMPL's root semantics: R(go) (x - J0) + J0 + transl, float64."""
    R = roma.rotvec_to_rotmat(seq.global_orient.double())
    return (points - J0) @ R.transpose(1, 2) + J0 + seq.transl.double()[:, None]


def walking_motion(world_from_yup: torch.Tensor, n=10, turn=0.7):
    """A body walking 3 m while bobbing, turned by ``turn`` about up, expressed in another world."""
    t = torch.arange(n, dtype=torch.float64) / n
    go_yup = torch.stack([torch.zeros(n), torch.full((n,), turn) + 0.1 * t, torch.zeros(n)], 1).double()
    transl = torch.stack([2 * t, 0.9 + 0.05 * torch.sin(6 * t), 3 * t], 1)
    go = roma.rotmat_to_rotvec(world_from_yup @ roma.rotvec_to_rotmat(go_yup))
    # transl transforms so that the root J0 + transl moves like a rigid point
    transl_w = (transl + J0) @ world_from_yup.T - J0
    return PoseSequence(go.float(), torch.zeros(n, 69), transl_w.float())


WORLDS = {
    "y-up": torch.eye(3, dtype=torch.float64),
    "z-up (AMASS)": roma.rotvec_to_rotmat(torch.tensor([math.pi / 2, 0, 0], dtype=torch.float64)),
    "camera frame (y down)": roma.rotvec_to_rotmat(torch.tensor([math.pi, 0, 0], dtype=torch.float64)),
}


@pytest.mark.parametrize("world", list(WORLDS))
def test_recenter_motion_upright_facing_in_place(world):
    seq = walking_motion(WORLDS[world])
    out = recenter_motion(seq, J0.float())
    points = torch.randn(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.5
    before = rigid_body(points, seq)
    after = rigid_body(points, out)
    R0 = roma.rotvec_to_rotmat(out.global_orient[0].double())
    # first frame: body up is +y and body front is +z
    torch.testing.assert_close(R0 @ torch.tensor([0, 1.0, 0], dtype=torch.float64),
                               torch.tensor([0, 1.0, 0], dtype=torch.float64), atol=1e-5, rtol=0)
    torch.testing.assert_close(R0 @ torch.tensor([0, 0, 1.0], dtype=torch.float64),
                               torch.tensor([0, 0, 1.0], dtype=torch.float64), atol=1e-5, rtol=0)
    # the root stays above the origin, its height keeps the bobbing (about the clip's mean)
    root = out.transl.double() + J0
    torch.testing.assert_close(root[:, [0, 2]], torch.zeros(len(seq), 2, dtype=torch.float64), atol=1e-5, rtol=0)
    bob = 0.05 * torch.sin(6 * torch.arange(10, dtype=torch.float64) / 10)
    torch.testing.assert_close(root[:, 1], bob - bob.mean(), atol=1e-5, rtol=0)
    # every frame is the original body moved rigidly by one rotation Q and a translation
    Q = upright_rotation(seq.global_orient)
    for i in range(len(seq)):
        moved = before[i] @ Q.T
        shift = (after[i] - moved).mean(0)
        torch.testing.assert_close(after[i], moved + shift, atol=1e-5, rtol=0)
    torch.testing.assert_close(out.body_pose, seq.body_pose)
    assert out.hand_pose is None  # no finger poses: the body's relaxed hands, as before


def test_recenter_motion_keeps_the_finger_poses():
    seq = walking_motion(WORLDS["z-up (AMASS)"])
    hands = torch.randn(len(seq), 90, generator=torch.Generator().manual_seed(1))
    out = recenter_motion(PoseSequence(seq.global_orient, seq.body_pose, seq.transl, hands), J0.float())
    assert torch.equal(out.hand_pose, hands)  # relative to their parents: the turn of the world leaves them


def test_rest_poses():
    t = rest_pose("tpose")
    go, tpose = t.global_orient[0], t.body_pose[0]
    assert float(go.abs().sum() + tpose.abs().sum()) == 0.0
    apose = rest_pose("apose").body_pose[0]
    assert apose.shape == (69,) and int((apose != 0).sum()) == 2
    with pytest.raises(UserError):
        rest_pose("dab")


def test_parse_frame_range():
    assert parse_frame_range(None, 5) == [0, 1, 2, 3, 4]
    assert parse_frame_range("1:3", 10) == [1, 2]
    assert parse_frame_range("7:", 10) == [7, 8, 9]
    assert parse_frame_range(":-8", 10) == [0, 1]
    assert parse_frame_range("0:10", 10, step=4) == [0, 4, 8]
    for bad in ("3", "a:b", "1:2:3"):
        with pytest.raises(UserError, match="--frames"):
            parse_frame_range(bad, 10)
    with pytest.raises(UserError, match="selects no frames"):
        parse_frame_range("20:30", 10)


def test_motion_shape_errors():
    good = Motion(np.zeros((4, 3), np.float32), np.zeros((4, 69), np.float32), np.zeros((4, 3), np.float32))
    assert len(motion_to_sequence(good)) == 4
    with pytest.raises(UserError, match=r"walk.npz: body_pose must have shape \(frames, 69\)"):
        motion_to_sequence(Motion(good.global_orient, np.zeros((4, 72), np.float32), good.transl), "walk.npz")
    with pytest.raises(UserError, match="different frame counts"):
        motion_to_sequence(Motion(good.global_orient, good.body_pose, np.zeros((3, 3), np.float32)))
    with pytest.raises(UserError, match="NaN"):
        motion_to_sequence(Motion(good.global_orient, good.body_pose, np.full((4, 3), np.nan, np.float32)))
    hands = np.ones((4, 90), np.float32)
    seq = motion_to_sequence(Motion(good.global_orient, good.body_pose, good.transl, hand_pose=hands))
    assert motion_to_sequence(good).hand_pose is None and torch.equal(seq.hand_pose, torch.ones(4, 90))
    with pytest.raises(UserError, match=r"hand_pose must have shape \(frames, 90\)"):
        motion_to_sequence(Motion(good.global_orient, good.body_pose, good.transl, hand_pose=hands[:, :45]))
    with pytest.raises(UserError, match="different frame counts"):
        motion_to_sequence(Motion(good.global_orient, good.body_pose, good.transl, hand_pose=hands[:3]))
    with pytest.raises(UserError, match="hand_pose contains NaN"):
        motion_to_sequence(Motion(good.global_orient, good.body_pose, good.transl, hand_pose=hands * np.nan))


# ----------------------------------------------------------------------------------------------- video
def gradient_frames(n, w, h):
    frames = []
    for i in range(n):
        x = np.linspace(0, 255, w)[None, :, None]
        y = np.linspace(0, 255, h)[:, None, None]
        f = np.concatenate([x + 0 * y, y + 0 * x, np.full((h, w, 1), 20.0 * i)], 2)
        frames.append(f.astype(np.uint8))
    return frames


def test_mp4_is_h264_yuv420p(tmp_path):
    frames = gradient_frames(6, 48, 32)
    out = tmp_path / "v.mp4"
    with frame_writer(out, 12, 48, 32) as write:
        for f in frames:
            write(f)
    reader = imageio.get_reader(str(out), "ffmpeg")
    meta = reader.get_meta_data()
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (48, 32) and meta["fps"] == 12
    back = [f for f in reader]
    reader.close()
    assert len(back) == 6
    for a, b in zip(back, frames):
        assert np.abs(a.astype(int) - b).mean() < 6  # lossy, but the same pictures
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]


def test_png_frames_folder(tmp_path):
    frames = gradient_frames(3, 20, 10)
    out = tmp_path / "frames"
    with frame_writer(str(out) + "/", 10, 20, 10) as write:
        for f in frames:
            write(f)
    names = sorted(p.name for p in out.iterdir())
    assert names == [".rmavatar", "frame_00000.png", "frame_00001.png", "frame_00002.png"]  # + ownership marker
    np.testing.assert_array_equal(imageio.imread(out / "frame_00002.png"), frames[2])  # PNG is lossless


@pytest.mark.parametrize("target", ["v.mp4", "frames/"])
def test_writer_failure_leaves_nothing(tmp_path, target):
    with pytest.raises(RuntimeError, match="renderer died"):
        with frame_writer(f"{tmp_path}/{target}", 10, 16, 16) as write:
            write(np.zeros((16, 16, 3), np.uint8))
            raise RuntimeError("renderer died")
    assert list(tmp_path.iterdir()) == []


def test_writer_keeps_existing_output_on_failure(tmp_path):
    out = tmp_path / "v.mp4"
    out.write_bytes(b"old video")
    with pytest.raises(UserError, match="v.mp4 exists and rmavatar cannot prove it wrote it"):
        frame_writer(out, 10, 16, 16).__enter__()  # not ours: refused before anything is written
    with pytest.raises(ValueError):
        with frame_writer(out, 10, 16, 16, overwrite=True) as write:
            write(np.zeros((8, 8, 3), np.uint8))  # wrong size
    assert out.read_bytes() == b"old video"
    assert [p.name for p in tmp_path.iterdir()] == ["v.mp4"]


def test_bad_outputs(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        check_output(tmp_path / "nope" / "v.mp4")
    with pytest.raises(UserError, match=r"\.mp4"):
        check_output(tmp_path / "v.avi")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    with pytest.raises(UserError, match="mine holds files that rmavatar did not write.*thesis.tex"):
        check_output(str(tmp_path / "mine") + "/")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(UserError, match="is not a folder"):
        check_output(blocker / "v.mp4")
    with pytest.raises(ValueError, match="even"):
        with frame_writer(tmp_path / "odd.mp4", 10, 15, 16):
            pass
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "mine"]


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc (a file system nobody can create files in)")
@pytest.mark.parametrize("target", ["/proc/rmavatar-test.mp4", "/proc/rmavatar-test-frames/"])
def test_unwritable_file_system(target):
    with pytest.raises(UserError, match="cannot write"):
        with frame_writer(target, 10, 16, 16) as write:
            write(np.zeros((16, 16, 3), np.uint8))


@pytest.mark.parametrize("fps", ["0", "-5", "nan", "inf"])
def test_animate_refuses_a_frame_rate_it_cannot_use(tmp_path, capsys, fps):
    """--fps 0 once wrote a video 'at 30 fps': a given frame rate is checked as given, before any work."""
    from rmavatar.commands import main

    motion = tmp_path / "m.npz"
    np.savez(motion, poses=np.zeros((3, 72), np.float32))
    code = main(["animate", str(tmp_path / "run"), "--motion", str(motion), "--out", str(tmp_path / "a.mp4"),
                 "--fps", fps])
    err = capsys.readouterr().err
    assert code == 2 and "--fps must be a positive number" in err, err
    assert not (tmp_path / "a.mp4").exists()


def test_csv_motion_is_an_unsupported_format(tmp_path):
    """A CSV is refused for what it is (an unsupported format, with the supported ones listed), not as a
    file of pickled Python objects."""
    from rmavatar.body import load_motion

    path = tmp_path / "walk.csv"
    path.write_text("frame,x,y,z\n0,0.1,0.2,0.3\n")
    with pytest.raises(UserError) as info:
        load_motion(path)
    msg = str(info.value)
    assert "unsupported format '.csv'" in msg and ".npz" in msg and ".npy" in msg
    assert "pickle" not in msg
