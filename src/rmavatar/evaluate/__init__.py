"""Evaluation: image metrics (PSNR, SSIM, LPIPS) usable as losses, and ``evaluate_run`` behind ``rmavatar eval``."""

from rmavatar.evaluate.metrics import lpips, psnr, ssim
from rmavatar.evaluate.run import evaluate_run

__all__ = ["evaluate_run", "lpips", "psnr", "ssim"]
