"""The safety criterion: time to reach a fraction of nominal flow (t90), and unsafe units.

A unit is unsafe when its flow does not reach ``fraction`` (90 %) of the unit type's nominal
flow within ``max_time`` (30 s) of start, or when its twin is in the non-physical mode.
"""
from __future__ import annotations

import numpy as np

from .config import SafetyConfig


def time_to_fraction(time: np.ndarray, flow: np.ndarray, safety: SafetyConfig) -> np.ndarray:
    """Time at which the flow first reaches ``fraction * nominal_flow`` (t90).

    The crossing is located by linear interpolation between the two samples around it, and
    the flow is taken as 0 at t = 0 (the unit starts from rest), so a crossing before the first
    sample is interpolated too.

    Parameters
    ----------
    time : ndarray, shape [n_t]
        Sample times (s), increasing.
    flow : ndarray, shape [..., n_t]
        Flow transients (kg/s).
    safety : SafetyConfig

    Returns
    -------
    ndarray, shape [...]
        t90 in seconds; ``inf`` where the level is never reached within the record.
    """
    flow = np.asarray(flow, dtype=float)
    level = safety.fraction * safety.nominal_flow
    t = np.concatenate([[0.0], np.asarray(time, float)])
    f = np.concatenate([np.zeros(flow.shape[:-1] + (1,)), flow], axis=-1)
    above = f >= level
    reached = above.any(axis=-1)
    k = np.argmax(above, axis=-1)                      # first sample at or above the level
    k = np.maximum(k, 1)
    f1 = np.take_along_axis(f, (k - 1)[..., None], -1)[..., 0]
    f2 = np.take_along_axis(f, k[..., None], -1)[..., 0]
    t1, t2 = t[k - 1], t[k]
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(f2 > f1, (level - f1) / (f2 - f1), 1.0)
    out = t1 + np.clip(frac, 0.0, 1.0) * (t2 - t1)
    return np.where(reached, out, np.inf)


def is_unsafe(t90: np.ndarray, safety: SafetyConfig,
              nonphysical: np.ndarray | None = None) -> np.ndarray:
    """True where t90 exceeds ``max_time`` or the twin is non-physical (same shape as t90)."""
    bad = np.asarray(t90) > safety.max_time
    if nonphysical is not None:
        bad = bad | np.asarray(nonphysical, bool)
    return bad


def failure_year(years: np.ndarray, p_unsafe: np.ndarray, safety: SafetyConfig) -> int | None:
    """First year whose probability of being unsafe exceeds ``failure_probability``."""
    over = np.flatnonzero(np.asarray(p_unsafe) > safety.failure_probability)
    return int(years[over[0]]) if over.size else None
