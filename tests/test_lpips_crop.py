"""LPIPS on a fixed-size window around the person (``loss.lpips_region: person``): the windows the frame
cache makes from the masks, the loss on the crop against LPIPS by hand on the slice, the cached target
features of the crop, the setting and the migration that keeps older runs on the whole frame."""

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from rmavatar.avatar.run import CHECKPOINT_VERSION, MIGRATIONS, migrate_config
from rmavatar.evaluate.lpips_net import load_lpips
from rmavatar.train.config import LossConfig, load_config, save_config, to_dict
from rmavatar.train.frames import (
    WINDOW_ALIGN,
    WINDOW_MIN,
    WINDOW_MULTIPLE,
    WINDOW_PAD_MIN,
    FrameCache,
    lpips_window_size,
    mask_box,
    place_window,
)
from rmavatar.train.losses import crop, lpips_units, total_loss
from rmavatar.utils import UserError

from devices import DEVICES

H, W = 96, 80  # frames of the fake dataset (not square: rows and columns must not be mixed up)
# (top, bottom, left, right) of each frame's person, bottom and right exclusive; None: an empty mask
BOXES = [(20, 60, 30, 50), (0, 30, 60, 80), (50, 96, 0, 12), None, (10, 86, 25, 45)]


def _mask(box, height=H, width=W, soft=True):
    m = np.zeros((height, width), np.float32)
    if box is not None:
        top, bottom, left, right = box
        m[top:bottom, left:right] = 1.0
        if soft:  # a soft edge below the threshold and faint noise: not part of the box
            if top > 0:
                m[top - 1, left:right] = 0.3
            m[(top + bottom) // 2, :] = np.maximum(m[(top + bottom) // 2, :], 0.1)
    return m


class _Dataset:
    """What FrameCache reads of a dataset: cameras, frames (image, mask)."""

    def __init__(self, boxes, height=H, width=W):
        gen = np.random.default_rng(0)
        self.boxes, self.height, self.width = boxes, height, width
        self.images = [gen.random((height, width, 3), dtype=np.float32) for _ in boxes]

    def num_frames(self, split):
        return len(self.boxes)

    def camera(self, split, i):
        return SimpleNamespace(viewmat=np.eye(4), K=np.eye(3), width=self.width, height=self.height)

    def frame(self, split, i):
        return SimpleNamespace(image=self.images[i], mask=_mask(self.boxes[i], self.height, self.width))


class _Avatar:
    """What FrameCache.fill reads of an avatar: the face count and the face tables."""

    binding_faces = torch.zeros(1)

    @staticmethod
    def face_table(vertices):
        return torch.zeros(1, 38)


def _cache(boxes=BOXES, region="person", budget=2**30, background="white", height=H, width=W, device="cpu"):
    frames = FrameCache(_Dataset(boxes, height, width), "train", None, torch.device(device))
    frames.vertices = torch.zeros(len(boxes), 1, 3, device=device)  # what hold() leaves
    frames.fill(_Avatar(), background, True, torch.Generator().manual_seed(0), budget, lpips_region=region)
    return frames


# ---------------------------------------------------------------------------------------------- windows
def test_mask_box_is_the_half_covered_pixels():
    assert mask_box(_mask((20, 60, 30, 50))) == (20, 60, 30, 50)  # the 0.3 edge and 0.1 noise left out
    assert mask_box(_mask((0, 30, 60, 80))) == (0, 30, 60, 80)
    assert mask_box(_mask(None)) is None
    assert mask_box(np.full((8, 8), 0.49, np.float32)) is None


def test_window_size_is_the_largest_padded_box_rounded():
    # heights 40, 30, 46, 76 (+ 2 x max(8% rounded up, 16)): 72, 62, 78, 76 + 2*7 -> 108 > 96: the image's
    # 96; widths 20, 20, 12, 20: + 32 -> 52 -> 56, but at least 64
    assert lpips_window_size(BOXES, H, W) == (96, 64)
    assert lpips_window_size([(0, 10, 0, 10)], 512, 512) == (WINDOW_MIN, WINDOW_MIN)
    # 8% wins over 16 px from a 200 px side: 200 + 2 x 16 = 232 -> 232; 300 + 2 x 24 = 348 -> 352
    assert lpips_window_size([(0, 200, 0, 300), None], 512, 512) == (232, 352)
    assert lpips_window_size([None, None], 512, 256) == (WINDOW_MIN, WINDOW_MIN)  # no person: a centred 64
    assert lpips_window_size([None], 40, 48) == (40, 48)  # an image smaller than the minimum: all of it
    assert lpips_window_size([(0, 40, 0, 48)], 40, 48) == (40, 48)
    h, w = lpips_window_size([(3, 117, 5, 101)], 300, 300)
    assert h % WINDOW_MULTIPLE == 0 and w % WINDOW_MULTIPLE == 0 and h >= 114 + 2 * WINDOW_PAD_MIN


def test_a_window_covers_its_box_inside_the_image():
    size = lpips_window_size(BOXES, H, W)
    for box in BOXES:
        r0, c0 = place_window(box, size, H, W)
        assert 0 <= r0 <= H - size[0] and 0 <= c0 <= W - size[1]
        if box is None:  # an empty mask: around the centre
            assert r0 <= H // 2 < r0 + size[0] and c0 <= W // 2 < c0 + size[1]
            assert abs(r0 - (H - size[0]) // 2) < WINDOW_ALIGN and abs(c0 - (W - size[1]) // 2) < WINDOW_ALIGN
        else:
            top, bottom, left, right = box
            assert r0 <= top and bottom <= r0 + size[0] and c0 <= left and right <= c0 + size[1], box
    assert place_window((0, 30, 60, 80), (64, 64), H, W) == (0, 16)  # at the corner: shifted inside
    # centred: 13, 13; the nearest start on the 16-pixel grid that holds the box
    assert place_window((40, 50, 40, 50), (64, 64), 128, 128) == (16, 16)
    assert place_window((40, 50, 4, 14), (64, 64), 128, 128) == (16, 0)
    # at the bottom edge no start on the grid holds the box (32 ends above it, 48 below the image): 36
    assert place_window((60, 100, 0, 10), (64, 64), 100, 100) == (36, 0)
    # a box with the padding lpips_window_size gives it (16 px a side) starts on the grid, but where
    # the image's edge holds it
    gen = np.random.default_rng(1)
    for _ in range(200):
        top, left = gen.integers(0, 220, 2)
        box = (int(top), int(top + gen.integers(1, 33)), int(left), int(left + gen.integers(1, 33)))
        r0, c0 = place_window(box, (64, 72), 256, 260)
        assert r0 <= box[0] and box[1] <= r0 + 64 <= 256 and c0 <= box[2] and box[3] <= c0 + 72 <= 260
        assert r0 % WINDOW_ALIGN == 0 or r0 + 64 == 256, (box, r0)
        assert c0 % WINDOW_ALIGN == 0 or c0 + 72 == 260, (box, c0)


def test_the_frame_cache_keeps_one_window_per_frame():
    frames = _cache()
    shapes = {tuple(t.shape) for i in range(len(BOXES)) for t in frames.lpips_window(i)}
    assert shapes == {(96,), (64,)}  # one size for every frame, empty mask included
    for i, box in enumerate(BOXES):
        rows, cols = frames.lpips_window(i)
        assert rows.dtype == cols.dtype == torch.long
        r0, c0 = int(rows[0]), int(cols[0])
        assert (r0, c0) == place_window(box, (96, 64), H, W)
        assert torch.equal(rows, torch.arange(r0, r0 + 96)) and torch.equal(cols, torch.arange(c0, c0 + 64))
        image = torch.rand(H, W, 3)
        assert torch.equal(crop(image, frames.lpips_window(i)), image[r0:r0 + 96, c0:c0 + 64])
    # "frame": no window, and the cached features are the whole targets'
    whole = _cache(region="frame")
    assert whole.lpips_window(0) is None and whole.window_rows is None
    bg = whole._cached_bg
    assert whole.target_units[0][0].shape[2:] != frames.target_units[0][0].shape[2:]
    for a, b in zip(whole.lpips_units(0, bg), lpips_units(whole.target(0, bg))):
        assert torch.equal(a, b)


@pytest.mark.parametrize("background", ["white", "random"])
def test_windows_do_not_depend_on_the_cache_budget(background):
    """The window comes from the masks whatever is cached (a zero budget, a random background)."""
    kept, bare = _cache(background=background), _cache(budget=0, background=background)
    assert bare.targets is None and bare.target_units is None
    for i in range(len(BOXES)):
        for a, b in zip(kept.lpips_window(i), bare.lpips_window(i)):
            assert torch.equal(a, b)


def test_cached_target_features_are_of_the_crop():
    frames = _cache()
    bg = frames._cached_bg
    for i in range(len(BOXES)):
        target = frames.target(i, bg)
        want = lpips_units(crop(target, frames.lpips_window(i)))
        assert len(frames.lpips_units(i, bg)) == len(want)
        for a, b in zip(frames.lpips_units(i, bg), want):
            assert torch.equal(a, b)


# ---------------------------------------------------------------------------------------------- the loss
def _images(h=H, w=W, seed=0):
    """A render (a little outside [0, 1], so the clamp is exercised) and a target, float64."""
    gen = torch.Generator().manual_seed(seed)
    target = torch.rand(h, w, 3, generator=gen, dtype=torch.float64)
    render = (target + 0.3 * torch.randn(h, w, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    return render, target


def _window(r0, c0, h, w, device="cpu"):
    return (torch.arange(r0, r0 + h, device=device), torch.arange(c0, c0 + w, device=device))


LPIPS_ONLY = LossConfig(rgb=0.0, ssim=0.0, lpips=1.0, pos=0.0, scaling=0.0, offset=0.0)


def _lpips_by_hand(x, y, frame):
    """LPIPS v0.1 of images x (clamped to [0, 1]) and y [h,w,3] float64 under plain autograd, from the
    network's five ReLU outputs: sum over layers of sum_c w_c sum over pixels of (u_x - u_y)^2 with
    u = f / (|f| + 1e-10), divided by the layer's pixel count in an image of size ``frame``."""
    net = load_lpips("cpu", torch.float64)
    fx, fy = (net.features(t.permute(2, 0, 1)[None]) for t in (x.clamp(0.0, 1.0), y))
    counts = [t.shape[2] * t.shape[3] for t in net.features(torch.zeros(1, 3, *frame, dtype=torch.float64))]
    total = 0.0
    for head, a, b, n in zip(net.heads, fx, fy, counts):
        ua, ub = (f / (torch.linalg.vector_norm(f, dim=1, keepdim=True) + 1e-10) for f in (a, b))
        total = total + (head.weight * (ua - ub).square()).sum() / n
    return total


def test_the_reference_is_lpips():
    from rmavatar.evaluate import lpips

    render, target = _images(64, 48)
    torch.testing.assert_close(_lpips_by_hand(render, target, (64, 48)),
                               lpips(render.clamp(0.0, 1.0), target, check_range=False), rtol=1e-12, atol=0)


@pytest.mark.parametrize("corner", [(10, 7), (0, 0), (32, 16)])  # inside, at the top-left, at the bottom-right
def test_loss_on_the_window_is_lpips_of_the_slice_by_hand(corner):
    """Value and gradient (float64) of the LPIPS term with a window against LPIPS by hand (plain
    autograd) of ``render[r0:r1, c0:c1]``, each layer averaged over the whole frame's pixel count: the
    pixels outside the window get exactly zero."""
    r0, c0 = corner
    h, w = 64, 64
    render, target = _images()
    loss, parts = total_loss(render, target, None, LPIPS_ONLY, lpips_window=_window(r0, c0, h, w))
    plain = _lpips_by_hand(render[r0:r0 + h, c0:c0 + w], target[r0:r0 + h, c0:c0 + w], (H, W))
    torch.testing.assert_close(loss, plain, rtol=1e-12, atol=0)
    torch.testing.assert_close(parts["lpips"], plain.detach(), rtol=1e-12, atol=0)
    (ours,) = torch.autograd.grad(loss, render)
    (want,) = torch.autograd.grad(plain, render)
    torch.testing.assert_close(ours, want, rtol=1e-10, atol=1e-12 * float(want.abs().max()))
    outside = torch.ones(H, W, dtype=torch.bool)
    outside[r0:r0 + h, c0:c0 + w] = False
    assert torch.all(ours[outside] == 0) and ours[~outside].abs().max() > 0
    whole, _ = total_loss(render, target, None, LPIPS_ONLY)  # no window: the whole frame, another number
    assert abs(float(whole.detach()) - float(loss.detach())) > 1e-6


def test_the_other_terms_still_see_the_whole_frame():
    """With the paper's weights and a window, L1 and SSIM are the whole frame's and LPIPS the window's."""
    from rmavatar.evaluate import ssim

    render, target = _images(seed=1)
    cfg = LossConfig()
    window = _window(8, 4, 64, 64)
    loss, _ = total_loss(render, target, None, cfg, lpips_window=window)
    plain = (cfg.rgb * (render - target).abs().mean() + cfg.ssim * (1.0 - ssim(render, target, check_range=False))
             + cfg.lpips * _lpips_by_hand(render[8:72, 4:68], target[8:72, 4:68], (H, W)))
    torch.testing.assert_close(loss, plain, rtol=1e-12, atol=0)
    for a, b in zip(torch.autograd.grad(loss, render), torch.autograd.grad(plain, render)):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12 * float(b.abs().max()))


def test_cached_units_with_the_window_equal_the_uncached_path():
    """total_loss from lpips_units of the cropped target (what training keeps per frame) against the
    target cropped at every step (float64): the same value and gradient; full-frame units with a
    window are refused (they are of another image)."""
    render, target = _images(seed=2)
    window = _window(20, 9, 72, 64)
    units = lpips_units(target, window)
    cached, _ = total_loss(render, target, None, LPIPS_ONLY, lpips_units=units, lpips_window=window)
    fresh, _ = total_loss(render, target, None, LPIPS_ONLY, lpips_window=window)
    torch.testing.assert_close(cached, fresh, rtol=1e-12, atol=0)
    (a,) = torch.autograd.grad(cached, render)
    (b,) = torch.autograd.grad(fresh, render)
    torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12 * float(b.abs().max()))
    with pytest.raises(ValueError, match="y_units"):
        total_loss(render, target, None, LPIPS_ONLY, lpips_units=lpips_units(target), lpips_window=window)


def test_a_custom_lpips_sees_both_crops_as_a_share_of_the_frame():
    render, target = _images(seed=3)
    seen = []
    fn = lambda a, b: seen.append((a.shape, b.shape)) or torch.tensor(0.5, dtype=a.dtype)  # noqa: E731
    loss, _ = total_loss(render, target, None, LPIPS_ONLY, lpips_fn=fn, lpips_window=_window(0, 0, 40, 48))
    assert seen == [((40, 48, 3), (40, 48, 3))]
    assert float(loss) == pytest.approx(0.5 * 40 * 48 / (H * W), rel=1e-12)


def test_the_window_keeps_the_whole_frames_meaning():
    """A person on a white background, the render wrong only on the person: LPIPS of the window (the
    run's window, on the 16-pixel grid) is near the whole frame's, in value and in gradient on the
    person (not equal: the deeper layers' receptive fields reach past the window's edges, into the
    background), where the window's own average would weigh it about frame / window times as much."""
    h_img = w_img = 160
    box = (16, 136, 60, 100)
    gen = torch.Generator().manual_seed(4)
    target = torch.ones(h_img, w_img, 3, dtype=torch.float64)
    person = (slice(box[0], box[1]), slice(box[2], box[3]))
    target[person] = torch.rand(box[1] - box[0], box[3] - box[2], 3, generator=gen, dtype=torch.float64)
    render = target.clone()
    render[person] += 0.2 * torch.randn(target[person].shape, generator=gen, dtype=torch.float64)
    render.requires_grad_(True)
    size = lpips_window_size([box], h_img, w_img)
    r0, c0 = place_window(box, size, h_img, w_img)
    assert r0 % WINDOW_ALIGN == 0 and c0 % WINDOW_ALIGN == 0 and size[0] * size[1] < 0.5 * h_img * w_img
    whole, _ = total_loss(render, target, None, LPIPS_ONLY)
    part, _ = total_loss(render, target, None, LPIPS_ONLY, lpips_window=_window(r0, c0, *size))
    own = _lpips_by_hand(render[r0:r0 + size[0], c0:c0 + size[1]], target[r0:r0 + size[0], c0:c0 + size[1]], size)
    assert 0.65 < float(part.detach() / whole.detach()) < 1.1 and float(own.detach() / whole.detach()) > 1.8
    (g_whole,) = torch.autograd.grad(whole, render)
    (g_part,) = torch.autograd.grad(part, render)
    assert float((g_part - g_whole)[person].norm() / g_whole[person].norm()) < 0.7


@pytest.mark.parametrize("device", DEVICES)
def test_a_step_with_the_window_reads_nothing_back(device):
    """Cropping and the loss with a window make no host synchronisation (on CUDA: sync debug mode
    raises on one), and the loss's shapes are the window's whatever frame it is."""
    frames = _cache(device=device)
    bg = frames._cached_bg
    render = torch.rand(H, W, 3, device=device, requires_grad=True)

    def steps():
        for i in range(len(BOXES)):
            loss, _ = total_loss(render, frames.target(i, bg), None, LossConfig(),
                                 lpips_units=frames.lpips_units(i, bg), lpips_window=frames.lpips_window(i))
            loss.backward()

    steps()  # the first steps upload the loss's constants once (cached per device): the steady state is checked
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
    try:
        steps()
    finally:
        if device == "cuda":
            torch.cuda.set_sync_debug_mode(0)
    assert render.grad is not None and torch.isfinite(render.grad).all()


# ---------------------------------------------------------------------------------------------- the setting
def test_lpips_region_is_validated():
    assert LossConfig().lpips_region == "frame"  # the default: no quality lost (docs/train.md)
    assert LossConfig(lpips_region="frame").validate().lpips_region == "frame"
    with pytest.raises(UserError, match="loss.lpips_region"):
        LossConfig(lpips_region="box").validate()


def test_lpips_region_in_a_config_file(tmp_path):
    (tmp_path / "frame.yaml").write_text("loss:\n  lpips_region: frame\n")
    assert load_config(tmp_path / "frame.yaml").loss.lpips_region == "frame"
    (tmp_path / "bad.yaml").write_text("loss:\n  lpips_region: crop\n")
    with pytest.raises(UserError, match="loss.lpips_region"):
        load_config(tmp_path / "bad.yaml")


def test_older_runs_keep_lpips_on_the_whole_frame(tmp_path):
    """Version 6 added loss.lpips_region: a run's own config of an older layout (as_trained; a
    checkpoint's always) reads as "frame", how it was trained; a hand-written older file takes today's
    default; a config written now keeps its value."""
    assert CHECKPOINT_VERSION == 9
    v5 = {"loss": {"lpips": 0.05}, "optim": {"iters": 10}}
    assert migrate_config(v5, 5, as_trained=True)["loss"] == {"lpips_region": "frame", "lpips": 0.05}
    assert migrate_config(v5, 5, as_trained=False) == v5
    assert migrate_config({"optim": {"iters": 10}}, 5, as_trained=True)["loss"] == {"lpips_region": "frame"}
    assert migrate_config({}, None, as_trained=True)["loss"]["lpips_region"] == "frame"  # unstamped: v4
    assert migrate_config({}, None, as_trained=False) == {}  # unstamped, hand-written: today's
    now = {"loss": {"lpips_region": "person"}}
    assert migrate_config(now, CHECKPOINT_VERSION, as_trained=True) == now
    assert migrate_config(now, 6, as_trained=True)["loss"] == now["loss"]
    payload = {"version": 5, "config": v5, "iteration": 3}
    migrated = MIGRATIONS[5](payload)
    assert migrated["config"]["loss"]["lpips_region"] == "frame" and migrated["iteration"] == 3
    assert "lpips_region" not in payload["config"]["loss"]  # the payload read is not changed

    (tmp_path / "run_v5.yaml").write_text("version: 5\nloss:\n  lpips: 0.05\n")
    assert load_config(tmp_path / "run_v5.yaml", as_trained=True).loss.lpips_region == "frame"
    assert load_config(tmp_path / "run_v5.yaml").loss.lpips_region == LossConfig().lpips_region  # today's
    cfg = load_config(tmp_path / "run_v5.yaml", as_trained=True)
    save_config(cfg, tmp_path / "again.yaml")
    assert (tmp_path / "again.yaml").read_text().startswith(f"version: {CHECKPOINT_VERSION}\n")
    again = load_config(tmp_path / "again.yaml", as_trained=True)
    assert again.loss.lpips_region == "frame" and to_dict(again) == to_dict(cfg)
    (tmp_path / "bad.yaml").write_text("version: 5\nloss: 3\n")  # not a section: refused, not replaced
    with pytest.raises(UserError, match="loss"):
        load_config(tmp_path / "bad.yaml", as_trained=True)
