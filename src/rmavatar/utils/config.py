"""Typed configs: nested dataclasses to and from plain dicts and YAML, with errors that name the key.

Every component's config is a dataclass next to the component; a run's config nests them. Reading
checks every value against its field's type (``true`` is not an integer, ``"1e-5"`` is a number) and
refuses unknown keys, so a typo in config.yaml is an error, not a silently ignored setting.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import types
import typing
from typing import Any

from rmavatar.utils.errors import UserError
from rmavatar.utils.files import atomic_path, read_yaml_file


def to_dict(cfg: Any) -> dict:
    """A config dataclass as plain nested dicts (YAML/pickle-safe)."""
    return dataclasses.asdict(cfg)


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Check/convert a YAML value against a dataclass field type; errors name the key."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        last = None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where)
            except UserError as exc:
                last = exc
        raise last or UserError(f"{where}: bad value {value!r}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise UserError(f"{where}: expected a mapping, got {value!r}")
        return from_dict(tp, value, where)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise UserError(f"{where}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise UserError(f"{where}: expected an integer, got {value!r}")
    if tp is float:
        number = None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number = float(value)
        elif isinstance(value, str):  # PyYAML reads "1e-5" (no dot) as a string
            with contextlib.suppress(ValueError):
                number = float(value)
        if number is None:
            raise UserError(f"{where}: expected a number, got {value!r}")
        if not math.isfinite(number):
            raise UserError(f"{where}: expected a finite number, got {value!r}")
        return number
    if tp is str:
        if isinstance(value, str):
            return value
        raise UserError(f"{where}: expected a string, got {value!r}")
    return value


def from_dict(cls: type, data: dict, where: str = "config") -> Any:
    """Build dataclass ``cls`` from nested dicts; missing keys keep their defaults, unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise UserError(f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    kwargs = {k: _coerce(v, hints[k], f"{where}.{k}") for k, v in data.items()}
    return cls(**kwargs)


def whole_number(value: Any, minimum: int) -> int | None:
    """``value`` as an int when it is a whole number >= ``minimum`` (an integral float counts, a bool
    does not) as a user writes one in a YAML file; None otherwise (the caller names what was expected)."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        return None
    return value


def check_fields(cfg: Any, section: str, *, positive: tuple[str, ...] = (), nonnegative: tuple[str, ...] = (),
                 at_least_one: tuple[str, ...] = ()) -> None:
    """UserError unless every number of the config dataclass ``cfg`` is finite and of its field's type, and
    the named fields are > 0, >= 0 or >= 1 (messages name ``section.key``, the config.yaml key)."""
    hints = typing.get_type_hints(type(cfg))
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        name = f"{section}.{f.name}" if section else f.name
        if not dataclasses.is_dataclass(value):
            _coerce(value, hints[f.name], name)  # the type: a CLI or code assignment skips from_dict
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(v, float) and not math.isfinite(v):
                raise UserError(f"{name} must be a finite number, got {value!r}")
        if f.name in positive and not value > 0:
            raise UserError(f"{name} must be > 0, got {value!r}")
        if f.name in nonnegative and not value >= 0:
            raise UserError(f"{name} must be >= 0, got {value!r}")
        if f.name in at_least_one and not value >= 1:
            raise UserError(f"{name} must be >= 1, got {value!r}")


def read_yaml(path: str | os.PathLike, what: str = "config file") -> dict:
    """A user's YAML file's top-level mapping ({} when empty); UserError naming ``what`` and the path when
    it is missing, a folder, unreadable, not UTF-8, not valid YAML (line and column) or not a mapping
    (see :func:`rmavatar.utils.files.read_yaml_file`)."""
    return read_yaml_file(path, what, mapping=True)


def write_yaml(cfg: Any, path: str | os.PathLike, header: dict | None = None) -> None:
    """Write the config dataclass ``cfg`` as YAML, atomically, after the keys of ``header`` (if any)."""
    import yaml

    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump({**(header or {}), **to_dict(cfg)}, sort_keys=False))


def flatten(values: dict, prefix: str = "") -> dict[str, Any]:
    """Nested mappings -> dotted keys: {"optim": {"iters": 5}} -> {"optim.iters": 5}."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def apply_overrides(cfg: Any, overrides: dict[str, Any], where: str = "overrides") -> Any:
    """A copy of the config dataclass ``cfg`` with dotted keys set (``{"optim.iters": 1000,
    "model.rectifier": False}``; nested mappings work too), type-checked like a config file: errors
    name ``where`` and the key."""
    merged = to_dict(cfg)
    sections = sorted(k for k, v in merged.items() if isinstance(v, dict))
    for key, value in flatten(overrides).items():
        *path, leaf = str(key).split(".")
        node = merged
        for depth, part in enumerate(path):
            if not isinstance(node.get(part), dict):
                head = ".".join(path[: depth + 1])
                raise UserError(f"{where}: unknown key {key!r} ({head!r} is not a config section; sections: "
                                f"{', '.join(sections)}; top-level keys: "
                                f"{', '.join(k for k in merged if k not in sections)})")
            node = node[part]
        if isinstance(node.get(leaf), dict):
            raise UserError(f"{where}: {key!r} is a config section, give one of its keys ({key}.KEY)")
        node[leaf] = value
    return from_dict(type(cfg), merged, where=where)
