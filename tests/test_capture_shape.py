"""The capture's shape fit (:mod:`rmavatar.capture.shape`): Anny body offsets fitted to masks with the
poses held. A body with known offsets rendered to masks from a few views is recovered (sign, size,
where), its own preset's masks leave the body near its preset, the Laplacian and frame picks are right,
SMPL bodies skip the fit, and ``rmavatar capture`` writes the offsets unless ``--no-shape``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from rmavatar.body import load_body_model
from rmavatar.capture import fit as F
from rmavatar.capture.shape import (
    ShapeFitConfig,
    can_fit_shape,
    edges,
    fit_body_offsets,
    free_vertices,
    laplacian,
    spread_frames,
)
from rmavatar.commands import main

SIDE = 256  # the frames' side; masks are compared at this size (as the capture's FIT_SIDE)


@pytest.fixture(scope="module")
def anny():
    return load_body_model("anny:neutral")


def _poses(T: int = 6) -> dict:
    """An A-pose turning through 150 degrees in front of the camera, 3 m away: params [T,...]."""
    upright = Rotation.from_euler("x", 180, degrees=True)  # the body's y up is the camera's -y
    go = np.stack([(upright * Rotation.from_euler("y", a, degrees=True)).as_rotvec()
                   for a in np.linspace(0, 150, T)]).astype(np.float32)  # fmt: skip
    return {"global_orient": go, "body_pose": F.rest_pose().expand(T, 69).numpy().copy(),
            "transl": np.tile(np.float32([0.0, 0.0, 3.0]), (T, 1))}


def _silhouettes(body, params: dict, K: np.ndarray) -> list[np.ndarray]:
    from rmavatar.capture.sheet import body_silhouette

    t = {k: torch.as_tensor(v) for k, v in params.items()}
    with torch.no_grad():
        vertices = body(None, t["global_orient"], t["body_pose"], t["transl"]).vertices.numpy().astype(np.float64)
    return [body_silhouette(v, body.faces.numpy(), K, SIDE, SIDE) for v in vertices]


def _mask_observations(masks: list[np.ndarray], K: np.ndarray) -> F.Observations:
    """What the shape fit reads of the capture's Observations: the mask maps, K, size, the height."""
    outside, outline, weight = F.mask_maps(masks, SIDE)
    rows = [np.nonzero(m.any(1))[0] for m in masks]
    T = len(masks)
    return F.Observations(keypoints=torch.zeros(T, 0, 2), visibility=torch.zeros(T, 0), world=torch.zeros(T, 0, 3),
                          outside=torch.as_tensor(outside), K=torch.as_tensor(K, dtype=torch.float32),
                          size=(SIDE, SIDE), gaps=torch.ones(T - 1),
                          height_px=float(np.median([r[-1] - r[0] + 1 for r in rows])),
                          outline=torch.as_tensor(outline), outline_weight=torch.as_tensor(weight))


def _iou(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    return float(np.mean([(x & y).sum() / (x | y).sum() for x, y in zip(a, b)]))


K = np.array([[300.0, 0, SIDE / 2], [0, 300.0, SIDE / 2], [0, 0, 1]])


def test_a_wider_torso_is_recovered_and_raises_the_iou(anny):
    """The true body: the preset with +3 cm on its torso and limbs (Anny's "body" part), rendered from
    six views. Fitted with the preset and the true poses, the offsets there come out positive and about
    3 cm, the head, hands and feet move less, and the IoU with the masks rises above the preset's."""
    V = anny.rest_vertices.shape[0]
    part = torch.zeros(V, dtype=torch.long)
    part[anny.faces.reshape(-1)] = anny.face_part.repeat_interleave(3)
    free, head = free_vertices(anny)
    torso = ((part == anny.part_names.index("body")) & free).numpy()
    truth = np.where(torso, 0.03, 0.0).astype(np.float32)
    params = _poses()
    masks = _silhouettes(load_body_model("anny:neutral", offsets=truth), params, K)
    d = fit_body_offsets(anny, params, _mask_observations(masks, K), ShapeFitConfig()).offsets
    assert d.shape == (V,) and d.dtype == np.float32
    assert np.all(d[~free.numpy()] == 0) and d.min() >= 0 and d.max() <= 0.10 + 1e-6
    assert d[head.numpy()].max() <= 0.03 + 1e-6
    # measured: median 2.69 cm on the torso and limbs, 0.04 mm elsewhere; IoU 0.772 -> 0.982 (with the
    # outline term off: 0.05 cm and 0.776, the silhouette term alone cannot widen a body)
    assert 0.02 < float(np.median(d[torso])) < 0.04, float(np.median(d[torso]))
    assert float(np.median(d[~torso & free.numpy()])) < float(np.median(d[torso])) / 2
    before = _iou(_silhouettes(anny, params, K), masks)
    after = _iou(_silhouettes(load_body_model("anny:neutral", offsets=d), params, K), masks)
    assert after > before + 0.02, (before, after)


def test_the_presets_own_masks_leave_it_near_the_preset(anny):
    """Masks of the preset body itself: the fitted offsets stay small (what the synthetic clip's
    subject, Anny's neutral preset, needs) and the IoU does not drop."""
    params = _poses()
    masks = _silhouettes(anny, params, K)
    d = fit_body_offsets(anny, params, _mask_observations(masks, K)).offsets
    free, _ = free_vertices(anny)
    # measured: 0.87 mm on average (at most 1.6 cm), IoU 1 -> 0.990 (the mask terms see surface points
    # 2 cm apart, which lie a little inside the silhouette's rim)
    assert float(np.abs(d[free.numpy()]).mean()) < 0.003, float(np.abs(d[free.numpy()]).mean())
    after = _iou(_silhouettes(load_body_model("anny:neutral", offsets=d), params, K), masks)
    assert after > 0.98, after


def test_laplacian_and_frame_picks(anny):
    """The Laplacian of a constant is zero and of a one-vertex bump is the bump there and minus the
    bump over the degree at each neighbour; frames spread over the clip, ends included."""
    e = edges(anny.faces)
    V = anny.rest_vertices.shape[0]
    degree = torch.bincount(e.reshape(-1), minlength=V).clamp_min(1).float()
    assert laplacian(torch.full((V,), 2.0), e, degree).abs().max() < 1e-6
    bump = torch.zeros(V)
    bump[100] = 1.0
    lap = laplacian(bump, e, degree)
    neighbours = torch.cat([e[e[:, 0] == 100, 1], e[e[:, 1] == 100, 0]])
    assert lap[100] == 1.0 and len(neighbours) == int(degree[100])
    assert torch.allclose(lap[neighbours], -1.0 / degree[neighbours])
    assert int((lap != 0).sum()) == 1 + len(neighbours)
    assert spread_frames(100, 24)[0] == 0 and spread_frames(100, 24)[-1] == 99 and len(spread_frames(100, 24)) == 24
    assert spread_frames(5, 24) == [0, 1, 2, 3, 4]


def test_an_smpl_body_skips_the_shape_fit(tmp_path, anny):
    from helpers import random_smpl, save_npz

    from rmavatar.capture.pipeline import _fit_shape

    save_npz(random_smpl(10, seed=7), tmp_path / "m.npz")
    smpl = load_body_model(f"smpl:{tmp_path / 'm.npz'}")
    assert not can_fit_shape(smpl) and can_fit_shape(anny)
    assert _fit_shape(smpl, {}, None, ShapeFitConfig()) == (None, smpl)
    assert _fit_shape(anny, {}, None, None) == (None, anny)


def test_capture_writes_the_offsets_unless_no_shape(tmp_path, capsys):
    """``rmavatar capture`` on a tiny synthetic clip: smpl.npz holds body_offsets [V] within the
    configured range, the dataset and meta.yaml carry them, the printout says so; --no-shape writes none."""
    pytest.importorskip("mediapipe")
    import yaml

    from rmavatar.data import load_dataset
    from rmavatar.data.synth import SynthConfig, synthesize

    from test_capture import _write_video

    truth = tmp_path / "truth"
    synthesize(truth, SynthConfig(size=128, seed=0, train=6, test=2, novel_pose=0, ss=1, turns=0.5), progress=False)
    ds = load_dataset(truth)
    _write_video(tmp_path / "turn.mp4", [(f.image * 255 + 0.5).astype(np.uint8) for s in ("train", "test")
                                         for f in ds.frames(s)], fps=7.5)
    out = tmp_path / "shaped"
    assert main(["capture", str(tmp_path / "turn.mp4"), "--out", str(out), "--iters", "40", "--quiet"]) == 0
    assert "shape: the body's surface moved by" in capsys.readouterr().out
    with np.load(out / "smpl.npz") as z:
        d = z["body_offsets"]
    cfg = ShapeFitConfig()
    assert d.shape == (13718,) and d.min() >= cfg.min_offset and d.max() <= cfg.max_offset + 1e-6 and d.max() > 0
    assert np.array_equal(load_dataset(out).body_offsets, d)
    extra = yaml.safe_load((out / "meta.yaml").read_text())["extra"]
    assert extra["shape"]["max_mm"] == round(float(d.max()) * 1000, 1) and extra["shape_fit"]["iters"] == cfg.iters
    flat = tmp_path / "preset"
    assert main(["capture", str(tmp_path / "turn.mp4"), "--out", str(flat), "--iters", "40", "--no-shape",
                 "--quiet"]) == 0
    assert "shape:" not in capsys.readouterr().out
    with np.load(flat / "smpl.npz") as z:
        assert "body_offsets" not in z.files
    assert load_dataset(flat).body_offsets is None
    assert yaml.safe_load((flat / "meta.yaml").read_text())["extra"]["shape"] is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_shape_fit_on_cuda_matches_the_cpu(anny):
    truth = np.where(free_vertices(anny)[0].numpy(), 0.02, 0.0).astype(np.float32)
    params = _poses(4)
    obs = _mask_observations(_silhouettes(load_body_model("anny:neutral", offsets=truth), params, K), K)
    cpu = fit_body_offsets(anny, params, obs).offsets
    on_gpu = F.Observations(**{k: v.cuda() if torch.is_tensor(v) else v for k, v in vars(obs).items()})
    gpu = fit_body_offsets(load_body_model("anny:neutral").cuda(), params, on_gpu).offsets
    assert np.abs(gpu - cpu).max() < 0.002, np.abs(gpu - cpu).max()


def test_the_no_shape_help_names_the_configs_bounds():
    """--help writes ShapeFitConfig's bounds out (importing it would import torch for every command)."""
    import argparse

    from rmavatar.commands.capture import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    text = " ".join(next(a.help for a in parser._actions if "--no-shape" in a.option_strings).split())
    cfg = ShapeFitConfig()
    assert cfg.min_offset == 0 and "outwards" in text
    assert f"at most {cfg.max_offset * 100:g} cm, the head {cfg.head_max_offset * 100:g} cm" in text
