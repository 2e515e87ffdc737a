"""Files: the user cache folder, output-folder checks and atomic writes (a kill never leaves a half-written file)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from rmavatar.utils.errors import UserError


def cache_dir(*parts: str) -> Path:
    """The rmavatar cache folder (created on demand).

    ``$RMAVATAR_CACHE`` wins, then ``$XDG_CACHE_HOME/rmavatar``, then ``~/.cache/rmavatar``.
    """
    root = os.environ.get("RMAVATAR_CACHE")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(xdg, "rmavatar")
    path = Path(root, *parts)
    path.mkdir(parents=True, exist_ok=True)
    return path


def check_writable_folder(path: str | os.PathLike, label: str | None = None) -> Path:
    """Raise UserError unless the folder that will hold ``path`` exists and is writable; returns it.

    ``label`` (e.g. "--json x.json") names the output in the message; default: the path itself."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    what = label or str(path)
    if not parent.is_dir():
        raise UserError(f"cannot write {what}: folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"cannot write {what}: folder {parent} is not writable")
    return parent


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    On any exception the temporary file is removed, so ``path`` is never half-written.
    The temporary name keeps ``path``'s suffix, since writers such as imageio pick the format from it.
    """
    path = Path(path)
    parent = check_writable_folder(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + path.suffix, dir=parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():  # mkstemp makes the file private (0600); give it the usual umask mode
            os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path``.

    On any exception the temporary folder is deleted and ``path`` is left as it was.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes the folder private (0700)
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
