"""Which reader opens a dataset: ``load_dataset(spec)`` and the spec grammar ``[KIND:]PATH[?key=value&...]``.

The kind is named in the spec or detected from the folder's layout; each reader module turns its
layout into a :class:`rmavatar.data.dataset.Dataset`.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from rmavatar.data.dataset import Dataset
from rmavatar.utils import UserError

KINDS = ("native", "peoplesnapshot", "zju")


def parse_spec(spec: str) -> tuple[str | None, Path, dict[str, str]]:
    """``[kind:]PATH[?key=value&...]`` -> (kind or None, path, options)."""
    spec = str(spec)
    kind = None
    head, sep, rest = spec.partition(":")
    if sep and head in KINDS:
        kind, spec = head, rest
    options: dict[str, str] = {}
    if "?" in spec:
        path_part, _, query = spec.rpartition("?")
        pairs = [q.partition("=") for q in query.split("&")]
        if all(p[1] and p[0] for p in pairs):
            options = {k: v for k, _, v in pairs}
            spec = path_part
    return kind, Path(spec).expanduser(), options


def normalize_spec(spec: str | Path) -> str:
    """The dataset spec with its path made absolute and resolved (``DATA/``, ``./DATA`` and a link to it
    all become the same string), its kind and options kept: a run remembers its data from any folder."""
    kind, path, options = parse_spec(str(spec))
    query = "&".join(f"{k}={v}" for k, v in options.items())
    return f"{kind + ':' if kind else ''}{path.resolve()}{'?' + query if query else ''}"


def same_dataset(a: str | Path | None, b: str | Path | None) -> bool:
    """True when the specs ``a`` and ``b`` name the same dataset: the same resolved path, the same kind
    (a missing kind is the one the folder's layout gives) and the same options in any order. Paths are
    never compared as strings (``DATA/`` is ``DATA``)."""
    if a is None or b is None:
        return False

    def key(spec):
        kind, path, options = parse_spec(str(spec))
        path = path.resolve()
        if kind is None:
            with contextlib.suppress(UserError, OSError):
                kind = detect_kind(path)
        return kind, path, sorted(options.items())

    return key(a) == key(b)


def detect_kind(path: Path) -> str:
    """The source kind from the folder's layout."""
    if (path / "meta.yaml").is_file():
        return "native"
    if (path / "annots.npy").is_file():
        return "zju"
    if (path / "cameras.npz").is_file() and ((path / "poses").is_dir() or (path / "poses.npz").is_file()):
        return "peoplesnapshot"
    inside = sorted(p.name for p in path.iterdir() if p.is_dir() and any(
        (p / f).is_file() for f in ("meta.yaml", "annots.npy", "cameras.npz")))
    hint = f"; it holds datasets: {', '.join(inside[:8])} (give one of those folders)" if inside else ""
    raise UserError(
        f"{path} is not a dataset rmavatar recognises: expected meta.yaml (native format), annots.npy "
        f"(ZJU-MoCap) or cameras.npz with poses/ (PeopleSnapshot, InstantAvatar layout); "
        f"or name the kind as KIND:PATH with KIND one of {', '.join(KINDS)}{hint}")


def load_dataset(spec: str | Path, size=None, *, cache_mb: float = 1024.0, **options) -> Dataset:
    """Open a dataset.

    spec: ``PATH`` (the kind is detected from the layout) or ``KIND:PATH`` with KIND one of native,
    peoplesnapshot, zju; options may follow as ``?key=value&...`` (ZJU: ``camera=N`` 0-based,
    ``mask=union|mask|cihp``, ``body=SPEC``). size: None (source resolution), an int (the longer side)
    or (width, height). cache_mb bounds the decoded-image cache. Keyword options override those in spec.
    """
    kind, path, spec_options = parse_spec(str(spec))
    spec_options.update({k: v for k, v in options.items() if v is not None})
    if not path.exists():
        raise UserError(f"dataset folder {path} does not exist")
    if not path.is_dir():
        raise UserError(f"dataset {path} is not a folder")
    kind = kind or detect_kind(path)
    if kind == "native":
        from rmavatar.data.native import open_native as opener
    elif kind == "peoplesnapshot":
        from rmavatar.data.peoplesnapshot import open_peoplesnapshot as opener
    else:
        from rmavatar.data.zju import open_zju as opener
    ds = opener(path, size=size, cache_mb=cache_mb, **spec_options)
    from rmavatar.data.checks import check_cameras, check_params

    # Cheap (no pixels): a zero focal length or a NaN pose is an error here, not a crash in a render.
    check_cameras(ds)
    check_params(ds)
    return ds
