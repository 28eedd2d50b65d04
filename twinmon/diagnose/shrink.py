"""Step 3, **shrink**: how far the gap shrinks once the identified effect is in the twin.

:func:`shrink` compares the base twin with the final one over the affected years: residual
RMS over noise before and after, the percentage of the excess gap closed, whether what
remains passes the noise tests, hence the verdict (``none``, ``effect``, ``unexplained``),
the effect estimates with a 90 % interval and the BIC gain. :func:`predictions`,
:func:`input_sd` and :func:`failure_years` then give the output of both twins, the
degradation estimates with their standard deviations, and how the projected failure year
moves; :func:`group_records` gives, for each member of each effect's group, the share of the
gap it closes and its projected failure year.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.special import ndtri

from ..errors import SimulationError
from .confirm import bic
from .groups import group_separation
from .identify import Identification
from .locate import year_tests
from .state import UnitState


@dataclass
class Shrink:
    """The final twin of one unit and how much of the gap it closes.

    Attributes
    ----------
    verdict : str
        ``"none"``, ``"effect"`` or ``"unexplained"``.
    onset : int or None
        Earliest onset of the accepted effects, else the detected onset if the gap is
        significant.
    aff : ndarray of bool, shape [n_y]
        The affected years (from ``onset`` on; all years if there is no onset).
    n_eff : int
        Number of effects in the final model (0 unless accepted).
    after_u : ndarray, shape [n_y, d]
        Normalised degradation inputs of the final twin (the base twin's unless ``effect``).
    after_rows, after_lev : list of ndarray
        Whitened residual rows and leverages of the final twin, per year.
    after_cov : ndarray or None
        Covariance of the final fit's unknowns (``effect`` only).
    k0 : int or None
        First year index fitted with the effects (``effect`` only).
    rms_before, rms_after, closed_percent : float
    chi2_after, p_chi2_after : ndarray, shape [n_y]
    effects : list of str
        Reported effects: the group, then further effects.
    estimate : dict
        ``{effect: (value, q05, q95)}`` (effect units).
    eff_year : list of dict
        Effects in the final twin per year ``{fmu parameter: value}`` [n_y].
    delta_bic_final : float
        BIC gain of the final model (of the best candidate if none was accepted).
    """

    verdict: str
    onset: Optional[int]
    aff: np.ndarray
    n_eff: int
    after_u: np.ndarray
    after_rows: list
    after_lev: list
    after_cov: Optional[np.ndarray]
    k0: Optional[int]
    rms_before: float
    rms_after: float
    closed_percent: float
    chi2_after: np.ndarray
    p_chi2_after: np.ndarray
    effects: list
    estimate: dict
    eff_year: list
    delta_bic_final: float


def shrink(s: UnitState, idn: Identification) -> Shrink:
    """Before / after over the affected years, the verdict and the estimates (needs steps 1
    and 2)."""
    significant, best, confirmed = idn.significant, idn.best, idn.confirmed
    model_effects, model_values, final = idn.model_effects, idn.model_values, idn.final
    after_u = s.base_u.copy()
    after_rows = list(s.base_rows)
    after_lev = list(s.base_lev)
    after_cov = None
    if final is not None:
        _, fit, k0 = final
        _, ut = fit.problem.unpack(fit.x)
        after_u[k0:] = ut
        lev = fit.leverage_rows()
        for j in range(len(ut)):
            after_rows[k0 + j] = fit.rows[j]
            after_lev[k0 + j] = lev[j]
        after_cov = fit.covariance()
    onset = (min(on for _, on in model_effects) if model_effects
             else (s.detected_onset if significant else None))
    aff = (s.years >= onset) if onset is not None else np.ones(s.n_y, bool)
    n_eff = len(model_effects)
    rss_b = float(s.chi2_base[aff].sum())
    rss_a = float(sum(float(after_rows[k] @ after_rows[k]) for k in np.flatnonzero(aff)))
    n_aff = int(s.n_rows[aff].sum())
    dof_b = max(n_aff - s.d * int(aff.sum()), 1)
    dof_a = max(dof_b - n_eff, 1)
    rms_before = math.sqrt(rss_b / dof_b)
    rms_after = math.sqrt(rss_a / dof_a)
    # If the gap was significant but nothing was accepted, show what the best candidate
    # would have done (so an "unexplained" verdict still says how far the best one got).
    if final is None and significant and best is not None and confirmed[best]:
        _, fit_x, k0_x, _ = confirmed[best]
        rows_x = list(s.base_rows[:k0_x]) + list(fit_x.rows)
        rss_x = float(sum(float(rows_x[k] @ rows_x[k]) for k in np.flatnonzero(aff)))
        rms_after = math.sqrt(rss_x / max(dof_b - 1, 1))
    ex_b = rms_before ** 2 - 1.0
    ex_a = max(rms_after ** 2 - 1.0, 0.0)
    closed = 100.0 * (1.0 - ex_a / ex_b) if ex_b > 0 else 0.0
    closed = float(np.clip(closed, 0.0, 100.0)) if significant else 0.0

    # Is what remains consistent with noise? (same battery of tests, affected years)
    chi2_a, dof_a_y, p_chi2_a, p_lb_a = year_tests(s, after_rows, after_lev, s.d)
    k_aff = np.flatnonzero(aff)
    p_rem_year = min(1.0, 2 * len(k_aff) * float(np.minimum(p_chi2_a, p_lb_a)[k_aff].min()))
    p_rem_pool = float(s.p_excess(chi2_a[k_aff].sum(), s.channel_counts[k_aff].sum(axis=0),
                                  max(dof_a, 1)))
    remaining = min(p_rem_year, p_rem_pool) < s.dc.alpha

    if not significant:
        verdict = "none"
    elif final is not None and closed >= s.dc.min_closed and (
            not remaining or closed >= s.dc.explained_closed):
        # A large gap closed almost entirely is explained even if the remainder fails the
        # noise tests (an unlucky noise draw, or the test's power on many years).
        verdict = "effect"
    else:
        verdict = "unexplained"
    if verdict != "effect":
        # The twin is left as it was: nothing is added that the data do not support.
        after_u = s.base_u.copy()
        after_rows, after_lev = list(s.base_rows), list(s.base_lev)
        chi2_a, p_chi2_a = s.chi2_base.copy(), s.p_chi2_before.copy()
        if verdict == "none":
            rms_after = rms_before
        after_cov = None

    group = idn.group
    effects_out, estimate = [], {}
    if verdict == "effect":
        effects_out = list(group) + [n for n, _ in model_effects[1:] if n not in group]
        cov = after_cov
        for j, (n, _) in enumerate(model_effects):
            sd_u = math.sqrt(max(cov[j, j], 0.0))
            estimate[n] = interval(s, n, model_values[j], sd_u)
        # Every member of every group gets its estimate from its own model's fit.
        for g in idn.groups:
            for m in g.members:
                if m.name in estimate:
                    continue
                sd_u = math.sqrt(max(m.fit[1].covariance()[m.index, m.index], 0.0))
                estimate[m.name] = interval(s, m.name, m.value, sd_u)

    eff_year = [{n: v for (n, on), v in zip(model_effects, model_values) if s.years[k] >= on}
                if verdict == "effect" else {} for k in range(s.n_y)]
    delta_final = (idn.bic_base - bic(s, final[0], n_eff)) if verdict == "effect" else (
        idn.dbic[best] if best is not None else 0.0)
    return Shrink(verdict=verdict, onset=onset, aff=aff, n_eff=n_eff, after_u=after_u,
                  after_rows=after_rows, after_lev=after_lev, after_cov=after_cov,
                  k0=final[2] if verdict == "effect" else None,
                  rms_before=rms_before, rms_after=rms_after, closed_percent=closed,
                  chi2_after=np.asarray(chi2_a, float), p_chi2_after=np.asarray(p_chi2_a, float),
                  effects=effects_out, estimate=estimate, eff_year=eff_year,
                  delta_bic_final=float(delta_final))


def interval(s: UnitState, name: str, value: float, sd_u: float) -> tuple:
    """``(value, q05, q95)`` of effect ``name``: linearised 90 % interval from the standard
    deviation ``sd_u`` in normalised units, clipped to the effect's range."""
    e = s.twin.effects[name]
    sd = sd_u * (e.high - e.low)
    z = ndtri(0.95)
    return (float(value), float(max(e.low, value - z * sd)), float(min(e.high, value + z * sd)))


# -- the twin before and after -----------------------------------------------------------------
def predictions(s: UnitState, sh: Shrink) -> tuple:
    """Output (its units) of the base and the final twin, each [n_y, n_t]."""
    pred_b = np.array([output_pred(s, s.base_u[k], {}) for k in range(s.n_y)])
    pred_a = np.array([output_pred(s, sh.after_u[k], sh.eff_year[k]) for k in range(s.n_y)])
    return pred_b, pred_a


def output_pred(s: UnitState, u: np.ndarray, effects: dict) -> np.ndarray:
    """The output variable [n_t] for normalised inputs ``u`` [d] and ``effects``."""
    return s.twin.run(s.twin.theta_of(u), effects)[s.cfg.model.output.variable]


def input_sd(s: UnitState, sh: Shrink) -> tuple:
    """Linearised standard deviations of the degradation inputs (input units), base and final
    twin, each [n_y, d]."""
    width = s.twin.in_hi - s.twin.in_lo
    sd_b = np.array([np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)), 0, None)) * width
                     for J in s.base_J])
    sd_a = sd_b.copy()
    if sh.verdict == "effect":
        var = np.clip(np.diag(sh.after_cov), 0, None)[sh.n_eff:].reshape(-1, s.d)
        sd_a[sh.k0:] = np.sqrt(var) * width
    return sd_b, sd_a


# -- the groups of the final twin, member by member --------------------------------------------
def group_records(s: UnitState, sh: Shrink, idn: Identification) -> list:
    """What each effect's group means, member by member (``verdict`` ``effect`` only).

    For every member of every group of ``idn.groups``, its model (the final model with this
    member in the group's place) gives the share of the excess gap it closes over the
    affected years ``sh.aff`` and the projected failure year; a group whose members' failure
    years differ by more than a year is flagged, since the one of the named effect alone
    would then be arbitrary. Returns one JSON-ready dict per group::

        {"effect": named effect, "onset": year,
         "members": [{"effect", "onset", "value", "q05", "q95", "weight", "delta_bic",
                      "together_with", "closed_percent", "failure_year"}, ...],
         "failure_year_range": [earliest, latest]   (null: no failure within the horizon),
         "failure_year_spread": bool, "separating_channel": str or null,
         "separation_scores": {channel: score}}
    """
    if sh.verdict != "effect":
        return []
    k_aff = np.flatnonzero(sh.aff)
    n_aff = int(s.n_rows[sh.aff].sum())
    dof_b = max(n_aff - s.d * int(sh.aff.sum()), 1)
    ex_b = sh.rms_before ** 2 - 1.0
    horizon_end = int(s.years[-1]) + s.cfg.forecast.horizon + 1
    out = []
    for g in idn.groups:
        members = []
        for m in g.members:
            chi2, fit, k0 = m.fit
            rows = list(s.base_rows[:k0]) + list(fit.rows)
            rss = float(sum(float(rows[k] @ rows[k]) for k in k_aff))
            rms = math.sqrt(rss / max(dof_b - len(m.effects), 1))
            closed = (100.0 * (1.0 - max(rms ** 2 - 1.0, 0.0) / ex_b)) if ex_b > 0 else 0.0
            _, ut = fit.problem.unpack(fit.x)
            u = s.base_u.copy()
            u[k0:] = ut
            fy = failure_year(s, s.twin.theta_of(u), dict(zip([n for n, _ in m.effects],
                                                             m.values)), dict(m.effects))
            # From the member's own fit: an effect may sit in two groups, beside different
            # partners, with two values.
            est = interval(s, m.name, m.value,
                           math.sqrt(max(fit.covariance()[m.index, m.index], 0.0)))
            members.append({"effect": m.name, "onset": int(m.onset), "value": float(m.value),
                            "q05": float(est[1]), "q95": float(est[2]),
                            "weight": float(m.weight), "delta_bic": float(m.dbic),
                            "together_with": list(m.together),
                            "closed_percent": float(np.clip(closed, 0.0, 100.0)),
                            "failure_year": fy})
        years = [horizon_end if r["failure_year"] is None else r["failure_year"]
                 for r in members]
        lo, hi = min(years), max(years)
        sep, scores = ("", {})
        if len(g.members) > 1:
            sep, scores = group_separation(s, g)
        out.append({"effect": g.name, "onset": int(g.members[0].onset), "members": members,
                    "failure_year_range": [None if lo == horizon_end else lo,
                                           None if hi == horizon_end else hi],
                    "failure_year_spread": bool(hi - lo > 1),
                    "separating_channel": sep or None,
                    "separation_scores": {c: float(v) for c, v in scores.items()}})
    return out


# -- failure year ----------------------------------------------------------------------------------
def failure_years(s: UnitState, sh: Shrink) -> tuple:
    """Projected failure year of the base and of the final twin (see :func:`failure_year`)."""
    fy_b = failure_year(s, s.twin.theta_of(s.base_u), {})
    if sh.verdict != "effect":
        return fy_b, fy_b
    # Each effect from the first year the final twin has it.
    onsets = {n: int(s.years[next(k for k in range(s.n_y) if n in sh.eff_year[k])])
              for n in sh.eff_year[-1]}
    return fy_b, failure_year(s, s.twin.theta_of(sh.after_u), sh.eff_year[-1], onsets)


def failure_year(s: UnitState, thetas: np.ndarray, effects: dict,
                 onsets: Optional[dict] = None) -> Optional[int]:
    """First year (observed or projected over ``forecast.horizon`` years by a straight
    line through the yearly estimates ``thetas`` [n_y, d]) in which the twin fails the safety
    criterion; None if none within the horizon. Each of ``effects`` ({fmu parameter: value})
    is in the twin from its year in ``onsets`` ({fmu parameter: year}; every year if not
    given): before it the plant did not have it. Effects that alter only the measurement
    (``measurement_only``) are left out: a lagging sensor does not make the machine
    unsafe."""
    from ..safety import Indicator
    ind = Indicator.from_config(s.cfg)
    effects = {k: v for k, v in (effects or {}).items()
               if not s.cfg.model.effects[k].measurement_only}
    onsets = onsets or {}
    yrs = s.years.astype(float)
    if len(yrs) >= 2:
        coef = np.polyfit(yrs, thetas, 1)                   # [2, d]
    else:
        coef = np.vstack([np.zeros(s.d), thetas[0]])
    future = np.arange(s.years[-1] + 1, s.years[-1] + 1 + s.cfg.forecast.horizon)
    cand = np.concatenate([s.years, future])
    np_var = s.cfg.model.nonphysical
    for i, yr in enumerate(cand):
        theta = thetas[i] if i < s.n_y else coef[0] * yr + coef[1]
        theta = np.clip(theta, s.twin.in_lo, s.twin.in_hi)
        try:
            out = s.twin.run(theta, {k: v for k, v in effects.items()
                                     if yr >= onsets.get(k, yr)})
        except SimulationError:
            return int(yr)
        value = ind(s.twin.time, out[ind.variable])
        nonphys = bool(out[np_var].max() > 0.5) if np_var else None
        if bool(ind.unsafe(np.array(value), nonphys)):
            return int(yr)
    return None
