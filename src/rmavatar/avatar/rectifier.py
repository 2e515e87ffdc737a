"""The Gaussian rectification MLP F_theta(gamma(x), P) -> (d_mu, d_s, d_r) (paper §3.3; docs/model.md).

Layers (ReLU between): [gamma 36 | pose 69] = 105 -> 128 -> 128 -> [+gamma: 164] -> 128 -> 128 -> 10.
The pose part of the first layer depends only on the pose (the paper's design: one pose for every
Gaussian) or on the pose and a Gaussian's pose-mask group (the "local" design: few distinct masks), so
it is one small matrix product per frame, [U,69] x [69,128], added to that layer's bias row by row;
the [N,105] and [N,164] concatenations are never built; forward and backward are one fused autograd
Function. Every fused Function here has a ``reference`` beside it: the same computation under plain
autograd, which the tests compare it with (values and gradients).

The designs (``model.rectifier``) are subclasses of :class:`Rectifier` that share its MLP (and its
state_dict keys) and decide what it is given and what its outputs mean: :class:`PaperRectifier` (the
posed world position, the whole pose, offsets in world units) and :class:`LocalRectifier` (the rest-pose
position, each face's masked pose, offsets in the triangle's frame in units of w).
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import nn

from rmavatar.avatar.geometry import triangle_frames
from rmavatar.avatar.rows import posed_means
from rmavatar.utils import UserError
from rmavatar.utils.device import constant, host_scalar, set_host_scalar

POSE_DIM = 69
PRECISIONS = ("auto", "float32", "bfloat16")  # the hidden layers' arithmetic (model.rectifier_precision)
OUT_WIDTHS = (3, 3, 4)  # the output's columns: d_mu, d_s, d_r
OUT_DIM = sum(OUT_WIDTHS)


@functools.cache
def cpu_multiplies_bf16() -> bool:
    """Whether this CPU has bf16 dot products (AVX512-BF16 or AMX), where the rectifier's matrix
    products in bf16 ran about 4x faster than in float32 (docs/model.md); elsewhere bf16 is emulated."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch.cpu's own probes
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def window_values(num_freqs: int, alpha: float) -> tuple[float, ...]:
    """Coarse-to-fine weights of the encoding bands (HumanNeRF's window), computed on the host.

    Band k gets (1 - cos(pi * clamp(alpha - k, 0, 1))) / 2: alpha = 0 switches every band off,
    alpha = num_freqs switches all on.
    """
    return tuple(0.5 * (1 - math.cos(math.pi * min(max(alpha - k, 0.0), 1.0))) for k in range(num_freqs))


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
    if weights is not None:
        weights = weights.to(x.dtype).repeat_interleave(x.shape[-1]).repeat(2)
    return _Encoding.apply(x, num_freqs, weights)


class _Encoding(torch.autograd.Function):
    """gamma(x) times per-column weights [6 num_freqs] (or None), with the backward written out: it
    reuses the forward's sines and cosines (d sin = cos, d cos = -sin) and sums over the bands in one
    matrix product, 4 operations where autograd records about 11."""

    @staticmethod
    def forward(ctx, x, num_freqs, weights):
        freqs = constant(tuple(2.0**k for k in range(num_freqs)), x.dtype, x.device)
        xb = (x.unsqueeze(-2) * freqs.unsqueeze(-1)).flatten(-2)  # [N, num_freqs*3]
        s, c = torch.sin(xb), torch.cos(xb)
        gamma = torch.cat((s, c), dim=-1)
        ctx.num_freqs = num_freqs
        ctx.save_for_backward(s, c, weights)
        return gamma if weights is None else gamma * weights

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        s, c, weights = ctx.saved_tensors
        if weights is not None:
            grad = grad * weights
        ds, dc = grad.chunk(2, dim=-1)
        dxb = torch.addcmul(ds * c, dc, s, value=-1.0)  # d/dxb of sin, cos
        # x's gradient: sum over bands of 2^k dxb_k, as [N, num_freqs*3] @ [num_freqs*3, 3]
        nf, d = ctx.num_freqs, s.shape[-1] // ctx.num_freqs
        rows = tuple(tuple(2.0**k if j == i else 0.0 for i in range(d)) for k in range(nf) for j in range(d))
        band_sum = constant(rows, s.dtype, s.device)
        return dxb @ band_sum, None, None

    @staticmethod
    def reference(x: torch.Tensor, num_freqs: int, weights: torch.Tensor | None) -> torch.Tensor:
        """The same under plain autograd: sin and cos of x scaled by 2^k, times the column weights."""
        freqs = 2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)
        xb = (x.unsqueeze(-2) * freqs.unsqueeze(-1)).flatten(-2)
        gamma = torch.cat((torch.sin(xb), torch.cos(xb)), dim=-1)
        return gamma if weights is None else gamma * weights


_threshold_backward = torch.ops.aten.threshold_backward


class _FusedMLP(torch.autograd.Function):
    """The rectifier MLP with a hand-written backward.

    Compared with autograd over nn.Linear/ReLU it saves the bias-broadcast and zero-fill passes, keeps
    only the four post-ReLU activations (the ReLU masks are read off them), and never builds the
    concatenated inputs. Hidden layers run in ``dtype`` (float32, or bfloat16 where the CPU has fast
    bf16 dot products; docs/model.md); the output layer and all returned gradients are float32.
    """

    @staticmethod
    def forward(ctx, gamma, pose, group, w1, b1, w2, b2, w3, b3, w4, b4, w5, b5, dtype):
        # pose [U,P]: one pose row per group; group [N] picks every Gaussian's row (None: U = 1).
        e = gamma.shape[1]
        h = w2.shape[0]
        out_dtype = gamma.dtype
        bias1 = torch.addmm(b1, pose.to(b1.dtype), w1[:, e:].t())  # pose part of layer 1, once per group
        bias1 = bias1[0] if group is None else bias1[group]
        g = gamma.to(dtype)
        w1g, w2c, w3h, w3g, w4c = (t.to(dtype) for t in (w1[:, :e], w2, w3[:, :h], w3[:, h:], w4))
        h1 = torch.addmm(bias1.to(dtype), g, w1g.t()).relu_()
        h2 = torch.addmm(b2.to(dtype), h1, w2c.t()).relu_()
        h3 = torch.addmm(b3.to(dtype), g, w3g.t()).addmm_(h2, w3h.t()).relu_()
        h4 = torch.addmm(b4.to(dtype), h3, w4c.t()).relu_()
        out = torch.addmm(b5, h4.to(out_dtype), w5.t())
        ctx.group = group
        ctx.save_for_backward(g, pose, w1[:, e:], w1g, w2c, w3h, w3g, w4c, w5, h1, h2, h3, h4)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        g, pose, w1p, w1g, w2c, w3h, w3g, w4c, w5, h1, h2, h3, h4 = ctx.saved_tensors
        f32 = grad_out.dtype
        go = grad_out.contiguous()
        dw5 = go.t() @ h4.to(f32)
        db5 = go.sum(0)
        d4 = _threshold_backward((go @ w5).to(h4.dtype), h4, 0)
        dw4 = d4.t() @ h3
        db4 = d4.sum(0)
        d3 = _threshold_backward(d4 @ w4c, h3, 0)
        dw3 = torch.cat((d3.t() @ h2, d3.t() @ g), 1)
        db3 = d3.sum(0)
        d2 = _threshold_backward(d3 @ w3h, h2, 0)
        dw2 = d2.t() @ h1
        db2 = d2.sum(0)
        d1 = _threshold_backward(d2 @ w2c, h1, 0)
        group = ctx.group
        if group is None:
            dgroup = d1.sum(0, dtype=f32).unsqueeze(0)  # [1,h]: gradient of the bias row
        else:
            dgroup = torch.zeros(pose.shape[0], d1.shape[1], dtype=f32, device=d1.device)
            dgroup.index_add_(0, group, d1.to(f32))  # [U,h]: gradient of each group's bias row
        db1 = dgroup.sum(0)
        dw1 = torch.cat((d1.t() @ g, (dgroup.t() @ pose.to(f32)).to(d1.dtype)), 1)
        dgamma = None
        if ctx.needs_input_grad[0]:
            dgamma = torch.addmm(d1 @ w1g, d3, w3g).to(f32)
        dpose = (dgroup @ w1p.to(f32)).to(pose.dtype) if ctx.needs_input_grad[1] else None
        grads = (dw1, db1, dw2, db2, dw3, db3, dw4, db4)
        dw1, db1, dw2, db2, dw3, db3, dw4, db4 = (t.to(f32) for t in grads)
        return dgamma, dpose, None, dw1, db1, dw2, db2, dw3, db3, dw4, db4, dw5, db5, None

    @staticmethod
    def reference(gamma, pose, group, w1, b1, w2, b2, w3, b3, w4, b4, w5, b5, dtype=None) -> torch.Tensor:
        """The same MLP under plain autograd, on the concatenated [N,105] and [N,164] inputs, in the
        inputs' dtype (``dtype`` is not used: a bfloat16 run is compared with this within tolerances)."""
        rows = pose.expand(gamma.shape[0], -1) if group is None else pose[group]
        h = F.relu(F.linear(torch.cat((gamma, rows.to(gamma.dtype)), -1), w1, b1))
        h = F.relu(F.linear(h, w2, b2))
        h = F.relu(F.linear(torch.cat((h, gamma), -1), w3, b3))
        h = F.relu(F.linear(h, w4, b4))
        return F.linear(h, w5, b5)


class Rectifier(nn.Module):
    """Pose-conditioned offsets of the Gaussians.

    forward(x [N,3], body_pose [69]) -> (d_mu [N,3], d_s [N,3], d_r [N,4]); d_r is an offset from the
    identity quaternion. x is the position the design encodes (the posed position mu* in the paper's
    design, the rest-pose position in the local one; the design also decides in which frame the outputs
    live: :class:`RectifierDesign`). With ``pose_masks`` [U,69] and ``group`` [N] (index into its rows),
    Gaussian i sees the pose ``body_pose * pose_masks[group[i]]`` instead of the whole pose. The last
    layer starts near zero, so the rectifier starts as (almost exactly) the identity. No dropout:
    evaluation is deterministic.
    """

    def __init__(self, num_freqs: int = 6, hidden: int = 128, pose_dim: int = POSE_DIM, precision: str = "float32"):
        super().__init__()
        if precision not in PRECISIONS:
            raise ValueError(f"rectifier precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.precision = precision  # the hidden layers' arithmetic for float32 inputs (compute_dtype)
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

    def compute_dtype(self, x: torch.Tensor) -> torch.dtype:
        """The hidden layers' dtype for inputs like ``x``: theirs unless float32; for float32, bfloat16 with
        ``precision`` "bfloat16", or "auto" on a CPU with bf16 dot products (:func:`cpu_multiplies_bf16`;
        on a GPU "auto" stays float32)."""
        if x.dtype != torch.float32 or self.precision == "float32":
            return x.dtype
        if self.precision == "auto" and not (x.device.type == "cpu" and cpu_multiplies_bf16()):
            return torch.float32
        return torch.bfloat16

    def set_frequency_alpha(self, alpha: float) -> None:
        set_host_scalar(self, "freq_alpha", alpha)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        alpha = host_scalar(self, "freq_alpha")
        return _Encoding.apply(x, self.num_freqs, None if alpha >= self.num_freqs else self._band_weights(x))

    def _band_weights(self, x: torch.Tensor) -> torch.Tensor:
        """The window as per-column weights of gamma [6 num_freqs], computed on the device from the
        ``freq_alpha`` buffer (:func:`window_values` written as tensor operations): a captured step (a
        CUDA graph) reads the window of each replay from that buffer, which the trainer fills in place."""
        k = constant(tuple(float(i) for i in range(self.num_freqs)), x.dtype, x.device)
        t = (self.freq_alpha.to(x.dtype) - k).clamp(0.0, 1.0)
        bands = 0.5 - 0.5 * torch.cos(t * math.pi)  # [F]
        column_band = constant(tuple(f for _ in range(2) for f in range(self.num_freqs) for _ in range(x.shape[-1])),
                               torch.long, x.device)
        return bands[column_band]

    def _pose_rows(self, x, body_pose, pose_masks, group) -> torch.Tensor:
        """The pose input as rows [U,69], one per mask group ([1,69] without masks)."""
        if body_pose.shape[-1] != self.pose_dim or body_pose.numel() != self.pose_dim:
            raise ValueError(f"body_pose must have {self.pose_dim} values, got {tuple(body_pose.shape)}")
        pose = body_pose.reshape(1, self.pose_dim).to(x.dtype)
        if (pose_masks is None) != (group is None):
            raise ValueError("pose_masks and group go together: give both or neither")
        if pose_masks is None:
            return pose
        if pose_masks.dim() != 2 or pose_masks.shape[1] != self.pose_dim or group.shape != x.shape[:1]:
            raise ValueError(f"pose_masks must be [U,{self.pose_dim}] and group [N={x.shape[0]}], got "
                             f"{tuple(pose_masks.shape)} and {tuple(group.shape)}")
        return pose * pose_masks.to(x.dtype)

    def _weights(self) -> tuple[torch.Tensor, ...]:
        """The layers' weights and biases in _FusedMLP's order (w1, b1, ..., w5, b5)."""
        return (self.l1.weight, self.l1.bias, self.l2.weight, self.l2.bias, self.l3.weight, self.l3.bias,
                self.l4.weight, self.l4.bias, self.l5.weight, self.l5.bias)

    def forward(
        self, x: torch.Tensor, body_pose: torch.Tensor, pose_masks: torch.Tensor | None = None,
        group: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        pose = self._pose_rows(x, body_pose, pose_masks, group)
        gamma = self.encode(x)  # [N,36]
        out = _FusedMLP.apply(gamma, pose, group, *self._weights(), self.compute_dtype(gamma))
        return out.split(OUT_WIDTHS, dim=1)  # one backward operation (a cat), not three slice ones

    def reference_forward(
        self, x: torch.Tensor, body_pose: torch.Tensor, pose_masks: torch.Tensor | None = None,
        group: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The same MLP written plainly with the concatenated [N,105] / [N,164] inputs
        (:meth:`_FusedMLP.reference`; the encoding is :meth:`encode`'s). ``bench speed`` times it."""
        pose = self._pose_rows(x, body_pose, pose_masks, group)
        out = _FusedMLP.reference(self.encode(x), pose, group, *self._weights())
        return out.split(OUT_WIDTHS, dim=1)


# ----------------------------------------------------------------------------------------------- the designs
class RectifierDesign(Rectifier):
    """A rectifier design (``model.rectifier``): the shared MLP, and what the design decides around it.

    A design answers three questions, for the avatar that holds it (as ``avatar.rectifier``):

    - what it encodes: :meth:`encoded_position` (``reads_posed_mesh``: whether that needs the posed mesh);
    - which pose values each Gaussian sees: :meth:`pose_groups` (the pose masks are built once, with
      the avatar, by :meth:`make_pose_masks` from the body's skinning weights when ``needs_joint_weights``);
    - in which frame its offsets live: ``offsets_in_face_frame`` (read by ``compose_gaussians``, which
      fuses the conversion) and :meth:`world_offsets` (the conversion written plainly).

    :meth:`rectify` runs the fast path; :meth:`reference` is the same design under plain autograd.
    """

    name = ""  # the model.rectifier value that selects the design
    reads_posed_mesh = False  # True: the encoded position depends on the posed mesh
    needs_joint_weights = False  # True: Gaussians see their face's masked pose, made from skinning weights
    offsets_in_face_frame = False  # True: d_mu, d_s in the triangle's frame, units of w; False: world units

    def encoded_position(self, avatar, g: torch.Tensor | None) -> torch.Tensor:
        """The position the MLP encodes [N,3], from the avatar's Gaussians; ``g``: their rows of the posed
        mesh's face table (``Avatar._posed``; None when ``reads_posed_mesh`` is False)."""
        raise NotImplementedError

    def pose_groups(self, avatar) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(pose_masks [U,69], group [N]): Gaussian i sees ``body_pose * pose_masks[group[i]]``;
        (None, None): every Gaussian sees the whole pose."""
        raise NotImplementedError

    def make_pose_masks(self, faces: torch.Tensor, joint_weights: torch.Tensor | None, threshold: float,
                        num_vertices: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The avatar's pose-mask buffers (pose_masks [U,69], face_pose_group [F]) for the mesh ``faces``
        [F,3], or None when the design sees the whole pose."""
        return None

    def world_offsets(self, offsets: tuple[torch.Tensor, torch.Tensor, torch.Tensor], wR: torch.Tensor,
                      w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The MLP's outputs (d_mu, d_s, d_r) in world units, given each Gaussian's posed w R [N,3,3] and
        w [N,1] (plain autograd; ``compose_gaussians`` does the same fused)."""
        raise NotImplementedError

    def rectify(self, avatar, g: torch.Tensor | None,
                body_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The MLP's raw outputs (d_mu, d_s, d_r) for the avatar's Gaussians (``g`` as in
        :meth:`encoded_position`; ``body_pose`` [69] checked and in the avatar's dtype)."""
        pose_masks, group = self.pose_groups(avatar)
        return self(self.encoded_position(avatar, g), body_pose, pose_masks, group)

    # ---------------------------------------------------------------- the plain reference (for tests)
    def reference(self, avatar, vertices: torch.Tensor,
                  body_pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The offsets this design adds to the avatar's Gaussians on the posed mesh ``vertices`` [V,3],
        in world units (what ``Avatar.forward_with_extras`` returns as ``extras.offsets``), written
        plainly: the encoding and the MLP under autograd on concatenated inputs, one pose row per
        Gaussian, each Gaussian's frame from :func:`triangle_frames` of its own face."""
        R, w, M = triangle_frames(vertices, avatar.faces[avatar.face_ids])  # [N,...]: per Gaussian
        x = self._reference_position(avatar, R, w, M)
        pose = self._reference_pose(avatar, body_pose.reshape(1, self.pose_dim).to(x.dtype))  # [N,69]
        alpha = host_scalar(self, "freq_alpha")
        window = None if alpha >= self.num_freqs else self._band_weights(x)
        out = _FusedMLP.reference(_Encoding.reference(x, self.num_freqs, window), pose, None, *self._weights())
        return self.world_offsets(out.split(OUT_WIDTHS, dim=1), w[:, None, None] * R, w.unsqueeze(-1))

    def _reference_position(self, avatar, R, w, M) -> torch.Tensor:
        """:meth:`encoded_position` written plainly, given every Gaussian's posed frame R, w, M."""
        raise NotImplementedError

    def _reference_pose(self, avatar, body_pose: torch.Tensor) -> torch.Tensor:
        """The pose every Gaussian sees [N,69], from ``body_pose`` [1,69]."""
        raise NotImplementedError


class PaperRectifier(RectifierDesign):
    """The paper's design (§3.3): F(gamma(mu*), P) with mu* = w R mu + M the posed world position and P
    all 69 pose values; d_mu and d_s are world offsets (metres), added to mu* and s*."""

    name = "paper"
    reads_posed_mesh = True

    def encoded_position(self, avatar, g):
        return posed_means(g, avatar.means)

    def pose_groups(self, avatar):
        return None, None

    def world_offsets(self, offsets, wR, w):
        return offsets

    def _reference_position(self, avatar, R, w, M):
        return w.unsqueeze(-1) * (R @ avatar.means.unsqueeze(-1)).squeeze(-1) + M

    def _reference_pose(self, avatar, body_pose):
        return body_pose.expand(avatar.means.shape[0], -1)


class LocalRectifier(RectifierDesign):
    """The local design (docs/model.md): F(gamma(mu_rest), P * m_f) with mu_rest = w0 R0 mu + M0 the
    Gaussian's position on the rest mesh and m_f its face's pose mask (the joints that skin the face's
    corners); the outputs (d, d', d_r) live in the triangle's frame in units of w: d_mu = w R d,
    d_s = w d', so the offsets turn and grow with the body."""

    name = "local"
    needs_joint_weights = True
    offsets_in_face_frame = True

    def encoded_position(self, avatar, g):
        return avatar.rest_means()

    def pose_groups(self, avatar):
        return avatar.pose_masks, avatar.rows.local(avatar)[2]

    def make_pose_masks(self, faces, joint_weights, threshold, num_vertices):
        """A face sees joint j's three pose values when j's skinning weight on one of its corners
        exceeds ``threshold``; the faces' distinct masks are the rows of pose_masks."""
        if joint_weights is None:
            raise UserError("model.rectifier 'local' needs the body model's skinning weights (joint_weights)")
        jw = torch.as_tensor(joint_weights, dtype=torch.float32)
        if jw.shape != (num_vertices, 1 + self.pose_dim // 3):
            raise UserError(f"joint_weights must be [V={num_vertices},{1 + self.pose_dim // 3}], got {tuple(jw.shape)}")
        # Joint 0 is the global orientation, not part of the pose values (and a local rectifier must not
        # depend on which way the body faces); with hands, the 30 finger joints follow SMPL's 23.
        seen = jw.to(faces.device)[faces].amax(1)[:, 1:] > threshold  # [F,23] (or [F,53])
        masks, group = torch.unique(seen, dim=0, return_inverse=True)
        return masks.repeat_interleave(3, dim=1).float(), group

    def world_offsets(self, offsets, wR, w):
        d_mu, d_s, d_r = offsets
        return (wR @ d_mu.unsqueeze(-1)).squeeze(-1), w * d_s, d_r

    def _reference_position(self, avatar, R, w, M):
        slot = avatar.face_slot()
        rest_mu = (avatar.rest_frames[slot] @ avatar.means.unsqueeze(-1)).squeeze(-1)
        return avatar.rest_scales[slot].unsqueeze(-1) * rest_mu + avatar.rest_centroids[slot]

    def _reference_pose(self, avatar, body_pose):
        return body_pose * avatar.pose_masks[avatar.face_pose_group[avatar.face_ids]]


# model.rectifier's values -> their designs
DESIGNS: dict[str, type[RectifierDesign]] = {d.name: d for d in (PaperRectifier, LocalRectifier)}


def rectifier_design(name: str | bool | None) -> type[RectifierDesign] | None:
    """The design class that ``model.rectifier`` names (None for False / None: no rectifier)."""
    if name is None or name is False:
        return None
    if name not in DESIGNS:
        raise ValueError(f"no rectifier design {name!r} (designs: {', '.join(DESIGNS)})")
    return DESIGNS[name]
