"""Pieces shared by the FMU modules: FMI type names, one-line error text, name hints."""
from __future__ import annotations

import difflib
import numbers
from typing import Iterable, Mapping

FLOAT_TYPES = frozenset({"Real", "Float64", "Float32"})
INTEGER_TYPES = frozenset({"Integer", "Enumeration", "Int8", "UInt8", "Int16", "UInt16",
                           "Int32", "UInt32", "Int64", "UInt64"})
NUMERIC_TYPES = FLOAT_TYPES | INTEGER_TYPES | {"Boolean"}


def _one_line(exc: BaseException, limit: int = 300) -> str:
    """An exception's message on one line (fmpy's span several: a heading, then one
    ``- problem`` line each), cut to ``limit`` characters."""
    lines = [ln.strip().lstrip("- ").strip() for ln in str(exc).splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        return type(exc).__name__
    text = lines[0]
    for ln in lines[1:]:
        text += (" " if text.endswith(":") else "; ") + ln
    return text if len(text) <= limit else text[:limit - 3] + "..."


def format_params(values: Mapping[str, float]) -> str:
    """A run's parameters as ``name=value, ...`` (6 significant digits; a value that is not a
    number shown as it is, for the message refusing it), ``defaults`` when there are none."""
    return ", ".join(f"{k}={v:.6g}" if isinstance(v, numbers.Real) else f"{k}={v!r}"
                     for k, v in values.items()) or "defaults"


def closest_names(name: str, candidates: Iterable[str], n: int = 3) -> list[str]:
    """The ``n`` candidates most like ``name`` (difflib ratio, case-insensitive), best first.

    Every candidate that shares something with ``name`` may be returned, so that an error
    message can always point at what exists; an empty list only when there are none.
    """
    key = name.lower()
    scored = []
    for c in dict.fromkeys(candidates):
        r = difflib.SequenceMatcher(None, key, c.lower()).ratio()
        if r > 0:
            scored.append((-r, c))
    return [c for _, c in sorted(scored)[:max(n, 0)]]


def _a(word: str) -> str:
    return ("an " if word[:1].lower() in "aeiou" else "a ") + word


def _closest_hint(name: str, candidates: Iterable[str]) -> str:
    near = closest_names(name, candidates)
    return f"; closest: {', '.join(near)}" if near else ""
