"""Import numba with its on-disk cache in the rmavatar cache folder, so later processes start fast.

A user's own ``NUMBA_CACHE_DIR`` is respected. Import numba through this module only.
"""

from __future__ import annotations

import os
import sys

from rmavatar.utils import cache_dir

if not os.environ.get("NUMBA_CACHE_DIR"):
    _dir = str(cache_dir("numba"))
    if "numba" in sys.modules:  # imported earlier by someone else: set the live config instead
        import numba.core.config as _config

        if not _config.CACHE_DIR:
            _config.CACHE_DIR = _dir
    else:
        os.environ["NUMBA_CACHE_DIR"] = _dir

import numba  # noqa: E402

__all__ = ["numba"]
