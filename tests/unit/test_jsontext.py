"""Tests of twinmon.jsontext: what --json and summary.json print is strict JSON."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from twinmon.jsontext import to_json


def strict_loads(text: str):
    """json.loads refusing NaN, Infinity and -Infinity (Python accepts them by default)."""
    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


def test_strict_loads_refuses_what_python_writes_by_default():
    with pytest.raises(ValueError, match="NaN"):
        strict_loads(json.dumps({"x": float("nan")}))


def test_non_finite_values_become_null_everywhere():
    obj = {"nan": float("nan"), "inf": math.inf, "ninf": -math.inf,
           "np": np.float32("nan"), "arr": np.array([1.0, np.nan, np.inf]),
           "nested": [{"t": (np.float64(2.5), np.int64(3))}], 4: Path("/a/b"),
           "ok": True, "none": None}
    back = strict_loads(to_json(obj))
    assert back == {"nan": None, "inf": None, "ninf": None, "np": None,
                    "arr": [1.0, None, None], "nested": [{"t": [2.5, 3]}], "4": "/a/b",
                    "ok": True, "none": None}
