"""A training step's steady parts replayed as CUDA graphs.

A step is posing (mesh embedding, rectifier, view colours: :func:`rmavatar.avatar.frame.pose_frame`) ->
rasterizer -> losses (:func:`rmavatar.train.losses.total_loss`), then backward and Adam. On a GPU a step
was bound by launching hundreds of small kernels from Python, not by the kernels (docs/train.md).
:class:`StepGraphs` runs the posing and the losses, forward and backward, as CUDA graphs made by
``torch.cuda.make_graphed_callables``; the rasterizer stays eager between them (gsplat reads a count
back to the host in every call, which a graph cannot hold).

A graph holds fixed shapes and fixed memory, so it is made for one *signature*: the identity and shapes
of the avatar's parameters and buffers (density control replaces them), the active SH degree (a shape),
whether the encoding window is still opening (a branch), which inputs are given and whether they take
gradients (pose refinement), the image size. A step whose signature differs captures again (after each
density-control event). Everything else that changes from step to step reaches the graphs as tensor
contents: the frame's inputs are copied into the graphs' input buffers, the encoding window is read from
the rectifier's ``freq_alpha`` buffer.

Without CUDA (or with graphs off) the same two functions run eagerly: one code path, only the replay
differs.
"""

from __future__ import annotations

import sys
import time
from typing import Callable, NamedTuple

import torch
from torch import nn

from rmavatar.avatar.frame import pose_frame
from rmavatar.avatar.model import Avatar, AvatarExtras
from rmavatar.train.losses import LossConfig, total_loss
from rmavatar.utils.device import host_scalar
from rmavatar.utils.graphs import WARMUP, capture_failure, no_collection


class PosedTensors(NamedTuple):
    """A posed frame as the rasterizer and the losses read it."""

    means: torch.Tensor  # [N,3] world positions
    quats: torch.Tensor  # [N,4] world rotations (wxyz)
    scales: torch.Tensor  # [N,3] world scales
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N,3] seen from the frame's camera
    offsets: tuple[torch.Tensor, ...] | None  # the rectifier's (d_mu, d_s, d_r) in world units, or None


class _Posing(nn.Module):
    """:func:`pose_frame` as a function of tensors only: (the given ones of vertices [V,3], body_pose
    [69], table [F,k], and viewmat [4,4]) -> (means, quats, scales, opacities, colors, *offsets); with
    ``body`` (a function of tensors -> vertices, body_pose: a pose refinement's corrected body), its
    inputs and viewmat instead. A module, so that ``make_graphed_callables`` takes the avatar's
    parameters as its inputs."""

    def __init__(self, avatar: Avatar, given: tuple[bool, bool, bool], body: Callable | None = None):
        super().__init__()
        self.avatar, self.given, self.body = avatar, given, body

    def forward(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        *inputs, viewmat = inputs
        if self.body is not None:
            (vertices, body_pose), table = self.body(*inputs), None
        else:
            it = iter(inputs)
            vertices, body_pose, table = (next(it) if g else None for g in self.given)
        gs, extras, colors = pose_frame(self.avatar, vertices, body_pose, viewmat, table=table)
        return (gs.means, gs.quats, gs.scales, gs.opacities, colors, *(extras.offsets or ()))


class _Losses:
    """:func:`total_loss` as a function of tensors only: (image, target, local_means, local_log_scales,
    *row weights, *offsets, *lpips units, *lpips window, *(alpha, mask)) -> (loss, the terms stacked [T]);
    ``names`` are the terms'."""

    def __init__(self, cfg: LossConfig, layout: tuple[int, int, int, int, int]):
        # how many row-weight, offset, LPIPS unit, window and (alpha, mask) tensors are given
        self.cfg, self.layout = cfg, layout
        self.names: list[str] = []

    def __call__(self, image, target, means, log_scales, *rest):
        groups, start = [], 0
        for count in self.layout:
            groups.append(rest[start:start + count])
            start += count
        row_weights, offsets, units, window, coverage = groups
        extras = AvatarExtras(local_means=means, local_log_scales=log_scales, offsets=tuple(offsets) or None,
                              row_weights=row_weights[0] if row_weights else None)
        alpha, mask = coverage if coverage else (None, None)
        loss, parts = total_loss(image, target, extras, self.cfg, lpips_units=list(units) or None,
                                 lpips_window=tuple(window) or None, alpha=alpha, mask=mask)
        self.names = list(parts)
        return loss, torch.stack(list(parts.values())) if parts else loss.new_zeros(0)


class StepGraphs:
    """The posing and the losses of ``avatar``'s training steps, eager or replayed as CUDA graphs
    (module docstring). ``enabled``: use graphs where the avatar lives on a CUDA device. ``captures``
    counts the graphs made, ``capture_s`` the seconds spent making them (warm-up runs included).

    A capture that fails leaves that signature's steps eager and is tried again at the next signature
    (the next density event); ``failures`` lists each failure's (piece, reason). After ``MAX_FAILURES``
    the run goes on eagerly and ``off_reason`` says why."""

    MAX_FAILURES = 3

    def __init__(self, avatar: Avatar, loss: LossConfig, enabled: bool = True):
        self.avatar, self.loss = avatar, loss
        self.enabled = enabled and avatar.means.device.type == "cuda"
        self.off_reason: str | None = None if self.enabled else "not a CUDA device" if enabled else "off"
        self.captures, self.capture_s = 0, 0.0
        self.failures: list[tuple[str, str]] = []
        self._accumulators: list = []  # the parameters' gradient accumulators, made on the capture stream
        if self.enabled and hasattr(torch.autograd.graph, "set_warn_on_accumulate_grad_stream_mismatch"):
            # eager steps accumulate into the accumulators pinned to the capture stream, on purpose
            torch.autograd.graph.set_warn_on_accumulate_grad_stream_mismatch(False)
        self._posing: tuple | None = None  # (signature, callable)
        self._losses: tuple | None = None

    # ------------------------------------------------------------------ the two pieces
    def pose(self, vertices: torch.Tensor | None, body_pose: torch.Tensor | None, table: torch.Tensor | None,
             viewmat: torch.Tensor) -> PosedTensors:
        """The frame posed: ``pose_frame(avatar, vertices, body_pose, viewmat, table=table)``'s tensors."""
        given = (vertices is not None, body_pose is not None, table is not None)
        inputs = tuple(t for t in (vertices, body_pose, table) if t is not None) + (viewmat,)
        return self._pose(("held", given), inputs, lambda: _Posing(self.avatar, given))

    def pose_body(self, body: Callable, inputs: tuple[torch.Tensor, ...], viewmat: torch.Tensor) -> PosedTensors:
        """The frame posed on ``body(*inputs)`` -> (vertices [V,3], body_pose [69]) (a pose refinement's
        corrected body, :func:`rmavatar.train.poses.pose_corrected`), in the same graph as the posing.
        ``body`` must be the same function at every step (its identity is not checked)."""
        return self._pose(("body",), (*inputs, viewmat), lambda: _Posing(self.avatar, (), body))

    def _pose(self, kind: tuple, inputs: tuple, make) -> PosedTensors:
        fn, _ = self._callable("_posing", lambda: (kind, _describe(inputs),
                                                   _describe([*self.avatar.parameters(), *self.avatar.buffers()],
                                                             identity=True),
                                                   self._switches()),
                               kind, make, inputs)
        out = fn(*inputs)
        return PosedTensors(*out[:5], tuple(out[5:]) or None)

    def losses(self, image: torch.Tensor, target: torch.Tensor, posed: PosedTensors,
               lpips_units: list[torch.Tensor] | None = None,
               lpips_window: tuple[torch.Tensor, torch.Tensor] | None = None,
               coverage: tuple[torch.Tensor, torch.Tensor] | None = None) -> tuple[torch.Tensor, dict]:
        """``total_loss`` of the rendered ``image`` [H,W,3] against ``target``, with the avatar's local
        means and log-scales and the posed frame's offsets (and ``coverage``: the render's alpha [H,W,1]
        and the frame's mask [H,W,1], for the mask term): (loss, each term by name)."""
        units, window, offsets = tuple(lpips_units or ()), tuple(lpips_window or ()), posed.offsets or ()
        coverage = tuple(coverage or ())
        rows = () if self.avatar.row_weights is None else (self.avatar.row_weights,)  # capacity buffers
        inputs = (image, target, self.avatar.means, self.avatar.log_scales, *rows, *offsets, *units, *window,
                  *coverage)
        layout = (len(rows), len(offsets), len(units), len(window), len(coverage))
        fn, terms = self._callable("_losses", lambda: ("loss", layout, _describe(inputs)), layout,
                                   lambda: _Losses(self.loss, layout), inputs)
        loss, values = fn(*inputs)
        # the graph's outputs are overwritten by its next replay: what the caller keeps is copied
        return loss, dict(zip(terms.names, values.detach().clone().unbind()))

    # ------------------------------------------------------------------ capturing
    def _switches(self) -> tuple:
        """The avatar's host-side switches that change a step's shapes or branches."""
        rect = self.avatar.rectifier
        window_open = rect is None or host_scalar(rect, "freq_alpha") >= rect.num_freqs
        return host_scalar(self.avatar, "active_sh_degree", int), window_open

    def _callable(self, slot: str, signature, eager_signature, make, inputs: tuple):
        """(callable, the object ``make`` made) for this step: the one held in ``slot`` if made for the
        same signature (``signature()``, what a graph fixes; ``eager_signature`` without graphs), else a
        new one, captured as CUDA graphs when enabled."""
        key = signature() if self.enabled else eager_signature
        held = getattr(self, slot)
        if held is not None and held[0] == key:
            return held[1], held[2]
        held = None
        setattr(self, slot, None)  # free the old graphs before capturing new ones (no_collection)
        obj = make()
        fn = self._capture(slot.strip("_"), obj, inputs) if self.enabled else obj
        setattr(self, slot, (key, fn, obj))
        return fn, obj

    def _capture(self, piece: str, fn, inputs: tuple):
        """``fn`` captured, or ``fn`` itself where capturing failed (recorded in ``failures``)."""
        # The sample inputs become the graph's input buffers, which every replay overwrites: copies, never
        # the caller's tensors (a cached frame would be overwritten by the next one).
        sample = tuple(t.detach().clone().requires_grad_(t.requires_grad) for t in inputs)
        started = time.perf_counter()
        try:
            with no_collection():
                self._pin_accumulators()
                graphed = torch.cuda.make_graphed_callables(fn, sample, num_warmup_iters=WARMUP,
                                                            allow_unused_input=True)
        except Exception as exc:  # noqa: BLE001 - any failure to capture: these steps run eagerly
            reason = capture_failure(exc)
            self.failures.append((piece, reason))
            if len(self.failures) >= self.MAX_FAILURES:
                self.enabled, self.off_reason = False, f"{len(self.failures)} captures failed, the last: {reason}"
                print(f"CUDA graphs off for this run (it continues without them): {self.off_reason}",
                      file=sys.stderr, flush=True)
            else:
                print(f"capturing the {piece} as a CUDA graph failed ({reason}); these steps run eagerly, "
                      f"tried again when the step's shapes next change", file=sys.stderr, flush=True)
            torch.cuda.synchronize()
            return fn
        self.captures += 1
        self.capture_s += time.perf_counter() - started
        return graphed

    def _pin_accumulators(self) -> None:
        """Make the parameters' gradient accumulators on the stream graphs are captured on, and hold them.

        An accumulator keeps the stream it was made on. One made by an eager step is on the legacy default
        stream (a graphed piece's autograd node has an edge to every parameter, used or not: at SH degree
        0 the higher bands are unused), and a capture whose backward reaches it must synchronise with that
        stream, which invalidates the capture. Made here first, every step uses these instead."""
        stream = torch.cuda.graph(torch.cuda.CUDAGraph()).capture_stream  # torch's stream for captures
        with torch.cuda.stream(stream):
            self._accumulators = [p.view_as(p).grad_fn.next_functions[0][0]
                                  for p in self.avatar.parameters() if p.requires_grad]


def _describe(tensors, identity: bool = False) -> tuple:
    """What a graph fixes about tensors: shape, dtype, whether they take gradients, and (``identity``:
    for the parameters a graph reads in place, not copied in) their storage."""
    return tuple((t.data_ptr() if identity else 0, tuple(t.shape), t.dtype, t.requires_grad) for t in tensors)
