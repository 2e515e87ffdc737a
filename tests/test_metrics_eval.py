"""`rmavatar eval` / `evaluate_run` end to end on a tiny run (Anny body, 48x48, two training steps).

The key check: a dataset whose ground-truth frames are the avatar's own renders (made here, directly
with the rasterizer) must score as pixel-exact up to PNG quantisation. Any mismatch of pose, camera,
image size, split or background in the evaluation path would show up as a large error.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers import front_camera

from rmavatar.commands import main
from rmavatar.utils import UserError

SIZE = 48


def camera_dict() -> dict:
    """One fixed camera looking at the Anny body (SMPL axes: y up, facing +z) from 3.2 m in front."""
    return front_camera(SIZE, 70.0)


def params(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    body_pose = (0.15 * rng.standard_normal((n, 69))).astype(np.float32)
    go = np.zeros((n, 3), np.float32)
    go[:, 1] = np.linspace(-0.4, 0.4, n)  # turn a little, frame to frame
    return {"betas": np.zeros((n, 10), np.float32), "global_orient": go, "body_pose": body_pose,
            "transl": np.zeros((n, 3), np.float32)}


def write_dataset(path, images, masks, p, splits):
    from rmavatar.data import write_native

    write_native(path, {"name": "tiny", "splits": splits, "body": "anny"}, camera_dict(), p,
                 images, masks, progress=False)
    return path


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, make_train_config):
    """A run trained for two steps, and a dataset whose test frames are that run's own renders."""
    from rmavatar.avatar import load_trained
    from rmavatar.render import rasterize
    from rmavatar.train import train

    root = tmp_path_factory.mktemp("eval")
    n = 4
    p = params(n, 0)
    grey = [np.full((SIZE, SIZE, 3), 0.5, np.float32)] * n
    ones = [np.ones((SIZE, SIZE), np.float32)] * n
    data = write_dataset(root / "data", grey, ones, p, {"train": [0, 1], "test": [2, 3]})
    cfg = make_train_config(data, 2, sh_degree=1)
    run_dir = root / "run"
    train(cfg, run_dir, progress=False)

    # The oracle: render the test frames directly, white background.
    run = load_trained(run_dir)
    cam = camera_dict()
    renders = []
    with torch.no_grad():
        for i in range(n):
            t = {k: torch.as_tensor(v[i : i + 1]) for k, v in p.items()}
            verts = run.body(t["betas"], t["global_orient"], t["body_pose"], t["transl"]).vertices[0]
            gs = run.avatar(verts, t["body_pose"][0])
            view = torch.as_tensor(cam["viewmat"])
            img, _, _ = rasterize(gs.means, gs.quats, gs.scales, gs.opacities, gs.colors(view),
                                  view, torch.as_tensor(cam["K"]), SIZE, SIZE, background=torch.ones(3))
            renders.append(img.clamp(0, 1).numpy())
    # Stored as 8-bit PNGs, as every dataset is.
    quantised = [np.round(r * 255).astype(np.uint8) for r in renders]
    exact = write_dataset(root / "exact", quantised, ones, p, {"train": [0, 1], "test": [2, 3]})
    return {"root": root, "run": run_dir, "data": data, "exact": exact, "renders": renders,
            "quantised": quantised, "iteration": run.iteration}


def test_self_renders_score_as_exact(tiny):
    from rmavatar.evaluate import psnr
    from rmavatar.evaluate.run import evaluate_run

    res = evaluate_run(tiny["run"], data=str(tiny["exact"]), split="test", progress=False)
    assert [r["index"] for r in res["frames"]] == [2, 3]
    for row, i in zip(res["frames"], (2, 3)):
        expected = psnr(tiny["renders"][i], tiny["quantised"][i].astype(np.float32) / 255)
        assert row["psnr"] == pytest.approx(expected, abs=1e-3)
        # 8-bit rounding alone: PSNR about 59 dB, no more error than that.
        assert row["psnr"] > 55 and row["ssim"] > 0.999 and row["lpips"] < 1e-3
    means = res["mean"]
    assert means["psnr"] == pytest.approx(np.mean([r["psnr"] for r in res["frames"]]))
    proto = res["protocol"]
    assert proto["split"] == "test" and proto["background"] == "white" and proto["pose_refinement"] is False
    assert proto["resolution"] == [SIZE, SIZE] and proto["frames"] == 2 and proto["iteration"] == tiny["iteration"]

    # The same ground truth against a black background: the render changes, the (unmasked) truth not.
    black = evaluate_run(tiny["run"], data=str(tiny["exact"]), split="test", bg="black", max_frames=1,
                         progress=False)
    assert black["mean"]["psnr"] < 30 and black["protocol"]["background"] == "black"


def test_mask_composites_ground_truth_over_background(tiny):
    # Frames with an empty mask are pure background: scoring them equals scoring the render against a
    # plain white image.
    from rmavatar.evaluate import psnr, ssim
    from rmavatar.evaluate.run import evaluate_run

    n = 4
    noise = [np.random.default_rng(i).random((SIZE, SIZE, 3)).astype(np.float32) for i in range(n)]
    empty = [np.zeros((SIZE, SIZE), np.float32)] * n
    data = write_dataset(tiny["root"] / "masked", noise, empty, params(n, 0), {"train": [0, 1], "test": [2, 3]})
    res = evaluate_run(tiny["run"], data=str(data), progress=False)
    white = np.ones((SIZE, SIZE, 3), np.float32)
    for row, i in zip(res["frames"], (2, 3)):
        assert row["psnr"] == pytest.approx(psnr(tiny["renders"][i], white), abs=1e-3)
        assert row["ssim"] == pytest.approx(ssim(tiny["renders"][i], white), abs=1e-4)


def test_cli_writes_json_and_images(tiny, capsys):
    from PIL import Image

    out = tiny["root"] / "cli" / "eval.json"
    out.parent.mkdir()
    code = main(["eval", str(tiny["run"]), "--data", str(tiny["exact"]), "--json", str(out), "--quiet"])
    assert code == 0
    res = json.loads(out.read_text())
    assert len(res["frames"]) == 2 and set(res["mean"]) == {"psnr", "ssim", "lpips"}
    assert "PSNR" in capsys.readouterr().out
    images = out.parent / "eval_images"
    pngs = sorted(images.glob("*.png"))
    assert [p.name for p in pngs] == ["test_0000_frame00002.png", "test_0001_frame00003.png"]
    panel = np.asarray(Image.open(pngs[0]))
    assert panel.shape == (SIZE, 3 * SIZE, 3)
    # render | ground truth | heat map: the first two agree to 8-bit rounding, the map is near-black.
    assert np.abs(panel[:, :SIZE].astype(int) - tiny["quantised"][2]).max() <= 1
    assert np.array_equal(panel[:, SIZE : 2 * SIZE], tiny["quantised"][2])
    assert panel[:, 2 * SIZE :].max() < 40
    assert json.loads((images / "metrics.json").read_text()) == res
    # Running again replaces our own images folder.
    assert main(["eval", str(tiny["run"]), "--data", str(tiny["exact"]), "--json", str(out), "--quiet",
                 "--frames", "1"]) == 0
    assert len(list(images.glob("*.png"))) == 1 and json.loads(out.read_text())["protocol"]["frames"] == 1


def test_heat_map_scale():
    from rmavatar.evaluate.run import HEAT_MAX, heat_map

    a = np.zeros((2, 2, 3))
    b = np.array([[[0, 0, 0], [HEAT_MAX] * 3], [[1, 1, 1], [HEAT_MAX / 2] * 3]], dtype=np.float64)
    h = heat_map(a, b)
    assert np.allclose(h[0, 0], [0, 0, 4 / 255]) and np.allclose(h[0, 1], h[1, 0])  # saturates at HEAT_MAX
    assert np.allclose(h[1, 1], np.array([188, 55, 84]) / 255)  # the middle anchor


def test_bad_input(tiny, tmp_path, capsys):
    from rmavatar.evaluate.run import evaluate_run

    # A folder without a run, a run without a checkpoint.
    with pytest.raises(UserError, match="not an rmavatar run"):
        evaluate_run(tmp_path, progress=False)
    # A split the dataset lacks names the ones it has.
    with pytest.raises(UserError, match="no split 'novel_pose'.*train, test"):
        evaluate_run(tiny["run"], split="novel_pose", progress=False)
    with pytest.raises(UserError, match="background"):
        evaluate_run(tiny["run"], bg="green", progress=False)
    # An unwritable JSON path fails before any work, and leaves nothing behind.
    code = main(["eval", str(tiny["run"]), "--json", str(tmp_path / "missing" / "e.json")])
    assert code == 2 and "does not exist" in capsys.readouterr().err
    # Someone else's non-empty folder is never replaced by the images.
    other = tmp_path / "mine"
    other.mkdir()
    (other / "keep.txt").write_text("precious")
    code = main(["eval", str(tiny["run"]), "--json", str(tmp_path / "e.json"), "--images", str(other), "--quiet"])
    assert code == 2 and "refusing to replace" in capsys.readouterr().err
    assert (other / "keep.txt").read_text() == "precious" and not (tmp_path / "e.json").exists()
    # A failure in the middle of the frames (a missing image file) leaves no images folder.
    import shutil

    broken = shutil.copytree(tiny["exact"], tmp_path / "broken")
    victim = sorted((broken / "images").iterdir())[3]  # the second test frame
    victim.unlink()
    with pytest.raises(Exception):
        evaluate_run(tiny["run"], data=str(broken), out_dir=tmp_path / "imgs", progress=False)
    assert not (tmp_path / "imgs").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken", "mine"]


def test_runs_own_data_is_recognised_by_resolved_path(tmp_path, monkeypatch):
    """`eval RUN --split train --data DATA/` scores with the run's refined poses, as `--data DATA` does:
    the dataset specs are compared as resolved paths, never as strings."""
    from types import SimpleNamespace

    from rmavatar.body import PoseSequence
    from rmavatar.data.registry import normalize_spec, same_dataset
    from rmavatar.evaluate.run import _choose_poses, _Evaluation

    data = tmp_path / "DATA"
    data.mkdir()
    (data / "meta.yaml").write_text("name: d\n")  # the native layout, for the kind-less specs
    monkeypatch.chdir(tmp_path)
    n = 2
    p = params(n, 1)
    refined = PoseSequence.from_arrays(p["global_orient"] + 0.1, p["body_pose"], p["transl"])
    run = SimpleNamespace(training_poses=refined, training_split="train", data_spec=str(data), config={})
    for spec in ("DATA/", "./DATA", str(data) + "/", f"native:{data}", "sub/../DATA"):
        (tmp_path / "sub").mkdir(exist_ok=True)
        ev = _Evaluation(run, SimpleNamespace(root=data), spec, "train", n, n, {**p, "index": np.arange(n)},
                         torch.device("cpu"), torch.ones(3))
        poses, source, _ = _choose_poses(ev, None, progress=False)
        assert source == "refined in training", spec
        assert torch.allclose(poses.global_orient, refined.global_orient)
    assert normalize_spec("DATA/") == str(data) and normalize_spec("zju:DATA/?camera=1") == f"zju:{data}?camera=1"
    assert not same_dataset("DATA?camera=1", "DATA") and not same_dataset("zju:DATA", "native:DATA")
    (tmp_path / "OTHER").mkdir()
    ev = _Evaluation(run, SimpleNamespace(root=data), "OTHER", "train", n, n, {**p, "index": np.arange(n)},
                     torch.device("cpu"), torch.ones(3))
    assert _choose_poses(ev, None, progress=False)[1] == "the dataset's"


def test_another_cameras_view_takes_the_refined_poses_of_its_instants(tmp_path, monkeypatch):
    """A novel_view split of another camera (same_instant: for each of its frames, the training frame of
    the same instant) is posed as the run refined those instants; --fit-poses on it is refused (it would
    fit each pose to the very view it scores)."""
    from types import SimpleNamespace

    from rmavatar.body import PoseSequence
    from rmavatar.evaluate.fit import PoseFitConfig
    from rmavatar.evaluate.run import _choose_poses, _Evaluation

    data = tmp_path / "DATA"
    data.mkdir()
    (data / "meta.yaml").write_text("name: d\n")
    p = params(3, 1)
    refined = PoseSequence.from_arrays(p["global_orient"] + 0.1, p["body_pose"] + 0.2, p["transl"])
    run = SimpleNamespace(training_poses=refined, training_split="train", data_spec=str(data), config={})
    dataset = SimpleNamespace(root=data, splits={"train": [0, 2, 4], "novel_view": [10, 11]},
                              same_instant={"novel_view": [4, 2]})
    q = {k: v[:2] for k, v in p.items()}
    ev = _Evaluation(run, dataset, str(data), "novel_view", 2, 2, {**q, "index": np.array([10, 11])},
                     torch.device("cpu"), torch.ones(3))
    poses, source, _ = _choose_poses(ev, None, progress=False)
    assert source.startswith("refined in training, of the same instants")
    assert torch.equal(poses.body_pose, refined.body_pose[[2, 1]])
    from rmavatar.evaluate import run as run_module

    monkeypatch.setattr(run_module, "_open", lambda *a: SimpleNamespace(dataset=SimpleNamespace(same_instant={"test": [0]})))
    with pytest.raises(UserError, match="--fit-poses on split test would fit each pose to the very view it scores"):
        run_module.evaluate_run(tmp_path, split="test", fit=PoseFitConfig(), progress=False)


def test_options_without_effect_are_refused(tmp_path, capsys):
    """Contradicting options, options that only matter beside another, and one path named as both
    outputs are errors before any work (nothing is written)."""
    run, out = str(tmp_path / "run"), str(tmp_path / "e.json")
    for extra, why in ((["--images", str(tmp_path / "i"), "--no-images"], "contradict"),
                       (["--fit-batch", "4"], "--fit-batch only matters with --fit-poses"),
                       (["--fit-smooth", "0", "--fit-batch", "2"], "--fit-smooth and --fit-batch"),
                       (["--images", str(tmp_path / "." / "e.json") + "/"], "would hold the --json file"),
                       (["--images", str(tmp_path)], "would hold the --json file")):
        assert main(["eval", run, "--json", out, *extra]) == 2
        assert why in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == []
