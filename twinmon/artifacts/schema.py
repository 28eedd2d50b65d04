"""Artifact kinds and their schema versions: what each reader expects and still accepts."""
from __future__ import annotations


#: Current major version of each artifact kind. Bump on an incompatible layout change.
SCHEMAS = {
    "simulations": 1,
    "surrogate": 1,
    "observations": 1,
    "truth": 1,
    "posterior": 2,
    "forecast": 1,
    "gap": 2,
    "backtest": 1,
}


#: Earlier major versions a reader still accepts (the reader handles their layout).
#: posterior/1, gap/1: one dataset per field and unit (the /2 layouts pack a unit's per-year
#: results into one compound dataset).
READABLE = {"posterior": (1,), "gap": (1,)}


def schema_name(kind: str) -> str:
    return f"twinmon.{kind}/{SCHEMAS[kind]}"
