"""The HTML page: one self-contained ``index.html`` (inline CSS, figures as base64 PNG, no
script, no external link), its tables and paragraphs."""
from __future__ import annotations

import base64
import html
from typing import Any, Optional

import numpy as np

from .. import artifacts
from ..config import Config
from .common import SECTION_TITLES, SECTIONS, Words, input_label, pct, qty
from .summary import ReportSummary

#: The calibration table's words for a noise level's source (calibrate's ``noise_source``).
NOISE_SOURCES = {"differences": "estimated; the residuals hold more than noise"}

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;max-width:1180px;margin:2em auto;
padding:0 1em;color:#222;line-height:1.45}
h1{margin-bottom:.2em}h2{border-bottom:2px solid #ddd;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.8em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.35em .6em;text-align:left;vertical-align:top}
th{background:#f3f3f3}.note{color:#777;font-style:italic}
.meta{color:#666;font-size:.88em}figure{margin:1.2em 0}
figure img{max-width:100%;border:1px solid #eee}figcaption{color:#444;font-size:.92em}
.unit{font-weight:bold}.bad{color:#b00}.ok{color:#070}.warn{color:#a60}
code{background:#f4f4f4;padding:0 .2em}
.scroll{max-height:34em;overflow-y:auto;border:1px solid #ddd;margin:.8em 0}
.scroll table{margin:0;width:100%}.scroll th{position:sticky;top:0}
table.rank{font-size:.86em}table.rank td,table.rank th{padding:.2em .45em}
td.num{text-align:right}
"""


def e(x: Any) -> str:
    return html.escape(str(x))


def e_p(text: str) -> str:
    return f"<p>{e(text)}</p>"


def figure_html(item: dict) -> str:
    data = base64.b64encode(item["_path"].read_bytes()).decode("ascii")
    return (f'<figure id="{e(item["name"])}"><img alt="{e(item["title"])}" '
            f'src="data:image/png;base64,{data}"><figcaption><b>{e(item["title"])}.</b> '
            f'{e(item["caption"])}</figcaption></figure>')


def _pct_or_na(x: Optional[float], digits: int) -> str:
    return "n/a" if x is None or x != x else f"{100 * x:.{digits}f} %"


def surrogate_text(si: dict, words: Words) -> str:
    """The surrogate section's paragraph: modes kept, errors on the test runs, coverage."""
    rel = ""
    if si.get("max_rel_error") is not None and si["max_rel_error"] == si["max_rel_error"]:
        rel = (f" Relative to the FMU value: max {_pct_or_na(si['max_rel_error'], 3)}, mean "
               f"{_pct_or_na(si['mean_rel_error'], 4)}.")
    span = float(f"{si['output_range']:.3g}")
    return (f"{si['modes']} Karhunen-Loeve modes kept ({100 * si['variance_ratio']:.4f} % of "
            f"the training variance). On {si['n_test']} held-out FMU runs the error is at most "
            f"{_pct_or_na(si['max_range_error'], 3)} of the {words.out_label}'s range over them "
            f"({qty(span, words.out_units)}), "
            f"{_pct_or_na(si['mean_range_error'], 4)} on average.{rel} "
            f"{100 * si['coverage_90']:.0f} % of the FMU values lie in the 90 % predictive band.")


def stored_validation_text(v: dict) -> str:
    """The surrogate's own validation (``reduce``), for a report without the test runs."""
    text = (f"stored validation: max error {_pct_or_na(v.get('max_range_error'), 3)} of the "
            f"output's range, mean {_pct_or_na(v.get('mean_range_error'), 4)}")
    if v.get("max_rel_error") is not None and v["max_rel_error"] == v["max_rel_error"]:
        text += (f"; relative: max {_pct_or_na(v['max_rel_error'], 3)}, mean "
                 f"{_pct_or_na(v.get('mean_rel_error'), 4)}")
    return text


def calibration_table(cfg: Config, diag: dict, fleet=None) -> list[str]:
    """The convergence table; for a large fleet (``fleet`` given, ``diag`` cut to the units
    drawn in detail by the stage), a line on the whole fleet first."""
    units = cfg.model.output.units
    rows = []
    whole = diag.get("fleet")
    if fleet is not None and whole:
        rows.append(e_p(f"Over the {whole['units']} units: max R-hat {whole['max_rhat']:.3f}, "
                        f"min ESS {whole['min_ess']:.0f}; {whole['warned_units']} unit(s) with "
                        "sampling warnings. The table lists the units drawn in detail."))
    rows += ["<table><tr><th>Unit</th><th>Years</th><th>max R-hat</th><th>min ESS</th>"
            f"<th>acceptance</th><th>noise std ({e(units if units not in ('', '1') else '-')})"
            "</th></tr>"]
    for u, d in diag["units"].items():
        bad = d["max_rhat"] > cfg.calibrate.rhat_warn or d["min_ess"] < cfg.calibrate.ess_warn
        rows.append(f"<tr><td class='unit'>{e(u)}</td><td>{d['years'][0]}-{d['years'][-1]}</td>"
                    f"<td class='{'warn' if bad else 'ok'}'>{d['max_rhat']:.3f}</td>"
                    f"<td>{d['min_ess']:.0f}</td>"
                    f"<td>{_acceptance(d['acceptance'], d.get('moved'))}</td>"
                    f"<td>{d['noise_std']:.3g} "
                    f"({e(NOISE_SOURCES.get(d['noise_source'], d['noise_source']))})"
                    + "".join(f"<br>{e(c)} {v['std']:.3g} "
                              f"({e(NOISE_SOURCES.get(v['source'], v['source']))})"
                              for c, v in d.get("channels", {}).items())
                    + "</td></tr>")
    rows.append("</table>")
    if diag["warnings"]:
        rows.append("<p class='warn'>Sampling warnings:</p><ul>"
                    + "".join(f"<li>{e(w)}</li>" for w in diag["warnings"]) + "</ul>")
    else:
        rows.append(e_p(f"No sampling warning (R-hat <= {cfg.calibrate.rhat_warn:g}, "
                        f"ESS >= {cfg.calibrate.ess_warn:g} everywhere)."))
    return rows


def _what_is_monitored(cfg: Config, words: Words) -> str:
    out = cfg.model.output
    ind = words.ind
    units = "" if out.units in ("", "1") else f", {out.units}"
    ind_units = "" if ind.units in ("", "1") else f", {ind.units}"
    physical = " or its twin leaves the physical domain" if words.has_nonphysical else ""
    return (f"<p>Observed output: <b>{e(out.label)}</b> (channel <code>{e(out.name)}</code>"
            f"{e(units)}). Health indicator: <b>{e(ind.name)}</b> ({e(ind.label)}"
            f"{e(ind_units)}); a unit is unsafe when its {e(ind.name)} is {e(words.side)} "
            f"{e(words.limit_text)}{e(physical)}, and fails in the first year its probability "
            f"of being unsafe exceeds {100 * cfg.safety.failure_probability:g} %.</p>")


def unit_anchor(unit: str) -> str:
    """The id of a unit's row in the detail table."""
    return "unit-" + "_".join(str(unit).split())


def _status_short(s) -> str:
    if s.status == "withheld":
        return "FORCED" if s.forced else "withheld"
    return {"none": "no forecast"}.get(s.status, s.status)


def fleet_overview(cfg: Config, summary: ReportSummary, fleet, fig_items: list) -> list[str]:
    """The overview a large fleet's page opens on: counts, the fleet figure, the ranking."""
    from .fleet import failure_cell, p_cell
    units = summary.units
    failing = sum(1 for s in units.values() if s.failure_year is not None)
    detail = set(fleet.detail)
    out = ['<h2 id="fleet">Fleet overview</h2>']
    text = (f"<p>{len(units)} units; {failing} fail within the forecast horizon; "
            f"{len(fleet.at_risk)} at risk (a failure year, a fault, a prognosis withheld or "
            "unreliable, or a gap found by diagnose). ")
    if fleet.detail:
        text += (f"Figures are drawn below for {len(fleet.detail)} of them"
                 + (f" (asked for: {e(', '.join(fleet.requested))})" if fleet.requested
                    else "") + ". ")
    else:
        text += "No unit needs figures. "
    if fleet.not_shown:
        text += (f"{len(fleet.not_shown)} more at risk have none here (at most "
                 f"{cfg.report.detail_units} units are drawn, <code>report.detail_units</code>)"
                 "; <code>twinmon report --unit U</code> draws any unit.")
    out.append(text + "</p>")
    fails = {k: 0 for k in fleet.counts}
    for s in units.values():
        fails[s.short_health] = fails.get(s.short_health, 0) + (s.failure_year is not None)
    out.append("<table><tr><th>Verdict</th><th>Units</th><th>of which fail within the "
               "horizon</th></tr>" + "".join(
                   f"<tr><td>{e(k)}</td><td class='num'>{v}</td>"
                   f"<td class='num'>{fails.get(k, 0)}</td></tr>"
                   for k, v in fleet.counts.items()) + "</table>")
    out += [figure_html(item) for item in fig_items]
    out.append("<h3>Units ranked by P(unsafe)</h3><p class='meta'>Largest P(unsafe) over "
               "the horizon first, then the earliest failure year; units without a prognosis "
               "last. Failure year: year of service (+ years after the last observation). "
               "Linked units are drawn in detail below.</p>")
    out.append('<div class="scroll"><table class="rank"><tr><th>#</th><th>Unit</th>'
               "<th>Verdict</th><th>Status</th><th>Failure year</th><th>max P(unsafe)</th>"
               "<th>At risk because</th><th>What to do</th></tr>")
    for i, u in enumerate(fleet.ranking, 1):
        s = units[u]
        name = (f'<a href="#{e(unit_anchor(u))}">{e(u)}</a>' if u in detail else e(u))
        cls = ("bad" if s.failure_year is not None else "warn" if u in fleet.at_risk
               else "ok" if s.root_cause == "healthy" else "")
        st_cls = {"ok": "ok", "none": ""}.get(s.status, "warn")
        out.append(f"<tr><td class='num'>{i}</td><td class='unit'>{name}</td>"
                   f"<td class='{cls}'>{e(s.short_health)}</td>"
                   f"<td class='{st_cls}'>{e(_status_short(s))}</td>"
                   f"<td>{e(failure_cell(s))}</td><td class='num'>{e(p_cell(s))}</td>"
                   f"<td>{e('; '.join(fleet.at_risk.get(u, [])))}</td>"
                   f"<td>{e(s.action)}</td></tr>")
    out.append("</table></div>")
    return out


def page(cfg: Config, words: Words, summary: ReportSummary, figs: list[dict],
         extra: dict, fleet=None) -> str:
    """The whole ``index.html``; a large fleet's (``fleet`` given) opens on its overview
    and its per-unit tables list the units drawn in detail only."""
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           "<title>twinmon health report</title>", f"<style>{CSS}</style></head><body>",
           "<h1>twinmon health report</h1>",
           f'<p class="meta">Generated {e(artifacts.utc_now())} by twinmon from config '
           f"<code>{e(cfg.source)}</code>.</p>", _what_is_monitored(cfg, words)]
    shown = summary.units
    if fleet is not None:
        out += extra.get("fleet", [])
        shown = {u: summary.units[u] for u in fleet.detail}
        out.append(f"<h2>Units drawn in detail ({len(shown)} of {len(summary.units)})</h2>")
    else:
        out.append("<h2>Summary per unit</h2>")
    if shown:
        out.append("<table><tr><th>Unit</th><th>Status</th><th>Health</th>"
                   "<th>Time to failure</th><th>What to do</th><th>What this rests on</th></tr>")
        for u, s in shown.items():
            cls = ("warn" if s.status in ("withheld", "unreliable")
                   else "ok" if s.root_cause == "healthy" else "bad" if s.failure_year is not None
                   else "warn" if s.root_cause else "")
            ttf = s.time_to_failure
            # Unsafe already: the summary's own words, not "1 year after the record".
            if s.unsafe_since is None and s.failure_year is not None \
                    and s.last_year is not None:
                n = s.failure_year - s.last_year
                ttf = (f"year {s.failure_year} of service: {n} year{'s' if n != 1 else ''} "
                       f"after the last observation (year {s.last_year}); P(unsafe) "
                       f"{pct(s.p_unsafe)} in year {s.failure_year}{s.median_note}")
            st_cls = {"ok": "ok", "none": ""}.get(s.status, "warn")
            anchor = f' id="{e(unit_anchor(u))}"' if fleet is not None else ""
            out.append(f'<tr{anchor}><td class="unit">{e(u)}</td>'
                       f'<td class="{st_cls}">{e(s.status_words)}</td>'
                       f'<td class="{cls}">{e(s.health)}</td>'
                       f"<td>{e(ttf)}</td><td>{e(s.action)}</td><td>{e(s.confidence)}</td></tr>")
        out.append("</table>")
        plans = [(u, s.plan) for u, s in shown.items() if s.plan]
        if plans:
            out.append("<p>Maintenance plans from the forecast:</p><ul>")
            out += [f"<li><b>{e(u)}</b>: {e(p)}</li>" for u, p in plans]
            out.append("</ul>")
        est = [(u, s) for u, s in shown.items() if s.estimates]
        if est:
            names = list(est[0][1].estimates)
            out.append("<p>Latest estimates (posterior mean, 90 % interval):</p><table><tr>"
                       "<th>Unit</th><th>Year</th>" + "".join(
                           f"<th>{e(input_label(cfg, n))}</th>" for n in names) + "</tr>")
            for u, s in est:
                cells = "".join(
                    f"<td>{s.estimates[n]['mean']:.4g} [{s.estimates[n]['q05']:.4g}, "
                    f"{s.estimates[n]['q95']:.4g}]</td>" for n in names if n in s.estimates)
                year = next(iter(s.estimates.values()))["year"]
                out.append(f"<tr><td class='unit'>{e(u)}</td><td>{year}</td>{cells}</tr>")
            out.append("</table>")
    elif fleet is not None:
        out.append('<p class="note">No unit is at risk or asked for: no per-unit figures '
                   "(<code>twinmon report --unit U</code> draws one).</p>")
    else:
        out.append('<p class="note">No units: no artifact with units was given.</p>')
    for note in summary.notes:
        out.append(f'<p class="note">{e(note)}</p>')

    for sec in SECTIONS:
        out.append(f'<h2 id="{sec}">{e(SECTION_TITLES[sec])}</h2>')
        state = summary.sections[sec]
        if state != "rendered":
            out.append(f'<p class="note">Section {e(state)}.</p>')
            continue
        out += extra.get(sec, [])
        for item in figs:
            if item["section"] == sec:
                out.append(figure_html(item))

    out.append("<h2>Artifacts</h2><table><tr><th>Role</th><th>Path</th><th>Schema</th>"
               "<th>Created</th></tr>")
    for role, path in summary.artifacts.items():
        prov = extra["provenance"].get(role, {})
        out.append(f"<tr><td>{e(role)}</td><td><code>{e(path)}</code></td>"
                   f"<td>{e(prov.get('schema', ''))}</td><td>{e(prov.get('created', ''))}"
                   "</td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out)


def _acceptance(rng: list, moved: bool = False) -> str:
    """An acceptance range as the table shows it; a method of independent draws has none
    (NaN, null in summary.json), nor do its weighted draws a Markov chain then ``moved``."""
    lo, hi = rng
    if lo is None or hi is None or not (np.isfinite(lo) and np.isfinite(hi)):
        return ("- (weighted draws, moved by a Markov chain)" if moved
                else "- (weighted independent draws)")
    return f"{lo:.2f}-{hi:.2f}"


def diagnose_table(cfg: Config, units: dict) -> list[str]:
    """Per unit of ``units`` ({unit: UnitGap}): each named effect with its group (the
    effects the data cannot tell apart, by posterior weight, a member that explains the gap
    together with the named effect marked so), the projected failure year (each member's
    when they differ by more than a year), the channel that would separate the group, and
    the candidates the recorded channels cannot see."""
    from ..diagnose.text import failure_range_text, hidden_by_channel, weight_text
    if not units:
        return []

    def unit_of(name: str) -> str:
        spec = cfg.model.effects.get(name)
        return "" if spec is None or spec.units in ("", "1") else f" {spec.units}"

    def value(m: dict) -> str:
        return (f"{m['value']:.4g} [{m['q05']:.4g}, {m['q95']:.4g}]{unit_of(m['effect'])}")

    def fy(y) -> str:
        return "none within the horizon" if y is None else f"year {y}"

    def hidden_cell(hidden: dict) -> str:
        if not hidden:
            return "none"
        parts = []
        for ch, names in hidden_by_channel(hidden).items():
            items = ", ".join(
                f"<code>{e(n)}</code> (at {hidden[n]['value']:.4g}{e(unit_of(n))}: "
                f"{hidden[n]['gap']:.1f} σ, {hidden[n]['visible']:.1f} σ left)" for n in names)
            it = "them" if len(names) > 1 else "it"
            parts.append(f"{items}: " + (f"recording <code>{e(ch)}</code> would show {it}"
                                         if ch else f"no unrecorded channel would show {it}"))
        return "<br>".join(parts)

    out = ["<p>What diagnose names per unit. A group holds the effects the data cannot tell "
           "apart in one place of the twin, each with its posterior weight (the BIC "
           "approximation, equal prior weights); a member marked <i>with</i> explains the gap "
           "together with the named effect. Hidden: candidates the recorded channels cannot "
           "see, since the degradation inputs take them up (the effect at the end of its "
           "range: its gap on the recorded channels, and what is left of it once the inputs "
           "are refitted, in noise σ); they are not tested for and may bias the "
           "estimates.</p>",
           "<table><tr><th>Unit</th><th>Named effect</th><th>Its group (posterior "
           "weight)</th><th>Projected failure year (the twin with the effect)</th><th>Recording "
           "this would separate the group</th><th>Hidden</th></tr>"]
    for u, g in units.items():
        rows = []
        if g.verdict == "effect" and g.groups:
            for grp in g.groups:
                ms = grp["members"]
                named = ms[0]
                first = (f"<code>{e(named['effect'])}</code> = {e(value(named))} from year "
                         f"{grp['onset']}")
                spread = bool(grp.get("failure_year_spread"))
                members = "<br>".join(
                    (f"<code>{e(' and '.join(m['together_with']))}</code> with "
                     if m.get("together_with") else "")
                    + f"<code>{e(m['effect'])}</code> = {e(value(m))}: "
                    f"<b>{e(weight_text(m['weight']))}</b>"
                    + (f" (failure {e(fy(m['failure_year']))})" if spread else "")
                    for m in ms) if len(ms) > 1 else "alone (no other candidate fits as well)"
                if spread:
                    years = ("<span class='warn'>differs across the group: "
                             f"{e(failure_range_text(grp['failure_year_range']))} (each "
                             "member's beside its name)</span>")
                else:
                    years = e(fy(named["failure_year"]))
                sep = (f"<code>{e(grp['separating_channel'])}</code>"
                       if grp.get("separating_channel") else "—")
                rows.append(f"<td>{first}</td><td>{members}</td><td>{years}</td><td>{sep}</td>")
        elif g.verdict == "effect":
            # A gap.h5 written before groups were recorded.
            rows.append(f"<td>{e(', '.join(g.effects))} from year {g.onset}</td>"
                        f"<td>{e(' or '.join(g.group)) if len(g.group) > 1 else '—'}</td>"
                        f"<td>{e(fy(g.failure_year_after))}</td>"
                        f"<td>{e(g.separating_channel or '—')}</td>")
        elif g.verdict == "unexplained":
            best = (f"; the best candidate, <code>{e(g.candidates[0])}</code>, closes only "
                    f"{g.closed_percent:.0f} % of it" if g.candidates else "")
            rows.append(f"<td colspan='4'>a gap from year {g.onset} that no candidate "
                        f"explains{best}</td>")
        else:
            rows.append("<td colspan='4'>no significant gap</td>")
        span = f" rowspan='{len(rows)}'" if len(rows) > 1 else ""
        hid = f"<td{span}>{hidden_cell(g.hidden)}</td>"
        out.append(f"<tr><td class='unit'{span}>{e(u)}</td>{rows[0]}{hid}</tr>")
        out += [f"<tr>{r}</tr>" for r in rows[1:]]
    out.append("</table>")
    return out
