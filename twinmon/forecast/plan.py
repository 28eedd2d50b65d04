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
from .trend import safe_way


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


#: Probability of being at fault below which a component is not among a plan's candidates.
CANDIDATE_FLOOR = 0.05


def ambiguous_candidates(probs: dict, confidence: float) -> tuple[list, list]:
    """An ambiguous attribution's candidates, most probable first: ``(sure, doubt)``, the
    components at fault with probability at least ``confidence`` and the others above
    :data:`CANDIDATE_FLOOR` (a part all but surely sound is none of them: with three parts
    or more, a sure one beside two in doubt read "the rotor or the prefilter or the
    vee-belt or the spindle", the spindle at 0.00). The plan and the report word them."""
    cands = sorted((c for c in probs if probs[c] > CANDIDATE_FLOOR), key=lambda c: -probs[c])
    sure = [c for c in cands if probs[c] >= confidence]
    return sure, [c for c in cands if c not in sure]


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
            # The candidates, most probable first; one surely at fault is named as such.
            sure, doubt = ambiguous_candidates(probs, conf)
            cands = sure + doubt
            faulty, maybe = (sure, doubt) if sure else (doubt, [])
            evidence += ("; the data cannot tell " + ("which component: " if not maybe else
                                                       "which others wear too: ") +
                         ", ".join(f"{c} {probs[c]:.2f}" for c in cands) +
                         (f"; recording {attribution.separating_channel} would separate them"
                          if attribution.separating_channel else ""))
        else:
            faulty = sorted(c for c, pr in probs.items() if pr >= conf)
            maybe = sorted(c for c, pr in probs.items() if CANDIDATE_FLOOR < pr < conf)
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
    # An ambiguous attribution lists the candidates, most probable first (those surely at
    # fault named together, the others in its evidence).
    join = " or the " if attribution is not None and attribution.verdict == AMBIGUOUS \
        and not maybe else " and the "
    # A part beyond normal ageing the safe way is no risk by the indicator, nor normal.
    away = safe_way(trends, cfg.forecast.alpha) if cfg is not None else {}
    # (Nor is a part whose own slope test rejects where the unit's tests together named no
    # fault: unconfirmed says so.)
    odd = {c for c, ts in comps.items() if any(n in away or t.rejects for n, t in ts)}
    sound = [c for c in sound if c not in odd]
    sound_txt = (f"; {' and '.join(sound)} within normal ageing" if sound else "")
    if away:
        sound_txt += "; " + "; ".join(
            f"{n} drifts {trends[n].slope:+.3g}/yr, beyond normal ageing "
            f"({trends[n].normal_rate:+.3g} +- {trends[n].tolerance:.3g}/yr) but away from "
            f"the limit (p = {p:.2g}): no risk by this indicator, yet not normal ageing -- "
            f"check the {trends[n].component or n}" for n, p in away.items())
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
    if away:
        return (f"No action for safety: no component wears towards the limit faster than "
                f"normal ageing; P(unsafe) stays <= {limit:.2f} through year {horizon_end} "
                f"(max {pmax:.2f}){sound_txt}.")
    return (f"No action: all components within normal ageing; P(unsafe) stays <= {limit:.2f} "
            f"through year {horizon_end} (max {pmax:.2f}). Re-check at next year's recording.")


def restore_points(cfg: Config, state: np.ndarray) -> np.ndarray:
    """The unit's state ``state`` [d] with each input alone set back to its nominal value
    (``model.inputs.<name>.nominal``), and then every input: [d + 1, d], row ``i < d``
    restoring input ``i``, row ``d`` the nominal unit."""
    names = cfg.model.input_names
    nominal = [cfg.model.inputs[n].nominal for n in names]
    out = np.repeat(np.asarray(state, float)[None, :], len(names) + 1, axis=0)
    out[np.arange(len(names)), np.arange(len(names))] = nominal
    out[-1] = nominal
    return out


def nominal_plan(cfg: Config, value: float, p_unsafe_now: float, last_year: int) -> str:
    """The sentence of a unit past its limit that a new unit crosses too: no part to blame,
    the limit (``safety.unsafe_if``) is the thing to check."""
    from ..safety import Indicator
    ind = Indicator.from_config(cfg)
    side = "above" if ind.sense > 0 else "below"
    return (f"Check the limit: the unit is past it (P(unsafe) {p_unsafe_now:.2f} in year "
            f"{last_year}), but so is a new unit -- at every input's nominal value the twin's "
            f"{ind.name} is {ind.fmt(value)}, unsafe by safety.unsafe_if ({side} "
            f"{ind.fmt(ind.limit)}); no part's wear or level is to blame")


def level_cause(cfg: Config, state: np.ndarray, unsafe: np.ndarray, value: np.ndarray,
                current: float) -> dict:
    """Which inputs' levels put a unit past its limit when no drift explains it (a part
    fitted worn, or a step before or early in the record: its slope is normal, so the
    detection, which tests wear rates, calls the unit healthy while it is unsafe).

    Each input alone is set back to nominal at the unit's last state (:func:`restore_points`)
    and the twin judges the result: the inputs whose restoration alone makes the unit safe
    are named; when none does alone, those whose restoration moves the indicator towards
    safe, most first (several parts together).

    Parameters
    ----------
    state : ndarray, shape [d]
        The unit's last estimated inputs (input units).
    unsafe, value : ndarray, shape [d] (or [d + 1], the nominal unit last)
        The twin's verdict and health indicator at the restored points; with the nominal
        unit, no input is named when it is unsafe too and no single restoration helps (a
        limit a new unit crosses blames no part).
    current : float
        The indicator at the unit's last state (the posterior's median).

    Returns
    -------
    dict
        ``{input: {"value", "nominal", "restored", "safe"}}`` for the inputs named, in
        order; empty when no input's restoration helps.
    """
    from ..safety import Indicator
    sense = Indicator.from_config(cfg).sense
    names = cfg.model.input_names
    d = len(names)
    with np.errstate(invalid="ignore"):
        gain = sense * (float(current) - np.asarray(value[:d], float))
    gain = np.where(np.isnan(gain), 0.0, gain)
    alone = [i for i in range(d) if not unsafe[i]]
    if not alone and len(unsafe) > d and unsafe[d]:
        return {}
    pick = alone if alone else [i for i in np.argsort(-gain) if gain[i] > 0]
    return {names[i]: {"value": float(state[i]), "nominal": cfg.model.inputs[names[i]].nominal,
                       "restored": float(value[i]), "safe": bool(not unsafe[i])}
            for i in pick}


def level_plan(cfg: Config, levels: dict, p_unsafe_now: float, last_year: int) -> str:
    """The maintenance sentence of a unit unsafe at a level (:func:`level_cause`)."""
    from ..safety import Indicator
    ind = Indicator.from_config(cfg)
    comps = list(dict.fromkeys(cfg.model.inputs[n].component or n for n in levels))
    parts = []
    for n, v in levels.items():
        u = cfg.model.inputs[n].units
        parts.append(f"{n} {v['value']:.4g} {u} (nominal {v['nominal']:.4g}; at nominal "
                     f"{ind.name} {ind.fmt(v['restored'])}"
                     + (", safe)" if v["safe"] else ")"))
    alone = all(v["safe"] for v in levels.values())
    # Each restoration alone safe: any one of the parts brings the unit back (not that each
    # alone would put it past: the twin judged each restored, the others as they are).
    join = " or the " if alone and len(comps) > 1 else " and the "
    return (f"Inspect/replace the {join.join(comps)} now (already unsafe: P(unsafe) "
            f"{p_unsafe_now:.2f} in year {last_year}): a level, not a drift -- "
            + "; ".join(parts)
            + (" -- together put the unit past its limit; restoring any one of them makes it "
               "safe" if alone and len(parts) > 1
               else " -- puts the unit past its limit" if alone
               else " -- together put the unit past its limit; no one of them restored alone "
               "makes it safe")
            + "; no input wears faster than normal ageing, so the level dates from before "
            "the record or from a step in it.")


def unconfirmed(cfg: Config, trends: dict, drift: Optional[IndicatorDrift],
                failure_year: Optional[int], years_future: np.ndarray,
                p_unsafe: np.ndarray) -> Optional[tuple[dict, str]]:
    """A unit judged healthy although an input's own slope test rejects: the unit's tests
    together (the indicator's drift, the inputs' slopes jointly: a test per input would
    find one of several inputs beyond its band by chance) did not confirm it, so no fault is
    named; but its part is the one to watch, and with a failure year the first to inspect
    (a fan's belt slip rising 0.3/yr, p = 0.02 alone, was "healthy: overhaul the unit", and
    its belt failed). Returns ``({component: why}, plan)``, or None when no input rejects.
    The plan replaces a plan without a failure year, and comes first in one with it."""
    lone = [n for n, t in trends.items() if t.rejects]
    if not lone:
        return None
    comps = list(dict.fromkeys(trends[n].component or n for n in lone))
    tests = ""
    if drift is not None:
        parts = [f"{what} p = {v:.2g}" for what, v in
                 (("indicator", drift.p_value), ("inputs jointly", drift.p_inputs))
                 if np.isfinite(v)]
        tests = f" ({', '.join(parts)})" if parts else ""
    alone = "; ".join(f"{n}'s slope {trends[n].slope:+.3g}/yr (p = {trends[n].p_value:.2g})"
                      for n in lone)
    said = (f"{alone} is beyond normal ageing alone, not once the unit's inputs are tested "
            f"together{tests}: no fault is named")
    limit = cfg.safety.failure_probability
    if failure_year is None:
        horizon = int(years_future[-1]) if np.size(years_future) else 0
        plan = (f"No action for safety: P(unsafe) stays <= {limit:.2f} through year {horizon} "
                f"(max {float(np.max(p_unsafe)) if np.size(p_unsafe) else 0.0:.2f}); {said}; "
                f"watch the {' and the '.join(comps)} (next year's record will tell).")
    else:
        plan = f"Inspect the {' and the '.join(comps)} first: {said}."
    return {c: "its slope alone beyond normal ageing" for c in comps}, plan


def accelerating(cfg: Config, name: str, failure_year: Optional[int],
                 years_future: np.ndarray, p_unsafe: np.ndarray, plan: str
                 ) -> tuple[dict, str]:
    """A unit with no fault found whose input ``name`` accelerates
    (:func:`~.trend.shape_gate`): the part to watch ``{component: why}`` and the plan, which
    names it (first, before ``plan``, when the unit has a failure year; in place of
    ``plan``'s "no action" otherwise)."""
    comp = cfg.model.inputs[name].component or name
    if failure_year is None:
        return {comp: "wear accelerating"}, (
            f"Inspect the {comp} at the next planned stop: no input's slope over the record is "
            "beyond normal ageing, but its wear accelerates; on the straight-line trends "
            f"P(unsafe) stays <= {cfg.safety.failure_probability:.2f} through year "
            f"{int(years_future[-1])} (max {float(np.max(p_unsafe)):.2f}).")
    return {comp: "wear accelerating"}, (
        f"Inspect the {comp} first: its wear accelerates, though no input's slope over the "
        f"record is beyond normal ageing. {plan}")
