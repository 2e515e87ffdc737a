"""Datasets: the native format, PeopleSnapshot and ZJU-MoCap on fixtures built here (tiny images)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import RNG, add_zju_frame, make_peoplesnapshot, make_zju, rodrigues, save_png
from PIL import Image

from rmavatar.data import Camera, NativeMeta, load_dataset, write_native
from rmavatar.data.dataset import target_size
from rmavatar.data.io import resample
from rmavatar.data.peoplesnapshot import SUBJECTS, split_frames
from rmavatar.data.registry import parse_spec
from rmavatar.data.zju import SPLITS as ZJU_SPLITS
from rmavatar.data.zju import undistort_maps, zju_to_smpl_params
from rmavatar.utils import UserError

# --- Camera ----------------------------------------------------------------------------------------

def test_camera_resized_scales_K_and_matches_resampled_pixels():
    K = np.array([[20.0, 0, 4.0], [0, 22.0, 3.0], [0, 0, 1]])
    cam = Camera(K, np.eye(4), 8, 6)
    small = cam.resized(4, 3)
    np.testing.assert_allclose(small.K, np.diag([0.5, 0.5, 1]) @ K, atol=1e-6)
    odd = cam.resized(6, 5)
    np.testing.assert_allclose(odd.K, np.diag([6 / 8, 5 / 6, 1]) @ K, atol=1e-5)
    assert (small.width, small.height) == (4, 3)

    # A 3D point that projects to the centre of a block of bright pixels, and the block resampled to
    # a size where the block covers whole output pixels: the resized camera projects the point to the
    # block's new centroid (pixel centres at +0.5 in both).
    for (W, H), (x0, x1, y0, y1), (w, h) in (((8, 6), (2, 4, 2, 4), (4, 3)),
                                             ((12, 6), (6, 9, 2, 4), (4, 3)),
                                             ((12, 12), (3, 9, 6, 9), (4, 4))):
        cam = Camera(K, np.eye(4), W, H)
        centre = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
        point = np.linalg.inv(K) @ np.array([*centre, 1.0]) * 2.0
        np.testing.assert_allclose(cam.project(point[None])[0], centre, atol=1e-5)
        img = np.zeros((H, W), np.float32)
        img[y0:y1, x0:x1] = 1
        out = resample(img, w, h)
        ys, xs = np.mgrid[0:h, 0:w]
        centroid = np.array([(out * (xs + 0.5)).sum(), (out * (ys + 0.5)).sum()]) / out.sum()
        np.testing.assert_allclose(cam.resized(w, h).project(point[None])[0], centroid, atol=1e-4)


def test_target_size_and_spec_parsing(tmp_path):
    assert target_size(1080, 1080, 540) == (540, 540)
    assert target_size(1000, 500, 256) == (256, 128)
    assert target_size(1000, 500, (100, 60)) == (100, 60)
    assert target_size(8, 6, None) == (8, 6)
    assert parse_spec("zju:/a/b?camera=3&mask=cihp") == ("zju", tmp_path.__class__("/a/b"),
                                                           {"camera": "3", "mask": "cihp"})
    kind, path, opts = parse_spec("/a/what?x")
    assert kind is None and str(path) == "/a/what?x" and opts == {}


# --- native format ---------------------------------------------------------------------------------

def make_native(out, n=6, h=6, w=8, per_frame=True, betas_per_frame=False):
    images = [RNG.random((h, w, 3)).astype(np.float32) for _ in range(n)]
    masks = [RNG.random((h, w)).astype(np.float32) for _ in range(n)]
    K = np.array([[10.0, 0, 4], [0, 10, 3], [0, 0, 1]], np.float32)
    if per_frame:
        cams = [Camera(K * np.array([[1 + i, 1, 1], [1, 1 + i, 1], [1, 1, 1]], np.float32),
                       np.eye(4), w, h) for i in range(n)]
    else:
        cams = Camera(K, np.eye(4), w, h)
    params = {
        "betas": RNG.normal(size=(n, 10) if betas_per_frame else (10,)),
        "global_orient": RNG.normal(size=(n, 3)),
        "body_pose": RNG.normal(size=(n, 69)) * 0.1,
        "transl": RNG.normal(size=(n, 3)),
    }
    meta = NativeMeta(name="subject", splits={"train": [0, 2, 4], "test": [1, 3], "novel_pose": [5]},
                      fps=25, gender="female", body="anny:female", extra={"seed": np.int64(3)})
    write_native(out, meta, cams, params, iter(images), (m for m in masks), progress=False)
    return images, masks, cams, params


def test_native_roundtrip(tmp_path):
    out = tmp_path / "nat"
    images, masks, cams, params = make_native(out, betas_per_frame=True)
    ds = load_dataset(str(out))
    assert (ds.kind, ds.name, ds.gender, ds.body, ds.fps) == ("native", "subject", "female", "anny:female", 25)
    assert ds.splits == {"train": [0, 2, 4], "test": [1, 3], "novel_pose": [5]}
    assert [ds.num_frames(s) for s in ("train", "test", "novel_pose")] == [3, 2, 1]
    f = ds.frame("test", 1)
    assert f.index == 3 and f.split == "test"
    assert f.image.dtype == np.float32 and f.image.shape == (6, 8, 3)
    np.testing.assert_allclose(f.image, images[3], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(f.mask, masks[3], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(f.camera.K, cams[3].K, atol=1e-6)
    for key in ("betas", "global_orient", "body_pose", "transl"):
        np.testing.assert_allclose(getattr(f, key), params[key][3], atol=1e-6)
    p = ds.params("train")
    np.testing.assert_allclose(p["transl"], params["transl"][[0, 2, 4]], atol=1e-6)
    assert list(p["index"]) == [0, 2, 4]
    # frames(split[, n]): the first n frames, decoded when indexed, the same as frame() gives.
    view = ds.frames("train", 2)
    assert len(view) == 2 and [f.index for f in view] == [0, 2] and len(ds.frames("train")) == 3
    np.testing.assert_array_equal(view[1].image, ds.frame("train", 1).image)
    with pytest.raises(IndexError):
        view[2]


def test_native_single_camera_broadcast_and_resize(tmp_path):
    out = tmp_path / "nat"
    images, masks, cam, params = make_native(out, per_frame=False)
    ds = load_dataset(f"native:{out}", size=4)
    assert ds.image_size == (4, 3)
    f = ds.frame("train", 2)
    assert f.image.shape == (3, 4, 3) and f.mask.shape == (3, 4)
    np.testing.assert_allclose(f.camera.K, np.diag([0.5, 0.5, 1]) @ cam.K, atol=1e-6)
    # box-filter downsampling by 2: each output pixel is the mean of its 2x2 block
    ref = images[4].reshape(3, 2, 4, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(f.image, ref, atol=1 / 255)
    np.testing.assert_allclose(f.betas, params["betas"], atol=1e-6)


def test_native_cache_is_bounded(tmp_path):
    out = tmp_path / "nat"
    make_native(out)
    ds = load_dataset(out, cache_mb=2 * (6 * 8 * 4 * 4) / 2**20)  # room for two frames
    first = ds.frame("train", 0).image
    for i in range(3):
        ds.frame("train", i)
    assert len(ds._cache) == 2 and ds._cache_bytes <= ds._cache_limit
    assert ds.frame("train", 2).image is ds.frame("train", 2).image  # a hit returns the cached array
    np.testing.assert_array_equal(ds.frame("train", 0).image, first)
    with pytest.raises(ValueError):
        first[0, 0, 0] = 1  # cached arrays are read-only


def test_native_write_is_atomic_and_checks_counts(tmp_path):
    out = tmp_path / "nat"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    n = 4
    with pytest.raises(UserError, match="nat holds files that rmavatar did not write.*keep.txt.*refusing"):
        write_native(out, {"name": "x", "splits": {"train": [0]}}, Camera(np.eye(3), np.eye(4), 8, 6),
                     {"betas": np.zeros(10), "global_orient": np.zeros((n, 3)), "body_pose": np.zeros((n, 69)),
                      "transl": np.zeros((n, 3))}, [np.zeros((6, 8, 3))] * n, [np.zeros((6, 8))] * n,
                     progress=False)
    (out / "meta.yaml").write_text("a dataset made by something else")  # not ours either: still refused
    with pytest.raises(UserError, match="refusing to replace"):
        write_native(out, {"name": "x", "splits": {"train": [0]}}, Camera(np.eye(3), np.eye(4), 8, 6),
                     {"betas": np.zeros(10), "global_orient": np.zeros((n, 3)), "body_pose": np.zeros((n, 69)),
                      "transl": np.zeros((n, 3))}, [np.zeros((6, 8, 3))] * n, [np.zeros((6, 8))] * n,
                     progress=False)
    assert (out / "meta.yaml").read_text() == "a dataset made by something else"
    theirs, out = out, tmp_path / "nat2"  # the checks of the frames, on a new folder
    params = {"betas": np.zeros(10), "global_orient": np.zeros((n, 3)), "body_pose": np.zeros((n, 69)),
              "transl": np.zeros((n, 3))}
    cam = Camera(np.eye(3), np.eye(4), 8, 6)
    imgs = (np.zeros((6, 8, 3)) for _ in range(3))  # one short
    masks = (np.zeros((6, 8)) for _ in range(n))
    with pytest.raises(UserError, match="3 images for 4 frames"):
        write_native(out, {"name": "x", "splits": {"train": [0]}}, cam, params, imgs, masks, progress=False)
    assert (theirs / "keep.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["nat"]  # no temporary folder left behind
    with pytest.raises(UserError, match="more images"):
        write_native(out, {"name": "x", "splits": {"train": [0]}}, cam, params,
                     [np.zeros((6, 8, 3))] * 5, [np.zeros((6, 8))] * 4, progress=False)
    with pytest.raises(UserError, match="outside"):
        write_native(out, {"name": "x", "splits": {"train": [7]}}, cam, params,
                     [np.zeros((6, 8, 3))] * 4, [np.zeros((6, 8))] * 4, progress=False)
    with pytest.raises(UserError, match="cameras are 8x6, images 9x6"):
        write_native(out, {"name": "x", "splits": {"train": [0]}}, cam, params,
                     [np.zeros((6, 9, 3))] * 4, [np.zeros((6, 9))] * 4, progress=False)
    assert (theirs / "keep.txt").read_text() == "old"


def test_native_bad_input(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_dataset(tmp_path / "nope")
    out = tmp_path / "nat"
    make_native(out)
    with pytest.raises(UserError, match="not a dataset .* it holds datasets: nat"):
        load_dataset(tmp_path)
    (out / "masks" / "00003.png").unlink()
    with pytest.raises(UserError, match=r"frame 3 has no mask: .*masks/00003.png"):
        load_dataset(out)
    make_native(out)
    (out / "images" / "00002.png").write_bytes(b"not a png")
    ds = load_dataset(out)
    with pytest.raises(UserError, match=r"cannot read image .*images/00002.png"):
        ds.frame("train", 1)
    make_native(out)
    np.savez(out / "cameras.npz", K=np.eye(3))
    with pytest.raises(UserError, match=r"cameras.npz is missing \['viewmat'\]"):
        load_dataset(out)
    make_native(out)
    z = dict(np.load(out / "smpl.npz"))
    z["transl"] = z["transl"][:5]
    z["global_orient"] = z["global_orient"][:5]
    z["body_pose"] = z["body_pose"][:5]
    np.savez(out / "smpl.npz", **z)
    with pytest.raises(UserError, match=r"smpl.npz has 5 frames, meta.yaml says 6"):
        load_dataset(out)


# --- PeopleSnapshot --------------------------------------------------------------------------------

SPEC_COUNTS = {  # the standard splits (docs/data.md): train / val / test frame counts
    "male-3-casual": (114, 1, 55), "male-4-casual": (110, 1, 36),
    "female-3-casual": (112, 1, 51), "female-4-casual": (84, 1, 48),
}


def test_peoplesnapshot_standard_split_counts():
    for subject, counts in SPEC_COUNTS.items():
        _, table = SUBJECTS[subject]
        assert tuple(len(split_frames(*table[s])) for s in ("train", "val", "test")) == counts


def test_peoplesnapshot_standard_subject(tmp_path):
    _, table = SUBJECTS["male-3-casual"]
    frames = {s: split_frames(*r) for s, r in table.items()}
    root = tmp_path / "male-3-casual"
    betas = make_peoplesnapshot(root, frames)
    ds = load_dataset(root)
    assert ds.kind == "peoplesnapshot" and ds.gender == "male" and ds.name == "male-3-casual"
    assert {s: ds.num_frames(s) for s in ds.splits} == {"train": 114, "val": 1, "test": 55}
    f = ds.frame("test", 2)
    assert f.index == 464 and f.transl[0] == 464
    np.testing.assert_allclose(f.image, 464 % 256 / 255, atol=1e-6)
    # betas per split: each split's own file applies to its frames
    np.testing.assert_allclose(ds.frame("train", 5).betas, betas["train"][0], atol=1e-6)
    np.testing.assert_allclose(f.betas, betas["test"][0], atol=1e-6)
    np.testing.assert_allclose(ds.frame("val", 0).betas, betas["val"][0], atol=1e-6)
    assert not np.allclose(betas["train"], betas["test"])
    np.testing.assert_array_equal(f.mask, np.repeat([[1, 1, 1, 0, 0, 0]], 4, axis=0))

    # a split without its anim_nerf file takes its frames' rows of poses.npz
    (root / "poses" / "anim_nerf_test.npz").unlink()
    thetas = RNG.normal(size=(700, 72)).astype(np.float32)
    transl = RNG.normal(size=(700, 3)).astype(np.float32)
    np.savez(root / "poses.npz", betas=np.full((1, 10), 0.3), thetas=thetas, transl=transl)
    f = load_dataset(root).frame("test", 2)
    np.testing.assert_allclose(f.global_orient, thetas[464, :3], atol=1e-6)
    np.testing.assert_allclose(f.body_pose, thetas[464, 3:], atol=1e-6)
    np.testing.assert_allclose(f.transl, transl[464], atol=1e-6)
    np.testing.assert_allclose(f.betas, 0.3, atol=1e-6)


def test_peoplesnapshot_png_soft_masks_and_unknown_subject(tmp_path):
    root = tmp_path / "my-subject"
    make_peoplesnapshot(root, {"train": list(range(5)), "test": list(range(5))}, mask_kind="png")
    ds = load_dataset(f"peoplesnapshot:{root}")
    assert ds.splits == {"train": [0, 1, 2, 3, 4], "test": [0, 1, 2, 3, 4]}
    assert ds.gender == "neutral"
    m = ds.frame("train", 0).mask
    assert m.dtype == np.float32 and m[0, 0] == pytest.approx(128 / 255) and m[1, 0] == 1 and m[1, 5] == 0


def test_peoplesnapshot_unknown_subject_needs_splits_file(tmp_path):
    root = tmp_path / "female-x"
    make_peoplesnapshot(root, {"train": [0, 2, 4], "test": [1, 3]}, total=5)
    with pytest.raises(UserError, match="splits.yaml"):
        load_dataset(root)
    (root / "splits.yaml").write_text("train: {start: 0, end: 4, step: 2}\ntest: [1, 3]\n")
    ds = load_dataset(root)
    assert ds.splits == {"train": [0, 2, 4], "test": [1, 3]} and ds.gender == "female"
    assert ds.frame("test", 1).transl[0] == 3


def test_peoplesnapshot_bad_input(tmp_path):
    root = tmp_path / "s"
    make_peoplesnapshot(root, {"train": [0, 1, 2]})
    np.savez(root / "cameras.npz", intrinsic=np.eye(3), extrinsic=np.eye(4), width=6)
    with pytest.raises(UserError, match=r"s/cameras.npz is missing \['height'\]"):
        load_dataset(root)
    root = tmp_path / "t"
    make_peoplesnapshot(root, {"train": [0, 1, 2]})
    (root / "masks" / "mask_0001.npy").unlink()
    with pytest.raises(UserError, match=r"frame 1 of split 'train' has no mask: .*mask_0001.npy"):
        load_dataset(root)
    root = tmp_path / "male-4-casual"
    make_peoplesnapshot(root, {"train": split_frames(0, 659, 6), "val": [660], "test": [660]})
    z = dict(np.load(root / "poses" / "anim_nerf_train.npz"))
    np.savez(root / "poses" / "anim_nerf_train.npz", **{k: v if k == "betas" else v[:109] for k, v in z.items()})
    with pytest.raises(UserError, match=r"anim_nerf_train.npz has 109 poses .* for the 110 frames"):
        load_dataset(root)


# --- ZJU-MoCap -------------------------------------------------------------------------------------

def test_zju_rh_th_conversion_rigid():
    """ZJU's placement x = R(Rh) SMPL(poses) + Th equals SMPL-style global_orient/transl about J0."""
    X = RNG.normal(size=(50, 3))  # a body's vertices articulated below the root (LBS-free check)
    for root_rot in (np.zeros(3), RNG.normal(size=3) * 0.7):
        Rh, Th, J0 = RNG.normal(size=3) * 1.2, RNG.normal(size=3), np.array([0.01, -0.23, 0.03])
        poses = np.concatenate([root_rot, RNG.normal(size=69) * 0.2])
        smpl_zju = (X - J0) @ rodrigues(root_rot).T + J0  # SMPL(poses): root rotation about J0
        zju_world = smpl_zju @ rodrigues(Rh).T + Th
        out = zju_to_smpl_params(Rh[None], Th[None], poses[None], J0)
        ours = (X - J0) @ rodrigues(out["global_orient"][0]).T + J0 + out["transl"][0]
        np.testing.assert_allclose(ours, zju_world, atol=1e-5)
        np.testing.assert_allclose(out["body_pose"][0], poses[3:], atol=1e-7)
    # with J0 at the origin the two conventions coincide
    out = zju_to_smpl_params(Rh[None], Th[None], np.zeros((1, 72)), np.zeros(3))
    np.testing.assert_allclose(out["transl"][0], Th, atol=1e-6)


def j0_of(betas):
    return np.tile([0.0, -0.2, 0.02], (len(betas), 1)) + betas[:, :1] * np.array([0, 1.0, 0])


def test_zju_paper_split_camera_and_params(tmp_path):
    root = tmp_path / "CoreView_377"
    last_train, last_test = ZJU_SPLITS["377"]
    Ks, Rs, Ts = make_zju(root, last_test)
    for i in list(range(0, last_train, 4)) + list(range(last_train, last_test)):
        add_zju_frame(root, i, cams=[1])  # only the camera used
    ds = load_dataset(f"{root}?camera=1", body=j0_of)
    assert ds.kind == "zju" and ds.gender == "neutral"
    assert {s: ds.num_frames(s) for s in ds.splits} == {"train": 114, "test": 161}
    assert ds.splits["train"][:3] == [0, 4, 8] and ds.splits["test"][0] == 456
    f = ds.frame("train", 1)
    np.testing.assert_allclose(f.camera.viewmat[:3, 3], Ts[1][:, 0] / 1000, atol=1e-6)  # mm -> m
    np.testing.assert_allclose(f.camera.viewmat[:3, :3], Rs[1], atol=1e-6)
    np.testing.assert_allclose(f.camera.K, Ks[1], atol=1e-6)
    # conversion with the provider's J0 for these shapes (0.1 -> J0 = (0, -0.1, 0.02))
    J0 = np.array([0.0, -0.1, 0.02])
    Rh, Th = np.array([0.4, 0.2, 0.0]), np.array([0.0, 0.5, 4.0])
    X = RNG.normal(size=(20, 3))
    zju_world = X @ rodrigues(Rh).T + Th  # poses[:3] = 0: SMPL(poses) = X
    ours = (X - J0) @ rodrigues(f.global_orient).T + J0 + f.transl
    np.testing.assert_allclose(ours, zju_world, atol=1e-5)
    np.testing.assert_allclose(f.body_pose, 0.04, atol=1e-6)
    np.testing.assert_allclose(f.betas, 0.1, atol=1e-6)
    # masks: union of mask/ (left half) and mask_cihp/ (top half)
    expect = np.zeros((6, 8), np.float32)
    expect[:, :4] = 1
    expect[:3] = 1
    np.testing.assert_array_equal(f.mask, expect)
    only_cihp = load_dataset(f"zju:{root}?camera=1", body=j0_of, mask="cihp").frame("test", 0)
    np.testing.assert_array_equal(only_cihp.mask[:, 0], [1, 1, 1, 0, 0, 0])
    # novel views: the test frames seen by other cameras, each with its own camera
    for i in range(last_train, last_test):
        add_zju_frame(root, i, cams=[0])
    nv = load_dataset(f"zju:{root}?camera=1&views=0", body=j0_of)
    assert nv.num_frames("novel_view") == 161 and nv.splits["novel_view"][0] == 456
    g, t = nv.frame("novel_view", 3), nv.frame("test", 3)
    assert g.index == t.index == 459
    np.testing.assert_allclose(g.camera.viewmat[:3, 3], Ts[0][:, 0] / 1000, atol=1e-6)
    np.testing.assert_allclose(g.camera.K, Ks[0], atol=1e-6)
    np.testing.assert_allclose(g.transl, t.transl, atol=1e-7)


def test_zju_undistortion_moves_points_to_the_undistorted_projection(tmp_path):
    w, h = 48, 36
    D = np.array([-0.6, 0.1, 0.01, -0.005, 0.0])
    root = tmp_path / "CoreView_500"
    (K,), _, _ = make_zju(root, 1, w=w, h=h, D=D, n_cams=1)
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    # OpenCV's distortion by hand: the undistorted pixel (u, v) = (44, 33) is seen in the distorted
    # image at (ud, vd), about 4 px closer to the centre (barrel distortion)
    x, y = (44 - cx) / f, (33 - cy) / f
    r2 = x * x + y * y
    rad = 1 + D[0] * r2 + D[1] * r2**2
    ud = f * (x * rad + 2 * D[2] * x * y + D[3] * (r2 + 2 * x * x)) + cx
    vd = f * (y * rad + D[2] * (r2 + 2 * y * y) + 2 * D[3] * x * y) + cy
    assert 44 - ud > 3 and 33 - vd > 2
    rows, cols = undistort_maps(K, D, w, h)
    assert (cols[33, 44], rows[33, 44]) == (pytest.approx(ud, abs=1e-4), pytest.approx(vd, abs=1e-4))
    # a bright dot drawn in the distorted image where that point is seen lands at (44, 33) after loading
    ys, xs = np.mgrid[0:h, 0:w]
    dot = np.exp(-((xs - ud) ** 2 + (ys - vd) ** 2) / (2 * 1.0**2))
    img = np.repeat((dot * 255).round().astype(np.uint8)[..., None], 3, axis=2)
    add_zju_frame(root, 0, w=w, h=h, n_cams=1, image=img)
    with pytest.warns(UserWarning, match="no standard split"):
        ds = load_dataset(root, body=j0_of)
    got = ds.frame("train", 0).image[..., 0]
    assert np.unravel_index(np.argmax(got), got.shape) == (33, 44)
    raw = ds._read_pixels(ds._records["train"][0])[0][..., 0]  # undistorted at source size
    assert raw[33, 44] > 0.8 and got[int(round(vd)), int(round(ud))] < 0.2


def test_zju_bad_input(tmp_path):
    root = tmp_path / "CoreView_377"
    make_zju(root, 617)
    with pytest.raises(UserError, match=r"CoreView_377 has no mask folder"):
        load_dataset(root, body=j0_of)
    (root / "mask").mkdir()
    with pytest.raises(UserError, match=r"frame 0 has no image: .*Camera_B1/000000.jpg"):
        load_dataset(root, body=j0_of)
    for i in (0, 4, 8):  # frames are checked in order: the errors below come before frame 12
        add_zju_frame(root, i)
    (root / "mask" / "Camera_B1" / "000004.png").unlink()
    (root / "mask_cihp" / "Camera_B1" / "000004.png").unlink()
    with pytest.raises(UserError, match=r"frame 4 has no mask"):
        load_dataset(root, body=j0_of)
    with pytest.raises(UserError, match="has 2 cameras"):
        load_dataset(root, body=j0_of, camera=5)
    with pytest.raises(UserError, match="has 2 cameras .* view 2 asked"):
        load_dataset(f"{root}?views=0,2", body=j0_of)
    small = tmp_path / "my_subject"  # every frame present, one parameter file broken
    make_zju(small, 9)
    for i in (0, 4, 8):
        add_zju_frame(small, i)
    np.save(small / "new_params" / "8.npy", {"poses": np.zeros((1, 72)), "Rh": np.zeros((1, 3))},
            allow_pickle=True)
    with pytest.raises(UserError, match=r"new_params/8.npy is missing 'Th'"), pytest.warns(UserWarning):
        load_dataset(small, body=j0_of)
    annots = np.load(root / "annots.npy", allow_pickle=True).item()
    del annots["cams"]["T"]
    np.save(root / "annots.npy", annots, allow_pickle=True)
    with pytest.raises(UserError, match=r"annots.npy: cams is missing \['T'\]"):
        load_dataset(root, body=j0_of)


# --- rmavatar inspect ------------------------------------------------------------------------------

def test_inspect_all_kinds(tmp_path, capsys):
    import json

    from rmavatar.commands import main

    nat = tmp_path / "nat"
    _, _, _, params = make_native(nat, per_frame=False)
    ps = tmp_path / "female-4-casual"
    make_peoplesnapshot(ps, {"train": [0, 4], "val": [335], "test": [335, 339]})  # not the full table
    zju = tmp_path / "my_subject"
    make_zju(zju, 10)
    for i in (0, 4, 8):
        add_zju_frame(zju, i)

    out = tmp_path / "nat.json"
    assert main(["inspect", str(nat), "--json", str(out), "--size", "4"]) == 0
    s = json.loads(out.read_text())
    assert s["kind"] == "native" and s["image_size"] == [4, 3] and s["source_size"] == [8, 6]
    assert {k: v["frames"] for k, v in s["splits"].items()} == {"train": 3, "test": 2, "novel_pose": 1}
    assert s["camera"]["fx"] == 5.0 and s["camera"]["cx"] == 2.0 and s["camera"]["distinct_cameras"] == 1
    np.testing.assert_allclose(s["poses"]["train"]["transl"]["max"], params["transl"][[0, 2, 4]].max(0), atol=1e-4)
    assert "novel_pose" in capsys.readouterr().out

    # the standard female-4-casual split needs frames this fixture lacks: a clear error, exit code 2
    assert main(["inspect", str(ps)]) == 2
    assert "image_0008.png does not exist" in capsys.readouterr().err

    # ZJU needs a body for J0; the CLI's --body takes a spec, so check the summary through the API
    from rmavatar.data import load_dataset
    from rmavatar.data.summary import summarize

    with pytest.warns(UserWarning, match="no standard split"):
        s = summarize(load_dataset(f"zju:{zju}", body=j0_of))
    assert {k: v["frames"] for k, v in s["splits"].items()} == {"train": 3}
    assert s["camera"]["position"] == pytest.approx((-np.asarray([[0.0], [-0.2], [3.0]])[:, 0]).tolist())


def test_rest_pelvis_provider_uses_the_body_joints_and_smpl_betas():
    import torch

    from rmavatar.data.zju import rest_pelvis_provider

    class FakeBody(torch.nn.Module):
        """Rest pelvis moves with betas[0]; records what forward received."""

        def __init__(self, spec, num_betas):
            super().__init__()
            self.spec, self.num_betas, self.v_template = spec, num_betas, torch.zeros(4, 3)
            self.seen = None

        def forward(self, betas, global_orient, body_pose, transl):
            self.seen = (betas, global_orient, body_pose, transl)
            n = global_orient.shape[0]
            j = torch.zeros(n, 24, 3)
            j[:, 0] = torch.tensor([0.0, -0.2, 0.03])
            if betas is not None:
                j[:, 0, 1] += betas[:, 0]
            return type("Out", (), {"joints": j, "vertices": torch.zeros(n, 4, 3)})()

    betas = np.zeros((2, 10), np.float32)
    betas[1, 0] = 0.5
    smpl = FakeBody("smpl:/x", 300)
    np.testing.assert_allclose(rest_pelvis_provider(smpl)(betas), [[0, -0.2, 0.03], [0, 0.3, 0.03]], atol=1e-6)
    assert smpl.seen[0].shape == (2, 300) and float(smpl.seen[0][1, 0]) == 0.5
    assert all(float(t.abs().max()) == 0 for t in smpl.seen[1:])  # rest pose, no translation
    anny = FakeBody("anny:default", 0)
    np.testing.assert_allclose(rest_pelvis_provider(anny)(betas), [[0, -0.2, 0.03]] * 2, atol=1e-6)
    assert anny.seen[0] is None  # Anny's shape space is not SMPL's: its default shape


def test_mask_file_variants(tmp_path):
    from rmavatar.data.io import read_binary_mask, read_mask

    np.save(tmp_path / "b.npy", np.array([[True, False]]))
    np.save(tmp_path / "u01.npy", np.array([[1, 0]], np.uint8))
    np.save(tmp_path / "u255.npy", np.array([[255, 51]], np.uint8))
    np.save(tmp_path / "f.npy", np.array([[0.25, 1.0]], np.float32))
    np.save(tmp_path / "bad.npy", np.array([[1.5, 0.0]], np.float32))
    save_png(tmp_path / "grey.png", np.array([[255, 64]], np.uint8))
    rgba = np.zeros((1, 2, 4), np.uint8)
    rgba[..., :3] = 255
    rgba[0, 0, 3] = 255  # a cut-out: the alpha is the mask
    save_png(tmp_path / "cut.png", rgba)
    save_png(tmp_path / "label.png", np.array([[0, 1]], np.uint8))
    np.testing.assert_allclose(read_mask(tmp_path / "b.npy"), [[1, 0]])
    np.testing.assert_allclose(read_mask(tmp_path / "u01.npy"), [[1, 0]])
    np.testing.assert_allclose(read_mask(tmp_path / "u255.npy"), [[1, 0.2]])
    np.testing.assert_allclose(read_mask(tmp_path / "f.npy"), [[0.25, 1]])
    np.testing.assert_allclose(read_mask(tmp_path / "grey.png"), [[1, 64 / 255]], atol=1e-6)
    np.testing.assert_allclose(read_mask(tmp_path / "cut.png"), [[1, 0]])
    np.testing.assert_allclose(read_binary_mask(tmp_path / "label.png"), [[0, 1]])
    with pytest.raises(UserError, match=r"bad.npy: float masks must lie in \[0,1\]"):
        read_mask(tmp_path / "bad.npy")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(UserError, match=r"cannot read mask .*broken.png"):
        read_mask(tmp_path / "broken.png")


def test_zju_conversion_with_a_real_body_places_the_skinned_mesh(tmp_path):
    """End to end with LBS: ZJU's R(Rh) body(poses) + Th equals the body driven by the loaded params."""
    import torch

    from rmavatar.body import load_body_model

    body = load_body_model("anny")
    root = tmp_path / "my_subject"
    make_zju(root, 1, n_cams=1)
    add_zju_frame(root, 0, n_cams=1)
    poses = np.concatenate([[0.3, -0.5, 0.2], RNG.normal(size=69) * 0.25])
    Rh, Th = np.array([0.2, 1.9, -0.4]), np.array([0.3, 1.1, -0.5])
    np.save(root / "new_params" / "0.npy", {"poses": poses[None], "Rh": Rh[None], "Th": Th[None],
                                             "shapes": np.zeros((1, 10))}, allow_pickle=True)
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32))[None]  # noqa: E731
    with torch.no_grad():
        smpl_space = body(None, t(poses[:3]), t(poses[3:]), t(np.zeros(3))).vertices[0].double().numpy()
    zju_world = smpl_space @ rodrigues(Rh).T + Th
    with pytest.warns(UserWarning, match="no standard split"):
        f = load_dataset(root, body=body).frame("train", 0)
    with torch.no_grad():
        ours = body(None, t(f.global_orient), t(f.body_pose), t(f.transl)).vertices[0].double().numpy()
    np.testing.assert_allclose(ours, zju_world, atol=2e-5)


def test_inspect_overlay_projects_the_body_onto_its_silhouette(tmp_path):
    """A native dataset whose masks are the Anny body's projected triangles: the overlay's dots land
    inside the masks (poses, camera and the overlay's projection agree)."""
    import torch
    from PIL import ImageDraw

    from rmavatar.body import load_body_model
    from rmavatar.data.summary import overlay_sheet

    body = load_body_model("anny")
    w, h = 64, 96
    cam = Camera(np.array([[110.0, 0, w / 2], [0, 110.0, h / 2], [0, 0, 1]]), np.eye(4), w, h)
    go = np.array([[math.pi, 0, 0], [2.2, 0, 2.2]])  # upright in OpenCV axes; turned
    tr = np.array([[0, 0.1, 3.0], [0.1, 0.0, 3.2]])
    bp = np.zeros((2, 69))
    with torch.no_grad():
        V = body(None, torch.tensor(go, dtype=torch.float32), torch.tensor(bp, dtype=torch.float32),
                 torch.tensor(tr, dtype=torch.float32)).vertices.numpy()
    masks = []
    for k in range(2):
        uv = cam.project(V[k])
        m = Image.new("L", (w, h), 0)
        draw = ImageDraw.Draw(m)
        for face in body.faces.numpy()[::3]:
            draw.polygon([tuple(uv[j]) for j in face], fill=255)
        masks.append(np.asarray(m))
    out = tmp_path / "nat"
    write_native(out, {"name": "o", "splits": {"train": [0, 1]}}, cam,
                 {"betas": np.zeros(10), "global_orient": go, "body_pose": bp, "transl": tr},
                 [np.full((h, w, 3), 0.5)] * 2, masks, progress=False)
    sheet = overlay_sheet(load_dataset(out), body, per_split=2)
    assert sheet.shape == (h + 14, 2 * w, 3)
    for k in range(2):
        tile = sheet[14:, k * w:(k + 1) * w].astype(int)
        dots = (tile[..., 0] == 255) & (tile[..., 1] == 40)
        assert dots.sum() > 100
        assert (masks[k][dots] > 0).mean() > 0.97
        assert dots[masks[k] > 0].mean() > 0.5  # and they cover the silhouette


def test_export_native_roundtrip_from_peoplesnapshot(tmp_path):
    from rmavatar.data import export_native

    root = tmp_path / "someone"
    make_peoplesnapshot(root, {"train": [0, 2, 4], "val": [5], "test": [5, 6]}, mask_kind="png", total=7)
    (root / "splits.yaml").write_text("train: [0, 2, 4]\nval: [5]\ntest: [5, 6]\n")
    src = load_dataset(root, size=3)
    out = export_native(src, tmp_path / "native", progress=False)
    ds = load_dataset(out)
    assert ds.image_size == src.image_size == (3, 2)
    # frame 5 is in val and test with each split's own betas: two native frames, not one
    assert ds.splits == {"train": [0, 1, 2], "val": [3], "test": [4, 5]}
    for split in src.splits:
        for i in range(src.num_frames(split)):
            a, b = src.frame(split, i), ds.frame(split, i)
            np.testing.assert_allclose(b.image, a.image, atol=0.5 / 255 + 1e-6)
            np.testing.assert_allclose(b.mask, a.mask, atol=0.5 / 255 + 1e-6)
            np.testing.assert_allclose(b.camera.K, a.camera.K, atol=1e-6)
            for key in ("betas", "global_orient", "body_pose", "transl"):
                np.testing.assert_allclose(getattr(b, key), getattr(a, key), atol=1e-6)


# --- meta.yaml's schema (a file users write by hand) ---------------------------------------------------------
META_CASES = [  # (key, YAML value or None to delete it, text the UserError must hold after "meta.yaml: ")
    ("fps", "fast", "fps must be a number > 0 (frames per second) or null, got 'fast'"),
    ("fps", "-25", "fps must be a number > 0 (frames per second) or null, got -25"),
    ("fps", ".nan", "fps must be a number > 0"),
    ("fps", "true", "fps must be a number > 0 (frames per second) or null, got True"),
    ("width", "-8", "width must be an integer >= 1, got -8"),
    ("height", "'6'", "height must be an integer >= 1, got '6'"),
    ("height", "6.5", "height must be an integer >= 1, got 6.5"),
    ("num_frames", "0", "num_frames must be an integer >= 1, got 0"),
    ("splits", "{train: [0, 2, 2, 4]}", "split 'train' lists frame(s) [2] more than once"),
    ("splits", "{train: [0, two]}", "split 'train' must hold frame indices (integers), got 'two'"),
    ("splits", "{train: [0, 1.5]}", "split 'train' must hold frame indices (integers), got 1.5"),
    ("splits", "{train: [0, true]}", "split 'train' must hold frame indices (integers), got True"),
    ("splits", "{train: 3}", "split 'train' must be a list of frame indices, got 3"),
    ("splits", "[0, 1]", "'splits' must map split names to lists of frame indices"),
    ("name", "[a, b]", "name must be a string, got ['a', 'b']"),
    ("gender", "true", "gender must be one of ('male', 'female', 'neutral') or null, got True"),
    ("body", "5", "body must be a body spec (a string such as anny:female) or null, got 5"),
    ("poses", "[given]", "poses must be one of ('given', 'estimated'), got ['given']"),
    ("extra", "[1, 2]", "extra must be a mapping (free-form key: value lines) or null, got [1, 2]"),
    ("fsp", "25", "unknown key(s) fsp (known: format, version,"),
]


def _edit_meta(root, key, value):
    import yaml

    doc = yaml.safe_load((root / "meta.yaml").read_text())
    if value is None:
        doc.pop(key)
    else:
        doc[key] = yaml.safe_load(value)
    (root / "meta.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


@pytest.mark.parametrize("key, value, needle", META_CASES, ids=[f"{k}={v}" for k, v, _ in META_CASES])
def test_native_meta_schema_names_the_key_and_what_was_expected(tmp_path, key, value, needle):
    out = tmp_path / "nat"
    make_native(out)
    _edit_meta(out, key, value)
    with pytest.raises(UserError) as info:
        load_dataset(out)
    assert str(info.value) == f"{out / 'meta.yaml'}: {needle}" or str(info.value).startswith(
        f"{out / 'meta.yaml'}: {needle}"), str(info.value)


def test_native_meta_accepts_what_yaml_writes_for_numbers(tmp_path):
    out = tmp_path / "nat"
    make_native(out)
    _edit_meta(out, "fps", "3e1")  # PyYAML reads this as a string
    _edit_meta(out, "width", "8.0")
    _edit_meta(out, "extra", "null")
    ds = load_dataset(out)
    assert ds.fps == 30.0 and ds.source_size == (8, 6)
    _edit_meta(out, "fps", "null")
    _edit_meta(out, "poses", None)
    assert load_dataset(out).fps is None and not load_dataset(out).poses_estimated


def test_native_meta_file_not_utf8_or_not_yaml(tmp_path):
    out = tmp_path / "nat"
    make_native(out)
    text = (out / "meta.yaml").read_text()
    (out / "meta.yaml").write_text(text, encoding="utf-16")
    with pytest.raises(UserError, match=r"dataset file .*nat/meta.yaml is UTF-16 \(little-endian\) text, not UTF-8: "
                                        r"save it as UTF-8"):
        load_dataset(out)
    (out / "meta.yaml").write_text(text + "splits: {train: [0\n")
    with pytest.raises(UserError, match=r"dataset file .*nat/meta.yaml is not valid YAML: line \d+, column \d+"):
        load_dataset(out)
    (out / "meta.yaml").write_text(text + "name: again\n")
    with pytest.raises(UserError, match=r"meta.yaml is not valid YAML: line \d+, column 1: the key 'name' is given "
                                        r"twice \(first on line 3\)"):
        load_dataset(out)


def test_write_native_checks_the_meta_fields(tmp_path):
    _, _, cams, params = make_native(tmp_path / "nat")
    frames = ([np.zeros((6, 8, 3))] * 6, [np.zeros((6, 8))] * 6)
    for meta, needle in (({"fps": "fast"}, "fps must be a number > 0"), ({"name": None}, "name must be a string"),
                         ({"splits": {"train": [1, 1]}}, r"lists frame\(s\) \[1\] more than once"),
                         ({"extra": [1]}, "extra must be a mapping")):
        with pytest.raises(UserError, match=f"write_native: .*{needle}"):
            write_native(tmp_path / "out", {"name": "x", "splits": {"train": [0]}, **meta}, cams, params, *frames,
                         progress=False)
    assert not (tmp_path / "out").exists()


def test_peoplesnapshot_splits_file_types(tmp_path):
    root = tmp_path / "female-x"
    make_peoplesnapshot(root, {"train": [0, 2, 4], "test": [1, 3]}, total=5)
    for text, needle in (("train: {start: zero, end: 4}\n", r"train.start: expected a frame number \(an integer >= 0\), "
                                                            r"got 'zero'"),
                         ("train: {start: 0, end: 4, step: 0}\n", "train.step: expected an integer >= 1, got 0"),
                         ("train: {start: 0, end: 4, stride: 2}\n", "split 'train' has unknown key"),
                         ("train: [0, -1]\n", "split 'train': expected a frame number .* got -1"),
                         ("- 1\n", "must map split names")):
        (root / "splits.yaml").write_text(text)
        with pytest.raises(UserError, match=f"splits.yaml: {needle}" if "must map" not in needle else needle):
            load_dataset(root)
    (root / "splits.yaml").write_text("train: [0, 2]\n", encoding="utf-16")
    with pytest.raises(UserError, match=r"splits file .*splits.yaml is UTF-16"):
        load_dataset(root)


def test_native_same_instant_roundtrip_and_checks(tmp_path):
    """meta.yaml's same_instant (a second camera's split: for each of its frames, the main camera's frame of
    the same instant) is written, read into Dataset.same_instant, and refused when it names an unknown
    split, has the wrong length or points outside the frames."""
    out = tmp_path / "nat"
    _, _, cams, params = make_native(tmp_path / "first")
    frames = ([np.zeros((6, 8, 3))] * 6, [np.zeros((6, 8))] * 6)
    meta = NativeMeta(name="x", splits={"train": [0, 1, 2], "novel_view": [3, 4, 5]},
                      same_instant={"novel_view": [0, 1, 2]})
    write_native(out, meta, cams, params, *frames, progress=False)
    assert load_dataset(out).same_instant == {"novel_view": [0, 1, 2]}
    assert load_dataset(tmp_path / "first").same_instant == {}
    for value, needle in (("{test: [0, 1, 2]}", "'same_instant' names split 'test', which the dataset does not have"),
                          ("{novel_view: [0, 1]}", "same_instant 'novel_view' must list one frame index per frame"),
                          ("{novel_view: [0, 1, 9]}", r"same_instant 'novel_view' refers to frames \[9\] outside 0..5"),
                          ("[0, 1, 2]", "'same_instant' must map split names to lists of frame indices")):
        _edit_meta(out, "same_instant", value)
        with pytest.raises(UserError, match=needle):
            load_dataset(out)
