"""Many avatars at once: ``rmavatar batch`` (JOBS.yaml -> Ray tasks -> results tables) and the paper's
tables in one command (``rmavatar reproduce paper``).

Ray is optional (``pip install 'rmavatar[cluster]'``); only the driver imports it, lazily.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Job": "rmavatar.batch.jobs",
    "load_jobs": "rmavatar.batch.jobs",
    "parse_jobs": "rmavatar.batch.jobs",
    "BatchOptions": "rmavatar.batch.driver",
    "run_batch": "rmavatar.batch.driver",
    "write_results": "rmavatar.batch.results",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'rmavatar.batch' has no attribute {name!r}")
