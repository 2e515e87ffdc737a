"""A function of tensors replayed as a CUDA graph: one launch instead of hundreds.

Posing a trained avatar for a frame (body model, mesh embedding, rectifier) is hundreds of small kernels
whose launches, not their work, bound a frame's time on a GPU. :class:`Replay` captures such a function
once per input signature (shapes, dtypes, device) and then replays it: the inputs are copied into the
graph's input buffers, the graph runs, and its output buffers are returned (overwritten by the next
call: copy what you keep). Without CUDA it simply calls the function: one code path on every device.
"""

from __future__ import annotations

import contextlib
import gc
import sys
from typing import Callable, Iterator

WARMUP = 2  # eager runs on a side stream before capturing (lazy initialisation stays out of the graph)


@contextlib.contextmanager
def no_collection() -> Iterator[None]:
    """Around a capture: collect the garbage first, then no cyclic collection until it ends.

    A graphed callable's autograd function is a class made per capture, so a replaced graph lives in
    reference cycles; if the collector frees it in the middle of a capture, destroying that CUDA graph is
    an operation a capturing stream does not permit and the new capture is invalidated. Collected here,
    old graphs are destroyed before capturing starts."""
    gc.collect()
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def capture_failure(exc: BaseException) -> str:
    """Why a capture failed, in one line: the error, and the one it happened during (ending a broken
    capture raises again, hiding the first error in ``__context__``)."""
    return "; during: ".join(f"{type(e).__name__}: {(str(e).splitlines() or [''])[0]}"
                             for e in (exc, exc.__context__) if e is not None)


class Replay:
    """``fn(*tensors) -> tuple of tensors``, run without autograd; on CUDA inputs replayed as a CUDA graph.

    ``fn`` must only do tensor operations on the device (no host reads, no new host-made tensors after
    its first calls), and read nothing that changes between calls except its inputs (or buffers it
    updates in place). ``enabled=False`` or a failed capture: plain calls (``off_reason`` says why).
    ``captures`` counts the graphs made."""

    def __init__(self, fn: Callable, enabled: bool = True):
        self.fn, self.enabled = fn, enabled
        self.off_reason: str | None = None if enabled else "off"
        self.captures = 0
        self._key = self._graph = self._inputs = self._outputs = None

    def __call__(self, *inputs):
        import torch

        with torch.no_grad():
            if not (self.enabled and inputs and inputs[0].device.type == "cuda"):
                return tuple(self.fn(*inputs))
            key = tuple((tuple(t.shape), t.dtype, t.device) for t in inputs)
            if key != self._key and not self._capture(key, inputs):
                return tuple(self.fn(*inputs))
            for buf, t in zip(self._inputs, inputs):
                buf.copy_(t)
            self._graph.replay()
            return self._outputs

    def _capture(self, key, inputs) -> bool:
        import torch

        self._key = self._graph = self._inputs = self._outputs = None  # free the old graph first
        static = tuple(t.clone() for t in inputs)
        try:
            with no_collection():
                side = torch.cuda.Stream()
                side.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(side):
                    for _ in range(WARMUP):
                        self.fn(*static)
                torch.cuda.current_stream().wait_stream(side)
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph):
                    outputs = tuple(self.fn(*static))
        except Exception as exc:  # noqa: BLE001 - any failure to capture: plain calls from now on
            self.enabled, self.off_reason = False, capture_failure(exc)
            print(f"CUDA graph off (running without it): {self.off_reason}", file=sys.stderr, flush=True)
            torch.cuda.synchronize()
            return False
        self._key, self._graph, self._inputs, self._outputs = key, graph, static, outputs
        self.captures += 1
        return True
