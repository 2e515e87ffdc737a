"""Import numba with its on-disk cache in the rmavatar cache folder, so later processes start fast.

A user's own ``NUMBA_CACHE_DIR`` is respected. Import numba through this module only.
"""

from __future__ import annotations

import os
import sys

from rmavatar.utils import cache_dir


def _configure_cache() -> None:
    if os.environ.get("NUMBA_CACHE_DIR"):
        return
    path = str(cache_dir("numba"))
    if "numba" in sys.modules:  # imported earlier by someone else: set the live config instead
        import numba.core.config as config

        if not config.CACHE_DIR:
            config.CACHE_DIR = path
    else:
        os.environ["NUMBA_CACHE_DIR"] = path


_configure_cache()

import numba  # noqa: E402

__all__ = ["numba"]
