"""Export / animate / turntable on an Avatar built directly (untrained, random colours) on the Anny body,
and the commands' bad-input handling. The trained-run end-to-end tests are in test_animate_e2e.py."""


import imageio.v2 as imageio
import numpy as np
import pytest
import torch
from helpers import dance

from rmavatar.animate.camera import intrinsics, look_at
from rmavatar.animate.jobs import VideoOptions, animate_video, turntable_video
from rmavatar.avatar import TrainedAvatar
from rmavatar.body import PoseSequence, motion_to_sequence
from rmavatar.body.hands import hand_axes, hand_pose_from_angles
from rmavatar.commands import main
from rmavatar.export.export import export_ply, pose_for_export
from rmavatar.export.ply import read_ply
from rmavatar.render import render_gaussians
from rmavatar.utils import UserError

SIZE = 48


@pytest.fixture(scope="module")
def fake_run():
    from rmavatar.avatar import AvatarConfig
    from rmavatar.body import load_body_model

    body = load_body_model("anny")
    # the rectifier's layers initialise from torch's global generator, which conftest seeds per module:
    # the avatar (and where its raised hands reach in the frame) does not depend on the tests before
    avatar = AvatarConfig(rectifier="paper", sh_degree=1).build(body)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        avatar.sh_dc.copy_(torch.randn(avatar.sh_dc.shape, generator=g))
        avatar.sh_rest.copy_(0.3 * torch.randn(avatar.sh_rest.shape, generator=g))
        avatar.opacity_logits.copy_(1.0 + torch.randn(avatar.opacity_logits.shape, generator=g))
        avatar.quats.copy_(torch.randn(avatar.quats.shape, generator=g))
        avatar.log_scales.add_(0.2 * torch.randn(avatar.log_scales.shape, generator=g))
        # a rectifier that does something: its last layer is usually initialised at zero
        last = [m for m in avatar.rectifier.modules() if isinstance(m, torch.nn.Linear)][-1]
        last.weight.copy_(1e-3 * torch.randn(last.weight.shape, generator=g))
        last.bias.copy_(1e-3 * torch.randn(last.bias.shape, generator=g))
    avatar.active_sh_degree.fill_(1)
    avatar.eval()
    return TrainedAvatar(avatar, body, betas=None, iteration=0, data_spec="", size=None, config={})


def write_motion(path, n=6, drift=3.0):
    poses, trans = dance(n, drift)
    np.savez(path, poses=poses, trans=trans, fps=np.float32(30.0))
    return path


def non_background(img, bg=255, tol=8):
    return np.abs(img.astype(int) - bg).max(-1) > tol


def render_image(gs, view, K, width, height):
    """gs on white through the one render path (render_gaussians)."""
    with torch.no_grad():
        return render_gaussians(gs, view, K, width, height, torch.ones(3))[0]


def test_trained_avatar_applies_rectifier(fake_run):
    poser = fake_run
    go, pose = torch.zeros(1, 3), torch.zeros(1, 69)
    pose[0, 50] = 0.7
    seq = PoseSequence(go, pose, torch.zeros(1, 3))
    gs = poser.pose(seq, 0)
    verts = fake_run.body(None, go, pose, torch.zeros(1, 3)).vertices[0]
    mu_star, _, _ = fake_run.avatar.posed(verts)
    with torch.no_grad():
        d_mu, _, _ = fake_run.avatar.rectifier(mu_star, pose[0])
    assert float(d_mu.abs().max()) > 1e-5
    torch.testing.assert_close(gs.means, mu_star + d_mu, atol=1e-6, rtol=0)


def test_export_round_trip_matches_avatar_render(fake_run, tmp_path):
    plyfile = pytest.importorskip("plyfile")
    out = tmp_path / "avatar.ply"
    poser = fake_run
    n = export_ply(poser, pose_for_export(poser, None, 0), out)
    assert n == fake_run.avatar.num_gaussians
    v = plyfile.PlyData.read(str(out))["vertex"]
    assert v.count == n and [p.name for p in v.properties][-8:] == [
        "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert len([p for p in v.properties if p.name.startswith("f_rest_")]) == 9
    # the avatar in the canonical pose, through the model's own forward (not export's code path)
    body, avatar = fake_run.body, fake_run.avatar
    zero = torch.zeros(1, 3)
    verts = body(None, zero, torch.zeros(1, 69), zero).vertices[0]
    with torch.no_grad():
        gs = avatar(verts, torch.zeros(69))
    back = read_ply(out)
    # the file holds those Gaussians to float32 round-trip accuracy: world-space scales (not face-local
    # ones), unit quaternions, the SH turned into world axes
    torch.testing.assert_close(back.means, gs.means, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.scales, gs.scales, rtol=1e-5, atol=0)
    torch.testing.assert_close(back.quats, gs.quats, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.opacities, gs.opacities, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.sh, gs.world_sh(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(np.exp(np.asarray(v["scale_1"], np.float64)), gs.scales[:, 1].numpy(), rtol=1e-5)
    for eye in ([0.0, 0.3, 3.0], [2.5, 0.8, -1.5]):
        view = look_at(eye, [0.0, 0.0, 0.0])
        K = intrinsics(SIZE, SIZE, 45.0)
        ref = render_image(gs, view, K, SIZE, SIZE)
        img = render_image(back, view, K, SIZE, SIZE)
        assert non_background((ref.numpy() * 255).astype(np.uint8)).mean() > 0.05
        # The rasterizer's cutoffs (alpha < 1/255, transmittance <= 1e-4) make a pixel jump when a
        # parameter moves by one float32 step across one of them, and the file cannot hold the
        # avatar's log-scales, opacities and quaternions to the bit. So: nearly every value the same to
        # 1e-5 (a wrong layout, unit or SH order changes most of them by far more), and the few that
        # jump by no more than a cutoff's contribution.
        diff = (img - ref).abs()
        assert float((diff > 1e-5).float().mean()) <= 1e-3
        assert float(diff.max()) < 0.02


def test_export_motion_frame(fake_run, tmp_path):
    motion = write_motion(tmp_path / "m.npz")
    poser = fake_run
    export_ply(poser, pose_for_export(poser, str(motion), 4), tmp_path / "f4.ply")
    poses, trans = dance()
    verts = fake_run.body(None, torch.tensor(poses[4:5, :3]), torch.tensor(poses[4:5, 3:]),
                          torch.tensor(trans[4:5])).vertices[0]
    ref = fake_run.avatar.world_gaussians(verts, torch.tensor(poses[4, 3:]))
    torch.testing.assert_close(read_ply(tmp_path / "f4.ply").means, ref.means, atol=1e-6, rtol=0)
    with pytest.raises(UserError, match="out of range"):
        pose_for_export(poser, str(motion), 6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f4.ply", "m.npz"]


def test_animate_keeps_drifting_body_in_view(fake_run, tmp_path):
    motion = write_motion(tmp_path / "m.npz", n=6, drift=3.0)
    from rmavatar.body import load_motion

    seq = motion_to_sequence(load_motion(motion))
    out = tmp_path / "dance.mp4"
    n = animate_video(fake_run, seq, out, camera="fixed",
                      opts=VideoOptions(size=SIZE, fps=10, progress=False))
    frames = [f for f in imageio.get_reader(str(out), "ffmpeg")]
    assert n == len(frames) == 6 and frames[0].shape == (SIZE, SIZE, 3)
    for f in frames:
        mask = non_background(f)
        assert 0.03 < mask.mean() < 0.6
        ys, xs = np.nonzero(mask)
        # centred although the motion walks 3 m away
        assert abs(xs.mean() - SIZE / 2) < SIZE * 0.15 and abs(ys.mean() - SIZE / 2) < SIZE * 0.2
        # white background in the corners
        assert not mask[:3, :3].any() and not mask[-3:, -3:].any()
    assert np.abs(frames[0].astype(int) - frames[2]).mean() > 1.0  # the arms move


def test_turntable_front_and_back_mirror(fake_run, tmp_path):
    out = f"{tmp_path}/tt/"
    turntable_video(fake_run, out, num_frames=8,
                    opts=VideoOptions(size=SIZE, fps=8, background=(0.0, 0.0, 0.0), progress=False))
    frames = [imageio.imread(f"{tmp_path}/tt/frame_{i:05d}.png") for i in range(8)]
    masks = [non_background(f, bg=0) for f in frames]
    front, side, back = masks[0], masks[2], masks[4]
    iou = (front & np.fliplr(back)).sum() / (front | np.fliplr(back)).sum()
    assert iou > 0.8  # seen from behind, the T-pose silhouette is the mirror image
    assert side.sum() < 0.7 * front.sum()  # from the side the spread arms are hidden
    assert np.abs(frames[0].astype(int) - frames[4]).mean() > 2.0  # but the colours differ


# ----------------------------------------------------------------------------------------------- finger poses
def write_hand_motion(path, body, n=3):
    """An AMASS SMPL-H file (z-up, 156 values a frame): standing still in the T-pose while both hands go
    from flat (frame 0) to fists (the last frame)."""
    bend = torch.linspace(0.0, 1.2, n)[:, None, None, None].expand(n, 2, 5, 3)
    poses = np.zeros((n, 156))
    poses[:, 0] = np.pi / 2  # the body's up along +z, as in AMASS
    poses[:, 66:] = hand_pose_from_angles(bend, torch.zeros(n, 2, 5), hand_axes(body)).numpy()
    np.savez(path, poses=poses, trans=np.zeros((n, 3)), mocap_framerate=np.array(30.0))
    return path


def test_export_hand_motion_frame_poses_the_fingers(fake_run, tmp_path):
    motion = write_hand_motion(tmp_path / "hands.npz", fake_run.body)
    seq = pose_for_export(fake_run, str(motion), 2)
    export_ply(fake_run, seq, tmp_path / "fists.ply")
    fists = read_ply(tmp_path / "fists.ply").means
    relaxed = fake_run.pose(PoseSequence(seq.global_orient, seq.body_pose, seq.transl), 0).means
    moved = (fists - relaxed).norm(dim=-1)
    assert float(moved.max()) > 0.03  # the fingers close
    torso = relaxed[:, 0].abs() < 0.3  # standing in the T-pose: the hands are far out on the sides
    assert int(torso.sum()) > 1000 and float(moved[torso].max()) < 1e-5


def test_animate_hand_motion_moves_only_the_hands(fake_run, tmp_path):
    from rmavatar.body import load_motion

    seq = motion_to_sequence(load_motion(write_hand_motion(tmp_path / "hands.npz", fake_run.body)))
    animate_video(fake_run, seq, f"{tmp_path}/frames/", opts=VideoOptions(size=64, progress=False))
    flat, fists = (imageio.imread(f"{tmp_path}/frames/frame_{i:05d}.png").astype(int) for i in (0, 2))
    changed = np.abs(flat - fists).max(-1) > 30
    columns = np.nonzero(changed.any(0))[0]
    # the body stands still: only the hands, at the two ends of the spread arms, change
    assert changed.sum() >= 4 and ((columns < 16) | (columns >= 48)).all()
    assert changed[:, :32].any() and changed[:, 32:].any()


# ----------------------------------------------------------------------------------------------- CLI bad input
@pytest.mark.parametrize("command", [
    ["animate", "{run}", "--motion", "{motion}", "--out", "{tmp}/v.mp4"],
    ["export", "{run}", "--ply", "{tmp}/a.ply"],
    ["render", "{run}", "--turntable", "--out", "{tmp}/t.mp4"],
    ["view", "{run}", "--port", "0"],
])
def test_commands_without_checkpoint(tmp_path, capsys, command):
    run = tmp_path / "run"
    run.mkdir()
    (run / "rmavatar-run.json").write_text('{"format": "rmavatar-run", "version": 1, "data": "x"}')
    motion = write_motion(tmp_path / "m.npz")
    args = [a.format(run=run, motion=motion, tmp=tmp_path) for a in command]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "no checkpoint" in err and str(run) in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "run"]


def test_animate_bad_motion_and_output(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    bad = tmp_path / "bad.npz"
    np.savez(bad, poses=np.zeros((5, 70), np.float32))
    assert main(["animate", str(run), "--motion", str(bad), "--out", f"{tmp_path}/v.mp4"]) == 2
    assert "poses must have shape" in capsys.readouterr().err
    good = write_motion(tmp_path / "m.npz")
    assert main(["animate", str(run), "--motion", str(good), "--out", f"{tmp_path}/no/such/v.mp4"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["export", str(run), "--ply", f"{tmp_path}/no/such/a.ply"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz", "m.npz", "run"]
