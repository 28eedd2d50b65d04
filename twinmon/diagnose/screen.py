"""Screening of candidate effects: how much of a residual each candidate's signature
explains, linearised, on a grid over its range and for every onset year at once.

:func:`screen` is cheap (a few FMU runs per candidate and year); :func:`to_confirm` picks the
candidates worth a full fit through the FMU (:mod:`~twinmon.diagnose.confirm`).
"""
from __future__ import annotations

import numpy as np

from ..errors import SimulationError
from .state import UnitState


def to_confirm(screened: dict, top: int, floor: float = 0.0) -> set:
    """Candidates worth a full fit: the ``top`` best screening scores (0: all), and any other
    scoring at least half the best (a group of near-equivalent effects stays whole); none
    when the best scores below ``floor`` (with ``top`` > 0).

    The screening's chi-square reduction is linearised: it misjudges sizes, rarely the
    ranking of candidates that matter (on the shipped gap fleet the effects that enter the
    model screen 100-230 and are all in the first three, an effect that explains nothing
    below 60; on 12 units without a gap the best screens 6 at most and its fit gains 8 in
    chi-square, against the 21 an accepted effect needs)."""
    if top <= 0:
        return set(screened)
    ranked = sorted(screened, key=lambda n: -screened[n][0])
    best = screened[ranked[0]][0] if ranked else 0.0
    if best < floor:
        return set()
    return set(ranked[:top]) | {n for n in ranked if best > 0 and screened[n][0] >= 0.5 * best}


def _grid(s: UnitState, name: str) -> np.ndarray:
    """Screening values of effect ``name``: ``screen_points`` per side of its baseline."""
    e = s.twin.effects[name]
    n = s.dc.screen_points
    fr = np.arange(1, n + 1) / n
    vals = []
    if e.high > e.baseline:
        vals += list(e.baseline + fr * (e.high - e.baseline))
    if e.low < e.baseline:
        vals += list(e.baseline - fr * (e.baseline - e.low))
    return np.array(vals)


def screen(s: UnitState, name: str, u_inputs, rows, Qs, fixed: dict,
           known: np.ndarray | None = None) -> tuple:
    """Chi-square reduction of adding effect ``name`` (value on a grid, onset any year),
    the degradation inputs re-adjusted linearly.

    Returns ``(score, value, onset, gain [n_v, n_y])``; ``fixed`` maps years index ->
    effects already in the twin. ``known`` [n_v, n_k]: the gains of the first ``n_k`` years,
    taken as they are (a year's gains depend on that year alone)."""
    grid = _grid(s, name)
    gains = np.zeros((grid.size, s.n_y))
    n_known = 0
    if known is not None:
        n_known = known.shape[1]
        gains[:, :n_known] = known
    for k in range(n_known, s.n_y):
        theta = s.twin.theta_of(u_inputs[k])
        eff0 = fixed.get(k, {})
        mask = np.isfinite(s.Y[k])
        try:
            f0 = s.twin.predict(theta, eff0)[mask]
        except SimulationError:
            continue
        Q = Qs[k]
        r = rows[k]
        rp = r - Q @ (Q.T @ r)
        base = float(rp @ rp)
        for i, v in enumerate(grid):
            try:
                f = s.twin.predict(theta, {**eff0, name: v})[mask]
            except SimulationError:
                gains[i, k] = -np.inf
                continue
            r2 = r - (f - f0)
            r2 = r2 - Q @ (Q.T @ r2)
            gains[i, k] = base - float(r2 @ r2)
    cum = np.cumsum(gains[:, ::-1], axis=1)[:, ::-1]      # [n_v, onset index]
    i, o = np.unravel_index(int(np.argmax(cum)), cum.shape)
    return float(cum[i, o]), float(grid[i]), int(s.years[o]), gains
