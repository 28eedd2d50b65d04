"""Strict JSON text for everything twinmon prints or writes as JSON (``--json``, summary.json).

Python's :func:`json.dumps` writes ``NaN`` and ``Infinity`` by default, which are not JSON:
``jq``, JavaScript and most parsers refuse them.  :func:`to_json` writes ``null`` for every
non-finite float instead, and turns numpy scalars and arrays, paths and tuples into plain JSON.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["plain", "to_json"]


def plain(obj: Any) -> Any:
    """A JSON-able copy of ``obj``: numpy scalars and arrays made plain, non-finite floats
    ``None``, paths strings, mapping keys strings; anything else unknown as ``str(obj)``."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        return plain(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (str, bool, int)):
        return obj
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def to_json(obj: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``obj`` (see :func:`plain`); never ``NaN`` or ``Infinity``."""
    return json.dumps(plain(obj), indent=indent, allow_nan=False)
