"""The Gaussian rectification MLP F_theta(gamma(mu*), P) -> (d_mu, d_s, d_r) (paper §3.3, SPEC §2).

Layers (ReLU between): [gamma 36 | pose 69] = 105 -> 128 -> 128 -> [+gamma: 164] -> 128 -> 128 -> 10.
The pose is the same for every Gaussian of a frame, so its part of the first layer is one
matrix-vector product per frame, folded into that layer's bias; the [N,105] and [N,164]
concatenations are never built. The two gamma-consuming slices (first layer and skip layer) are
one [N,36] x [36,256] product.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

POSE_DIM = 69
OUT_DIM = 10  # d_mu 3, d_s 3, d_r 4


def frequency_window(num_freqs: int, alpha: float, device=None) -> torch.Tensor:
    """Coarse-to-fine weights [num_freqs] of the encoding bands (HumanNeRF's window).

    Band k gets (1 - cos(pi * clamp(alpha - k, 0, 1))) / 2: alpha = 0 switches every band off,
    alpha = num_freqs switches all on.
    """
    k = torch.arange(num_freqs, dtype=torch.float32, device=device)
    return 0.5 * (1 - torch.cos(math.pi * (alpha - k).clamp(0.0, 1.0)))


def window_alpha(iteration: int, start: int, end: int, num_freqs: int) -> float:
    """Window position for an iteration: 0 until ``start``, rising linearly to ``num_freqs`` at ``end``."""
    if end <= start:
        return float(num_freqs) if iteration >= start else 0.0
    return float(num_freqs) * min(max((iteration - start) / (end - start), 0.0), 1.0)


def positional_encoding(x: torch.Tensor, num_freqs: int, weights: torch.Tensor | None = None) -> torch.Tensor:
    """gamma(x) = [sin(2^k x), cos(2^k x)] for k < num_freqs, without x itself.

    x [N,3] -> [N, 6 * num_freqs], laid out as [sin (k, xyz) | cos (k, xyz)].
    ``weights`` [num_freqs] scales each band (the coarse-to-fine window).
    """
    freqs = 2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)
    xb = (x.unsqueeze(-2) * freqs.unsqueeze(-1)).flatten(-2)  # [N, num_freqs*3]
    s, c = torch.sin(xb), torch.cos(xb)
    if weights is not None:
        wb = weights.to(x.dtype).repeat_interleave(x.shape[-1])
        s, c = s * wb, c * wb
    return torch.cat((s, c), dim=-1)


class Rectifier(nn.Module):
    """Pose-conditioned offsets of the posed Gaussians.

    forward(mu_star [N,3], body_pose [69]) -> (d_mu [N,3], d_s [N,3], d_r [N,4]); d_r is an offset
    from the identity quaternion. The last layer starts near zero, so the rectifier starts as
    (almost exactly) the identity. No dropout: evaluation is deterministic.
    """

    def __init__(self, num_freqs: int = 6, hidden: int = 128, pose_dim: int = POSE_DIM):
        super().__init__()
        self.num_freqs = num_freqs
        self.hidden = hidden
        self.pose_dim = pose_dim
        self.enc_dim = 6 * num_freqs
        self.in_dim = self.enc_dim + pose_dim  # 105 for the paper's setting
        self.l1 = nn.Linear(self.in_dim, hidden)
        self.l2 = nn.Linear(hidden, hidden)
        self.l3 = nn.Linear(hidden + self.enc_dim, hidden)  # skip: gamma concatenated again
        self.l4 = nn.Linear(hidden, hidden)
        self.l5 = nn.Linear(hidden, OUT_DIM)
        nn.init.normal_(self.l5.weight, std=1e-5)
        nn.init.zeros_(self.l5.bias)
        # Window position of the coarse-to-fine encoding; a buffer so checkpoints keep it.
        self.register_buffer("freq_alpha", torch.tensor(float(num_freqs)))

    @property
    def layer_widths(self) -> list[tuple[int, int]]:
        return [(m.in_features, m.out_features) for m in (self.l1, self.l2, self.l3, self.l4, self.l5)]

    def set_frequency_alpha(self, alpha: float) -> None:
        self.freq_alpha.fill_(float(alpha))

    def encode(self, mu_star: torch.Tensor) -> torch.Tensor:
        alpha = float(self.freq_alpha)
        weights = None
        if alpha < self.num_freqs:
            weights = frequency_window(self.num_freqs, alpha, mu_star.device)
        return positional_encoding(mu_star, self.num_freqs, weights)

    def forward(
        self, mu_star: torch.Tensor, body_pose: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if body_pose.shape[-1] != self.pose_dim or body_pose.numel() != self.pose_dim:
            raise ValueError(f"body_pose must have {self.pose_dim} values, got {tuple(body_pose.shape)}")
        h = self.hidden
        gamma = self.encode(mu_star)  # [N,36]
        pose = body_pose.reshape(self.pose_dim).to(mu_star.dtype)
        w1 = self.l1.weight
        w3 = self.l3.weight
        # Per-frame bias of the first layer: b1 + W1[:, pose] @ P.
        b1 = torch.addmv(self.l1.bias, w1[:, self.enc_dim:], pose)
        w_gamma = torch.cat((w1[:, : self.enc_dim], w3[:, h:]), dim=0)  # [256,36]
        g = gamma @ w_gamma.t()  # [N,256]
        x = torch.relu(g[:, :h] + b1)
        x = F.relu(self.l2(x))
        x = torch.relu(torch.addmm(self.l3.bias, x, w3[:, :h].t()) + g[:, h:])
        x = F.relu(self.l4(x))
        out = self.l5(x)
        return out[:, 0:3], out[:, 3:6], out[:, 6:10]

    def reference_forward(
        self, mu_star: torch.Tensor, body_pose: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The same MLP written plainly with the concatenated [N,105] / [N,164] inputs (for tests)."""
        gamma = self.encode(mu_star)
        pose = body_pose.reshape(1, self.pose_dim).to(mu_star.dtype).expand(gamma.shape[0], -1)
        x = F.relu(self.l1(torch.cat((gamma, pose), -1)))
        x = F.relu(self.l2(x))
        x = F.relu(self.l3(torch.cat((x, gamma), -1)))
        x = F.relu(self.l4(x))
        out = self.l5(x)
        return out[:, 0:3], out[:, 3:6], out[:, 6:10]
