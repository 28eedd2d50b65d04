"""From parsed YAML to typed sections and back.

:func:`_build` turns a mapping into a frozen dataclass by reading the dataclass's type
hints, so adding a field to a section is a one-line change and needs no parser code: every
unknown key is rejected, every value checked against its type, then the section's own
``_check`` runs; each error names the file, the YAML path and the value received.
:func:`to_plain` is the way back (printing, provenance), in field order.

A section's type hints are resolved in the section's own module (``from __future__ import
annotations`` makes them strings), so each section module imports every type its fields
name.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import typing
from pathlib import Path
from typing import Any, Literal

from ..errors import ConfigError

#: Fields of :class:`~twinmon.config.Config` that are not YAML keys.
_NOT_KEYS = {"source", "raw"}


def _where(source: Path, path: tuple) -> str:
    return f"{source}: {'.'.join(str(p) for p in path) or '<top>'}"


def _build(tp: Any, value: Any, path: tuple, source: Path) -> Any:
    """Turn ``value`` (parsed YAML) into type ``tp``, or raise ConfigError naming ``path``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build_dataclass(tp, value, path, source)
    if origin is typing.Union:  # Optional[X]
        if value is None:
            return None
        inner = [a for a in args if a is not type(None)]
        return _build(inner[0], value, path, source)
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{_where(source, path)}: expected one of "
                              f"{', '.join(map(str, args))}, got {value!r}")
        return value
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{_where(source, path)}: expected a mapping, got {value!r}")
        return {str(k): _build(args[1], v, path + (k,), source) for k, v in value.items()}
    if origin is tuple:
        if isinstance(value, str) or not isinstance(value, (list, tuple)):
            raise ConfigError(f"{_where(source, path)}: expected a list, got {value!r}")
        return tuple(_build(args[0], v, path + (i,), source) for i, v in enumerate(value))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{_where(source, path)}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{_where(source, path)}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{_where(source, path)}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{_where(source, path)}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{_where(source, path)}: expected a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str) or not value:
            raise ConfigError(f"{_where(source, path)}: expected a path, got {value!r}")
        return Path(value)
    raise TypeError(f"config type {tp!r} is not supported")  # programming error


@functools.lru_cache(maxsize=None)
def _schema(cls: type) -> tuple[dict, dict]:
    """A config dataclass's field types and fields (keys). Cached: evaluating the string
    annotations compiles each one, and a fleet's ``fabricate.units`` builds the same few
    classes thousands of times (half of the 0.7 s a 1000-unit fleet's config took to
    load)."""
    return (typing.get_type_hints(cls),
            {f.name: f for f in dataclasses.fields(cls) if f.name not in _NOT_KEYS})


def _build_dataclass(cls: type, value: Any, path: tuple, source: Path) -> Any:
    if not isinstance(value, dict):
        raise ConfigError(f"{_where(source, path)}: expected a mapping, got {value!r}")
    hints, fields = _schema(cls)
    unknown = [k for k in value if not isinstance(k, str) or k not in fields]
    if unknown:
        key = unknown[0]
        raise ConfigError(f"{_where(source, path + (key,))}: unknown key (value {value[key]!r}); "
                          f"expected one of {', '.join(fields)}")
    kwargs = {}
    for name, f in fields.items():
        if name in value:
            kwargs[name] = _build(hints[name], value[name], path + (name,), source)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{_where(source, path + (name,))}: required key is missing")
    obj = cls(**kwargs)
    check = getattr(obj, "_check", None)
    if check is not None:
        for key, msg, got in check():
            raise ConfigError(f"{_where(source, path + (key,))}: {msg}, got {got!r}")
    return obj


def to_plain(obj: Any) -> Any:
    """A config object as plain YAML-able Python (for printing and provenance)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if f.name not in _NOT_KEYS}
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj
