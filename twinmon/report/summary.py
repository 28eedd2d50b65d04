"""What the report says in words: the per-unit summary, the verdict and action words, the
terminal text and the content of ``summary.json``."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..config import Config
from .common import pct, plain, state_words
from .load import Inputs


@dataclass
class UnitSummary:
    """Plain-language state of one unit, derived from the artifacts given.

    Attributes
    ----------
    name : str
    health : str
        ``"healthy"``, ``"degrading: <component>"`` (components from the config's inputs), ...
        or ``"unknown"`` when no forecast was given.
    root_cause : str or None
        The forecast's verdict (``healthy``, a component name, ``both``), None without one.
    failure_year : int or None
        First future year with P(unsafe) above the limit (year of service): the year to act by.
    median_failure_year : int or None
        First future year with P(unsafe) >= 0.5: the point forecast of the failure.
    p_unsafe : float or None
        P(unsafe) in the failure year, or the largest over the horizon when none fails.
    last_year : int or None
        Last observed (or calibrated) year.
    horizon_end : int or None
        Last forecast year.
    last_indicator : float or None
        Health indicator of the last recorded transient (its units); inf for a level never
        reached.
    indicator : str
        The health indicator's name (from the config).
    last_indicator_text : str
        ``last_indicator`` for people, with its units.
    action : str
        Short recommendation, e.g. ``"inspect the <component> before year 13 ends"``.
    plan : str
        The forecast's full maintenance plan with its evidence ("" without a forecast).
    estimates : dict
        Latest year's estimate per input: ``{name: {year, mean, q05, q95, units}}``.
    confidence : str
        What the statements rest on (tests, diagnostics), in one or two sentences.
    diagnose : dict or None
        The sim-to-real gap verdict of this unit, if a gap artifact was given.
    true_failure_year : int or None
        From the forecast's truth check, when the data were fabricated.
    """

    name: str
    health: str = "unknown"
    root_cause: Optional[str] = None
    failure_year: Optional[int] = None
    median_failure_year: Optional[int] = None
    p_unsafe: Optional[float] = None
    last_year: Optional[int] = None
    horizon_end: Optional[int] = None
    last_indicator: Optional[float] = None
    indicator: str = "indicator"
    last_indicator_text: str = ""
    action: str = ""
    plan: str = ""
    estimates: dict = field(default_factory=dict)
    confidence: str = ""
    diagnose: Optional[dict] = None
    true_failure_year: Optional[int] = None
    #: The prognosis status (``ok``, ``withheld``, ``unreliable``; ``none`` without a
    #: forecast), why, and whether a withheld prognosis was forced.
    status: str = "none"
    status_reason: str = ""
    forced: bool = False
    #: Largest P(unsafe) over the horizon, and P(unsafe) 1, 2, ... years after the last
    #: observation (the fleet overview ranks and sums them); None / () without a prognosis.
    p_unsafe_max: Optional[float] = None
    p_unsafe_ahead: tuple = ()

    @property
    def status_words(self) -> str:
        """The status as a maintenance engineer reads it at a glance."""
        return {"ok": "prognosis given: the twin fits the data",
                "withheld": ("FORCED prognosis: the twin misses the plant" if self.forced
                             else "prognosis withheld: the twin misses the plant"),
                "unreliable": "prognosis unreliable: calibration did not converge",
                "none": "no forecast"}.get(self.status, self.status)

    @property
    def short_health(self) -> str:
        if self.status == "withheld" and not self.forced:
            return "prognosis withheld"
        words = state_words(self.root_cause)
        return f"{words} (forced)" if self.forced else \
            f"{words} (unreliable)" if self.status == "unreliable" else words

    @property
    def median_note(self) -> str:
        """``"; median year 15"`` where the median failure year (the point forecast) differs
        from the year to act by, ``"; median after year 17"`` past the horizon, else ""."""
        med = self.median_failure_year
        if self.failure_year is None or med == self.failure_year:
            return ""
        return f"; median year {med}" if med is not None else \
            f"; median after year {self.horizon_end}"

    @property
    def time_to_failure(self) -> str:
        """e.g. ``"fails in year 14 (P(unsafe) 12 % in 14; median year 15)"`` (the median
        year where it differs from the year to act by)."""
        if self.status == "withheld" and not self.forced:
            return "withheld: the twin misses the plant"
        if self.root_cause is None:
            if self.last_indicator is None:
                return "no forecast"
            return f"last {self.indicator} {self.last_indicator_text} (no forecast)"
        if self.failure_year is not None:
            return (f"fails in year {self.failure_year} "
                    f"(P(unsafe) {pct(self.p_unsafe)} in {self.failure_year}{self.median_note})")
        return f"no failure by year {self.horizon_end} (max P(unsafe) {pct(self.p_unsafe)})"

    def as_dict(self) -> dict:
        return {
            "health": self.health, "root_cause": self.root_cause,
            "failure_year": self.failure_year,
            "median_failure_year": self.median_failure_year, "p_unsafe": self.p_unsafe,
            "last_year": self.last_year, "horizon_end": self.horizon_end,
            "last_indicator": (None if self.last_indicator is None
                               or not np.isfinite(self.last_indicator)
                               else round(float(self.last_indicator), 3)),
            "last_indicator_text": self.last_indicator_text or None,
            "time_to_failure": self.time_to_failure, "action": self.action, "plan": self.plan,
            "estimates": self.estimates, "confidence": self.confidence,
            "diagnose": self.diagnose, "true_failure_year": self.true_failure_year,
            "status": self.status, "status_reason": self.status_reason or None,
            "status_words": self.status_words, "forced": self.forced,
            "p_unsafe_max": self.p_unsafe_max,
        }


@dataclass
class ReportSummary:
    """What :func:`~twinmon.report.report` wrote; ``as_dict()`` is the content of
    ``summary.json``.

    Attributes
    ----------
    output_dir : str
    index : str
        Path of ``index.html``.
    units : dict of str to UnitSummary
    sections : dict of str to str
        ``"rendered"`` or ``"skipped: <why>"`` per section.
    figures : list of dict
        ``{name, section, title, caption, file, path}`` per PNG written (``file`` relative
        to ``output_dir``).
    surrogate : dict or None
        Validation figures of the surrogate on the test runs.
    calibration : dict or None
        Convergence diagnostics per unit (R-hat, ESS, acceptance, noise).
    artifacts : dict of str to str
        The artifacts the report was made from.
    notes : list of str
    output : dict
        The observed output's words: ``{name, label, units}``.
    indicator : dict
        The health indicator: ``{name, label, units, kind, variable, limit, sense, rule}``.
    fleet : dict or None
        For a fleet of more than ``report.detail_units`` units: the ranking, verdict counts,
        units at risk and units drawn in detail (:class:`~twinmon.report.fleet.FleetView`).
    """

    output_dir: str
    index: str
    units: dict[str, UnitSummary]
    sections: dict[str, str]
    figures: list[dict]
    surrogate: Optional[dict] = None
    calibration: Optional[dict] = None
    artifacts: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    output: dict = field(default_factory=dict)
    indicator: dict = field(default_factory=dict)
    fleet: Optional[dict] = None

    def as_dict(self) -> dict:
        return {**({"fleet": self.fleet} if self.fleet is not None else {}),
            "units": {u: s.as_dict() for u, s in self.units.items()},
            "sections": dict(self.sections),
            "figures": list(self.figures),
            "surrogate": self.surrogate,
            "calibration": self.calibration,
            "artifacts": dict(self.artifacts),
            "notes": list(self.notes),
            "output": dict(self.output),
            "indicator": dict(self.indicator),
            "index": self.index,
        }

    def terminal(self) -> str:
        """A short multi-line text: one line per unit, then the report's path."""
        if not self.units:
            lines = ["report: no units"]
        elif self.fleet is not None:
            from .fleet import FleetView, overview_lines
            ends = [s.horizon_end - s.last_year for s in self.units.values()
                    if s.horizon_end is not None and s.last_year is not None]
            lines = overview_lines(FleetView(**self.fleet), self.units,
                                   max(ends) if ends else None)
        else:
            w = max(len(u) for u in self.units)
            h = max(len(s.short_health) for s in self.units.values())
            t = max(len(s.time_to_failure) for s in self.units.values())
            lines = [f"{u:<{w}}  {s.short_health:<{h}}  {s.time_to_failure:<{t}}"
                     + (f"  -> {s.action}" if s.action else "")
                     for u, s in self.units.items()]
        skipped = [k for k, v in self.sections.items() if v != "rendered"]
        if skipped:
            lines.append(f"(skipped: {', '.join(skipped)})")
        return "\n".join(lines)


def words_dict(inp: Inputs) -> tuple[dict, dict]:
    """The output's and the indicator's words, for ``summary.json``."""
    cfg, ind = inp.cfg, inp.words.ind
    out = cfg.model.output
    return ({"name": out.name, "variable": out.variable, "label": out.label, "units": out.units},
            {"name": ind.name, "label": ind.label, "units": ind.units, "kind": ind.spec.kind,
             "variable": ind.variable, "limit": ind.limit, "sense": ind.sense,
             "rule": ind.rule})


def calibration_diagnostics(inp: Inputs) -> dict:
    """Convergence diagnostics per unit and the sampler's warnings (``summary.json``)."""
    from ..calibrate import diagnostics_warnings
    post, cfg = inp.posterior, inp.cfg
    units, warnings = {}, []
    names = list(post.input_names)
    for u, p in post.units.items():       # one read of each unit (a fleet's are lazy)
        units[u] = {"years": [int(y) for y in p.years],
                    "max_rhat": float(np.nanmax(p.rhat)), "min_ess": float(np.nanmin(p.ess)),
                    "acceptance": [float(np.min(p.acceptance)), float(np.max(p.acceptance))],
                    "noise_std": float(np.asarray(p.noise_std)[0]),
                    "noise_source": p.noise_source}
        warnings += diagnostics_warnings({u: p}, names, cfg)
    return {"units": units, "warnings": warnings}


def faulty_components(cfg: Config, uf) -> list[str]:
    """Components the forecast's attribution names, with their probabilities when the data
    cannot tell which ("pump 0.62 or motor 0.38"); for forecasts made before attribution,
    the components of the inputs whose slope test rejects (the config's ``component``
    words; the input's name when it has none)."""
    att = getattr(uf, "attribution", None)
    if att is not None and att.verdict != "withheld":
        probs = att.probabilities
        if att.verdict == "healthy":
            return []
        if att.verdict == "ambiguous":
            return [" or ".join(f"{c} {probs[c]:.2f}" for c in
                                sorted(probs, key=lambda c: -probs[c])) + " (ambiguous)"]
        conf = cfg.forecast.attribution_confidence
        return sorted(c for c, p in probs.items() if p >= conf)
    out = set()
    for name, t in uf.trends.items():
        if t.rejects:
            spec = cfg.model.inputs.get(name)
            out.add((spec.component if spec is not None else "") or t.component or name)
    return sorted(out)


def unit_summary(unit: str, inp: Inputs, observed: dict) -> UnitSummary:
    """The plain-language summary of one unit; ``observed``: {unit: (years, indicator)}."""
    cfg, ind = inp.cfg, inp.words.ind
    s = UnitSummary(unit, indicator=ind.name)
    limit = cfg.safety.failure_probability
    if unit in observed:
        yrs, values = observed[unit]
        s.last_year, s.last_indicator = int(yrs[-1]), float(values[-1])
        s.last_indicator_text = ind.fmt(s.last_indicator)
    elif inp.obs is not None and unit in inp.obs.units:
        s.last_year = int(inp.obs.units[unit].years[-1])
    post = inp.posterior.units.get(unit) if inp.posterior is not None else None
    if post is not None:
        s.last_year = s.last_year or int(post.years[-1])
        s.estimates = {
            name: {"year": int(post.years[-1]), "mean": float(post.mean[-1, j]),
                   "q05": float(post.q05[-1, j]), "q95": float(post.q95[-1, j]),
                   "units": cfg.model.inputs[name].units if name in cfg.model.inputs else ""}
            for j, name in enumerate(inp.posterior.input_names)}
    uf = inp.forecast.units.get(unit) if inp.forecast is not None else None
    gap = (inp.gap.units.get(unit) if inp.gap is not None and inp.gap_other_source is None
           else None)
    why: list[str] = []

    if uf is not None:
        s.status, s.status_reason, s.forced = uf.status, uf.status_reason, uf.forced
    if uf is not None and uf.status == "withheld" and not uf.forced:
        # No failure year and no root cause from a twin that misses the data: say so, and
        # what would settle it.
        s.root_cause = uf.root_cause
        s.health = "not judged (see status)"
        s.horizon_end = int(uf.years_future[-1])
        s.last_year = s.last_year or int(uf.years_observed[-1])
        s.plan = uf.plan
        s.action = "run `twinmon diagnose` to find what the twin lacks; no prognosis until it fits"
        why.append(uf.status_reason)
    elif uf is not None:
        comps = faulty_components(cfg, uf)
        s.root_cause = uf.root_cause
        s.health = "healthy" if not comps else "degrading: " + " and ".join(comps)
        if uf.forced:
            s.health += " (FORCED: the twin misses the plant)"
            why.append("FORCED: " + uf.status_reason)
        elif uf.status == "unreliable":
            s.health += " (unreliable)"
            why.append(uf.status_reason)
        s.failure_year = uf.failure_year
        s.median_failure_year = uf.median_failure_year
        s.p_unsafe_ahead = tuple(float(p) for p in uf.p_unsafe)
        s.p_unsafe_max = max(s.p_unsafe_ahead) if s.p_unsafe_ahead else None
        s.horizon_end = int(uf.years_future[-1])
        s.last_year = s.last_year or int(uf.years_observed[-1])
        s.plan = uf.plan
        s.true_failure_year = uf.true_failure_year if uf.has_truth else None
        yf = np.asarray(uf.years_future)
        last = int(uf.years_observed[-1])
        what = " and the ".join(comps) if comps else None
        if uf.failure_year is not None:
            s.p_unsafe = float(uf.p_unsafe[int(np.flatnonzero(yf == uf.failure_year)[0])])
            now = (uf.p_unsafe_observed.size and uf.p_unsafe_observed[-1] > limit) \
                or uf.failure_year <= last + 1
            when = "now" if now else f"before year {uf.failure_year - 1} ends"
            s.action = (f"inspect the {what} {when}" if what
                        else f"overhaul the unit {when} (normal ageing reaches the limit)")
        else:
            s.p_unsafe = float(np.max(uf.p_unsafe)) if uf.p_unsafe.size else 0.0
            s.action = (f"inspect the {what} at the next planned stop" if what
                        else "no action; re-check at next year's recorded transient")
        for name, t in uf.trends.items():
            if t.rejects:
                lo, hi = t.slope_ci
                why.append(f"{name} drifts {t.slope:+.3g}/yr (90 % interval {lo:+.3g} to "
                           f"{hi:+.3g}) against normal ageing {t.normal_rate:+.3g} +- {t.tolerance:.3g}/yr "
                           f"({'one' if t.direction else 'two'}-sided test, p = {t.p_value:.1g})")
        if not comps:
            pmin = min(t.p_value for t in uf.trends.values())
            why.append(f"every input drifts within normal ageing (tests of the slopes, all "
                       f"p >= {np.floor(pmin * 100) / 100:.2f})")
        why.append(f"P(unsafe) from {uf.n_samples} Monte Carlo draws of the {ind.name} "
                   f"per year through the twin; failure = first year above {100 * limit:g} %")
    elif post is not None:
        s.action = "run `twinmon forecast` for a trend and a time to failure"
    else:
        s.action = "run `twinmon calibrate` and `twinmon forecast` for a diagnosis"
        if s.last_indicator is not None and bool(ind.unsafe(np.asarray(s.last_indicator))):
            s.action = (f"unsafe at the last recorded transient ({ind.name} "
                        f"{s.last_indicator_text}, {ind.rule} is unsafe): inspect the unit; "
                        + s.action)

    if post is not None:
        cc = cfg.calibrate
        rmax, emin = float(np.nanmax(post.rhat)), float(np.nanmin(post.ess))
        if post.fit and s.status != "withheld":
            why.append(f"the twin fits every calibrated year (residual RMS <= "
                       f"{float(np.max(post.fit['rms'])):.2f} noise sd)"
                       if np.all(post.status != "misfit") else
                       f"the twin misses the plant in {int(np.sum(post.status == 'misfit'))} "
                       "year(s)")
        if rmax <= cc.rhat_warn and emin >= cc.ess_warn:
            why.append(f"calibration converged (R-hat <= {rmax:.3f}, ESS >= {emin:.0f})")
        else:
            why.append(f"calibration diagnostics miss their thresholds (max R-hat {rmax:.3f} "
                       f"vs {cc.rhat_warn:g}, min ESS {emin:.0f} vs {cc.ess_warn:g}): the "
                       "intervals are less certain than they look")

    if gap is not None:
        s.diagnose = {
            "verdict": gap.verdict, "effects": list(gap.effects), "group": list(gap.group),
            "onset": gap.onset, "where_windows": list(gap.where_windows),
            "where_years": [int(y) for y in gap.where_years],
            "absorbed_share": plain(float(gap.absorbed_share)),
            "closed_percent": plain(float(gap.closed_percent)),
            "rms_before": plain(float(gap.rms_before)), "rms_after": plain(float(gap.rms_after)),
            "separating_channel": gap.separating_channel or None,
            "failure_year_before": gap.failure_year_before,
            "failure_year_after": gap.failure_year_after,
            "groups": list(getattr(gap, "groups", []) or []),
            "estimate": {k: {"mean": plain(float(v[0])), "q05": plain(float(v[1])),
                             "q95": plain(float(v[2]))} for k, v in gap.estimate.items()},
        }
        withheld = s.status == "withheld" and not s.forced
        if gap.verdict == "unexplained" and withheld:
            s.action = ("revise the model: the twin misses the plant and no candidate effect of "
                        "model.effects explains the gap (diagnose)")
        elif gap.verdict == "none" and withheld:
            # The two stages disagree: say it rather than let one silently win.
            why.append("diagnose found no significant gap although calibration finds the twin "
                       "missing the plant; compare their settings (noise, windows, alpha)")
        if gap.verdict == "effect":
            group = gap.group if len(gap.group) > 1 else gap.effects
            eff = " or ".join(group)
            groups = getattr(gap, "groups", None) or []
            if len(groups) > 1:
                # Several effects: one of each group, which one the data cannot tell.
                eff = " and ".join("(" + " or ".join(m["effect"] for m in grp["members"]) + ")"
                                   if len(grp["members"]) > 1 else grp["effect"]
                                   for grp in groups)
            if s.status == "withheld" and not s.forced:
                s.action = (f"check {eff} (diagnose: the twin misses the plant from year "
                            f"{gap.onset}); with it in the twin, diagnose projects "
                            + (f"failure in year {gap.failure_year_after}"
                               if gap.failure_year_after is not None
                               else "no failure within the horizon"))
            else:
                s.action += (f"; the twin misses the plant from year {gap.onset}: check {eff}"
                             if gap.onset is not None
                             else f"; the twin misses the plant: check {eff}")
            if s.status != "withheld" or s.forced:
                why.append("the failure year shown is the forecast's (the calibrated twin, "
                           f"without {eff}); diagnose's projection with it is "
                           + (f"year {gap.failure_year_after}"
                              if gap.failure_year_after is not None
                              else "no failure within the horizon"))
            eff_units = {k: (cfg.model.effects[k].units if k in cfg.model.effects else "")
                         for k in gap.estimate}
            est = "; ".join(f"{k} = {v[0]:.3g} (90 % interval {v[1]:.3g} to {v[2]:.3g}) "
                            f"{'' if eff_units[k] == '1' else eff_units[k]}".rstrip()
                            for k, v in gap.estimate.items())
            where = " and ".join(gap.where_windows)
            plural = "s" if len(gap.where_windows) > 1 else ""
            why.append(f"diagnose: the gap sits in the {where or 'whole record'} window{plural}; "
                       "adding "
                       f"{', '.join(gap.effects)} closes {gap.closed_percent:.0f} % of the "
                       f"excess gap (BIC gain {gap.delta_bic_final:.0f}); {est}"
                       + (f"; {gap.separating_channel} would tell the group apart"
                          if len(gap.group) > 1 and gap.separating_channel else ""))
            share = float(gap.absorbed_share)
            if uf is not None and np.isfinite(share) and share > 0.1 and s.status != "withheld":
                why.append(f"the calibrated twin lacks this effect and its degradation inputs "
                           f"absorb {100 * share:.0f} % of its signature, so the root cause and "
                           "time to failure above may be biased")
            if gap.failure_year_before != gap.failure_year_after:
                why.append(f"with the effect in the twin the projected failure year moves from "
                           f"{gap.failure_year_before or 'none'} to "
                           f"{gap.failure_year_after or 'none'}")
            for grp in groups:
                if grp.get("failure_year_spread"):
                    # The named member's year alone would be arbitrary: show each member's.
                    why.append(
                        f"the effects that cannot be told apart for {grp['effect']} project "
                        "different failure years: " + ", ".join(
                            f"{m['effect']} ({100 * m['weight']:.0f} %) "
                            + (f"year {m['failure_year']}" if m["failure_year"] is not None
                               else "none within the horizon") for m in grp["members"])
                        + (f"; {grp['separating_channel']} would tell them apart"
                           if grp.get("separating_channel") else ""))
        elif gap.verdict == "unexplained":
            s.action += "; the twin misses the plant and no candidate explains it: check the data"
            why.append("diagnose: a significant gap no candidate effect explains, so the "
                       "estimates may be biased")
        else:
            why.append("diagnose: no significant gap between the twin and the plant")
    if s.true_failure_year is not None or (uf is not None and uf.has_truth):
        why.append(f"true failure year (fabricated data): {s.true_failure_year or 'none'}")
    s.confidence = "; ".join(why) + ("." if why else "")
    return s
