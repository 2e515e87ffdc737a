"""Picking the torch device."""

from __future__ import annotations

import functools

from rmavatar.utils.errors import UserError


def resolve_device(name: str):
    """A torch.device from "auto" (CUDA when available), "cpu", "cuda" or "cuda:N"; UserError otherwise."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise UserError(f"device {name!r} is not a torch device (use auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"device {name!r} asked for, but this torch has no CUDA device")
    return dev


def constant(values, dtype, device):
    """``torch.tensor(values, dtype=dtype, device=device)`` made once per (values, dtype, device) and
    shared: steps that run thousands of times must not rebuild (or upload) their constants. ``values``
    must be hashable (nested tuples of numbers). Never modify the returned tensor in place."""
    import torch

    return _constant(values, dtype, torch.device(device))


@functools.lru_cache(maxsize=256)
def _constant(values, dtype, device):
    import torch

    return torch.tensor(values, dtype=dtype, device=device)
