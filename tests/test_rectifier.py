"""The rectifier's two designs (docs/model.md): the paper's (posed input, whole pose, world offsets) and the
local one (rest-pose input, skinning-masked pose, offsets in the triangle's frame in units of w)."""

import pytest
import torch
import trimesh

from rmavatar.avatar import GAUSSIAN_PARAMS, Avatar, AvatarConfig, Rectifier, quat_to_rotmat
from rmavatar.avatar.geometry import FaceTable
from rmavatar.avatar.rectifier import DESIGNS, LocalRectifier, PaperRectifier, RectifierDesign, rectifier_design
from rmavatar.avatar.run import read_checkpoint
from rmavatar.train.config import TrainConfig, apply_overrides, load_config, save_config
from rmavatar.utils import UserError

from devices import DEVICES


class ToyBody:
    """A stretched icosphere skinned to a few SMPL joints: the upper half to the left shoulder (16),
    the lower half to the left hip (1), a band around the middle to both and to spine1 (3)."""

    def __init__(self):
        m = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
        self.v_template = torch.tensor(m.vertices, dtype=torch.float32) * torch.tensor([1.0, 2.0, 0.7])
        self.faces = torch.tensor(m.faces, dtype=torch.long)
        self.binding_faces = torch.arange(self.faces.shape[0])
        y = self.v_template[:, 1]
        w = torch.zeros(self.v_template.shape[0], 24)
        w[y > 0.15, 16] = 1.0
        w[y < -0.15, 1] = 1.0
        band = y.abs() <= 0.15
        w[band, 16], w[band, 1], w[band, 3] = 0.4, 0.4, 0.2
        self.weights = w

    def joint_weights(self):
        return self.weights


def posed_toy(body, gen):
    """A non-rigid deformation of the rest mesh (every triangle changes shape a little)."""
    return (body.v_template.double() * 1.1 + 0.02 * torch.randn(body.v_template.shape, generator=gen,
                                                                 dtype=torch.float64))


def make_avatar(body, design, gen, **kw):
    av = AvatarConfig(rectifier=design, **kw).build(body).double()
    with torch.no_grad():
        for p in (getattr(av, name) for name in GAUSSIAN_PARAMS):
            p.copy_(torch.randn(p.shape, generator=gen, dtype=p.dtype) * 0.3)
        if av.rectifier is not None:  # a rectifier with visible outputs (it starts at ~1e-5)
            av.rectifier.l5.weight.normal_(0, 0.05, generator=gen)
            av.rectifier.l5.bias.normal_(0, 0.05, generator=gen)
    return av


def random_rotation(gen):
    q = torch.randn(4, generator=gen, dtype=torch.float64)
    return quat_to_rotmat(q / q.norm())


# ---------------------------------------------------------------- turning with the body
@pytest.mark.parametrize("design", ["paper", "local"])
def test_only_local_offsets_turn_with_the_body(design):
    gen = torch.Generator().manual_seed(0)
    body = ToyBody()
    av = make_avatar(body, design, gen)
    pose = torch.randn(69, generator=gen, dtype=torch.float64) * 0.5
    v = posed_toy(body, gen)
    Q, t = random_rotation(gen), torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    (a, ea), (b, eb) = av.forward_with_extras(v, pose), av.forward_with_extras(v @ Q.T + t, pose)
    for x in (ea, eb):
        assert x.offsets[0].abs().max() > 1e-3  # the check below is not about zeros
    rotated = (ea.offsets[0] @ Q.T, ea.offsets[1], ea.offsets[2])
    same = [torch.allclose(got, want, atol=1e-12, rtol=0) for got, want in zip(eb.offsets, rotated)]
    if design == "local":
        assert all(same)
        # so the whole rectified Gaussian moves rigidly with the body
        assert torch.allclose(b.means, a.means @ Q.T + t, atol=1e-12)
        assert torch.allclose(quat_to_rotmat(b.quats), Q @ quat_to_rotmat(a.quats), atol=1e-12)
        assert torch.allclose(b.scales, a.scales, atol=1e-12)
    else:  # the paper's MLP reads the posed position and gives world offsets: they do not turn
        assert not same[0] and not same[1]


@pytest.mark.parametrize("design", ["paper", "local"])
def test_rest_means_are_the_gaussians_on_the_rest_mesh(design):
    gen = torch.Generator().manual_seed(7)
    body = ToyBody()
    av = make_avatar(body, design, gen)
    assert torch.allclose(av.rest_means(), av.posed(body.v_template.double())[0], atol=1e-12)


def test_local_offsets_are_in_units_of_the_triangle_scale():
    gen = torch.Generator().manual_seed(1)
    body = ToyBody()
    av = make_avatar(body, "local", gen)
    pose = torch.randn(69, generator=gen, dtype=torch.float64) * 0.5
    v = posed_toy(body, gen)
    (a, ea), (b, eb) = av.forward_with_extras(v, pose), av.forward_with_extras(2.5 * v, pose)
    assert torch.allclose(eb.offsets[0], 2.5 * ea.offsets[0], atol=1e-12)
    assert torch.allclose(eb.offsets[1], 2.5 * ea.offsets[1], atol=1e-12)
    assert torch.allclose(b.scales, 2.5 * a.scales, atol=1e-12)


@pytest.mark.parametrize("design", ["local", "paper"])
def test_held_rectifier_outputs_give_the_same_gaussians(design):
    """forward(..., rectified=rectify(...)) (what test-time pose fitting holds between refreshes) is the
    forward that runs the rectifier; held outputs of another pose are not."""
    gen = torch.Generator().manual_seed(3)
    body = ToyBody()
    av = make_avatar(body, design, gen)
    pose = torch.randn(69, generator=gen, dtype=torch.float64) * 0.5
    v = posed_toy(body, gen)
    (a, ea), (b, eb) = av.forward_with_extras(v, pose), av.forward_with_extras(v, rectified=av.rectify(v, pose))
    for x, y in zip((a.means, a.quats, a.scales, *ea.offsets), (b.means, b.quats, b.scales, *eb.offsets)):
        torch.testing.assert_close(x, y, atol=1e-12, rtol=0)
    c = av(v, rectified=av.rectify(v, pose + 0.5))
    assert not torch.allclose(a.means, c.means, atol=1e-6)
    with pytest.raises(ValueError, match="no rectifier"):
        AvatarConfig(rectifier=False).build(body).rectify(v.float(), pose.float())


# ---------------------------------------------------------------- the pose mask
def test_mask_groups_follow_the_skinning_weights():
    body = ToyBody()
    av = AvatarConfig(rectifier="local").build(body)
    y = body.v_template[body.faces, 1]  # [F,3]
    masks = av.pose_masks[av.face_pose_group]  # [F,69]
    joint_cols = lambda j: slice(3 * (j - 1), 3 * j)  # noqa: E731 - body_pose columns of joint j
    upper, lower = (y > 0.15).all(1), (y < -0.15).all(1)
    assert upper.any() and lower.any()
    assert (masks[upper][:, joint_cols(16)] == 1).all() and (masks[upper][:, joint_cols(1)] == 0).all()
    assert (masks[lower][:, joint_cols(1)] == 1).all() and (masks[lower][:, joint_cols(16)] == 0).all()
    touches_band = (y.abs() <= 0.15).any(1)
    assert torch.equal(masks[:, joint_cols(3)].bool().all(1), touches_band)
    assert masks.sum(1).max() == 9  # three joints at most; global orientation is never an input
    # a threshold above the band's weights drops spine1 everywhere
    av2 = AvatarConfig(rectifier="local", rectifier_mask_threshold=0.3).build(body)
    assert av2.pose_masks[:, joint_cols(3)].sum() == 0


def test_unseen_joints_change_nothing_seen_joints_do():
    gen = torch.Generator().manual_seed(2)
    body = ToyBody()
    av = make_avatar(body, "local", gen)
    v = posed_toy(body, gen)
    pose = torch.randn(69, generator=gen, dtype=torch.float64) * 0.5
    seen16 = av.pose_masks[av.face_pose_group[av.face_ids], 3 * 15] == 1  # Gaussians that see joint 16
    assert seen16.any() and (~seen16).any()
    for joint, seen in ((16, seen16), (5, torch.zeros_like(seen16))):  # joint 5 skins nothing
        moved = pose.clone()
        moved[3 * (joint - 1): 3 * joint] += torch.tensor([0.4, -0.3, 0.2], dtype=torch.float64)
        # same mesh: only the rectifier's pose input differs
        (a, ea), (b, eb) = av.forward_with_extras(v, pose), av.forward_with_extras(v, moved)
        for x, y in zip(ea.offsets, eb.offsets):
            assert torch.equal(x[~seen], y[~seen])  # exactly
            if seen.any():
                assert ((x[seen] - y[seen]).abs().amax(1) > 1e-9).all()
        assert torch.equal(a.means[~seen], b.means[~seen])


def test_masked_rectifier_equals_one_gaussian_at_a_time():
    """The grouped first layer against the unmasked MLP run on each Gaussian's own masked pose."""
    gen = torch.Generator().manual_seed(3)
    r = Rectifier().double()
    with torch.no_grad():
        r.l5.weight.normal_(0, 0.1, generator=gen)
    r.set_frequency_alpha(4.2)
    x = torch.randn(40, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    pose = torch.randn(69, generator=gen, dtype=torch.float64, requires_grad=True)
    masks = (torch.rand(5, 69, generator=gen) > 0.6).double()
    group = torch.randint(0, 5, (40,), generator=gen)
    wts = [torch.randn(40, k, generator=gen, dtype=torch.float64) for k in (3, 3, 4)]
    inputs = [x, pose, *r.parameters()]
    fast = r(x, pose, masks, group)
    ref = [torch.cat(t) for t in zip(*(r.reference_forward(x[i:i + 1], pose * masks[group[i]])
                                       for i in range(40)))]
    for a, b in zip(fast, ref):
        assert torch.allclose(a, b, atol=1e-12)
    g_fast = torch.autograd.grad(sum((o * w).sum() for o, w in zip(fast, wts)), inputs)
    g_ref = torch.autograd.grad(sum((o * w).sum() for o, w in zip(ref, wts)), inputs)
    for a, b in zip(g_fast, g_ref):
        assert torch.allclose(a, b, atol=1e-10)
    assert torch.autograd.gradcheck(lambda m, p: r(m, p, masks, group[:3]), (x[:3].detach().requires_grad_(), pose))
    with pytest.raises(ValueError):
        r(x, pose, masks, None)


def test_gradients_reach_the_mlp_and_the_gaussians():
    gen = torch.Generator().manual_seed(4)
    body = ToyBody()
    av = make_avatar(body, "local", gen)
    gs = av(posed_toy(body, gen), torch.randn(69, generator=gen, dtype=torch.float64))
    (gs.means.square().sum() + gs.scales.sum() + gs.quats.sum()).backward()
    for name, p in av.rectifier.named_parameters():
        assert p.grad is not None and p.grad.abs().max() > 0, name
    # the rest-pose position is the encoded input: the local means get a gradient through it too
    assert av.means.grad.abs().max() > 0


# ---------------------------------------------------------------- on the real body
def test_anny_global_orientation_and_an_unseen_joint():
    from rmavatar.body import load_body_model
    from rmavatar.body.lbs import axis_angle_to_matrix

    body = load_body_model("anny")
    gen = torch.Generator().manual_seed(5)
    av = AvatarConfig(rectifier="local").build(body)
    with torch.no_grad():
        av.rectifier.l5.weight.normal_(0, 0.05, generator=gen)
    pose = torch.randn(1, 69, generator=gen) * 0.2
    zero = torch.zeros(1, 3)
    orient = torch.tensor([[0.3, 1.2, -0.4]])
    with torch.no_grad():
        v0 = body(None, zero, pose, zero).vertices[0]
        v1 = body(None, orient, pose, zero).vertices[0]
        a, b = av.forward_with_extras(v0, pose[0])[1], av.forward_with_extras(v1, pose[0])[1]
        Q = axis_angle_to_matrix(orient)[0]
        scale = a.offsets[0].abs().max()
        assert scale > 1e-4
        assert torch.allclose(b.offsets[0], a.offsets[0] @ Q.T, atol=1e-4 * float(scale))
        assert torch.equal(b.offsets[2], a.offsets[2])
        # the left wrist (joint 20): Gaussians whose triangle it does not skin are untouched, exactly
        moved = pose.clone()
        moved[0, 57:60] += torch.tensor([0.5, -0.4, 0.3])
        v2 = body(None, zero, moved, zero).vertices[0]
        c = av.forward_with_extras(v2, moved[0])[1]
    seen = av.pose_masks[av.face_pose_group[av.face_ids], 57] == 1
    still = (v2 == v0).all(1)[body.faces[av.face_ids]].all(1)  # triangles the wrist does not move at all
    assert seen.sum() > 10 and (still & ~seen).sum() > 10000
    for x, y in zip(a.offsets, c.offsets):
        assert torch.equal(x[still & ~seen], y[still & ~seen])
    assert ((a.offsets[0][seen] - c.offsets[0][seen]).abs().amax(1) > 0).all()
    # the joint weights are the body's skinning weights per SMPL joint
    jw = body.joint_weights()
    assert jw.shape == (body.v_template.shape[0], 24)
    assert torch.allclose(jw.sum(1), torch.ones(jw.shape[0]), atol=1e-5)


# ---------------------------------------------------------------- configs and checkpoints
def test_config_values_and_yaml_round_trip(tmp_path):
    assert AvatarConfig().rectifier == "local"  # the default since the measurement in docs/model.md
    with pytest.raises(UserError, match="model.rectifier must be one of"):  # the old switch: configs are migrated
        AvatarConfig(rectifier=True)
    assert AvatarConfig(rectifier=False).rectifier is False
    with pytest.raises(UserError, match="model.rectifier must be one of paper, local"):
        AvatarConfig(rectifier="lokal")
    with pytest.raises(UserError, match="rectifier_mask_threshold"):
        AvatarConfig(rectifier_mask_threshold=1.5)
    cfg = apply_overrides(TrainConfig(), {"model.rectifier": "local", "model.rectifier_mask_threshold": 0.05})
    save_config(cfg, tmp_path / "c.yaml")
    assert "rectifier: local" in (tmp_path / "c.yaml").read_text()
    back = load_config(tmp_path / "c.yaml")
    assert back == cfg and back.model.rectifier == "local" and back.model.rectifier_mask_threshold == 0.05
    for value in (True, False, "paper"):
        (tmp_path / "d.yaml").write_text(f"model:\n  rectifier: {str(value).lower()}\n")
        assert load_config(tmp_path / "d.yaml").model.rectifier == ("paper" if value is True else value)
    (tmp_path / "e.yaml").write_text("model:\n  rectifier: 3\n")
    with pytest.raises(UserError, match="rectifier"):
        load_config(tmp_path / "e.yaml")


def test_local_avatar_needs_joint_weights_and_reloads_exactly():
    gen = torch.Generator().manual_seed(6)
    body = ToyBody()
    with pytest.raises(UserError, match="joint_weights"):
        Avatar(body.faces, None, body.v_template, AvatarConfig(rectifier="local"))
    av = make_avatar(body, "local", gen).float()  # checkpoints are float32
    state = av.checkpoint_state()
    assert state["config"]["rectifier"] == "local" and "pose_masks" in state["state_dict"]
    back = Avatar.from_state(body, state)
    v, pose = posed_toy(body, gen).float(), torch.randn(69, generator=gen)
    a, b = av(v, pose), back(v, pose)
    assert back.config == av.config
    for x, y in zip((a.means, a.quats, a.scales), (b.means, b.quats, b.scales)):
        assert torch.equal(x, y)
    with pytest.raises(UserError):  # a paper-design state cannot be read as a local one
        Avatar.from_state(body, {**state, "config": {**state["config"], "rectifier": "paper"}})


def test_checkpoints_without_a_design_read_as_paper(tmp_path):
    """A version-2 checkpoint's rectifier: true is the paper's design (the v1 fixture is in test_trained)."""
    payload = {"format": "rmavatar-checkpoint", "version": 2, "iteration": 0, "betas": None,
               "avatar": {"config": {"rectifier": True}, "state_dict": {}},
               "config": {"model": {"rectifier": False}}, "data_spec": "synth", "body": {}, "optimizer": {},
               "density": {}, "sampler": {}, "rng": {}, "saved_at": 0.0}
    torch.save(payload, tmp_path / "last.pt")
    got = read_checkpoint(tmp_path / "last.pt")  # read at all: migrated to today's version
    assert got.avatar["config"]["rectifier"] == "paper" and got.poses is None
    assert got.config["model"]["rectifier"] is False


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("design", ["local", "paper", False])
def test_a_precomputed_face_table_gives_the_same_gaussians(device, design):
    """forward(table=face_table(v)) (what training passes, one table per frame computed once) is
    forward(v): the same values and gradients; face_table of a batch of meshes is each one's."""
    from rmavatar.avatar.model import FACE_TABLE

    gen = torch.Generator().manual_seed(4)
    body = ToyBody()
    av = make_avatar(body, design, gen).to(device)
    pose = (torch.randn(69, generator=gen, dtype=torch.float64) * 0.5).to(device)
    verts = torch.stack([posed_toy(body, gen), posed_toy(body, gen)]).to(device)
    tables = av.face_table(verts)
    assert tables.shape == (2, av.binding_faces.shape[0], FACE_TABLE)
    for k in range(2):
        torch.testing.assert_close(tables[k], av.face_table(verts[k]), atol=1e-12, rtol=0)
        outs = []
        for kwargs in ({"vertices": verts[k]}, {"vertices": None, "table": av.face_table(verts[k])}):
            av.zero_grad()
            gs = av(body_pose=pose if design else None, **kwargs)
            (gs.means.sum() + gs.quats.pow(2).sum() + gs.scales.sum()).backward()
            outs.append((gs.means, gs.quats, gs.scales, av.means.grad.clone(), av.quats.grad.clone()))
        for a, b in zip(*outs):
            assert torch.equal(a, b)
    with pytest.raises(ValueError, match="table must be"):
        av(None, pose, table=tables)
    with pytest.raises(ValueError, match="vertices must be"):
        av.face_table(verts[:, :5])


# ---------------------------------------------------------------- the design classes
def test_each_config_value_builds_its_design_with_the_same_state_keys():
    assert list(DESIGNS) == ["paper", "local"] and rectifier_design(False) is None
    assert rectifier_design("paper") is PaperRectifier and rectifier_design("local") is LocalRectifier
    with pytest.raises(ValueError, match="no rectifier design"):
        rectifier_design("lokal")
    body = ToyBody()
    mlp_keys = {f"rectifier.{k}" for k in Rectifier().state_dict()}  # the MLP's keys, as checkpoints hold them
    layers = {f"rectifier.l{i}.{p}" for i in range(1, 6) for p in ("weight", "bias")}
    assert mlp_keys == layers | {"rectifier.freq_alpha"}
    for design, cls in (("paper", PaperRectifier), ("local", LocalRectifier)):
        av = AvatarConfig(rectifier=design).build(body)
        assert type(av.rectifier) is cls and isinstance(av.rectifier, Rectifier) and av.rectifier.name == design
        keys = set(av.state_dict())
        assert mlp_keys <= keys and not any(k.startswith("rectifier.") for k in keys - mlp_keys)
        assert ({"pose_masks", "face_pose_group"} <= keys) == (design == "local")
    assert PaperRectifier.reads_posed_mesh and not LocalRectifier.reads_posed_mesh
    assert LocalRectifier.offsets_in_face_frame and not PaperRectifier.offsets_in_face_frame
    assert LocalRectifier.needs_joint_weights and not PaperRectifier.needs_joint_weights
    assert AvatarConfig(rectifier="paper").body_joint_weights(body) is None
    assert torch.equal(AvatarConfig(rectifier="local").body_joint_weights(body), body.weights)
    with pytest.raises(NotImplementedError):
        RectifierDesign().encoded_position(None, None)


@pytest.mark.parametrize("design", ["paper", "local"])
@pytest.mark.parametrize("alpha", [6.0, 3.4])
def test_design_reference_gives_the_avatars_offsets(design, alpha):
    """Each design's plain reference (encoding, MLP on concatenated inputs, one pose row per Gaussian, frames
    per Gaussian) against the offsets the avatar's fast path gives: values and gradients, float64."""
    gen = torch.Generator().manual_seed(8)
    body = ToyBody()
    av = make_avatar(body, design, gen, placement="area", num_gaussians=200)
    av.set_frequency_alpha(alpha)
    v = posed_toy(body, gen).requires_grad_(True)
    pose = (torch.randn(69, generator=gen, dtype=torch.float64) * 0.5).requires_grad_(True)
    fast = av.forward_with_extras(v, pose)[1].offsets
    ref = av.rectifier.reference(av, v, pose)
    assert fast[0].abs().max() > 1e-3
    for a, b in zip(fast, ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    weights = [torch.randn(t.shape, generator=gen, dtype=torch.float64) for t in fast]
    inputs = [v, pose, av.means, *av.rectifier.parameters()]
    g_fast = torch.autograd.grad(sum((o * w).sum() for o, w in zip(fast, weights)), inputs, allow_unused=True)
    g_ref = torch.autograd.grad(sum((o * w).sum() for o, w in zip(ref, weights)), inputs, allow_unused=True)
    for a, b in zip(g_fast, g_ref):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert g_fast[0] is not None  # paper: through the encoded mu*; local: through w R and w
    # the raw outputs are what rectify() gives, brought to world units by the design
    raw = av.rectify(v, pose)
    rows = av.face_table(v)[av.face_slot()]
    wR, w = rows[:, FaceTable.wR].reshape(-1, 3, 3), rows[:, FaceTable.w]
    for a, b in zip(av.rectifier.world_offsets(raw, wR, w), fast):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
