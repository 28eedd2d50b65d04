"""Confirmation of a candidate by the augmented fit through the FMU (per-year degradation
inputs plus effects, each shared by the years from its onset), and the BIC that compares
models of a unit.
"""
from __future__ import annotations

import numpy as np

from ..errors import SimulationError
from .fit import JointFit
from .state import UnitState


def fit_with(s: UnitState, effects: list, values: list, u_start: np.ndarray):
    """Fit the twin with ``effects`` [(name, onset)] from start values; years before the
    earliest onset keep the base fit. Returns ``(chi2 total, FitResult, first row)``."""
    first = min(on for _, on in effects)
    k0 = int(np.searchsorted(s.years, first))
    if k0 >= s.n_y:
        return np.inf, None, k0
    prob = JointFit(s.twin, s.Y[k0:], s.years[k0:], effects)
    x0 = np.concatenate([[s.twin.effect_u(n, v) for (n, _), v in zip(effects, values)],
                         np.asarray(u_start)[k0:].ravel()])
    fit = prob.solve(x0)
    chi2 = float(s.chi2_base[:k0].sum() + fit.chi2_rows.sum())
    return chi2, fit, k0


def bic(s: UnitState, chi2: float, n_effects: int) -> float:
    """BIC of a model of the unit with per-year degradation inputs and ``n_effects`` effects."""
    # Each effect costs its value and its onset year.
    return chi2 + (s.d * s.n_y + 2 * n_effects) * s.ln_n


def confirm(s: UnitState, name: str, value: float, onset: int, fixed_fit=None):
    """Best augmented fit of candidate ``name`` over onsets ``onset +- onset_search``:
    ``(chi2, FitResult, first fitted row, onset)``, or None if no onset is within the years."""
    best = None
    near = range(onset - s.dc.onset_search, onset + s.dc.onset_search + 1)
    # The screening's onset first, from the inputs moved to make room for the effect; the
    # other onsets from its fit (the effect's value, the years' inputs), a few steps away.
    first = None
    for on in sorted(near, key=lambda o: (abs(o - onset), o)):
        if on < s.years[0] or on > s.years[-1]:
            continue
        if first is not None:
            u0, v0 = _from_fit(s, name, value, on, first)
        else:
            u0, v0 = _readjusted_start(s, name, value, on), value
        chi2, fit, k0 = fit_with(s, [(name, on)], [v0], u0)
        if fit is not None and first is None:
            first = fit
        if fit is not None and (best is None or chi2 < best[0]):
            best = (chi2, fit, k0, on)
    return best


def _from_fit(s: UnitState, name, value, onset, fit):
    """Start values for onset ``onset`` from ``fit`` (the same candidate at another onset):
    its value and its fitted years' inputs; a year it did not fit is moved as
    :func:`_readjusted_start` moves it."""
    ue, ut = fit.problem.unpack(fit.x)
    rows = np.searchsorted(s.years, fit.problem.years)
    u = _readjusted_start(s, name, value, onset, skip=set(rows.tolist()))
    u[rows] = ut
    return u, s.twin.effect_of(name, ue[0])


def _readjusted_start(s: UnitState, name, value, onset, skip=()):
    """Base inputs moved by one linear step to make room for the effect, in every year from
    the onset but the rows of ``skip``."""
    u = s.base_u.copy()
    for k in range(s.n_y):
        if s.years[k] < onset or k in skip:
            continue
        mask = np.isfinite(s.Y[k])
        theta = s.twin.theta_of(u[k])
        try:
            df = (s.twin.predict(theta, {name: value}) - s.twin.predict(theta))[mask]
        except SimulationError:
            continue
        J = -s.base_J[k]                        # d f / d u
        step = np.linalg.lstsq(J, s.base_rows[k] - df, rcond=None)[0]
        u[k] = np.clip(u[k] + step, 0.0, 1.0)
    return u
