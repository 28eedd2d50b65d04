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
           known: np.ndarray | None = None, Gs: list | None = None,
           onset: int | None = None) -> tuple:
    """Chi-square reduction of adding effect ``name`` (value on a grid, onset any year),
    the degradation inputs re-adjusted linearly.

    Parameters
    ----------
    u_inputs : ndarray, shape [n_y, d]
        Normalised degradation inputs the signatures are taken at.
    rows : list of ndarray, each [n_k]
        The whitened residual of each year (its non-missing samples).
    Qs : list of ndarray, each [n_k, q]
        Per year, an orthonormal basis of what is re-adjusted within the year alone (the
        degradation inputs' sensitivities).
    fixed : dict
        Years index -> effects already in the twin ``{fmu parameter: value}``.
    known : ndarray, shape [n_v, n_k], optional
        The gains of the first ``n_k`` years, taken as they are (a year's gains depend on
        that year alone).
    Gs : list of ndarray, each [n_k, n_e], optional
        Per year, the sensitivities of the effects already in the twin (zero columns in the
        years before an effect's onset): these are re-adjusted too, linearly, by one change
        of each effect's value shared by all years, as the confirming fit does. A further
        effect alike to one in the twin then explains only what that one cannot: a change
        from a later onset (a second plateau shift), or a shape its value cannot take up.
    onset : int, optional
        Only this onset year (default: every year).

    Returns
    -------
    score : float
        The best chi-square reduction.
    value : float
        Its effect value (effect units).
    onset : int
        Its onset year.
    gain : ndarray, shape [n_v, n_y]
        Per grid value and year, the reduction within the year (the effects of ``Gs`` not
        re-adjusted).
    """
    grid = _grid(s, name)
    gains = np.zeros((grid.size, s.n_y))
    n_e = Gs[0].shape[1] if Gs else 0
    # Per grid value and year, the signature's projection on the effects' sensitivities.
    w = np.zeros((grid.size, s.n_y, n_e))
    A = np.zeros((n_e, n_e))                          # sum over years of G~^T G~
    b0 = np.zeros(n_e)                                # sum over years of G~^T r~
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
        if n_e:
            G = Gs[k] - Q @ (Q.T @ Gs[k])
            A += G.T @ G
            b0 += G.T @ rp
        for i, v in enumerate(grid):
            try:
                f = s.twin.predict(theta, {**eff0, name: v})[mask]
            except SimulationError:
                gains[i, k] = -np.inf
                continue
            h = (f - f0) - Q @ (Q.T @ (f - f0))
            r2 = rp - h
            gains[i, k] = base - float(r2 @ r2)
            if n_e:
                w[i, k] = G.T @ h
    cum = np.cumsum(gains[:, ::-1], axis=1)[:, ::-1]      # [n_v, onset index]
    if n_e:
        # The effects' shared change d minimises sum_k |r~_k - h~_k - G~_k d|^2:
        # the gain from onset o is C(o) - 2 b0' A+ W(o) + W(o)' A+ W(o), W(o) the sum of
        # G~_k' h~_k over the years from o.
        W = np.cumsum(w[:, ::-1], axis=1)[:, ::-1]         # [n_v, onset index, n_e]
        Ap = np.linalg.pinv(A)
        cum = cum - 2 * (W @ (Ap @ b0)) + np.einsum("vke,ef,vkf->vk", W, Ap, W)
    cum = np.where(np.isfinite(cum), cum, -np.inf)
    if onset is not None:
        cum = np.where(s.years[None, :] == onset, cum, -np.inf)
    i, o = np.unravel_index(int(np.argmax(cum)), cum.shape)
    return float(cum[i, o]), float(grid[i]), int(s.years[o]), gains
