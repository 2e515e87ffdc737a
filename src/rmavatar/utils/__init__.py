"""The ground floor: errors, files (atomic writes, the cache folder), the torch device, typed configs."""

from rmavatar.utils.device import resolve_device
from rmavatar.utils.errors import UserError
from rmavatar.utils.files import (
    TMP_PREFIX,
    atomic_dir,
    atomic_path,
    cache_dir,
    check_writable_folder,
)

__all__ = ["TMP_PREFIX", "UserError", "atomic_dir", "atomic_path", "cache_dir", "check_writable_folder", "resolve_device"]
