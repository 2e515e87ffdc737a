"""Count the tensor operations and host synchronisations of a block of PyTorch code.

On a GPU each tensor operation is (about) one kernel launch, and a host synchronisation stalls the
CPU until the GPU has caught up; both are what keeps a GPU idle during small training steps. They can
be counted on any machine, so they serve as a device-independent proxy for GPU step time.

``OpCounter`` is a ``TorchDispatchMode``: it sees every ATen operation that reaches the dispatcher
below autograd, forward and backward (the autograd engine's calls included).

- operations: every ATen call except views and pure metadata changes (``view``, ``t``, ``detach``,
  ``expand``, ...), which launch no kernel. The profiler's own annotations (``profiler::`` calls that
  ``torch.optim`` makes around each ``step()``) are not tensor operations and are not counted at all.
- syncs: the calls that make the host wait for the device on CUDA: reading a value on the host
  (``_local_scalar_dense``: ``.item()``, ``float(t)``, ``bool(t)``, ``if t:``), operations whose output
  size depends on the data (``nonzero``, ``masked_select``, boolean-mask indexing, ``unique``,
  ``repeat_interleave`` without ``output_size``), and copies from a GPU to the CPU (``.cpu()``,
  ``.tolist()``, ``.numpy()`` after ``.cpu()``). A ``.cpu()``/``.numpy()`` of a tensor already on the
  CPU dispatches nothing and is not seen: on the CPU the count covers the first two kinds.

Work done outside PyTorch (the CPU rasterizer's Numba kernels) is neither an operation nor a sync.
"""

from __future__ import annotations

from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

_aten = torch.ops.aten
# Output size depends on the values: the host must read a count from the device.
_DATA_DEPENDENT = {
    _aten.nonzero.default, _aten.masked_select.default, _aten.unique_dim.default, _aten._unique2.default,
    _aten._unique.default, _aten.unique_consecutive.default,
}
_METADATA = {_aten.detach.default, _aten.alias.default, _aten._unsafe_view.default, _aten.lift_fresh.default,
             _aten.set_.source_Storage_storage_offset, _aten.as_strided.default, _aten.resize_.default}


def _is_bool_mask_index(func, args) -> bool:
    if func not in (_aten.index.Tensor, _aten.index_put.default, _aten.index_put_.default,
                    _aten._index_put_impl_.default):
        return False
    indices = args[1] if len(args) > 1 else ()
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices if i is not None)


def _is_sync(func, args, kwargs) -> bool:
    if func is _aten._local_scalar_dense.default or func in _DATA_DEPENDENT:
        return True
    if func is _aten.repeat_interleave.Tensor and kwargs.get("output_size") is None:
        return True
    if _is_bool_mask_index(func, args):
        return True
    if func in (_aten._to_copy.default, _aten.copy_.default):
        src = args[1] if func is _aten.copy_.default else args[0]
        dst_cpu = (args[0].device.type == "cpu") if func is _aten.copy_.default else (
            kwargs.get("device") is not None and torch.device(kwargs["device"]).type == "cpu")
        return isinstance(src, torch.Tensor) and src.device.type != "cpu" and dst_cpu
    return False


class OpCounter(TorchDispatchMode):
    """``with OpCounter() as c: ...`` then ``c.ops``, ``c.syncs``, ``c.views`` and ``c.by_name`` /
    ``c.syncs_by_name`` (Counter of ATen op names)."""

    def __init__(self):
        super().__init__()
        self.ops = 0
        self.views = 0
        self.syncs = 0
        self.by_name: Counter = Counter()
        self.syncs_by_name: Counter = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func.namespace == "profiler":
            return func(*args, **kwargs)
        name = func.name()
        if getattr(func, "is_view", False) or func in _METADATA:
            self.views += 1
        else:
            self.ops += 1
            self.by_name[name] += 1
        if _is_sync(func, args, kwargs):
            self.syncs += 1
            self.syncs_by_name[name] += 1
        return func(*args, **kwargs)

    def summary(self, steps: int, top: int = 8) -> dict:
        """Per-step averages over ``steps`` and the most frequent operations / syncs (totals)."""
        steps = max(steps, 1)
        return {
            "ops_per_step": self.ops / steps,
            "syncs_per_step": self.syncs / steps,
            "views_per_step": self.views / steps,
            "top_ops": dict(self.by_name.most_common(top)),
            "syncs_by_op": dict(self.syncs_by_name),
        }
