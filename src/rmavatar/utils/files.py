"""Files: the user cache folder, output-folder checks and atomic writes (a kill never leaves a half-written file)."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
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


# Every temporary file or folder rmavatar makes beside an output starts with this prefix, then the host and
# process that made it: a later run removes those whose process is gone (a SIGKILL leaves them behind).
TMP_PREFIX = ".rmavatar-tmp."
_TMP_RE = re.compile(r"^\.rmavatar-tmp\.([A-Za-z0-9_-]+)\.(\d+)\.")


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname().split(".")[0]) or "host"


def tmp_prefix(name: str) -> str:
    """The prefix of this process's temporaries for an output called ``name``."""
    return f"{TMP_PREFIX}{_host()}.{os.getpid()}.{name}."


def is_temporary(name: str) -> bool:
    """True for the name of a temporary file or folder that rmavatar makes beside its outputs."""
    return name.startswith(TMP_PREFIX)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


def sweep_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporaries in ``folder`` left by killed rmavatar processes of this host; returns them.

    A temporary of a process that still runs (this one included) or of another host is kept."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    host = _host()
    for entry in entries:
        m = _TMP_RE.match(entry.name)
        if not m or m.group(1) != host or int(m.group(2)) == os.getpid() or _alive(int(m.group(2))):
            continue
        with contextlib.suppress(OSError):
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def nearest_existing(path: Path) -> Path:
    """``path`` or its closest ancestor that exists."""
    path = Path(os.path.abspath(path))
    while not os.path.lexists(path) and path != path.parent:
        path = path.parent
    return path


def check_writable_folder(path: str | os.PathLike, label: str | None = None, *, create: bool = False) -> Path:
    """Raise UserError unless a file can be created at ``path``; returns its folder.

    The folder must exist, unless ``create`` (then its nearest existing ancestor must be a folder in which
    folders can be made). Writability is proven by making (and removing) a temporary folder there: permission
    bits lie to root and about read-only or pseudo file systems such as /proc. ``label`` (e.g. "--json x.json")
    names the output in the message; default: the path itself."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    what = label or str(path)
    base = nearest_existing(parent)
    if not base.is_dir():
        raise UserError(f"cannot write {what}: {base} is not a folder")
    if base != Path(os.path.abspath(parent)) and not create:
        raise UserError(f"cannot write {what}: folder {parent} does not exist")
    try:
        probe = tempfile.mkdtemp(prefix=tmp_prefix("probe"), dir=base)
        os.rmdir(probe)
    except OSError as exc:
        raise UserError(f"cannot write {what}: folder {base} is not writable ({exc.strerror or exc})") from None
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
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        check_writable_folder(path)  # the error that names the missing or non-folder parent
    sweep_temporaries(parent)
    try:
        fd, tmp = tempfile.mkstemp(prefix=tmp_prefix(path.stem), suffix=".tmp" + path.suffix, dir=parent)
    except OSError as exc:
        raise UserError(f"cannot write {path}: folder {parent} is not writable ({exc.strerror or exc})") from None
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
def atomic_dir(path: str | os.PathLike, *, replace: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it becomes ``path``.

    An existing non-empty ``path`` is replaced only with ``replace`` (the caller has proven it owns every
    file there: see :func:`rmavatar.utils.outputs.output_folder`); otherwise it is an error, before the
    block runs. On any exception the temporary folder is deleted and ``path`` is left as it was.
    """
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if os.path.lexists(path) and not replace and (not path.is_dir() or any(path.iterdir())):
        raise UserError(f"{path} exists and is not empty: refusing to replace it")
    check_writable_folder(path, create=True)
    parent.mkdir(parents=True, exist_ok=True)
    sweep_temporaries(parent)
    tmp = Path(tempfile.mkdtemp(prefix=tmp_prefix(path.name), suffix=".tmp", dir=parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes the folder private (0700)
        if path.is_dir() and not path.is_symlink():
            # Swap by renames, then delete the old copy: a kill in between leaves a temporary, never a gap.
            old = Path(tempfile.mkdtemp(prefix=tmp_prefix(path.name), suffix=".old", dir=parent))
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
