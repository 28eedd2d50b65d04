"""The judgement of a unit: degrading or not, which component, and whether to trust it.

A unit is judged in two steps (:func:`judge`):

1. **Detection** (:mod:`.detection`): the trend of the unit's health indicator is tested
   against the drift normal ageing of every input produces, and the inputs' slopes jointly
   against the normal-ageing box; the unit is degrading when Simes' test of the p-values
   rejects at ``forecast.alpha`` (:func:`~.detection.simes`; either one below ``alpha /
   2`` is enough). The first sees a fault the inputs trade off between, the second a fault
   another input's normal ageing hides from the indicator. When most of a trend posterior
   lies on wear that changed or accelerated, the inputs' rates at the last year are tested
   too, and after a repair the rates pooled over the repairs.
2. **Attribution** (:mod:`.attribution`): a degrading unit's components get probabilities
   of ageing faster than normal; the verdict names those at or above
   ``forecast.attribution_confidence``, or says ``ambiguous`` with the probabilities and the
   unrecorded channel that would tell them apart.

A repaired component's inputs are fitted from the repair on (:func:`~.trend.segment_trend`):
their pre-repair history does not make the unit degrading. :func:`verdict` is the paper's
verdict from the per-input slope tests alone.

:func:`prognosis_status` says whether the twin fits the unit's data well enough for a
prognosis at all (``ok``, ``withheld``, ``unreliable``), from calibrate's goodness of fit.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..calibrate.diagnostics import year_ranges
from ..calibrate.rejuvenate import moved_by_chain
from ..config import Config
from .attribution import AMBIGUOUS, HEALTHY, Attribution, attribute, separating_channel
from .covariance import MIN_ATTENUATION, slope_covariance
from .detection import (IndicatorDrift, box_test_uniform, detectable_multiples,
                        indicator_drift, simes)
from .streams import unit_rng
from .trend import POSTERIOR_DOF, Trend

#: Prognosis status of a unit.
STATUS_OK, STATUS_WITHHELD, STATUS_UNRELIABLE = "ok", "withheld", "unreliable"


#: Posterior weight of the trend shapes other than the line (wear that changed or
#: accelerated) beyond which detection also tests the inputs' rates at the last year
#: (:func:`judge`): "most of the posterior".
CHANGED_SHARE = 0.5


#: Fewest future draws on the straight line whose P(unsafe) tells whether the line alone
#: reaches the limit (:func:`describe_bend`).
MIN_LINE_DRAWS = 100


#: Fewest calibrated years a trend is forecast from (a line and its prediction interval
#: need a degree of freedom): a unit with fewer is not forecast, and an input whose trend
#: restarted fewer years ago makes its unit's prognosis unreliable.
MIN_TREND_YEARS = 3


def verdict(trends: dict[str, Trend]) -> str:
    """``healthy``, one component name, or ``both`` (several components) from the tests."""
    bad = sorted({t.component or name for name, t in trends.items() if t.rejects})
    if not bad:
        return "healthy"
    return bad[0] if len(bad) == 1 else "both"


def prognosis_status(up, cfg: Config, windows: list) -> tuple[str, str]:
    """Whether a unit's twin fits its data well enough for a prognosis.

    Withheld when at least ``forecast.withhold_years`` calibrated years (or the last one)
    miss the plant or sit on the design box's edge (calibrate's goodness of fit); the reason
    names the box when the years that miss sit on its edge on an input's degrading side too
    (a part worn beyond the design range cannot be followed by the twin), else the misfit.
    Years on the box's edge only on their inputs' sound side (the side away from their
    declared wear) do not withhold: as many of them (or the last year) make the prognosis
    unreliable, with the bound in the reason. Else unreliable when a year did not
    converge; else ok.

    Returns
    -------
    status : str
        ``ok``, ``withheld`` or ``unreliable``.
    reason : str
        One sentence with the figures ("" when ok).
    """
    from ..calibrate import STATUS_EDGE, STATUS_MISFIT, STATUS_UNCONVERGED
    st = np.asarray(up.status)
    edge_years = np.flatnonzero(st == STATUS_EDGE)
    # A year whose estimates lean on the box only on their inputs' sound side (an input
    # whose sound value lies near a bound the model cannot pass, a conductance near 0) says
    # nothing of a part worn past the box: it makes the prognosis unreliable, not withheld.
    sound = np.array([k for k in edge_years
                      if not any(_wear_side(cfg, j, side)
                                 for j, side in _edge_inputs(cfg, up, k))], dtype=int)
    bad = np.setdiff1d(np.flatnonzero((st == STATUS_MISFIT) | (st == STATUS_EDGE)), sound)
    if bad.size and (bad.size >= cfg.forecast.withhold_years or bad[-1] == st.size - 1):
        f, k0 = up.fit, int(bad[0])
        first = int(up.years[k0])
        misfit = np.flatnonzero(st == STATUS_MISFIT)
        edge = np.asarray(f["edge_share"], float)
        # A misfit whose years' estimates also sit on the box's edge where wear takes the
        # input (its degrading side): the twin cannot follow the plant because a part has
        # worn past the design range, which the edge's message says. On the other side, or
        # for an input whose degrading direction is not declared, the edge is the
        # calibration's way of making up for a structure the twin lacks (a delayed start
        # pinned the pump coefficient to its high bound in every year): the misfit's.
        if misfit.size and not any(_worn_past_box(cfg, up, edge, k) for k in misfit):
            k = int(misfit[np.argmax(f["window_rms"][misfit])])
            win = windows[int(f["window"][k])] if windows else "worst"
            return STATUS_WITHHELD, (
                f"prognosis withheld: the twin misses the plant by {f['window_rms'][k]:.1f} "
                f"noise sd in the {win} window (residual RMS {f['rms'][k]:.1f} sd in year "
                f"{int(up.years[k])}; {misfit.size} of {st.size} years miss) from year {first}; "
                "run 'twinmon diagnose'")
        k = int(bad[-1])
        j, side = _edge_side(cfg, up, edge, k)
        name, bound = _bound_words(cfg, j, side)
        return STATUS_WITHHELD, (
            f"prognosis withheld: the estimates of {name} sit on the design box's {side} "
            f"edge ({100 * f['edge_share'][k][j]:.0f} % of the posterior in year "
            f"{int(up.years[k])} within {100 * cfg.calibrate.edge_margin:g} % of the range "
            f"of {bound}) from year {first}"
            + (f", and the twin misses the plant in year(s) "
               f"{year_ranges(up.years[misfit])}" if misfit.size else "")
            + ": the plant needs, or nearly needs, inputs beyond the twin's box; widen "
            f"model.inputs.{name}.{side} or run 'twinmon diagnose'")
    if sound.size and (sound.size >= cfg.forecast.withhold_years or sound[-1] == st.size - 1):
        k = int(sound[-1])
        j, side = max(_edge_inputs(cfg, up, k), key=lambda js: up.fit["edge_share"][k][js[0]])
        name, bound = _bound_words(cfg, j, side)
        return STATUS_UNRELIABLE, (
            f"prognosis unreliable: the estimates of {name} lean on the design box's {side} "
            f"edge of {bound}, its sound side, in year(s) "
            f"{year_ranges(up.years[sound])}: the box cuts their spread there, and the trend "
            f"read from them may be off; {'lower' if side == 'low' else 'raise'} "
            f"model.inputs.{name}.{side} if the model allows it")
    unconv = np.flatnonzero(st == STATUS_UNCONVERGED)
    if unconv.size:
        return STATUS_UNRELIABLE, _unconverged(up, cfg, unconv)
    return STATUS_OK, ""


def _edge_inputs(cfg: Config, up, k: int) -> list:
    """The inputs whose estimates of year ``k`` lean on the box's edge (more than
    ``calibrate.edge_share`` of the posterior within the margin), each with the bound's
    side (``low`` or ``high``, by the year's mean)."""
    edge = np.asarray(up.fit["edge_share"], float)
    return [(j, _bound_side(cfg, up, k, j)) for j in range(len(cfg.model.input_names))
            if edge[k, j] > cfg.calibrate.edge_share]


def _bound_words(cfg: Config, j: int, side: str) -> tuple[str, str]:
    """Input ``j``'s name and its ``side`` bound with its units, as a reason says them."""
    name = cfg.model.input_names[j]
    spec = cfg.model.inputs[name]
    unit = f" {spec.units}" if spec.units not in ("", "1") else ""
    return name, f"{spec.low if side == 'low' else spec.high:g}{unit}"


def _bound_side(cfg: Config, up, k: int, j: int) -> str:
    """The bound of input ``j`` year ``k``'s estimates are nearer, by their mean."""
    spec = cfg.model.inputs[cfg.model.input_names[j]]
    return "low" if float(np.asarray(up.mean)[k, j]) < 0.5 * (spec.low + spec.high) else "high"


def _wear_side(cfg: Config, j: int, side: str, undeclared: bool = True) -> bool:
    """Whether bound ``side`` of input ``j`` is where its declared wear (``degrading``)
    takes it; ``undeclared`` for an input whose direction is not declared."""
    deg = cfg.model.inputs[cfg.model.input_names[j]].degrading
    if deg not in ("up", "down"):
        return undeclared
    return deg == {"high": "up", "low": "down"}[side]


def _edge_side(cfg: Config, up, edge: np.ndarray, k: int) -> tuple[int, str]:
    """The input whose estimates of year ``k`` lean most on the box's edge (``edge``: the
    posterior's share within the margin [n_y, d]) and the bound's side, ``low`` or ``high``.
    The draws pile up there when the plant needs a value beyond it, and also when its true
    value lies just inside: either way the box does not leave the estimate room, and
    widening it tells which."""
    j = int(np.argmax(edge[k]))
    return j, _bound_side(cfg, up, k, j)


def _worn_past_box(cfg: Config, up, edge: np.ndarray, k: int) -> bool:
    """Whether year ``k``'s estimates sit on the box's edge (``calibrate.edge_share``) on
    the degrading side of the input leaning on it."""
    j, side = _edge_side(cfg, up, edge, k)
    return edge[k, j] > cfg.calibrate.edge_share and _wear_side(cfg, j, side,
                                                                undeclared=False)


def box_bound_of(reason: str) -> Optional[str]:
    """The config key of the box bound a withheld unit's estimates sit on
    (``model.inputs.<name>.<low|high>``), read from the reason :func:`prognosis_status`
    wrote; None for any other reason."""
    import re
    m = re.search(r"sit on the design box's (?:low|high) edge .* widen (model\.inputs\.\S+?\."
                  r"(?:low|high)) ", reason)
    return m.group(1) if m else None


def _unconverged(up, cfg: Config, unconv: np.ndarray) -> str:
    """Why the years ``unconv`` (indices) are unreliable, with the figures that say so.

    Draws made without a chain per year (the laplace method: no acceptance rates) are the
    Gaussian model's weighted to the exact likelihood, moved by a Markov chain where the
    weights stay too uneven (their trend moves' acceptance recorded); too few effective
    draws mean the likelihood is far from any Gaussian and the chain slow along it."""
    cc = cfg.calibrate
    yrs = year_ranges(np.asarray(up.years)[unconv])
    ess = np.asarray(up.ess, float)[unconv]
    ext = np.asarray((up.fit or {}).get("extensions", [0]))
    more = int(ext[unconv].max()) if ext.size == len(up.years) else 0
    lowest = float(np.nanmin(ess)) if np.isfinite(ess).any() else float("nan")
    if np.isnan(np.asarray(up.acceptance, float)).all():
        tried = [f"doubled {more} time(s)"] if more else []
        if moved_by_chain(up.acceptance, (getattr(up, "trend", None) or {}).get("acceptance")):
            tried.append("moved by a Markov chain")
        doubled = f" even with the draws {' and '.join(tried)}" if tried else ""
        return (f"prognosis unreliable: the posterior of year(s) {yrs} rests on {lowest:.0f} "
                f"effective draws (calibrate.ess_warn {cc.ess_warn:g}){doubled}: the "
                "likelihood is far from Gaussian (inputs the recorded channels hardly tell "
                "apart, or estimates against the design box's edge)")
    rhat = np.asarray(up.rhat, float)[unconv]
    worst = float(np.nanmax(rhat)) if np.isfinite(rhat).any() else float("nan")
    return (f"prognosis unreliable: the posterior of year(s) {yrs} did not converge even "
            f"with longer chains (R-hat up to {worst:.3f}, ESS down to {lowest:.0f}; "
            f"calibrate.rhat_warn {cc.rhat_warn:g}, ess_warn {cc.ess_warn:g})")


def describe_blind(cfg: Config, drift: IndicatorDrift, years: np.ndarray) -> str:
    """Why a healthy verdict is unreliable: the record could miss a fault of
    ``forecast.detectable_multiple`` tolerances or more ("" when it could not, or off)."""
    limit = cfg.forecast.detectable_multiple
    m = np.asarray(drift.detectable, float)
    if not limit or m.size == 0 or not np.any(m > limit):
        return ""
    names = cfg.model.input_names
    order = [i for i in np.argsort(-np.where(np.isnan(m), -np.inf, m)) if m[i] > limit]
    what = ", or ".join(f"of {names[i]} up to {m[i]:.1f}x" if np.isfinite(m[i]) else
                        f"of {names[i]} of any size" for i in order)
    return (f"prognosis unreliable: with {len(years)} year(s) of record, a fault {what} would "
            "be missed half the time (x: its normal-ageing tolerance); 'healthy' does not "
            "rule it out")


def describe_lag(names: list, attenuation: np.ndarray) -> str:
    """Why a sequential unit's prognosis is unreliable when its yearly estimates of an input
    show less than :data:`~.covariance.MIN_ATTENUATION` of a drift
    (:func:`~.covariance.filter_attenuation`), or ``""``."""
    low = [(float(a), n) for n, a in zip(names, attenuation)
           if np.isfinite(a) and a < MIN_ATTENUATION]
    if not low:
        return ""
    what = ", ".join(f"{n} {100 * a:.0f} %" for a, n in sorted(low))
    return ("prognosis unreliable: each year's estimate leans on the year before (its data "
            f"give little a year), so the yearly estimates show only part of a steady drift "
            f"({what}): the trends, their tests and the failure year understate one; a less "
            "noisy record, or the fleet calibrated jointly (5 or more units), would show it")


def describe_bend(cfg: Config, shape: dict, years_future: np.ndarray, p_unsafe: np.ndarray,
                  failure_year: Optional[int], p_line: Optional[np.ndarray],
                  healthy: bool) -> str:
    """Why a unit with no fault found but a failure year is unreliable when only its trend's
    bend takes it there, or ``""``.

    No input's slope over the record is beyond normal ageing, so the failure year rests on
    the bent draws (the accelerating and change shapes) alone: the draws that extend a
    straight line (``p_line``, P(unsafe) per future year among them [h], when there are
    :data:`MIN_LINE_DRAWS` of them) stay at or under ``safety.failure_probability`` in the
    failure year; with fewer line draws, most of the posterior (``shape``, as
    :func:`~twinmon.calibrate.shapes.shape_summary` gives it) is on the bent shapes. Yearly
    estimates of inputs that trade off in the likelihood bend together as they slide along
    the trade-off (a healthy fan's belt slip and spindle drag arched up then down while its
    filter load curved up; extended, the bends took it past its limit in year 14, and it
    never fails); a fleet's prior of the shapes, learnt from its worn units, lends a sound
    one their bends. The record does not confirm such a bend."""
    if not healthy or failure_year is None or not shape:
        return ""
    k = int(np.flatnonzero(np.asarray(years_future) == failure_year)[0])
    limit = cfg.safety.failure_probability
    if p_line is not None:
        if p_line[k] > limit:
            return ""
        line = f"the straight-line draws {p_line[k]:.2f}"
    elif shape.get("line", 1.0) >= 0.5:
        return ""
    else:
        line = f"a straight line {shape.get('line', 0):.2f} of the posterior"
    return (f"prognosis unreliable: no input wears faster than normal ageing over its "
            f"record, yet the trend's bend alone takes the unit to its limit: P(unsafe) "
            f"{p_unsafe[k]:.2f} in year {failure_year}, {line} (accelerating "
            f"{shape.get('accelerating', 0):.2f}, a change {shape.get('change', 0):.2f}); "
            "estimates of inputs that trade off bend together as they slide along the "
            "trade-off, so the failure year is not confirmed (a channel that separates the "
            "inputs, or more years, would)")


def recent_restarts(since: dict, years: np.ndarray) -> dict:
    """The inputs whose trend restarted (after their first recorded year) fewer than
    :data:`MIN_TREND_YEARS` recorded years before the record's end: name -> (restart year,
    recorded years since)."""
    years = np.asarray(years)
    out = {}
    for n, y in since.items():
        k = int(np.sum(years >= y))
        if y > years[0] and k < MIN_TREND_YEARS:
            out[n] = (int(y), k)
    return out


def describe_restart(since: dict, years: np.ndarray) -> str:
    """Why a unit's prognosis is unreliable when an input's trend restarted (a recorded
    replacement, or a repair found in the estimates) fewer than :data:`MIN_TREND_YEARS`
    recorded years before the record's end, or ``""``.

    The new part's rate is then assumed, not measured (:func:`~.chunk.new_parts_as_before`:
    the rate of the part it replaced; :func:`~.trend.segment_trend`: normal ageing). Before
    either, a motor replaced in the last year was told to be inspected "now", with P(unsafe)
    26 % the next year, from its slope's wide prior.

    Parameters
    ----------
    since : dict input name -> int
        First year of each input's current part.
    years : ndarray of int, shape [n_y]
        The recorded years.
    """
    late = recent_restarts(since, years)
    if not late:
        return ""
    what = ", ".join(f"{n} in year {y} ({k} recorded year(s) since)"
                     for n, (y, k) in late.items())
    return (f"prognosis unreliable: the trend restarted after a repair, of {what}: too few "
            f"years (a trend needs {MIN_TREND_YEARS}) to show the new part's own rate, so the "
            "forecast assumes one (the rate of the part it replaced; normal ageing for a "
            "unit calibrated year by year)")


def describe_power(cfg: Config, drift: IndicatorDrift | None) -> str:
    """What a healthy verdict rules out: per input, the fault (in multiples of its
    normal-ageing tolerance) this record shows half the time (:func:`describe_blind` says
    when that is too large to trust the verdict). "" when the forecast did not record it.

    A repaired pump with four to six years since the repair, or a record of three or four
    years, shows a fault of two or three tolerances only about half the time on the flow
    alone; "healthy" with no figure would read as "no fault", which it is not."""
    m = np.asarray(getattr(drift, "detectable", ()), float)
    names = cfg.model.input_names
    if m.size != len(names) or np.all(np.isnan(m)):
        return ""
    parts = [f"{n} {v:.1f}x" if np.isfinite(v) else f"{n} of any size"
             for n, v in zip(names, m) if not np.isnan(v)]
    return (f"a fault shows in this record half the time from {', '.join(parts)} the "
            "input's normal-ageing tolerance; a smaller one may go unseen")


def _spread(draws: Optional[np.ndarray]) -> Optional[np.ndarray]:
    """``draws`` [n, d] when their covariance is positive definite, else None: draws that
    collapsed onto a few points (an unconverged weighting, the unit unreliable already)
    have no covariance to test with, and the tests fall back on the yearly means'
    regression (all-equal slopes stopped the forecast with "Singular matrix")."""
    if draws is None:
        return None
    C = np.atleast_2d(np.cov(draws, rowvar=False))
    if not np.all(np.isfinite(C)) or not np.all(np.diag(C) > 0):
        return None
    scale = np.sqrt(np.diag(C))
    return draws if np.linalg.eigvalsh(C / np.outer(scale, scale)).min() > 1e-10 else None


def _floored(C: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """``C`` [d, d] with its diagonal floored at a thousandth of each input's normal-ageing
    tolerance squared (or of 1e-12): the yearly means of a unit whose draws collapsed lie
    on one line, and a slope covariance of zero is no metric for the box tests (the unit
    is unreliable already; its slopes are then judged as if known)."""
    floor = (1e-3 * np.where(tol > 0, tol, 1e-9)) ** 2
    return C + np.diag(np.where(np.diag(C) > floor, 0.0, floor))


def history_slope_draws(trend: dict) -> Optional[np.ndarray]:
    """Draws [n, d] of each input's wear rate pooled over its trend's segments, or None when
    no input has more than one (no repair restarted a trend).

    A repair (recorded, or found by calibrate) restarts an input's trend; the component
    usually goes on wearing as fast as before (same duty, same kind of part). Per input, each
    draw's segment slopes are averaged with weights proportional to their posterior
    precision (a segment of two years weighs little): the rate the whole record shows if
    every segment wore alike.

    Parameters
    ----------
    trend : dict
        ``UnitPosterior.trend``: ``start`` [n_seg, d] (-1 = no such segment) and ``slope``
        [n, n_seg, d] (input units per year).
    """
    start = np.asarray(trend["start"])
    if not np.any((start >= 0).sum(axis=0) > 1):
        return None
    slope = np.asarray(trend["slope"], float)
    out = np.empty((slope.shape[0], start.shape[1]))
    for i in range(start.shape[1]):
        s = slope[:, start[:, i] >= 0, i]                                  # [n, k]
        w = 1.0 / np.maximum(s.var(axis=0, ddof=1), np.finfo(float).tiny)
        out[:, i] = s @ (w / w.sum())
    return out


def judge(cfg: Config, unit: str, plan: dict, ind_obs: np.ndarray, gradient: np.ndarray,
          directions: dict, observed: set) -> tuple[IndicatorDrift, Attribution]:
    """Detection on the health indicator (:mod:`.detection`), then attribution
    (:mod:`.attribution`).

    A unit is degrading when its indicator drifts beyond normal ageing or its inputs' slopes,
    jointly, leave the normal-ageing box; a unit whose indicator trend cannot be tested
    (fewer than 3 years with a finite indicator, e.g. a level no longer reached) is judged
    on its inputs alone."""
    from ..safety import Indicator
    names = cfg.model.input_names
    specs = [cfg.model.inputs[n] for n in names]
    rate = np.array([s.normal_rate for s in specs])
    tol = np.array([s.normal_rate_tolerance for s in specs])
    ind = Indicator.from_config(cfg)
    alpha = cfg.forecast.alpha
    years = plan["years"]
    after = years >= plan["since"]     # a repair restarts the trends
    slope_draws = _spread(plan["slope_draws"])
    # A joint unit's indicator slope is its posterior trend's (the slopes of the last
    # segments, i.e. after any repair), through the gradient: the null is built on the same
    # linearisation.
    drift = indicator_drift(years[after], ind_obs[after], gradient, rate, tol,
                            ind.sense, alpha, slope_draws=None if slope_draws is None
                            else slope_draws @ np.asarray(gradient, float))
    trends = plan["trends"]
    tl = [trends[n] for n in names]
    dirs = [directions[n].sign for n in names]
    if slope_draws is not None:
        # The joint method sampled the slopes with the years: test its posterior's own
        # slopes (their spread includes the year-to-year variation and every year's
        # uncertainty, with the correlations the yearly means' regression cannot see).
        b, C, dof = slope_draws.mean(axis=0), np.cov(slope_draws, rowvar=False), POSTERIOR_DOF
    else:
        err = plan["err_cov"][after][:, after]
        b = np.array([t.slope for t in tl])
        C, dof = slope_covariance(tl, plan["resid"], years[after], err), max(tl[0].dof, 1)
    C = _floored(np.atleast_2d(C), tol)
    drift.p_inputs = box_test_uniform(b, C, dof, rate, tol, dirs, unit_rng(cfg, unit, 4))
    history = _spread(plan.get("history_draws"))
    if history is not None:
        # A repair restarted a trend: the segments before it wore too. Their rates pooled
        # with the current one's test the component's wear between repairs, which a
        # segment of a few years since the repair cannot show alone.
        drift.p_history = box_test_uniform(history.mean(axis=0),
                                           np.atleast_2d(np.cov(history, rowvar=False)),
                                           POSTERIOR_DOF, rate, tol, dirs,
                                           unit_rng(cfg, unit, 5))
    current = _spread(plan.get("rate_draws"))
    if current is not None and plan.get("changed", 0.0) > CHANGED_SHARE:
        # The slopes above are chords over the segment: a part whose wear rate jumped late
        # (or accelerates) shows only part of its current rate in them (a water heater's
        # input ageing -1/yr, then -9/yr from year 5 of 10: chord -4.4/yr, p = 0.09, though
        # 94 % of the posterior lay on the change and accelerating shapes). Where the
        # posterior puts most of its weight on such shapes, the inputs' test is also made
        # on the trend's rate at the last year (its draws: the line's slope for the line's
        # draws, the rate since the change or at the curve's end for the others): a
        # healthy unit ages at a rate in its band now as over the record, so it is one
        # more view of the same question, pooled below. Not the indicator's: its gradient
        # is the mid-history state's, not the current one's. Not for a unit the line
        # explains: its current rate is its chord, and a further look would only cost the
        # other views' level. The shapes' evidence (curvature, a change beyond the line,
        # centred on the segment) is nearly independent of the line's slope, so the gate
        # leaves each stratum's test at its level when the unit ages normally (13 of the
        # 252 healthy units of benchmarks/prognosis.py's families pass it, none of them
        # then called degrading; docs/forecast.md).
        drift.p_inputs_rate = box_test_uniform(
            current.mean(axis=0), np.atleast_2d(np.cov(current, rowvar=False)),
            POSTERIOR_DOF, rate, tol, dirs, unit_rng(cfg, unit, 7))
    # Two to four views of one question, pooled by Simes' test at alpha: the indicator's
    # drift (sees a fault the inputs trade off between), the inputs' slopes jointly (sees a
    # fault another input's normal ageing hides from the indicator), the inputs' current
    # rates when wear changed and, after a repair, the wear rates pooled over the repairs.
    # Simes rejects whenever Bonferroni (alpha over the views' number) does, keeps alpha
    # when the views are positively dependent (each grows with the same rates), and costs
    # less than Bonferroni when views agree: two p-values each below alpha / 2 reject
    # however many views there are.
    tests = [p for p in (drift.p_value, drift.p_inputs, drift.p_inputs_rate, drift.p_history)
             if np.isfinite(p)]
    drift.abnormal = simes(tests, alpha)
    drift.detectable = detectable_multiples(drift, C, dof, tol, dirs, alpha / max(len(tests), 1))
    if not drift.abnormal:
        return drift, Attribution(HEALTHY)
    # The components are named from the slopes whose evidence is the strongest: the chord's,
    # the current rates' or the rates pooled over the repairs.
    draws = slope_draws
    best = drift.p_inputs
    for p, d in ((drift.p_inputs_rate, current), (drift.p_history, history)):
        if np.isfinite(p) and not p >= best:
            draws, best = d, p
    att = attribute(tl, names, [s.component or n for s, n in zip(specs, names)], C, rate, tol,
                    dirs, cfg.forecast.attribution_confidence, unit_rng(cfg, unit, 3),
                    draws=draws)
    if att.verdict == AMBIGUOUS and att.leading_slopes is not None:
        years = plan["years"]
        first = np.array([trends[n].intercept + trends[n].slope * years[0] for n in names])
        observed = observed | {cfg.model.output.variable}
        att.separating_channel, att.channel_scores = separating_channel(
            cfg, observed, first, att.leading_slopes, float(years[-1] - years[0]))
    return drift, att
