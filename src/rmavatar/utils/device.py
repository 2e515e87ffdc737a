"""Picking the torch device; constants and scalar buffers read without a host sync per step."""

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


def host_scalar(owner, name: str, cast=float):
    """The 0-d buffer ``owner.<name>`` as a Python number, read from the device (a host sync) only when
    the buffer changed since the last read (its identity or in-place version), not on every step."""
    buf = getattr(owner, name)
    cache = owner.__dict__.setdefault("_host_scalars", {})
    cached = cache.get(name)
    if cached is None or cached[0] is not buf or cached[1] != buf._version:
        cached = cache[name] = (buf, buf._version, cast(buf))
    return cached[2]


def set_host_scalar(owner, name: str, value, cast=float) -> None:
    """Fill the 0-d buffer ``owner.<name>`` with ``value`` unless it already holds it (no write, no
    sync), keeping :func:`host_scalar`'s copy current."""
    value = cast(value)
    if host_scalar(owner, name, cast) != value:
        buf = getattr(owner, name)
        buf.fill_(value)
        owner.__dict__["_host_scalars"][name] = (buf, buf._version, value)


def set_threads(n: int) -> None:
    """Use ``n`` CPU threads in torch and in the Numba rasterizer kernels."""
    import numba
    import torch

    torch.set_num_threads(n)
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


def keep_freed_memory() -> None:
    """Let glibc keep freed heap memory for reuse instead of returning it to the OS.

    A CPU step allocates and frees tens of MB of tensors; by default glibc serves the large ones with
    fresh mmaps and trims the heap after frees, so every step pays page faults that zero the memory
    again (docs/train.md has the measurement). No-op where glibc's mallopt is not available.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    mallopt(M_MMAP_THRESHOLD, 32 * 2**20)  # glibc's largest allowed value on 64-bit
    mallopt(M_TRIM_THRESHOLD, 2**31 - 1)
    mallopt(M_TOP_PAD, 256 * 2**20)
