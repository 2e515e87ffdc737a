"""Files: the user cache folder, output-folder checks and atomic writes (a kill never leaves a half-written file)."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Any, Iterator

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


# ----------------------------------------------------------------------------------------- the user's text files
# Byte-order marks that say a file is not UTF-8 (UTF-32 first: its little-endian mark starts with UTF-16's).
_BOMS = ((b"\xff\xfe\x00\x00", "UTF-32 (little-endian)"), (b"\x00\x00\xfe\xff", "UTF-32 (big-endian)"),
         (b"\xff\xfe", "UTF-16 (little-endian)"), (b"\xfe\xff", "UTF-16 (big-endian)"))


def _encoding_hint(data: bytes) -> str | None:
    """What a file that is not UTF-8 looks like, from its byte-order mark or NUL bytes; None if unknown."""
    for bom, name in _BOMS:
        if data.startswith(bom):
            return name
    head = data[:4096]
    if head and head.count(0) * 4 >= len(head):  # ASCII text as UTF-16: every other byte is NUL
        odd, even = head[1::2].count(0), head[0::2].count(0)
        if odd > 3 * max(even, 1) or even > 3 * max(odd, 1):
            return "UTF-16 (no byte-order mark)"
    return None


def read_text_file(path: str | os.PathLike, what: str = "file") -> str:
    """The text of a user's file (a config, a jobs file, meta.yaml) decoded as UTF-8; a UTF-8 byte-order
    mark is accepted and dropped. A missing file, a folder, an unreadable file and one that is not UTF-8
    text (UTF-16 or UTF-32 as saved by some Windows editors, a binary file) are a UserError that starts
    with ``what`` and the path, e.g. "jobs file x.yaml is UTF-16 (little-endian) text: save it as UTF-8"."""
    path = Path(path)
    name = f"{what} {path}"
    if path.is_dir():
        raise UserError(f"{name} is a folder, not a file")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise UserError(f"{name} does not exist") from None
    except OSError as exc:
        raise UserError(f"cannot read {name}: {exc.strerror or exc}") from None
    hint = _encoding_hint(data)
    if hint:
        raise UserError(f"{name} is {hint} text, not UTF-8: save it as UTF-8")
    if b"\x00" in data[:4096]:
        raise UserError(f"{name} is not a text file (it holds binary data, starting {data[:8]!r})")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise UserError(f"{name} is not UTF-8 text (byte 0x{data[exc.start]:02x} on line {line} cannot be "
                        f"decoded; it may be Latin-1 or another legacy encoding): save it as UTF-8") from None


def _yaml_loader():
    """PyYAML's safe loader, refusing a key that a mapping gives twice (the first value would be lost)."""
    import yaml

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen: dict = {}
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    try:
                        first = seen.setdefault(key, key_node.start_mark)
                    except TypeError:  # an unhashable key: PyYAML's own error follows
                        continue
                    if first is not key_node.start_mark:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"the key {key!r} is given twice (first on line {first.line + 1})",
                            key_node.start_mark)
            return super().construct_mapping(node, deep=deep)

    return Loader


def _yaml_problem(exc: Exception, text: str) -> str:
    """A PyYAML error as one line: where (line, column) and what."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    parts = [p for p in (getattr(exc, "context", None), getattr(exc, "problem", None)) if p]
    what = ", ".join(parts) if parts else str(exc).strip().splitlines()[0]
    if mark is not None:
        return f"line {mark.line + 1}, column {mark.column + 1}: {what}"
    position = getattr(exc, "position", None)
    if isinstance(position, int) and getattr(exc, "reason", None):  # a ReaderError: a control character
        char = text[position] if position < len(text) else ""
        line = text[:position].count("\n") + 1
        column = position - (text.rfind("\n", 0, position) + 1) + 1
        return f"line {line}, column {column}: the character U+{ord(char or chr(0)):04X} is not allowed ({exc.reason})"
    return what


def read_yaml_file(path: str | os.PathLike, what: str = "file", *, mapping: bool = True) -> Any:
    """A user's YAML file, read with :func:`read_text_file`; every problem is a UserError naming ``what``
    and the path: invalid YAML (with the line and column), a key given twice in one mapping, and, with
    ``mapping``, a top level that is not a mapping (an empty file is an empty mapping)."""
    import yaml

    text = read_text_file(path, what)
    try:
        data = yaml.load(text, Loader=_yaml_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise UserError(f"{what} {path} is not valid YAML: {_yaml_problem(exc, text)}") from None
    except RecursionError:
        raise UserError(f"{what} {path} is not valid YAML: it nests too deeply") from None
    if mapping:
        if data is None:
            return {}
        if not isinstance(data, dict):
            raise UserError(f"{what} {path}: expected a mapping (key: value lines) at the top level, "
                            f"got {_kind(data)}")
    return data


def _kind(value: Any) -> str:
    """'a list', 'a string', ... for messages."""
    if isinstance(value, bool):
        return f"true/false ({value!r})"
    names = {list: "a list", str: "a string", int: "an integer", float: "a number", dict: "a mapping"}
    for tp, name in names.items():
        if isinstance(value, tp):
            if isinstance(value, (list, dict)):
                return name
            text = repr(value)
            return f"{name} ({text[:60]}...)" if len(text) > 60 else f"{name} ({text})"
    return type(value).__name__
