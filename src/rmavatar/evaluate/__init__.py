"""Evaluation: image metrics (PSNR, SSIM, LPIPS) usable as losses, and the ``rmavatar eval`` protocol."""

from rmavatar.evaluate.metrics import lpips, psnr, ssim

__all__ = ["lpips", "psnr", "ssim"]
