"""What the report says in words: the per-unit summary, the verdict and action words, the
terminal text and the content of ``summary.json``."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..config import Config
from ..forecast.judge import box_bound_of, describe_power
from ..forecast.plan import ambiguous_candidates, no_fault_due
from ..forecast.trend import safe_way
from ..repairs import FoundRepair
from ..safety import trailing_run
from .common import plain
from .fleet import FleetView, overview_lines
from .load import Inputs
from .unit_summary import UnitSummary


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
    made_from : dict
        What the report was made from (:func:`~twinmon.report.stage.made_from`): ``twinmon
        run`` makes it again only when that changed.
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
    made_from: dict = field(default_factory=dict)

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
            "terminal": self.terminal(),
            "made_from": dict(self.made_from),
        }

    def terminal(self) -> str:
        """A short multi-line text: one line per unit, then the report's path."""
        if not self.units:
            lines = ["report: no units"]
        elif self.fleet is not None:
            ends = [s.horizon_end - s.last_year for s in self.units.values()
                    if s.horizon_end is not None and s.last_year is not None]
            lines = overview_lines(FleetView(**self.fleet), self.units,
                                   max(ends) if ends else None)
        else:
            w = max(len(u) for u in self.units)
            h = max(len(s.short_health) for s in self.units.values())
            t = max(len(s.time_to_failure) for s in self.units.values())
            lines = []
            # Candidates hidden alike on every unit (a fleet recording the same channels)
            # are said once, after the units, as twinmon diagnose says them.
            shared = shared_hidden([s.diagnose for s in self.units.values()])
            for u, s in self.units.items():
                lines.append(f"{u:<{w}}  {s.short_health:<{h}}  {s.time_to_failure:<{t}}"
                             + (f"  -> {s.action}" if s.action else ""))
                lines += diagnose_lines(s.diagnose, hidden=not shared)
            if shared:
                from ..diagnose.text import hidden_line
                lines.append(f"every unit: {hidden_line(shared)}")
        sur = self.surrogate or {}
        if sur.get("max_range_error") is not None:
            n = f" on {sur['n_test']} test runs" if sur.get("n_test") else ""
            lines.append(f"surrogate: max error {100 * sur['max_range_error']:.3g} % of the "
                         f"output's range{n}"
                         + (f" (warning: {sur['warning']})" if sur.get("warning") else ""))
        skipped = [k for k, v in self.sections.items() if v != "rendered"]
        if skipped:
            lines.append(f"(skipped: {', '.join(skipped)})")
        return "\n".join(lines)


def diagnose_lines(d: Optional[dict], hidden: bool = True) -> list[str]:
    """Under a unit's line: each named effect's group of more than one member (posterior
    weights, separating channel, failure-year spread) and the candidates the recorded
    channels cannot see (left out with ``hidden=False``), as ``twinmon diagnose`` words
    them; none without either."""
    show = hidden and bool(d and d.get("hidden"))
    if not d or not (show or any(len(g["members"]) > 1 for g in d["groups"])):
        return []
    from ..diagnose.text import INDENT, group_line, hidden_line
    lines = [INDENT + group_line(g) for g in d["groups"] if len(g["members"]) > 1]
    if show:
        lines.append(INDENT + hidden_line(d["hidden"]))
    return lines


def shared_hidden(diagnoses: list) -> dict:
    """The hidden candidates' record every unit shares (``{}`` unless there are several
    units, all diagnosed, whose recorded channels hide the same candidates alike)."""
    from ..diagnose.text import hidden_line
    if len(diagnoses) < 2 or not all(d and d.get("hidden") for d in diagnoses):
        return {}
    lines = {hidden_line(d["hidden"]) for d in diagnoses}
    return diagnoses[0]["hidden"] if len(lines) == 1 else {}


def words_dict(inp: Inputs) -> tuple[dict, dict]:
    """The output's and the indicator's words, for ``summary.json``."""
    cfg, ind = inp.cfg, inp.words.ind
    out = cfg.model.output
    return ({"name": out.name, "variable": out.variable, "label": out.label, "units": out.units},
            {"name": ind.name, "label": ind.label, "units": ind.units, "kind": ind.spec.kind,
             "variable": ind.variable, "limit": ind.limit, "sense": ind.sense,
             "rule": ind.rule})


def _trend_acceptance(path) -> dict:
    """Each unit's trend moves' acceptance [chains] in the posterior at ``path`` (units
    without a trend left out): whether the laplace method's weighted draws were moved by its
    Markov chain. Read here, a few numbers a unit: the report reads the posterior without
    its trend."""
    from .. import artifacts
    with artifacts.open_artifact(path, "posterior") as f:
        return {u: g["trend/acceptance"][()] for u, g in f.get("units", {}).items()
                if "trend/acceptance" in g}


def calibration_diagnostics(inp: Inputs) -> dict:
    """Convergence diagnostics per unit and the sampler's warnings (``summary.json``)."""
    from ..calibrate import diagnostics_warnings
    from ..calibrate.rejuvenate import moved_by_chain
    post, cfg = inp.posterior, inp.cfg
    units, warnings = {}, []
    names = list(post.input_names)
    trend_acceptance = _trend_acceptance(post.path)
    for u, p in post.units.items():       # one read of each unit (a fleet's are lazy)
        units[u] = {"years": [int(y) for y in p.years],
                    "max_rhat": float(np.nanmax(p.rhat)), "min_ess": float(np.nanmin(p.ess)),
                    "acceptance": [float(np.min(p.acceptance)), float(np.max(p.acceptance))],
                    "moved": moved_by_chain(p.acceptance, trend_acceptance.get(u)),
                    "noise_std": float(np.asarray(p.noise_std)[0]),
                    "noise_source": p.noise_source,
                    # Each further channel's level and where it came from (a channel whose
                    # residuals hold more than noise says so here too).
                    "channels": {c: {"std": float(v["std"]), "source": v["source"]}
                                 for c, v in (getattr(p, "channels", None) or {}).items()
                                 if c != cfg.model.output.name}}
        warnings += diagnostics_warnings({u: p}, names, cfg)
    return {"units": units, "warnings": warnings}


def recorded_events(inp: Inputs, unit: str, post) -> list[str]:
    """One phrase per maintenance event recorded for ``unit`` (the observations', with
    their notes; else the posterior's copy): "bearing replaced in year 8 (WO 77) as
    recorded: its trend restarts there"."""
    u = inp.obs.units.get(unit) if inp.obs is not None else None
    if u is not None:
        events = [(e.year, e.component, e.action, e.note) for e in u.events]
    else:
        events = [(int(e[0]), str(e[1]), str(e[2]) if len(e) > 2 else "replaced", "")
                  for e in (getattr(post, "events", None) or ())]
    return [f"{c} {a} in year {y}" + (f" ({n})" if n else "") + " as recorded: its trend "
            "restarts there" for y, c, a, n in events]


def faulty_components(cfg: Config, uf) -> list[str]:
    """Components the forecast's attribution names, with their probabilities when the data
    cannot tell which ("pump 0.62 or motor 0.38"); for forecasts made before attribution,
    the components of the inputs whose slope test rejects (the config's ``component``
    words; the input's name when it has none)."""
    levels = getattr(uf, "level_cause", None)
    if levels:
        # Unsafe at a level with no drift: the parts whose level puts it there.
        return list(dict.fromkeys((cfg.model.inputs[n].component if n in cfg.model.inputs
                                   else "") or n for n in levels))
    att = getattr(uf, "attribution", None)
    if att is not None and att.verdict != "withheld":
        probs = att.probabilities
        if att.verdict == "healthy":
            return []
        conf = cfg.forecast.attribution_confidence
        if att.verdict == "ambiguous":
            # As the plan words it: the parts surely at fault, then those in doubt.
            sure, rest = ambiguous_candidates(probs, conf)
            doubt = " or ".join(f"{c} {probs[c]:.2f}" for c in rest)
            if sure:
                return sure + ([doubt + " (possibly)"] if doubt else [])
            return [doubt + " (ambiguous)"] if doubt else []
        return sorted(c for c, p in probs.items() if p >= conf)
    out = set()
    for name, t in uf.trends.items():
        if t.rejects:
            spec = cfg.model.inputs.get(name)
            out.add((spec.component if spec is not None else "") or t.component or name)
    return sorted(out)


def _measured_unsafe(s: UnitSummary, ind) -> str:
    """The action's prefix when the recorded transients themselves are past the limit
    (``s.measured_unsafe_since``): what they show needs no twin, whatever the prognosis
    (withheld, or none); "" otherwise."""
    if s.measured_unsafe_since is None:
        return ""
    return (f"unsafe as measured since year {s.measured_unsafe_since} ({ind.name} "
            f"{s.last_indicator_text} in year {s.last_year}, {ind.rule} is unsafe): inspect "
            "the unit now; ")


def unit_summary(unit: str, inp: Inputs, observed: dict) -> UnitSummary:
    """The plain-language summary of one unit; ``observed``: {unit: (years, indicator)}."""
    cfg, ind = inp.cfg, inp.words.ind
    s = UnitSummary(unit, indicator=ind.name)
    limit = cfg.safety.failure_probability
    if unit in observed:
        yrs, values = observed[unit]
        s.last_year, s.last_indicator = int(yrs[-1]), float(values[-1])
        s.last_indicator_text = ind.fmt(s.last_indicator)
        s.measured_unsafe_since = trailing_run(yrs, ind.unsafe(np.asarray(values, float)))
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
        # Known for fabricated data whether or not the twin may judge the unit.
        s.true_failure_year = uf.true_failure_year if uf.has_truth else None
    if uf is not None and uf.status == "withheld" and not uf.forced:
        # No failure year and no root cause from a twin that misses the data: say so, and
        # what would settle it.
        s.root_cause = uf.root_cause
        s.health = "not judged (see status)"
        s.horizon_end = int(uf.years_future[-1])
        s.last_year = s.last_year or int(uf.years_observed[-1])
        s.plan = uf.plan
        bound = box_bound_of(uf.status_reason)
        s.action = (f"widen {bound} and run again: the estimates sit on the twin's box, which "
                    "the plant has left or nearly left; no prognosis until they have room"
                    if bound else "run `twinmon diagnose` to find what the twin lacks; no "
                    "prognosis until it fits")
        s.action = _measured_unsafe(s, ind) + s.action
        why.append(uf.status_reason)
    elif uf is not None:
        comps = faulty_components(cfg, uf)
        s.root_cause = uf.root_cause
        watched = dict(getattr(uf, "watch", None) or {})
        watch = list(watched)
        s.health = ("unsafe: " + " and ".join(comps) + " (a level, not a drift)"
                    if comps and getattr(uf, "level_cause", None) else
                    "degrading: " + " and ".join(comps) if comps else
                    "no fault confirmed; watch: " + "; ".join(
                        f"{c} ({why})" for c, why in watched.items()) if watch else "healthy")
        # A part watched though no fault is confirmed (its wear accelerating, or its own
        # slope beyond normal ageing alone) is the one the action names.
        found, comps = comps, comps or watch
        s.components = [c for c in found
                        if not c.endswith((" (ambiguous)", " (possibly)"))]
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
        yf = np.asarray(uf.years_future)
        last = int(uf.years_observed[-1])
        if np.size(uf.p_unsafe_observed):
            s.p_unsafe_last = float(uf.p_unsafe_observed[-1])
            s.unsafe_since = trailing_run(uf.years_observed,
                                          np.asarray(uf.p_unsafe_observed) > limit)
        what = " and the ".join(comps) if comps else None
        # Parts beyond normal ageing the safe way: no risk by the indicator, nor normal.
        away = safe_way(uf.trends, cfg.forecast.alpha)
        away_comps = list(dict.fromkeys(uf.trends[n].component or n for n in away))
        if uf.failure_year is not None:
            s.p_unsafe = float(uf.p_unsafe[int(np.flatnonzero(yf == uf.failure_year)[0])])
            now = s.unsafe_since is not None or uf.failure_year <= last + 1
            when = "now" if now else f"before year {uf.failure_year - 1} ends"
            nominal = getattr(uf, "unsafe_at_nominal", None)
            s.action = (f"inspect the {what} {when}" if what
                        else "check the limit (safety.unsafe_if): a new unit is past it too"
                        if nominal is not None
                        else f"overhaul the unit {when} "
                        f"({no_fault_due(uf.years_future, uf.p_unsafe, limit)})")
        else:
            s.p_unsafe = float(np.max(uf.p_unsafe)) if uf.p_unsafe.size else 0.0
            s.action = (f"inspect the {what} at the next planned stop" if what
                        else f"check the {' and the '.join(away_comps)} at the next planned "
                        "stop (beyond normal ageing, though away from the limit)" if away_comps
                        else "no action; re-check at next year's recorded transient")
        for text in recorded_events(inp, unit, post):
            # The user's own records: the trends restart there.
            why.append(text)
        for r in (FoundRepair(**d) for d in uf.repairs):
            # A repair nobody recorded: the trend restarts there, and the record should say so.
            why.append(f"{r.headline()}: the trend restarts there")
            s.action += (f"; record the year-{r.year} repair of the "
                         f"{' or the '.join(r.components)} if it was done (twinmon events add)")
        for name, t in uf.trends.items():
            if t.rejects:
                lo, hi = t.slope_ci
                why.append(f"{name} drifts {t.slope:+.3g}/yr (90 % interval {lo:+.3g} to "
                           f"{hi:+.3g}) against normal ageing {t.normal_rate:+.3g} +- {t.tolerance:.3g}/yr "
                           f"({'one' if t.direction else 'two'}-sided test, p = {t.p_value:.1g})")
        if uf.shape:
            # The trend's shape, as weighed by calibrate (calibrate.shapes).
            sh = uf.shape
            per = [f"{n} in year {y}" for n, y in zip(uf.trends, sh.get("change_years") or ())
                   if y is not None]
            change = (f", a change ({', '.join(per)}) {sh['change']:.2f}" if per else
                      f", a change in year {sh['change_year']} {sh['change']:.2f}"
                      if sh.get("change_year") is not None else f", a change {sh['change']:.2f}")
            why.append(f"trend shape on the current segment: straight line {sh['line']:.2f}, "
                       f"accelerating {sh['accelerating']:.2f}{change}")
        for n, p in away.items():
            t = uf.trends[n]
            why.append(f"{n} drifts {t.slope:+.3g}/yr, beyond normal ageing {t.normal_rate:+.3g} "
                       f"+- {t.tolerance:.3g}/yr but away from the limit (p = {p:.1g}): no risk "
                       f"by the {ind.name}, yet not normal ageing")
        if not found and any(t.rejects for t in uf.trends.values()):
            why.append("not confirmed once the unit's inputs are tested together: no fault "
                       "is named")
        elif not found and not away:
            pmin = min(t.p_value for t in uf.trends.values())
            why.append(f"every input drifts within normal ageing (tests of the slopes, all "
                       f"p >= {np.floor(pmin * 100) / 100:.2f})")
        elif not found:
            why.append("no input wears towards the limit faster than normal ageing")
        if not found and uf.status == "ok":
            # How large a fault 'healthy' rules out (an unreliable unit's reason says it
            # already when that is too large).
            power = describe_power(cfg, uf.drift)
            if power:
                why.append(power)
        why.append(f"P(unsafe) from {uf.n_samples} Monte Carlo draws of the {ind.name} "
                   f"per year through the twin; failure = first year above {100 * limit:g} %")
    elif post is not None and unit in getattr(inp.forecast, "too_few_years", {}):
        # Left out of the forecast: a unit new in service.
        k = inp.forecast.too_few_years[unit]
        s.health = "not judged (too few years)"
        s.action = (f"no prognosis yet: {k} calibrated year(s), a trend needs 3; re-check "
                    "at next year's recorded transient")
    elif post is not None:
        s.action = "run `twinmon forecast` for a trend and a time to failure"
    else:
        s.action = (_measured_unsafe(s, ind)
                    + "run `twinmon calibrate` and `twinmon forecast` for a diagnosis")

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
        # Where diagnose estimated the noise its residuals are measured in, how well it is
        # known (the command's own words).
        from ..diagnose.text import noise_note as _noise_words
        noise_note = _noise_words(gap)
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
            "hidden": dict(getattr(gap, "hidden", {}) or {}),
            "estimate": {k: {"mean": plain(float(v[0])), "q05": plain(float(v[1])),
                             "q95": plain(float(v[2]))} for k, v in gap.estimate.items()},
            "noise_std": plain(float(gap.noise_std)),
            "noise_dof": plain(float(gap.noise_dof)) if getattr(gap, "noise_dof", None)
            else None,
        }
        withheld = s.status == "withheld" and not s.forced
        if gap.verdict == "unexplained" and withheld and not box_bound_of(s.status_reason):
            s.action = ("revise the model: the twin misses the plant and no candidate effect of "
                        "model.effects explains the gap (diagnose)")
        elif gap.verdict == "none" and withheld and not box_bound_of(s.status_reason):
            # The two stages disagree: say it rather than let one silently win. (Withheld
            # for estimates on the box's edge, the twin may fit: no disagreement.)
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
            if withheld and box_bound_of(s.status_reason):
                # The box, not an effect, is the first thing to rule out: with an input held
                # at its bound, an effect takes up what the input cannot.
                why.append(f"diagnose's {eff} may take up the box's limit: widen it first")
            elif s.status == "withheld" and not s.forced:
                s.action = (f"check {eff} (diagnose: the twin misses the plant from year "
                            f"{gap.onset}); with it in the twin, diagnose projects "
                            + (f"failure in year {gap.failure_year_after}"
                               if gap.failure_year_after is not None
                               else "no failure within the horizon"))
            else:
                # Diagnose's finding, beside a status that may say the twin fits: each year's
                # fit can pass while the degradation inputs absorb the effect.
                since = f" from year {gap.onset}" if gap.onset is not None else ""
                s.action += (f"; diagnose finds {eff}{since}"
                             + (", though each year's fit passes calibrate's test"
                                if s.status == "ok" else "") + f": check {eff}")
            projection = (f"year {gap.failure_year_after}"
                          if gap.failure_year_after is not None
                          else "no failure within the horizon")
            if uf is None:
                why.append(f"diagnose's projected failure year with {eff} in the twin: "
                           + projection)
            elif s.status != "withheld" or s.forced:
                why.append("the failure year shown is the forecast's (the calibrated twin, "
                           f"without {eff}); diagnose's projection with it is " + projection)
            eff_units = {k: (cfg.model.effects[k].units if k in cfg.model.effects else "")
                         for k in gap.estimate}
            est = "; ".join(f"{k} = {v[0]:.3g} (90 % interval {v[1]:.3g} to {v[2]:.3g}) "
                            f"{'' if eff_units[k] == '1' else eff_units[k]}".rstrip()
                            for k, v in gap.estimate.items())
            where = " and ".join(gap.where_windows)
            plural = "s" if len(gap.where_windows) > 1 else ""
            # No window significant alone: the gap is spread over the record, not in one
            # window called "the whole record".
            sits = (f"the gap sits in the {where} window{plural}" if where
                    else "the gap is spread over the record (no window is significant alone)")
            why.append(f"diagnose{noise_note}: {sits}; adding "
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
            # (Said as diagnose's finding: calibrate's test of each year's fit may pass, and
            # the status says so beside it.)
            s.action += ("; diagnose finds a gap between the twin and the plant that no "
                         "candidate effect explains" + (", though each year's fit passes "
                         "calibrate's test" if s.status == "ok" else "")
                         + ": check the data")
            why.append(f"diagnose{noise_note}: a significant gap no candidate effect explains, "
                       "so the estimates may be biased")
        else:
            why.append(f"diagnose{noise_note}: no significant gap between the twin and the "
                       "plant")
        if getattr(gap, "hidden", None):
            from ..diagnose.text import hidden_line
            why.append("diagnose: " + hidden_line(gap.hidden) + "; the estimates may carry "
                       "such an effect unnoticed")
    if s.true_failure_year is not None or (uf is not None and uf.has_truth):
        why.append(f"true failure year (fabricated data): {s.true_failure_year or 'none'}")
    s.confidence = "; ".join(why) + ("." if why else "")
    return s
