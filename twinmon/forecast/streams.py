"""The forecast's random streams: one generator per unit and purpose, keyed by the unit's name.

A unit's draws therefore do not depend on the other units of the fleet, nor on the workers
and chunks the units were forecast in. The streams of a unit:

======  ==============================================================================
0       its future inputs (the Monte Carlo points through the twin)
1       which posterior draws of each observed year run through the twin
2       the null distribution of the indicator's drift (detection)
3       the slope draws of the attribution
4       the null distribution of the inputs' joint box test (detection)
5       the resampling of a joint posterior to the fleet's prior of its year-to-year sd
6       the same with the fleet's prior of the trend forms too (the draws the future
        extends)
7       the null distribution of the inputs' box test on their current rates (detection)
======  ==============================================================================
"""
from __future__ import annotations

import zlib

import numpy as np

from ..config import Config

#: Offset added to ``cfg.seed`` for this stage's random streams (other stages use others).
SEED_OFFSET = 5000


def unit_rng(cfg: Config, unit: str, stream: int) -> np.random.Generator:
    """The generator of ``stream`` (0-7, above) for ``unit``."""
    return np.random.default_rng([cfg.seed + SEED_OFFSET, zlib.crc32(unit.encode()), stream])
