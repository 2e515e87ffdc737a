"""The output-safety rule, in one place: a command replaces only what it made itself.

Folders (a dataset, an eval images folder, a frames folder, a demo folder) carry a marker file,
``.rmavatar``, naming the kind of output, the command and version that wrote it and every file it wrote.
A folder is replaced only when it is absent, empty, or holds that marker of the same kind and nothing
the marker does not list; anything else is refused with an error naming the path. ``--overwrite`` writes
into such a folder anyway, but still deletes no file it did not write and refuses to replace one.

Single files (a JSON, PNG, PLY or MP4 the user names) cannot carry a marker in every format, so the proof
is kept beside the user's cache: a registry of the files rmavatar wrote with their SHA-256. An existing
file is replaced only when its content is still what rmavatar wrote there, or with ``--overwrite``.
Copying a file elsewhere or editing it loses the proof, which errs on the side of refusing.

Run folders keep their own marker (``rmavatar-run.json``, see :mod:`rmavatar.avatar.run`): training
never deletes anything in them, it only refuses folders that are not its runs. Batch folders (``rmavatar
batch`` / ``reproduce --out``) likewise keep their own marker (see :mod:`rmavatar.batch.driver`): a
non-empty folder without it is refused; inside one, the tables and jobs.yaml are single files under this
rule (``rmavatar.batch.results.RootFiles``) and each job's folder carries a marker of kind ``batch-job``.
Every command's output options are walked by tests/test_outputs_walk.py, which puts a user's file where
each output goes and checks it is kept.
"""

from __future__ import annotations

import contextlib
import fnmatch
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterable, Iterator

from rmavatar.utils.errors import UserError
from rmavatar.utils.files import (
    atomic_dir,
    atomic_path,
    cache_dir,
    check_writable_folder,
    is_temporary,
    sweep_temporaries,
    tmp_prefix,
)

MARKER = ".rmavatar"
FORMAT = "rmavatar-output"
OVERWRITE_HELP = ("replace an existing output that rmavatar cannot prove it wrote (files it did not write "
                  "are never deleted)")

# The command line being run ("rmavatar eval"), recorded in markers; set by rmavatar.commands.main.
command_name = "rmavatar (library)"


def add_overwrite_argument(parser) -> None:
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


# ----------------------------------------------------------------------------------------------- folders
def read_marker(folder: str | os.PathLike) -> dict | None:
    """The ``.rmavatar`` marker of ``folder``, or None when it has none (or an unreadable one)."""
    try:
        doc = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("files"), list):
        return None
    return doc


def _entries(folder: Path) -> list[str]:
    """Every file, link and folder under ``folder`` as a relative POSIX path (links are not followed)."""
    out = []
    for root, dirs, files in os.walk(folder):
        rel = Path(root).relative_to(folder)
        for name in dirs + files:
            out.append((rel / name).as_posix())
    return sorted(out)


def _owned(marker: dict | None) -> set[str]:
    """The marker's files, its folders (ancestors of its files) and the marker itself. An entry ending in
    '/' (a folder written in place, e.g. a demo's run/) owns everything below it: see ``_is_owned``."""
    if marker is None:
        return set()
    owned = {MARKER}
    for f in marker["files"]:
        parts = Path(f).parts
        owned.update(Path(*parts[: i + 1]).as_posix() for i in range(len(parts)))
        if f.endswith("/"):
            owned.add(f)
    return owned


def _is_owned(entry: str, owned: set[str]) -> bool:
    parts = entry.split("/")
    return entry in owned or any("/".join(parts[:i]) + "/" in owned for i in range(1, len(parts)))


def foreign_files(folder: str | os.PathLike, kind: str) -> list[str]:
    """Entries of ``folder`` that an output of ``kind`` did not write (empty when ``folder`` is absent)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    marker = read_marker(folder)
    owned = _owned(marker) if marker is not None and marker.get("kind") == kind else set()
    return [e for e in _entries(folder) if not _is_owned(e, owned) and not is_temporary(Path(e).name)]


def some_of(names: list[str], most: int = 3) -> str:
    """The first ``most`` of ``names`` for a message, and how many more: "a, b, c and 4 more"."""
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def _describe(kind: str, marker: dict | None) -> str:
    if marker is None:
        return f"no {MARKER} marker"
    if marker.get("kind") != kind:
        return f"its {MARKER} marker is from {marker.get('command', '?')} ({marker.get('kind')})"
    return "files rmavatar did not write"


def check_output_folder(path: str | os.PathLike, kind: str, *, option: str, overwrite: bool = False,
                        writes: Iterable[str] = ()) -> Path:
    """Raise UserError unless an output folder of ``kind`` may be written at ``path``; call it before any
    long work. ``writes``: glob patterns of the names it will write (checked against foreign files with
    ``overwrite``, which never replaces a file rmavatar did not write)."""
    path = Path(path)
    full = Path(os.path.abspath(path))
    if not full.name:
        raise UserError(f"{option} {path}: give a folder below the file system root")
    if Path.cwd() == full or full in Path.cwd().parents:
        raise UserError(f"{option} {path} is the current folder or holds it: give a new folder for the output")
    if os.path.lexists(path) and not path.is_dir():
        raise UserError(f"{option} {path} exists and is not a folder")
    check_writable_folder(path, f"{option} {path}", create=True)
    sweep_temporaries(path.parent if str(path.parent) else Path("."))
    foreign = foreign_files(path, kind)
    if not foreign:
        return path
    if not overwrite:
        raise UserError(
            f"{option} {path} holds files that rmavatar did not write there ({_describe(kind, read_marker(path))}: "
            f"{some_of(foreign)}): refusing to replace it; choose a new or empty folder, or pass --overwrite to write into "
            "it (files rmavatar did not write are kept, never replaced)")
    clash = [f for f in foreign if f == MARKER or any(fnmatch.fnmatch(Path(f).name, w) for w in writes)]
    if clash:
        raise UserError(f"{option} {path}: --overwrite would replace files rmavatar did not write "
                        f"({', '.join(clash[:3])}); move them away or choose another folder")
    return path


@contextlib.contextmanager
def output_folder(path: str | os.PathLike, kind: str, *, option: str = "output", overwrite: bool = False,
                  writes: Iterable[str] = ()) -> Iterator[Path]:
    """Yield a temporary folder; when the block ends cleanly its files become ``path``'s, with a marker.

    Without foreign files the old folder is swapped out whole (atomically, see ``atomic_dir``); with
    ``overwrite`` and foreign files, the earlier files of this kind are removed and the new ones moved in
    one by one, foreign files untouched."""
    path = Path(path)
    writes = tuple(writes)
    check_output_folder(path, kind, option=option, overwrite=overwrite, writes=writes)
    foreign = foreign_files(path, kind)
    path = Path(os.path.abspath(path))
    if not foreign:
        with atomic_dir(path, replace=True) as tmp:
            yield tmp
            _write_marker(tmp, kind, [e for e in _files(tmp)])
        return
    old = read_marker(path)
    old_files = set(old["files"]) if old is not None and old.get("kind") == kind else set()
    tmp = Path(tempfile.mkdtemp(prefix=tmp_prefix(path.name), suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        new_files = _files(tmp)
        clash = sorted(set(new_files) & set(foreign))
        if clash:
            raise UserError(f"{option} {path}: would replace files rmavatar did not write ({', '.join(clash[:3])}); "
                            "move them away or choose another folder")
        for f in sorted(old_files - set(new_files)):
            with contextlib.suppress(FileNotFoundError, IsADirectoryError, NotADirectoryError):
                (path / f).unlink()
        for f in new_files:
            (path / f).parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / f, path / f)
        _write_marker(path, kind, new_files)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _files(folder: Path) -> list[str]:
    return [e for e in _entries(folder) if not (folder / e).is_dir() or (folder / e).is_symlink()]


def _write_marker(folder: Path, kind: str, files: list[str]) -> None:
    from rmavatar import __version__

    doc = {"format": FORMAT, "kind": kind, "command": command_name, "version": __version__,
           "files": sorted(f for f in files if f != MARKER)}
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / MARKER) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")


def mark_folder(folder: str | os.PathLike, kind: str, files: Iterable[str]) -> None:
    """Write ``folder``'s marker for an output that is written in place (a demo folder), listing ``files``
    ('name/' owns a whole sub-folder); the files already listed there are kept in the list."""
    old = read_marker(folder)
    keep = old["files"] if old is not None and old.get("kind") == kind else []
    _write_marker(Path(folder), kind, sorted(set(keep) | set(files)))


# ----------------------------------------------------------------------------------------------- single files
def _registry() -> Path:
    return cache_dir() / "outputs.json"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _load_registry() -> dict:
    try:
        doc = json.loads(_registry().read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def wrote_file(path: str | os.PathLike) -> bool:
    """True when ``path`` holds exactly what rmavatar last wrote there."""
    path = Path(path)
    entry = _load_registry().get(str(path.resolve()))
    try:
        return isinstance(entry, dict) and entry.get("size") == path.stat().st_size \
            and entry.get("sha256") == _sha256(path)
    except OSError:
        return False


def _record(path: Path) -> None:
    """Add ``path`` to the registry; a registry that cannot be written only means a refusal later."""
    with contextlib.suppress(OSError, UserError):
        import fcntl

        lock = cache_dir() / "outputs.lock"
        with open(lock, "a") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            reg = {k: v for k, v in _load_registry().items() if os.path.lexists(k)}
            reg[str(path.resolve())] = {"size": path.stat().st_size, "sha256": _sha256(path),
                                        "command": command_name}
            with atomic_path(_registry()) as tmp:
                tmp.write_text(json.dumps(reg) + "\n")


def check_output_file(path: str | os.PathLike, *, option: str, overwrite: bool = False,
                      suffixes: tuple[str, ...] = ()) -> Path:
    """Raise UserError unless ``path`` may be written as a single-file output; call it before any long work.

    The folder must exist and be writable; an existing ``path`` must be a regular file that rmavatar wrote
    (or ``overwrite``); never a folder, a device or a link."""
    text = os.fspath(path)
    if text.endswith("/") or text.endswith(os.sep):  # Path() would drop the slash and write a file there
        raise UserError(f"{option} {text}: a name ending in '/' is a folder; give a file name (e.g. "
                        f"{text.rstrip('/' + os.sep) or 'out'})")
    path = Path(path)
    what = f"{option} {path}"
    if suffixes and path.suffix.lower() not in suffixes:
        raise UserError(f"{what}: the file name must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise UserError(f"{what} is a folder; give a file name")
    check_writable_folder(path, what)
    if os.path.lexists(path):
        if path.is_symlink() or not path.is_file():
            raise UserError(f"{what} exists and is not a regular file: refusing to replace it")
        if not overwrite and not wrote_file(path):
            raise UserError(f"{what} exists and rmavatar cannot prove it wrote it (it was made by something "
                            "else, or changed since): refusing to replace it; choose another name or pass "
                            "--overwrite")
    return path


@contextlib.contextmanager
def output_file(path: str | os.PathLike, *, option: str = "output", overwrite: bool = False,
                suffixes: tuple[str, ...] = ()) -> Iterator[Path]:
    """``atomic_path`` for a single-file output, checked by ``check_output_file`` and recorded after."""
    path = check_output_file(path, option=option, overwrite=overwrite, suffixes=suffixes)
    with atomic_path(path) as tmp:
        yield tmp
    _record(path)


def write_json(path: str | os.PathLike, doc, *, option: str = "--json", overwrite: bool = False) -> None:
    """``doc`` as indented JSON to a single-file output. A NaN or infinity (which JSON cannot hold and
    strict readers refuse) is a UserError naming the file, raised before anything is written."""
    try:
        text = json.dumps(doc, indent=2, allow_nan=False) + "\n"
    except ValueError as exc:
        raise UserError(f"{option} {path}: not written: the results hold a value that is not a finite number "
                        f"({exc})") from None
    with output_file(path, option=option, overwrite=overwrite) as tmp:
        tmp.write_text(text)
