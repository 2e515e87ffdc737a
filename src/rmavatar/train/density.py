"""Adaptive density control of mesh-embedded Gaussians (paper §3.2; 3DGS's rules on a mesh, docs/model.md).

- Statistics: per visible Gaussian, the norm of the view-space positional gradient
  ``info["means2d"].grad`` converted from pixels to NDC-like units (x W/2, y H/2, as gsplat's default
  strategy does), so the 3DGS threshold 2e-4 means the same at any resolution; averaged over the
  steps the Gaussian was visible.
- Densify (Gaussians with average gradient >= threshold): small ones are cloned (an exact copy),
  large ones split into two children drawn from the parent's Gaussian, scales / 1.6, the parent
  removed. Small/large compares the Gaussian's largest world-space scale on the rest mesh
  (``w_rest * exp(log_scale)``) with ``percent_dense * extent``, extent = half the diagonal of the
  rest mesh's bounding box (the avatar's "scene"). Everything happens in the parent triangle's frame:
  children keep the parent's face.
- Prune: opacity < 0.005, but never a face's last Gaussian (its most opaque one is kept).
- Opacity reset: opacity = min(opacity, 0.01), Adam moments of the opacity cleared (as 3DGS).
Every change is mirrored in the given ``torch.optim.Adam``: kept rows keep their moments, new rows
start at zero, removed rows are dropped, and the optimiser's parameters are the avatar's new ones.

Capacity buffers (:func:`use_capacity`; ``Avatar`` docstring): the live Gaussians are the first rows
of tensors of a fixed size, in the order they would have without buffers, so a run gives the same
Gaussians either way (to float rounding: sums over more rows). Densify and prune then rewrite those
rows and the mask in place, and the parameters, their Adam moments and every tensor a captured CUDA
graph reads stay where they are; only outgrowing the buffers allocates anew (half as many again, or
the density cap).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from rmavatar.avatar.geometry import quat_rotate
from rmavatar.avatar.model import GAUSSIAN_PARAMS
from rmavatar.utils.config import check_fields
from rmavatar.utils.device import constant


# ------------------------------------------------------------------------------------------ schedule
@dataclass(frozen=True)
class DensitySchedule:
    """When to densify/prune and reset opacities (iterations are 1-based, counted after the step).

    Densify at start, start + every, ... while < stop; reset opacity at reset_start,
    reset_start + reset_every, ... while < stop; gradient statistics gathered while < stop.
    """

    start: int
    every: int
    stop: int
    reset_start: int
    reset_every: int

    def gather_at(self, it: int) -> bool:
        return it < self.stop

    def densify_at(self, it: int) -> bool:
        return self.start <= it < self.stop and (it - self.start) % self.every == 0

    def reset_at(self, it: int) -> bool:
        return self.reset_start <= it < self.stop and (it - self.reset_start) % self.reset_every == 0


@dataclass
class DensityConfig:
    """Mesh-bound density control: the paper's schedule, stated for ``reference_iters`` iterations and
    stretched to the run's length (:meth:`schedule`), and the 3DGS thresholds. ``build`` makes the
    controller."""

    max_gaussians: int = 0  # the Gaussian cap: densification stops adding past it; 0 = unlimited
    enabled: bool = True  # densify, prune and reset opacities at all
    # Keep the Gaussians in fixed-size buffers between density events (the cap, or grown by half when
    # full), so a step captured as CUDA graphs need not be captured again; None = where the step runs as
    # CUDA graphs. Same results either way; checkpoints hold the live Gaussians only.
    capacity: bool | None = None
    # --- advanced ---
    reference_iters: int = 50_000  # the schedule below is scaled by iters / reference_iters
    start: int = 10_000  # first densification (at reference_iters)
    every: int = 500  # densify every this many iterations
    stop: int = 35_000  # no densification, pruning or opacity reset from here on
    reset_every: int = 5_000  # reset opacities every this many iterations
    reset_start: int = 10_000  # the first opacity reset
    grad_threshold: float = 2e-4  # view-space position-gradient norm (3DGS rule)
    prune_opacity: float = 0.005  # prune Gaussians less opaque than this (never a face's last)
    percent_dense: float = 0.01  # clone if largest rest-pose scale <= this x the body's extent, else split
    reset_opacity_to: float = 0.01  # opacity resets cap every opacity at this (3DGS)

    def validate(self) -> "DensityConfig":
        """Raise UserError for values no schedule can use (names are the config.yaml keys); returns self."""
        check_fields(self, "density", at_least_one=("reference_iters", "every", "reset_every"),
                     nonnegative=("start", "stop", "reset_start", "grad_threshold", "prune_opacity",
                                  "percent_dense", "reset_opacity_to", "max_gaussians"))
        return self

    def schedule(self, iters: int) -> DensitySchedule:
        """The schedule for a run of ``iters`` iterations, keeping the paper's proportions (e.g. 2,000
        iterations: densify every 20 from 400 to 1,400, reset every 200)."""
        f = iters / self.reference_iters
        return DensitySchedule(*(max(1, round(v * f)) for v in (
            self.start, self.every, self.stop, self.reset_start, self.reset_every)))

    def build(self, avatar, optimizer: torch.optim.Optimizer | None, iters: int, seed: int = 0) -> "DensityController":
        """The controller for ``avatar`` (its changes mirrored in ``optimizer``) over a run of ``iters``."""
        return DensityController(avatar, optimizer, self, iters, seed)


# ------------------------------------------------------------------------------------------ surgery
def _find_in_optimizer(optimizer: torch.optim.Optimizer, param: torch.Tensor) -> tuple[int, int] | None:
    for gi, group in enumerate(optimizer.param_groups):
        for pi, p in enumerate(group["params"]):
            if p is param:
                return gi, pi
    return None


def rebuild_gaussians(
    avatar,
    optimizer: torch.optim.Optimizer | None,
    keep: torch.Tensor,
    new_rows: dict[str, torch.Tensor] | None = None,
    new_face_ids: torch.Tensor | None = None,
) -> None:
    """Make the live Gaussians ``cat(old[keep], new_rows[name])`` (and face_ids likewise), carrying Adam
    moments along: kept rows keep theirs, new rows get zeros. keep [K] long indices of live rows.

    Without capacity buffers every per-Gaussian tensor is replaced; with them the rows are rewritten in
    place (buffers outgrown: reallocated, :func:`grown_capacity`)."""
    n_new = 0 if new_face_ids is None else int(new_face_ids.shape[0])
    rows = int(keep.shape[0]) + n_new
    capacity = None
    if avatar.live_rows is not None:
        capacity = avatar.capacity if rows <= avatar.capacity else grown_capacity(rows)
    _place_rows(avatar, optimizer, keep, new_rows or {}, new_face_ids, capacity)


def use_capacity(avatar, optimizer: torch.optim.Optimizer | None, max_gaussians: int = 0) -> None:
    """Put ``avatar``'s Gaussians (and ``optimizer``'s moments of them) into capacity buffers: the density
    cap's rows where it holds them all, else :func:`grown_capacity`'s."""
    n = avatar.num_gaussians
    keep = torch.arange(n, device=avatar.means.device)
    _place_rows(avatar, optimizer, keep, {}, None, grown_capacity(n, max_gaussians))


def grown_capacity(rows: int, cap: int = 0) -> int:
    """Buffer rows for ``rows`` live Gaussians: ``cap`` where it holds them, else half as many again, in
    whole 1,024s (a few re-allocations in a run, each a new CUDA graph capture)."""
    return cap if cap >= rows else -(-(rows * 3 // 2) // 1024) * 1024


def _unused_rows(name: str, like: torch.Tensor, k: int) -> torch.Tensor:
    """What an unused row of parameter ``name`` holds: zeros (an identity rotation for quats); finite,
    so that its zero opacity keeps it out of every image and gradient."""
    rows = like.new_zeros((k,) + tuple(like.shape[1:]))
    if name == "quats":
        rows[:, 0] = 1.0
    return rows


def _fill(old: torch.Tensor, rows: torch.Tensor, capacity: int | None, unused: torch.Tensor | None) -> torch.Tensor:
    """``rows`` then ``unused`` to ``capacity`` rows: in ``old``'s memory where it has that many rows,
    else a new tensor (``capacity`` None: ``rows`` alone)."""
    if capacity is None:
        return rows.contiguous()
    if old.shape[0] == capacity:
        old[: rows.shape[0]] = rows
        old[rows.shape[0]:] = unused
        return old
    return torch.cat((rows, unused), 0)


def _place_rows(avatar, optimizer, keep, new_rows: dict, new_face_ids, capacity: int | None) -> None:
    """The live rows ``cat(old[keep], new_rows)`` into tensors of ``capacity`` rows (None: exactly that
    many), with the moments, face_ids and the capacity mask (``rebuild_gaussians``)."""
    n_new = 0 if new_face_ids is None else int(new_face_ids.shape[0])
    n = int(keep.shape[0]) + n_new
    pad = 0 if capacity is None else capacity - n
    for name in GAUSSIAN_PARAMS:
        old = getattr(avatar, name)
        rows = old.data[keep]
        if n_new:
            rows = torch.cat((rows, new_rows[name].to(rows.dtype)), dim=0)
        data = _fill(old.data, rows, capacity, _unused_rows(name, rows, pad))
        new = old if data is old.data else nn.Parameter(data, requires_grad=old.requires_grad)
        where = _find_in_optimizer(optimizer, old) if optimizer is not None else None
        if where is not None:
            state = optimizer.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
                    if key in state and torch.is_tensor(state[key]) and state[key].shape == old.shape:
                        moment = state[key][keep]
                        moment = torch.cat((moment, moment.new_zeros((n_new + pad,) + moment.shape[1:])), 0)
                        state[key] = _fill(state[key], moment[:n], capacity, moment[n:])
                optimizer.state[new] = state
            optimizer.param_groups[where[0]]["params"][where[1]] = new
        if new is not old:
            setattr(avatar, name, new)
    face_ids = avatar.face_ids[keep]
    if n_new:
        face_ids = torch.cat((face_ids, new_face_ids.to(face_ids)), 0)
    unused_face = avatar.binding_faces[:1].expand(pad).to(face_ids)
    avatar.face_ids = _fill(avatar.face_ids, face_ids, capacity, unused_face)
    _set_live(avatar, n, capacity)


def _set_live(avatar, n: int, capacity: int | None) -> None:
    """The capacity mask of ``n`` live rows out of ``capacity`` (None: off), in place where it fits."""
    if capacity is None:
        avatar.live_rows, avatar.live, avatar.row_weights = None, None, None
        return
    live = (torch.arange(capacity, device=avatar.means.device) < n).to(avatar.means.dtype)
    weights = live / n
    if avatar.live is not None and avatar.live.shape == live.shape:
        avatar.live.copy_(live)
        avatar.row_weights.copy_(weights)
        avatar.rows.refresh(avatar)  # the face slots and the rectifier's inputs, in place too
    else:
        avatar.live, avatar.row_weights = live, weights
    avatar.live_rows = n


def live_optimizer_state(optimizer: torch.optim.Optimizer, avatar) -> dict:
    """``optimizer.state_dict()`` with the moments of the avatar's live Gaussians only (a checkpoint's;
    the same as without capacity buffers)."""
    state = optimizer.state_dict()
    if avatar.live_rows is None:
        return state
    gaussians = {id(getattr(avatar, name)) for name in GAUSSIAN_PARAMS}
    params = [p for group in optimizer.param_groups for p in group["params"]]  # state_dict's numbering
    n, live = avatar.live_rows, {}
    for index, values in state["state"].items():
        if id(params[index]) in gaussians:
            values = {k: v[:n].clone() if torch.is_tensor(v) and v.dim() > 0 else v for k, v in values.items()}
        live[index] = values
    return {**state, "state": live}


def world_rest_scale(avatar) -> torch.Tensor:
    """Largest world-space scale of every Gaussian on the rest mesh [N]: w_rest * max exp(log_scale)."""
    return avatar.rest_face_scale[avatar.face_ids] * torch.exp(avatar.log_scales.detach()).amax(-1)


def densify(
    avatar,
    optimizer: torch.optim.Optimizer | None,
    grad_avg: torch.Tensor,
    grad_threshold: float = 2e-4,
    percent_dense: float = 0.01,
    extent: float | None = None,
    max_gaussians: int = 0,
    generator: torch.Generator | None = None,
) -> tuple[int, int]:
    """Clone small / split large Gaussians whose average view-space gradient >= threshold.

    grad_avg [N] (or [capacity]). Returns (number cloned, number split). ``max_gaussians`` > 0 caps the
    count: the Gaussians with the largest gradients go first.
    """
    n = avatar.num_gaussians
    if grad_avg.shape not in ((n,), (avatar.capacity,)):
        raise ValueError(f"grad_avg must be [{n}], got {tuple(grad_avg.shape)}")
    grad_avg = grad_avg[:n]
    extent = float(avatar.rest_extent) if extent is None else extent
    selected = grad_avg >= grad_threshold
    if max_gaussians > 0:
        room = max(0, max_gaussians - n)  # every clone or split adds one Gaussian
        if int(selected.sum()) > room:
            order = torch.argsort(torch.where(selected, grad_avg, -math.inf), descending=True)
            selected = torch.zeros_like(selected)
            selected[order[:room]] = True
    small = world_rest_scale(avatar)[:n] <= percent_dense * extent
    clone = selected & small
    split = selected & ~small
    n_clone, n_split = int(clone.sum()), int(split.sum())
    if n_clone + n_split == 0:
        return 0, 0
    params = {name: getattr(avatar, name).detach()[:n] for name in GAUSSIAN_PARAMS}
    ci = clone.nonzero().squeeze(-1)
    si = split.nonzero().squeeze(-1)
    rows = {name: [p[ci], p[si].repeat(2, *([1] * (p.dim() - 1)))] for name, p in params.items()}
    # Split children: positions drawn from the parent's Gaussian in its face's frame, scales / 1.6.
    std = torch.exp(params["log_scales"][si]).repeat(2, 1)
    z = torch.randn(std.shape, generator=generator, dtype=std.dtype, device=std.device)
    offset = quat_rotate(params["quats"][si].repeat(2, 1), z * std)
    rows["means"][1] = rows["means"][1] + offset
    rows["log_scales"][1] = rows["log_scales"][1] - math.log(1.6)
    new_rows = {name: torch.cat(parts, 0) for name, parts in rows.items()}
    face_ids = avatar.face_ids[:n]
    new_faces = torch.cat((face_ids[ci], face_ids[si].repeat(2)), 0)
    keep = (~split).nonzero().squeeze(-1)
    rebuild_gaussians(avatar, optimizer, keep, new_rows, new_faces)
    return n_clone, n_split


def prune_mask(opacities: torch.Tensor, face_ids: torch.Tensor, threshold: float, num_faces: int) -> torch.Tensor:
    """Which Gaussians to remove [N] bool: opacity < threshold, except each face's most opaque one
    when all of that face's Gaussians would go (lowest index on ties)."""
    remove = opacities < threshold
    kept_per_face = torch.zeros(num_faces, dtype=torch.long, device=face_ids.device)
    kept_per_face.index_add_(0, face_ids, (~remove).long())
    orphan = remove & (kept_per_face[face_ids] == 0)
    if bool(orphan.any()):
        best = torch.full((num_faces,), -math.inf, dtype=opacities.dtype, device=opacities.device)
        best.scatter_reduce_(0, face_ids, opacities, reduce="amax")
        cand = orphan & (opacities == best[face_ids])
        idx = torch.arange(face_ids.shape[0], device=face_ids.device)
        first = torch.full((num_faces,), face_ids.shape[0], dtype=torch.long, device=face_ids.device)
        first.scatter_reduce_(0, face_ids[cand], idx[cand], reduce="amin")
        rescue = torch.zeros_like(remove)
        rescue[first[first < face_ids.shape[0]]] = True
        remove &= ~rescue
    return remove


def prune(avatar, optimizer: torch.optim.Optimizer | None, min_opacity: float = 0.005) -> int:
    """Remove Gaussians with opacity < min_opacity, never a face's last one. Returns how many went."""
    live = avatar.num_gaussians
    with torch.no_grad():
        remove = prune_mask(torch.sigmoid(avatar.opacity_logits[:live]), avatar.face_ids[:live], min_opacity,
                            avatar.faces.shape[0])
    n = int(remove.sum())
    if n:
        rebuild_gaussians(avatar, optimizer, (~remove).nonzero().squeeze(-1))
    return n


def reset_opacity(avatar, optimizer: torch.optim.Optimizer | None, max_opacity: float = 0.01) -> None:
    """opacity = min(opacity, max_opacity) in place; the opacity's Adam moments are cleared."""
    cap = math.log(max_opacity / (1 - max_opacity))
    with torch.no_grad():
        avatar.opacity_logits[: avatar.num_gaussians].clamp_(max=cap)  # live rows: unused ones stay as made
    if optimizer is not None:
        state = optimizer.state.get(avatar.opacity_logits)
        if state:
            for key in ("exp_avg", "exp_avg_sq", "max_exp_avg_sq"):
                if key in state and torch.is_tensor(state[key]) and state[key].dim() > 0:
                    state[key].zero_()


# ------------------------------------------------------------------------------------------ controller
class DensityController:
    """Gathers gradient statistics every step and applies densify/prune/reset on the schedule.

    Call ``after_step(iteration, info, width, height)`` after each optimiser step with the
    rasterizer's info (``info["means2d"].grad`` must have been filled by backward).
    """

    def __init__(self, avatar, optimizer: torch.optim.Optimizer | None, config: DensityConfig, iters: int,
                 seed: int = 0):
        self.avatar = avatar
        self.optimizer = optimizer
        self.config = config
        self.schedule = config.schedule(iters)
        self.generator = torch.Generator(device=avatar.means.device).manual_seed(seed)
        self._zero_stats()

    def use_capacity(self) -> None:
        """Put the avatar's Gaussians into capacity buffers (:func:`use_capacity`; the cap's rows where
        there is one), the statistics with them."""
        n = self.avatar.num_gaussians
        use_capacity(self.avatar, self.optimizer, self.config.max_gaussians)
        self._set_stats(self.grad_accum[:n], self.count[:n])

    def _set_stats(self, grad_accum: torch.Tensor, count: torch.Tensor) -> None:
        """The statistics [N] of the live Gaussians, with zero rows for the unused rows of capacity buffers."""
        pad = self.avatar.capacity - grad_accum.shape[0]
        self.grad_accum, self.count = (torch.cat((t, t.new_zeros(pad))) for t in (grad_accum, count))

    def _zero_stats(self) -> None:
        n, dev = self.avatar.capacity, self.avatar.means.device  # a row per Gaussian, unused ones included
        self.grad_accum = torch.zeros(n, device=dev)
        self.count = torch.zeros(n, device=dev)

    def accumulate(self, info: dict, width: int, height: int, valid: torch.Tensor | None = None) -> None:
        """Add this step's view-space gradient norms of the visible Gaussians. ``valid``: a bool tensor,
        False for a step that was skipped (non-finite): it adds nothing (decided on the device)."""
        m2d = info["means2d"]
        grad = m2d.grad if m2d.grad is not None else None
        if grad is None:
            return
        if grad.shape[0] != self.grad_accum.shape[0]:
            raise ValueError(
                f"means2d has {grad.shape[0]} rows but the avatar has {self.grad_accum.shape[0]} Gaussians"
            )
        visible = info.get("visible")
        if visible is None:
            visible = info["radii"] > 0
        dtype, dev = self.grad_accum.dtype, self.grad_accum.device
        # |(gx W/2, gy H/2)| = H/2 |(gx W/H, gy)|: the H/2 rides on the accumulation, and a square image
        # needs no scaling pass at all.
        g = grad.detach().to(dtype)
        if width != height:
            g = g * constant((width / height, 1.0), dtype, dev)
        norm = torch.linalg.vector_norm(g, dim=-1)
        vis = visible.to(dev)
        if valid is not None:
            vis = vis & valid
        # (a 0-d constant, not 0.0: a Python scalar becomes a new tensor every step)
        self.grad_accum.add_(torch.where(vis, norm, constant(0.0, dtype, dev)), alpha=height / 2.0)
        self.count += vis  # a bool adds as 0 / 1

    def grad_average(self) -> torch.Tensor:
        return self.grad_accum / self.count.clamp_min(1.0)

    def after_step(self, iteration: int, info: dict, width: int, height: int,
                   valid: torch.Tensor | None = None) -> dict:
        """Returns what happened: {"cloned", "split", "pruned", "reset"} (only the keys that apply).
        ``valid``: see :meth:`accumulate`. Densifying and pruning read counts on the host (syncs);
        gathering statistics does not."""
        out: dict = {}
        if not self.config.enabled:
            return out
        if self.schedule.gather_at(iteration):
            self.accumulate(info, width, height, valid)
        if self.schedule.densify_at(iteration):
            out.update(self.densify_and_prune())
        if self.schedule.reset_at(iteration):
            reset_opacity(self.avatar, self.optimizer, self.config.reset_opacity_to)
            out["reset"] = True
        return out

    def densify_and_prune(self) -> dict:
        c = self.config
        cloned, split = densify(
            self.avatar, self.optimizer, self.grad_average(), c.grad_threshold, c.percent_dense,
            max_gaussians=c.max_gaussians, generator=self.generator,
        )
        pruned = prune(self.avatar, self.optimizer, c.prune_opacity)
        self._zero_stats()
        return {"cloned": cloned, "split": split, "pruned": pruned}

    def state_dict(self) -> dict:
        """The statistics of the live Gaussians (as without capacity buffers) and the generator's state."""
        n = self.avatar.num_gaussians
        return {"grad_accum": self.grad_accum[:n].clone(), "count": self.count[:n].clone(),
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        n = self.avatar.num_gaussians
        if state["grad_accum"].shape != (n,):
            raise ValueError(f"density state is for {state['grad_accum'].shape[0]} Gaussians, the avatar has {n}")
        self._set_stats(*(state[k].to(self.avatar.means.device) for k in ("grad_accum", "count")))
        self.generator.set_state(state["generator"])
