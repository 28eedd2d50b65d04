"""Loading a config: the YAML file (strict: duplicate keys are errors), ``extends:``
merged key by key, ``--set a.b=v`` overrides applied to the raw mapping, and only then
validation into a :class:`~twinmon.config.Config`."""
from __future__ import annotations

import copy
import dataclasses
import os
import re
import typing
from pathlib import Path
from typing import Any, Mapping

import yaml

from ..errors import ConfigError, ReadError
from .schema import _build, _where
from .top import Config


def load_config(path: str | os.PathLike, overrides: typing.Sequence[str] = ()) -> Config:
    """Load, merge (``extends``), override and validate a YAML config.

    Parameters
    ----------
    path : path-like
        The YAML file.
    overrides : sequence of str
        ``"a.b.c=value"`` items; the value is parsed as YAML (so ``3``, ``0.5``, ``true``,
        ``[1, 2]`` keep their types).

    Raises
    ------
    ConfigError
        On a missing file, malformed YAML, an unknown key or an invalid value; the message
        names the file, the YAML path and the value.
    """
    path = Path(path)
    raw = _load_yaml_tree(path, seen=())
    for item in overrides:
        _apply_override(raw, item, path)
    return config_from_mapping(raw, path)


def config_from_mapping(raw: Mapping[str, Any], source: Path = Path("<memory>")) -> Config:
    """Validate an already-merged mapping into a :class:`Config` (paths relative to
    ``source``'s folder)."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{source}: top level must be a mapping, got {type(raw).__name__}")
    raw = copy.deepcopy(dict(raw))
    model = raw.get("model")
    if isinstance(model, dict) and isinstance(model.get("channels"), (list, tuple)):
        # A plain list of channel names is the short form of {name: {}}.
        chans = model["channels"]
        if not all(isinstance(c, str) for c in chans):
            bad = next(c for c in chans if not isinstance(c, str))
            raise ConfigError(f"{source}: model.channels: expected FMU variable names, got {bad!r}")
        model["channels"] = {c: {} for c in chans}
    _refuse_placeholders(raw, (), source)
    cfg = _build(Config, raw, (), source)
    return dataclasses.replace(cfg, source=source, raw=raw)


#: What ``twinmon init`` writes for each value only the user can give.
PLACEHOLDER = "<fill in>"


def _refuse_placeholders(value: Any, path: tuple, source: Path) -> None:
    # A starter config must not load until every placeholder is replaced, whatever the
    # type of the key (a units string would otherwise load and reach the report).
    if isinstance(value, str) and PLACEHOLDER in value:
        raise ConfigError(f"{_where(source, path)}: still {value!r}, the placeholder "
                          "`twinmon init` wrote; fill in the value")
    if isinstance(value, dict):
        for k, v in value.items():
            if isinstance(k, str) and PLACEHOLDER in k:
                raise ConfigError(f"{_where(source, path + (k,))}: the key is still the "
                                  "placeholder `twinmon init` wrote; fill it in")
            _refuse_placeholders(v, path + (k,), source)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _refuse_placeholders(v, path + (i,), source)


def _load_yaml_tree(path: Path, seen: tuple) -> dict:
    if path.resolve() in seen:
        raise ConfigError(f"{path}: 'extends' forms a cycle")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, expected a YAML file") from None
    except OSError as exc:
        raise ReadError(f"{path}: cannot read config: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}: line {line}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x}); "
                          "save the config as UTF-8") from None
    try:
        data = yaml.load(text, Loader=StrictLoader)
    except DuplicateKeyError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}: malformed YAML at {where}{problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    parent = data.pop("extends", None)
    if parent is None:
        return _absolutise_paths(data, path.parent)
    if not isinstance(parent, str):
        raise ConfigError(f"{path}: extends: expected a file name, got {parent!r}")
    base = _load_yaml_tree(path.parent / parent, seen + (path.resolve(),))
    return _merge(base, _absolutise_paths(data, path.parent))


def _absolutise_paths(data: dict, folder: Path) -> dict:
    # model.fmu is written relative to the YAML file that names it, so that a config that
    # extends another from elsewhere still finds the FMU.
    model = data.get("model")
    if isinstance(model, dict) and isinstance(model.get("fmu"), str):
        fmu = Path(model["fmu"])
        if not fmu.is_absolute():
            model["fmu"] = os.path.normpath(folder / fmu)
    return data


class DuplicateKeyError(yaml.YAMLError):
    """A mapping names the same key twice (PyYAML would silently keep the last)."""


# libyaml's parser when PyYAML was built with it (the wheels are): a fleet config that lists
# 1000 units parses in 0.2 s instead of 2.2 s; the constructor and resolver stay Python.
_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class StrictLoader(_SafeLoader):
    """PyYAML's safe loader, stricter and kinder: duplicate keys are an error, and numbers
    such as ``1e6`` or ``4e2`` (YAML 1.1 wants ``1.0e+6``) are read as floats."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.get(key)
            except TypeError:
                continue  # an unhashable key: PyYAML reports it itself
            if first is not None:
                raise DuplicateKeyError(
                    f"line {key_node.start_mark.line + 1}: key {key!r} appears twice in one "
                    f"mapping (first on line {first}); remove one")
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


# YAML 1.1's float rule needs a dot and a signed exponent; accept what people write too.
StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$""", re.X),
    list("-+0123456789"))


def _merge(base: dict, top: dict) -> dict:
    """``top`` over ``base``, mapping by mapping; ``KEY: null`` in ``top`` drops an entry the
    base gives as a mapping (a diagnose window, a candidate effect, an input), which there
    is no other way to remove from a config that extends another."""
    out = dict(base)
    for key, value in top.items():
        if value is None and isinstance(out.get(key), dict):
            del out[key]
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _named_parts(parts: list) -> list:
    """``parts`` with an FMU variable's name joined into one part where the path runs
    through a mapping keyed by such names: ``model.fixed.tacho.gain`` is the name
    ``tacho.gain``, ``model.effects.shaft.J.baseline`` the field ``baseline`` of the effect
    ``shaft.J`` (the last part is a field when the entries have it), whether or not the
    config has the entry yet."""
    from .model import ChannelSpec, EffectSpec
    fields = {("model", "effects"): {f.name for f in dataclasses.fields(EffectSpec)},
              ("model", "channels"): {f.name for f in dataclasses.fields(ChannelSpec)},
              ("model", "fixed"): set()}
    head = tuple(parts[:2])
    if head not in fields or len(parts) < 4:
        return parts
    rest = parts[2:]
    if rest[-1] in fields[head]:
        return list(head) + [".".join(rest[:-1]), rest[-1]]
    return list(head) + [".".join(rest)]


def _apply_override(raw: dict, item: str, source: Path) -> None:
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected KEY.PATH=VALUE")
    key, _, text = item.partition("=")
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set {item!r}: empty key")
    try:
        value = yaml.load(text, Loader=StrictLoader)
    except yaml.YAMLError:
        raise ConfigError(f"--set {item!r}: value {text!r} is not valid YAML") from None
    parts = _named_parts(parts)
    node, i = raw, 0
    while True:
        # An FMU variable's name holds dots (model.effects.tacho.gain.baseline): the longest
        # run of parts the mapping has as a key is one key.
        j = next((j for j in range(len(parts), i + 1, -1) if ".".join(parts[i:j]) in node),
                 i + 1)
        part = ".".join(parts[i:j])
        if j == len(parts):
            break
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            raise ConfigError(
                f"--set {item!r}: {'.'.join(parts[:j])} is not a mapping in {source}")
        node, i = child, j
    if parts == ["model", "fmu"] and isinstance(value, str):
        value = os.path.abspath(value)
    if value is None and isinstance(node.get(part), dict):
        del node[part]          # as KEY: null under extends: the entry is dropped
    else:
        node[part] = value
