"""The HTML page: one self-contained ``index.html`` (inline CSS, figures as base64 PNG, no
script, no external link), its tables and paragraphs."""
from __future__ import annotations

import base64
import html
from typing import Any, Optional

from .. import artifacts
from ..config import Config
from .common import SECTION_TITLES, SECTIONS, Words, input_label, pct, qty
from .summary import ReportSummary

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


def calibration_table(cfg: Config, diag: dict) -> list[str]:
    units = cfg.model.output.units
    rows = ["<table><tr><th>Unit</th><th>Years</th><th>max R-hat</th><th>min ESS</th>"
            f"<th>acceptance</th><th>noise std ({e(units if units not in ('', '1') else '-')})"
            "</th></tr>"]
    for u, d in diag["units"].items():
        bad = d["max_rhat"] > cfg.calibrate.rhat_warn or d["min_ess"] < cfg.calibrate.ess_warn
        rows.append(f"<tr><td class='unit'>{e(u)}</td><td>{d['years'][0]}-{d['years'][-1]}</td>"
                    f"<td class='{'warn' if bad else 'ok'}'>{d['max_rhat']:.3f}</td>"
                    f"<td>{d['min_ess']:.0f}</td><td>{d['acceptance'][0]:.2f}-"
                    f"{d['acceptance'][1]:.2f}</td><td>{d['noise_std']:.3g} "
                    f"({e(d['noise_source'])})</td></tr>")
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


def page(cfg: Config, words: Words, summary: ReportSummary, figs: list[dict],
         extra: dict) -> str:
    """The whole ``index.html``."""
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           "<title>twinmon health report</title>", f"<style>{CSS}</style></head><body>",
           "<h1>twinmon health report</h1>",
           f'<p class="meta">Generated {e(artifacts.utc_now())} by twinmon from config '
           f"<code>{e(cfg.source)}</code>.</p>", _what_is_monitored(cfg, words)]
    out.append("<h2>Summary per unit</h2>")
    if summary.units:
        out.append("<table><tr><th>Unit</th><th>Status</th><th>Health</th>"
                   "<th>Time to failure</th><th>What to do</th><th>What this rests on</th></tr>")
        for u, s in summary.units.items():
            cls = ("warn" if s.status in ("withheld", "unreliable")
                   else "ok" if s.root_cause == "healthy" else "bad" if s.failure_year is not None
                   else "warn" if s.root_cause else "")
            ttf = s.time_to_failure
            if s.failure_year is not None and s.last_year is not None:
                n = s.failure_year - s.last_year
                ttf = (f"year {s.failure_year} of service: {n} year{'s' if n != 1 else ''} "
                       f"after the last observation (year {s.last_year}); P(unsafe) "
                       f"{pct(s.p_unsafe)} in year {s.failure_year}")
            st_cls = {"ok": "ok", "none": ""}.get(s.status, "warn")
            out.append(f'<tr><td class="unit">{e(u)}</td>'
                       f'<td class="{st_cls}">{e(s.status_words)}</td>'
                       f'<td class="{cls}">{e(s.health)}</td>'
                       f"<td>{e(ttf)}</td><td>{e(s.action)}</td><td>{e(s.confidence)}</td></tr>")
        out.append("</table>")
        plans = [(u, s.plan) for u, s in summary.units.items() if s.plan]
        if plans:
            out.append("<p>Maintenance plans from the forecast:</p><ul>")
            out += [f"<li><b>{e(u)}</b>: {e(p)}</li>" for u, p in plans]
            out.append("</ul>")
        est = [(u, s) for u, s in summary.units.items() if s.estimates]
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
