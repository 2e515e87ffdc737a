"""PSNR and SSIM against analytic values and scikit-image; input checking shared by all metrics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from rmavatar.evaluate import lpips, psnr, ssim
from rmavatar.utils import UserError


def skimage_ssim(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1
    )


def noisy_pair(shape, sigma, seed):
    rng = np.random.default_rng(seed)
    a = rng.random(shape)
    return a, np.clip(a + sigma * rng.standard_normal(shape), 0, 1)


def test_identical_images():
    img = np.random.default_rng(0).random((40, 36, 3))
    assert psnr(img, img) == math.inf
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    assert lpips(img, img) == 0.0
    t = torch.from_numpy(img).float()
    assert torch.isinf(psnr(t, t)) and float(ssim(t, t)) == pytest.approx(1.0, abs=1e-6)


def test_psnr_analytic():
    # +-0.1 on a mid-grey image: MSE is exactly 0.01, so PSNR is exactly 20 dB.
    a = np.full((16, 16, 3), 0.5)
    signs = np.where((np.indices((16, 16, 3)).sum(0) % 2) == 0, 1.0, -1.0)
    assert psnr(a, a + 0.1 * signs) == pytest.approx(20.0, abs=1e-9)
    # Gaussian noise of sigma 0.05 (no clipping needed around 0.5): 20 log10(1/RMSE) of the sample,
    # and close to the expected 20 log10(1/0.05) = 26.02 dB.
    noise = 0.05 * np.random.default_rng(1).standard_normal((64, 64, 3))
    value = psnr(a.repeat(4, 0).repeat(4, 1), a.repeat(4, 0).repeat(4, 1) + noise)
    assert value == pytest.approx(20 * math.log10(1 / math.sqrt(np.mean(noise**2))), abs=1e-9)
    assert value == pytest.approx(26.0206, abs=0.05)


def test_psnr_batched_is_per_image():
    a, b = noisy_pair((3, 20, 24, 3), 0.1, 2)
    values = psnr(a, b)
    assert isinstance(values, np.ndarray) and values.shape == (3,)
    np.testing.assert_allclose(values, [psnr(a[i], b[i]) for i in range(3)], rtol=1e-12)
    tv = psnr(torch.from_numpy(a), torch.from_numpy(b))
    assert torch.is_tensor(tv) and tv.shape == (3,)


@pytest.mark.parametrize("shape,sigma", [((32, 32, 3), 0.05), ((40, 53, 3), 0.3), ((11, 17, 3), 0.2)])
def test_ssim_matches_scikit_image(shape, sigma):
    a, b = noisy_pair(shape, sigma, 3)
    expected = skimage_ssim(a, b)
    assert ssim(a, b) == pytest.approx(expected, abs=1e-4)
    # float32 torch as a training loop would pass it.
    got = ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    assert got.dtype == torch.float32 and float(got) == pytest.approx(expected, abs=1e-4)
    # Independent uniform images (SSIM near 0) too.
    c = np.random.default_rng(4).random(shape)
    assert ssim(a, c) == pytest.approx(skimage_ssim(a, c), abs=1e-4)


def test_ssim_batched_matches_scikit_image():
    a, b = noisy_pair((4, 30, 26, 3), 0.15, 5)
    values = ssim(a, b)
    assert values.shape == (4,)
    np.testing.assert_allclose(values, [skimage_ssim(a[i], b[i]) for i in range(4)], atol=1e-4)
    tv = ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    np.testing.assert_allclose(tv.numpy(), values, atol=1e-4)


def test_ssim_on_smooth_images_matches_scikit_image():
    # Smooth content exercises the mean/variance terms differently from white noise.
    y, x = np.mgrid[0:48, 0:48] / 48.0
    a = np.stack([np.sin(6 * x) * 0.4 + 0.5, x * y, np.cos(4 * y) * 0.3 + 0.5], -1)
    b = np.clip(a * 0.9 + 0.05 + 0.02 * np.random.default_rng(6).standard_normal(a.shape), 0, 1)
    assert ssim(a, b) == pytest.approx(skimage_ssim(a, b), abs=1e-4)


def test_gradients_flow():
    a, b = noisy_pair((32, 32, 3), 0.1, 7)
    x = torch.from_numpy(b).float().requires_grad_(True)
    target = torch.from_numpy(a).float()
    for metric in (psnr, ssim, lpips):
        x.grad = None
        metric(x, target).backward()
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0, metric.__name__
    # Gradients agree with finite differences (float64, a small image keeps gradcheck quick).
    xs = torch.from_numpy(b[:12, :13]).requires_grad_(True)
    ts = torch.from_numpy(a[:12, :13])
    assert torch.autograd.gradcheck(lambda v: ssim(v, ts), (xs,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda v: psnr(v, ts), (xs,), fast_mode=True)


def autograd_ssim(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """SSIM written directly from its definition (five filtered moment maps), differentiated by autograd."""
    from rmavatar.evaluate.metrics import gaussian_window_1d

    x, y = a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2)
    maps = torch.cat([x, y, x * x, y * y, x * y], 1)
    g = gaussian_window_1d(dtype=a.dtype)
    n = maps.shape[1]
    filt = torch.nn.functional.conv2d(maps, g.view(1, 1, -1, 1).expand(n, 1, -1, 1), groups=n)
    filt = torch.nn.functional.conv2d(filt, g.view(1, 1, 1, -1).expand(n, 1, 1, -1), groups=n)
    mx, my, exx, eyy, exy = filt.chunk(5, 1)
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * (exy - mx * my) + c2)
         / ((mx * mx + my * my + c1) * (exx - mx * mx + eyy - my * my + c2)))
    return s.mean(dim=(1, 2, 3))


def test_ssim_value_and_gradient_match_autograd_of_the_definition():
    # The written-out backward against autograd through the textbook formula, float64; a batch with
    # noise, a flat patch (variances 0) and values outside [0, 1] (unclamped renders).
    a, b = noisy_pair((2, 23, 19, 3), 0.2, 10)
    a[1, :12, :12] = 0.3
    b[1, :12, :12] = 0.3
    b[0, 5:9] += 0.4
    for with_y_grad in (False, True):
        x = torch.from_numpy(b).requires_grad_(True)
        y = torch.from_numpy(a).requires_grad_(with_y_grad)
        w = torch.tensor([0.7, -1.3], dtype=torch.float64)
        got = ssim(x, y, check_range=False)
        (got @ w).backward()
        x2, y2 = x.detach().clone().requires_grad_(True), y.detach().clone().requires_grad_(with_y_grad)
        want = autograd_ssim(x2, y2)
        (want @ w).backward()
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
        torch.testing.assert_close(x.grad, x2.grad, rtol=0, atol=1e-10)
        if with_y_grad:
            torch.testing.assert_close(y.grad, y2.grad, rtol=0, atol=1e-10)
            assert y.grad.abs().sum() > 0
    # Finite differences through the target too (the image gradient is checked in test_gradients_flow).
    xs = torch.from_numpy(b[0, :12, :13]).requires_grad_(True)
    ys = torch.from_numpy(a[0, :12, :13]).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda u, v: ssim(u, v, check_range=False), (xs, ys))


def test_loss_use_moves_towards_target():
    # A few gradient steps on 1 - ssim + lpips raise SSIM: the losses work as training losses.
    a, b = noisy_pair((32, 32, 3), 0.2, 8)
    target = torch.from_numpy(a).float()
    x = torch.from_numpy(b).float().requires_grad_(True)
    opt = torch.optim.Adam([x], lr=0.01)
    start = float(ssim(x.detach(), target))
    for _ in range(20):
        opt.zero_grad()
        loss = 1 - ssim(x, target, check_range=False) + lpips(x, target, check_range=False)
        loss.backward()
        opt.step()
    assert float(ssim(x.detach().clamp(0, 1), target)) > start + 0.1


def test_numpy_returns_float_and_torch_returns_tensor():
    a, b = noisy_pair((32, 32, 3), 0.1, 9)
    for metric in (psnr, ssim, lpips):
        assert type(metric(a, b)) is float
        out = metric(torch.from_numpy(a).float(), b)  # mixed input follows the tensor
        assert torch.is_tensor(out) and out.ndim == 0


@pytest.mark.parametrize("metric", [psnr, ssim, lpips])
def test_bad_input_is_a_clear_error(metric):
    good = np.zeros((32, 32, 3), np.float32)
    with pytest.raises(UserError, match="same shape"):
        metric(good, np.zeros((32, 30, 3), np.float32))
    with pytest.raises(UserError, match=r"\[H,W,3\]"):
        metric(np.zeros((3, 32, 32), np.float32), np.zeros((3, 32, 32), np.float32))
    with pytest.raises(UserError, match="divide uint8 images by 255"):
        metric(good.astype(np.uint8), good.astype(np.uint8))
    with pytest.raises(UserError, match=r"values in \[0, 1\]"):
        metric(good + 255, good)
    with pytest.raises(UserError, match=r"argument b must have values in \[0, 1\]"):
        metric(good, good - 1)
    nan = good.copy()
    nan[3, 4, 1] = np.nan
    with pytest.raises(UserError, match=r"values in \[0, 1\]"):
        metric(nan, good)
    with pytest.raises(UserError, match="torch tensor or numpy array"):
        metric(good.tolist(), good)
    # Unclamped renders are accepted when asked for.
    metric(torch.from_numpy(good + 1.5), torch.from_numpy(good), check_range=False)


def test_ssim_too_small_is_a_clear_error():
    with pytest.raises(UserError, match="at least 11x11"):
        ssim(np.zeros((10, 40, 3)), np.zeros((10, 40, 3)))
