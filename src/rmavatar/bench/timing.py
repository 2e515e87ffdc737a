"""Timing helpers shared by the benchmarks: a wall + CPU clock, median-of-repeats, machine facts."""

from __future__ import annotations

import os
import platform
import statistics
import time


class Clock:
    """Wall and process-CPU seconds of a block (CPU time sums all threads: less sensitive to other load).

    ``sync`` runs before the clock starts and before it stops (``torch.cuda.synchronize`` for GPU work).
    """

    def __init__(self, sync=None):
        self.sync = sync or (lambda: None)
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def __enter__(self):
        self.sync()
        self._t, self._c = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc):
        self.sync()
        self.wall.append(time.perf_counter() - self._t)
        self.cpu.append(time.process_time() - self._c)
        return False

    def result(self) -> dict:
        """{"wall_s", "cpu_s"}: medians over the timed blocks."""
        return {"wall_s": statistics.median(self.wall), "cpu_s": statistics.median(self.cpu)}


def timed(fn, repeats: int, sync=None, warmup: int = 0) -> Clock:
    """Run ``fn()`` ``warmup`` times untimed, then ``repeats`` times timed; the Clock of the timed runs."""
    for _ in range(warmup):
        fn()
    clock = Clock(sync)
    for _ in range(repeats):
        with clock:
            fn()
    return clock


def median_time(fn, repeats: int, sync=None, warmup: int = 0) -> dict:
    """``timed(...).result()``: the medians of ``repeats`` timed runs of ``fn()`` after ``warmup`` untimed."""
    return timed(fn, repeats, sync, warmup).result()


def machine_info() -> dict:
    """CPU count, platform, library versions and thread settings of this process, load average now."""
    import torch

    from rmavatar.render._numba import numba

    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numba": numba.__version__,
        "torch_threads": torch.get_num_threads(),
        "numba_threads": numba.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "load_average": list(os.getloadavg()),
    }
