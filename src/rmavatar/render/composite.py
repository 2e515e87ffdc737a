"""Compositing an image over a background: how a frame's photo and mask become the target a render is
compared with (training, evaluation and pose fitting alike)."""

from __future__ import annotations

import torch


def composite(image: torch.Tensor, mask: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """image * mask + background * (1 - mask): image [H,W,3], mask [H,W] or [H,W,1] in 0..1, background
    [3] -> [H,W,3].

    As one lerp (background + mask (image - background), exact where the mask is 0) rather than four
    operations."""
    if mask.dim() == image.dim() - 1:
        mask = mask.unsqueeze(-1)
    return torch.lerp(background, image, mask)
