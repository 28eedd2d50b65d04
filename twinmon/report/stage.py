"""Stage ``report``: figures, a self-contained HTML report, ``summary.json`` and a terminal summary.

Every section is optional: it is rendered when its artifact is given and skipped with a note
when it is not, so a report can be made after any prefix of the pipeline (observations only,
then the surrogate, the posterior, the forecast, the sim-to-real gap).

Figures (one PNG each, 150 dpi; numbers follow the paper's):

==========================  ================================================================
``fig2_last_transients``    last observed start-up of every unit, 90 %-of-nominal level, 30 s
``fig3_t90_history``        time to 90 % of nominal per observed year, with the 30 s limit
``fig5_surrogate``          surrogate against the FMU on held-out test runs, relative error
``fig6_estimates``          posterior estimates per year with 90 % intervals (truth if known)
``fig7_trends``             linear trends with 90 % prediction intervals over the horizon
``fig8_marginals``          marginal distributions of the forecast inputs, selected years
``fig9_t90_forecast``       t90 distribution per year, P(unsafe), failure year
``diag_residual_map``       residuals (observation - twin) by year and time, windows marked
``diag_candidates``         candidate unmodelled effects ranked by BIC gain
``diag_overlay``            one affected year: observation, base twin, augmented twin
==========================  ================================================================

Everything is written to a temporary folder beside ``output_dir`` and moved into place at the
end, ``index.html`` last, so a failing report never leaves a half-written ``index.html``.
All artifacts are loaded (and their schemas checked) before anything is drawn.

Plotting lives here and only here (matplotlib, Agg canvas, no pyplot global state).
"""
from __future__ import annotations

import base64
import html
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np

from . import artifacts
from .config import Config
from .errors import ArtifactError

#: Resolution of every PNG (dots per inch).
DPI = 150
#: The paper's surrogate accuracy on its test set (max, mean relative error), for comparison.
PAPER_SURROGATE_ERROR = (0.015, 0.002)
#: Colours of the units, in order of first appearance (tab10 without red: red means "limit").
UNIT_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2",
                "#7f7f7f", "#bcbd22", "#17becf"]
LIMIT_COLOUR = "#d62728"

SECTIONS = ("observations", "surrogate", "calibration", "forecast", "diagnose")
_SECTION_TITLES = {
    "observations": "Observations",
    "surrogate": "Reduced model (surrogate) against the FMU",
    "calibration": "Calibration: degradation inputs per year",
    "forecast": "Forecast: trends, failure probability, time to failure",
    "diagnose": "Sim-to-real gap (diagnose)",
}
_SKIP_HINTS = {
    "observations": "no observations file given (--observations)",
    "surrogate": "no surrogate artifact given (run `twinmon reduce`)",
    "calibration": "no posterior artifact given (run `twinmon calibrate`)",
    "forecast": "no forecast artifact given (run `twinmon forecast`)",
    "diagnose": "no gap artifact given (run `twinmon diagnose`)",
}


# ---------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------
@dataclass
class UnitSummary:
    """Plain-language state of one unit, derived from the artifacts given.

    Attributes
    ----------
    name : str
    health : str
        ``"healthy"``, ``"degrading: pump"``, ``"degrading: motor"``, ... or ``"unknown"``
        when no forecast was given.
    root_cause : str or None
        The forecast's verdict (``healthy``, a component name, ``both``), None without one.
    failure_year : int or None
        First future year with P(unsafe) above the limit (year of service).
    p_unsafe : float or None
        P(unsafe) in the failure year, or the largest over the horizon when none fails.
    last_year : int or None
        Last observed (or calibrated) year.
    horizon_end : int or None
        Last forecast year.
    last_t90 : float or None
        t90 of the last observed start-up (s); inf if 90 % of nominal was never reached.
    action : str
        Short recommendation, e.g. ``"inspect the pump before year 13 ends"``.
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
    p_unsafe: Optional[float] = None
    last_year: Optional[int] = None
    horizon_end: Optional[int] = None
    last_t90: Optional[float] = None
    action: str = ""
    plan: str = ""
    estimates: dict = field(default_factory=dict)
    confidence: str = ""
    diagnose: Optional[dict] = None
    true_failure_year: Optional[int] = None

    @property
    def short_health(self) -> str:
        if self.root_cause is None:
            return "unknown"
        if self.root_cause == "healthy":
            return "healthy"
        if self.root_cause == "both":
            return "several faults"
        return f"{self.root_cause} fault"

    @property
    def time_to_failure(self) -> str:
        """e.g. ``"fails in year 14 (P(unsafe) 12 % in 14)"``."""
        if self.root_cause is None:
            if self.last_t90 is None:
                return "no forecast"
            return f"last t90 {_fmt_t90(self.last_t90)} (no forecast)"
        if self.failure_year is not None:
            return (f"fails in year {self.failure_year} "
                    f"(P(unsafe) {_pct(self.p_unsafe)} in {self.failure_year})")
        return f"no failure by year {self.horizon_end} (max P(unsafe) {_pct(self.p_unsafe)})"

    def as_dict(self) -> dict:
        return {
            "health": self.health, "root_cause": self.root_cause,
            "failure_year": self.failure_year, "p_unsafe": self.p_unsafe,
            "last_year": self.last_year, "horizon_end": self.horizon_end,
            "last_t90": (None if self.last_t90 is None or not np.isfinite(self.last_t90)
                         else round(float(self.last_t90), 3)),
            "time_to_failure": self.time_to_failure, "action": self.action, "plan": self.plan,
            "estimates": self.estimates, "confidence": self.confidence,
            "diagnose": self.diagnose, "true_failure_year": self.true_failure_year,
        }


@dataclass
class ReportSummary:
    """What :func:`report` wrote; ``as_dict()`` is the content of ``summary.json``.

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

    def as_dict(self) -> dict:
        return {
            "units": {u: s.as_dict() for u, s in self.units.items()},
            "sections": dict(self.sections),
            "figures": list(self.figures),
            "surrogate": self.surrogate,
            "calibration": self.calibration,
            "artifacts": dict(self.artifacts),
            "notes": list(self.notes),
            "index": self.index,
        }

    def terminal(self) -> str:
        """A short multi-line text: one line per unit, then the report's path."""
        if not self.units:
            lines = ["report: no units"]
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


# ---------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------
def _pct(p: Optional[float]) -> str:
    if p is None or not np.isfinite(p):
        return "n/a"
    if 0 < p < 0.005:
        return "<1 %"
    return f"{100 * p:.0f} %"


def _fmt_t90(t: float) -> str:
    return "never reached" if not np.isfinite(t) else f"{t:.1f} s"


def _plain(obj: Any) -> Any:
    """JSON-able copy (numpy scalars and arrays made plain, non-finite floats -> None)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return _plain(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _input_label(cfg: Config, name: str) -> str:
    spec = cfg.model.inputs.get(name)
    units = spec.units if spec is not None else ""
    return f"{name} ({units})" if units and units != "1" else f"{name} (-)"


def _t90_rows(time: np.ndarray, flow: np.ndarray, safety) -> np.ndarray:
    """t90 per row of ``flow`` [n, n_t] (s), missing samples (NaN) left out row by row."""
    from .safety import time_to_fraction
    out = np.empty(len(flow))
    for i, row in enumerate(flow):
        ok = np.isfinite(row)
        out[i] = time_to_fraction(time[ok], row[ok], safety) if ok.any() else np.nan
    return out


# ---------------------------------------------------------------------------------------
# Loading (all before drawing: a bad artifact fails the report before anything is written)
# ---------------------------------------------------------------------------------------
@dataclass
class _Inputs:
    cfg: Config
    obs: Any = None
    sims: Any = None
    surrogate: Any = None
    validation: Optional[dict] = None
    posterior: Any = None
    forecast: Any = None
    gap: Any = None
    truth: Any = None
    paths: dict = field(default_factory=dict)
    #: The observations file the gap artifact diagnosed, when it is not ``obs``: its units are
    #: then other machines (or other records) and must not be merged into the unit summaries.
    gap_other_source: Optional[str] = None

    def unit_names(self) -> list[str]:
        """Units in order of first appearance: observations, posterior, forecast, gap."""
        names: list[str] = []
        for src in (self.obs, self.posterior, self.forecast):
            if src is not None:
                names += [u for u in src.units if u not in names]
        if self.gap is not None and self.gap_other_source is None:
            names += [u for u in _gap_units(self.gap) if u not in names]
        return names


def _gap_units(gap) -> list[str]:
    units = getattr(gap, "units", None)
    return list(units) if units is not None else []


def _load(cfg: Config, paths: dict) -> _Inputs:
    inp = _Inputs(cfg=cfg, paths={k: str(v) for k, v in paths.items() if v is not None})
    if paths.get("observations") is not None:
        from .observations import read_observations
        inp.obs = read_observations(paths["observations"])
    if paths.get("simulations") is not None:
        from .simulate import read_simulations
        inp.sims = read_simulations(paths["simulations"])
    if paths.get("surrogate") is not None:
        from .reduce import read_surrogate, read_validation
        inp.surrogate = read_surrogate(paths["surrogate"])
        inp.validation = read_validation(paths["surrogate"])
    if paths.get("posterior") is not None:
        from .calibrate import read_posterior
        inp.posterior = read_posterior(paths["posterior"])
    if paths.get("forecast") is not None:
        from .forecast import read_forecast
        inp.forecast = read_forecast(paths["forecast"])
    if paths.get("gap") is not None:
        inp.gap = _read_gap(paths["gap"])
        diagnosed = artifacts.read_provenance(paths["gap"]).get("inputs", [])
        if diagnosed and paths.get("observations") is not None:
            same = diagnosed[0]["sha256"] == artifacts.file_sha256(paths["observations"])
            if not same:
                inp.gap_other_source = diagnosed[0]["path"]
    if paths.get("truth") is not None:
        from .fabricate import read_truth
        inp.truth = read_truth(paths["truth"])
    return inp


def _read_gap(path):
    try:
        from .diagnose import read_gap
    except ImportError:  # diagnose not installed in this build: still check the schema
        with artifacts.open_artifact(path, "gap"):
            pass
        raise ArtifactError(f"{path}: this twinmon has no diagnose module to read it") from None
    return read_gap(path)


# ---------------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------------
class _Figures:
    """Saves figures as PNG files and remembers them for the HTML."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.items: list[dict] = []

    def new(self, width: float, height: float, **kw):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        fig = Figure(figsize=(width, height), layout="constrained", **kw)
        FigureCanvasAgg(fig)
        return fig

    def save(self, fig, name: str, section: str, title: str, caption: str) -> None:
        path = self.folder / f"{name}.png"
        fig.savefig(path, dpi=DPI)
        self.items.append({"name": name, "section": section, "title": title,
                           "caption": caption, "file": f"figures/{name}.png", "_path": path})


def _limit_lines(ax, safety, *, horizontal_flow: bool = False, vertical_time: bool = False,
                 horizontal_time: bool = False) -> None:
    if horizontal_flow:
        level = safety.fraction * safety.nominal_flow
        ax.axhline(level, color=LIMIT_COLOUR, ls="--", lw=1.2,
                   label=f"{100 * safety.fraction:g} % of nominal ({level:g} kg/s)")
    if vertical_time:
        ax.axvline(safety.max_time, color=LIMIT_COLOUR, ls=":", lw=1.5,
                   label=f"{safety.max_time:g} s limit")
    if horizontal_time:
        ax.axhline(safety.max_time, color=LIMIT_COLOUR, ls="--", lw=1.2,
                   label=f"{safety.max_time:g} s limit")


def fig_last_transients(figs: _Figures, inp: _Inputs, colours: dict) -> None:
    """Figure 2: the last observed start-up of every unit."""
    obs, safety = inp.obs, inp.cfg.safety
    fig = figs.new(8, 4.8)
    ax = fig.add_subplot()
    for unit, u in obs.units.items():
        y = u.m_flow[-1]
        ok = np.isfinite(y)
        t90 = _t90_rows(obs.time, y[None], safety)[0]
        ax.plot(obs.time[ok], y[ok], "o-", ms=4, lw=1.2, color=colours[unit],
                label=f"{unit} (year {int(u.years[-1])}, t90 {_fmt_t90(t90)})")
    _limit_lines(ax, safety, horizontal_flow=True, vertical_time=True)
    ax.set_xlabel("time since start (s)")
    ax.set_ylabel("mass flow (kg/s)")
    ax.set_xlim(0, obs.time[-1] + 1)
    ax.set_ylim(bottom=0)
    ax.set_title("Last observed start-up transient per unit")
    ax.legend(loc="lower right", fontsize=9)
    ax.grid(alpha=0.3)
    figs.save(fig, "fig2_last_transients", "observations", "Last observed transients",
              "Measured flow of each unit's last recorded start-up (dots: samples). The unit is "
              f"safe when it crosses the dashed line ({100 * safety.fraction:g} % of nominal "
              f"flow) before the dotted {safety.max_time:g} s limit.")


def fig_t90_history(figs: _Figures, inp: _Inputs, colours: dict) -> dict:
    """Figure 3: t90 per observed year; returns {unit: t90 [n_y]}."""
    obs, safety = inp.obs, inp.cfg.safety
    t90s = {unit: _t90_rows(obs.time, u.m_flow, safety) for unit, u in obs.units.items()}
    fig = figs.new(8, 4.8)
    ax = fig.add_subplot()
    record = float(obs.time[-1])
    never = False
    for unit, u in obs.units.items():
        t = t90s[unit]
        fin = np.isfinite(t)
        ax.plot(u.years[fin], t[fin], "o-", color=colours[unit], label=unit)
        if (~fin).any():
            never = True
            ax.plot(u.years[~fin], np.full((~fin).sum(), record), "^", ms=9,
                    color=colours[unit], mec="k")
    _limit_lines(ax, safety, horizontal_time=True)
    if never:
        ax.plot([], [], "^", color="grey", mec="k", label=f"not reached within {record:g} s")
    ax.set_xlabel("year of service")
    ax.set_ylabel(f"time to {100 * safety.fraction:g} % of nominal flow (s)")
    ax.set_title(f"Observed time to {100 * safety.fraction:g} % of nominal flow (t90) per year")
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_ylim(0, max(safety.max_time * 1.1,
                       np.nanmax(np.where(np.isfinite(np.concatenate(list(t90s.values()))),
                                          np.concatenate(list(t90s.values())), record)) * 1.08))
    ax.legend(loc="upper left", fontsize=9)
    ax.grid(alpha=0.3)
    figs.save(fig, "fig3_t90_history", "observations", "t90 history",
              "Time to reach 90 % of the nominal flow, computed from each year's measured "
              "start-up (linear interpolation between samples). A rise that steepens hints at a "
              "fault but does not say which component.")
    return t90s


def fig_surrogate(figs: _Figures, inp: _Inputs) -> dict:
    """Figure 5: surrogate against the FMU on the test runs."""
    from matplotlib.ticker import FuncFormatter
    sur, sims, cfg = inp.surrogate, inp.sims, inp.cfg
    ok = sims.ok["test"]
    X, Y = sims.X["test"][ok], sims.Y["test"][ok]
    pred, var = sur.predict_with_var(X)
    rel = np.abs(pred - Y) / np.abs(Y)                     # [n_test, n_t]
    time = sims.time
    # Four runs spanning the range of responses (slowest to fastest start-up).
    order = np.argsort(_t90_rows(time, Y, cfg.safety))
    pick = order[np.unique(np.linspace(0, len(order) - 1, min(4, len(order))).round()
                           .astype(int))]
    fig = figs.new(12, 4.8)
    a1, a2 = fig.subplots(1, 2, width_ratios=[1.25, 1])
    cmap = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd"]
    sd = np.sqrt(np.maximum(var, 0.0))
    for c, i in zip(cmap, pick):
        lab = ", ".join(f"{n}={v:.3g}" for n, v in zip(sur.input_names, X[i]))
        a1.fill_between(time, pred[i] - 1.645 * sd[i], pred[i] + 1.645 * sd[i], color=c,
                        alpha=0.25, lw=0)
        a1.plot(time, pred[i], "-", color=c, lw=1.5, label=lab)
        a1.plot(time, Y[i], "o", color=c, ms=4, mec="k", mew=0.4)
    a1.plot([], [], "ko", ms=4, label="FMU (dots)")
    a1.plot([], [], "k-", label="surrogate (lines, 90 % band)")
    a1.set_xlabel("time since start (s)")
    a1.set_ylabel(f"mass flow ({sur.units})")
    a1.set_ylim(bottom=0)
    a1.set_title(f"{len(pick)} of {len(X)} test runs")
    a1.legend(fontsize=8, loc="lower right")
    a1.grid(alpha=0.3)
    a2.semilogy(time, 100 * rel.max(axis=0), "o-", color="#d62728", ms=3,
                label="max over test runs")
    a2.semilogy(time, 100 * rel.mean(axis=0), "s-", color="#1f77b4", ms=3,
                label="mean over test runs")
    pmax, pmean = PAPER_SURROGATE_ERROR
    a2.axhline(100 * pmax, color="#d62728", ls=":", lw=1, label=f"paper max ({100 * pmax:g} %)")
    a2.axhline(100 * pmean, color="#1f77b4", ls=":", lw=1,
               label=f"paper mean ({100 * pmean:g} %)")
    a2.set_xlabel("time since start (s)")
    a2.set_ylabel("relative error |surrogate - FMU| / FMU (%)")
    a2.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    a2.set_title("Relative error per time step")
    a2.legend(fontsize=8, loc="upper right")
    a2.grid(alpha=0.3, which="both")
    mx, mn = float(rel.max()), float(rel.mean())
    fig.suptitle(f"Surrogate against FMU on {len(X)} test runs: max relative error "
                 f"{100 * mx:.2f} %, mean {100 * mn:.3f} % (paper: {100 * pmax:g} % / "
                 f"{100 * pmean:g} %)")
    figs.save(fig, "fig5_surrogate", "surrogate", "Surrogate against FMU",
              "Left: test transients never seen in training (FMU runs as dots, surrogate "
              "prediction as lines with its 90 % predictive band). Right: relative error "
              "at each time step over all test runs.")
    cover = float(np.mean(np.abs(pred - Y) <= 1.6449 * sd))
    return {"n_test": int(len(X)), "max_rel_error": mx, "mean_rel_error": mn,
            "coverage_90": cover, "paper_max_rel_error": pmax, "paper_mean_rel_error": pmean}


def _truth_at(truth, unit: str, name: str, years) -> Optional[np.ndarray]:
    """True values of an input at the given years (NaN where the truth has no such year)."""
    if truth is None or unit not in truth.inputs or name not in truth.inputs[unit]:
        return None
    ty = np.asarray(truth.years[unit])
    tv = np.asarray(truth.inputs[unit][name], float)
    out = np.full(len(years), np.nan)
    for k, y in enumerate(years):
        hit = np.flatnonzero(ty == y)
        if hit.size:
            out[k] = tv[hit[0]]
    return out


def fig_estimates(figs: _Figures, inp: _Inputs, colours: dict) -> dict:
    """Figure 6: posterior estimates per year with 90 % intervals (+ truth). Returns truth
    errors per input when the truth is known."""
    post, cfg, truth = inp.posterior, inp.cfg, inp.truth
    names, units = list(post.input_names), list(post.units)
    fig = figs.new(3.6 * len(units) + 0.8, 2.9 * len(names) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(names), len(units), sharey="row", sharex=True,
                                      squeeze=False))
    errors: dict = {}
    for j, name in enumerate(names):
        rel, cover = [], []
        for i, unit in enumerate(units):
            ax = axes[j, i]
            p = post.units[unit]
            yrs = np.asarray(p.years)
            m, lo, hi = p.mean[:, j], p.q05[:, j], p.q95[:, j]
            ax.errorbar(yrs, m, yerr=[m - lo, hi - m], fmt="o", ms=4, capsize=3,
                        color=colours[unit], label="estimate (90 % interval)")
            tv = _truth_at(truth, unit, name, yrs)
            if tv is not None:
                ax.plot(yrs, tv, "D", ms=4, color="k", mfc="none", label="true value")
                ok = np.isfinite(tv)
                rel.append(np.abs(m[ok] - tv[ok]) / np.abs(tv[ok]))
                cover.append((lo[ok] <= tv[ok]) & (tv[ok] <= hi[ok]))
            if j == 0:
                ax.set_title(unit, color=colours[unit], fontweight="bold")
            if j == len(names) - 1:
                ax.set_xlabel("year of service")
            if i == 0:
                ax.set_ylabel(_input_label(cfg, name))
            ax.xaxis.get_major_locator().set_params(integer=True)
            ax.grid(alpha=0.3)
        if rel:
            r, c = np.concatenate(rel), np.concatenate(cover)
            errors[name] = {"max_rel_error": float(r.max()), "mean_rel_error": float(r.mean()),
                            "coverage_90": float(c.mean())}
    axes[0, -1].legend(fontsize=8, loc="best")
    title = "Calibrated degradation inputs per year (posterior mean and 90 % interval)"
    if errors:
        title += "\n" + "; ".join(
            f"{n}: error max {100 * e['max_rel_error']:.1f} %, mean "
            f"{100 * e['mean_rel_error']:.1f} %, 90 % coverage {100 * e['coverage_90']:.0f} %"
            for n, e in errors.items())
    fig.suptitle(title)
    figs.save(fig, "fig6_estimates", "calibration", "Estimates per year",
              "Each year's start-up is calibrated by Bayesian inference through the surrogate; "
              "dots are posterior means, bars the 90 % credible intervals"
              + (", open diamonds the true values used to fabricate the data." if errors
                 else "."))
    return errors


def fig_trends(figs: _Figures, inp: _Inputs, colours: dict) -> None:
    """Figure 7: trend lines with prediction intervals over the horizon."""
    fc, cfg, truth = inp.forecast, inp.cfg, inp.truth
    names, units = list(fc.input_names), list(fc.units)
    conf = fc.confidence
    fig = figs.new(3.6 * len(units) + 0.8, 2.9 * len(names) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(names), len(units), sharey="row", sharex=True,
                                      squeeze=False))
    for j, name in enumerate(names):
        for i, unit in enumerate(units):
            ax = axes[j, i]
            u = fc.units[unit]
            c = colours[unit]
            yo, yf = np.asarray(u.years_observed), np.asarray(u.years_future)
            grid = np.linspace(yo[0], yf[-1], 200)
            t = u.trends[name]
            mean, lo, hi, _ = t.predict(grid, conf)
            ax.fill_between(grid, lo, hi, color=c, alpha=0.2, lw=0)
            ax.plot(grid, mean, "-", color=c, lw=1.5)
            ax.plot(yo, u.estimates[name], "x", color="k", ms=6, mew=1.5)
            tv = _truth_at(truth, unit, name, yo)
            if tv is not None:
                ax.plot(yo, tv, "o", ms=4, color="k", mfc="none")
            if u.has_truth and u.true_inputs is not None:
                ax.plot(yf, u.true_inputs[name], "o", ms=4, color="grey", mfc="none")
            ax.axvline(yo[-1] + 0.5, color="grey", ls=":", lw=1)
            # The slope in the corner the line leaves free.
            up = t.slope >= 0
            ax.text(0.03 if up else 0.97, 0.95, f"slope {t.slope:+.3g}/yr"
                    + ("\nabnormal (p = %.1g)" % t.p_value if t.rejects else ""),
                    transform=ax.transAxes, ha="left" if up else "right", va="top", fontsize=9,
                    color=LIMIT_COLOUR if t.rejects else "k",
                    bbox={"fc": "white", "alpha": 0.8, "lw": 0})
            if j == 0:
                label = "healthy" if u.root_cause == "healthy" else f"{u.root_cause} fault"
                ax.set_title(f"{unit}: {label}", color=c, fontweight="bold")
            if j == len(names) - 1:
                ax.set_xlabel("year of service")
            if i == 0:
                ax.set_ylabel(_input_label(cfg, name))
            ax.xaxis.get_major_locator().set_params(integer=True)
            ax.grid(alpha=0.3)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    handles = [Line2D([], [], color="k", lw=1.5, label="linear trend (unit colour)"),
               Patch(color="grey", alpha=0.3, label=f"{100 * conf:g} % prediction interval"),
               Line2D([], [], ls="", marker="x", color="k", mew=1.5, label="yearly estimate")]
    if truth is not None:
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", color="k",
                              label="true value"))
    if any(f.has_truth for f in fc.units.values()):
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", color="grey",
                              label="true trend, extended"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=9)
    fig.suptitle(f"Linear trends of the estimates, extended over {len(yf)} years with "
                 f"{100 * conf:g} % prediction intervals (dotted line: last observation)")
    figs.save(fig, "fig7_trends", "forecast", "Trends with prediction intervals",
              "A straight line is fitted to each input's yearly estimates (crosses) and extended "
              "past the last observation; the band is where a new year's value is expected with "
              f"{100 * conf:g} % probability. A slope beyond normal ageing is marked abnormal.")


def _selected_years(years_future: np.ndarray) -> list[int]:
    """Future years shown in Figure 8: next year, three years on, end of the horizon."""
    first = int(years_future[0])
    want = [first, first + 2, int(years_future[-1])]
    return [y for y in dict.fromkeys(want) if y in set(years_future.tolist())]


def fig_marginals(figs: _Figures, inp: _Inputs, colours: dict) -> list[str]:
    """Figure 8: marginal distributions of the forecast inputs; returns the units shown."""
    import matplotlib
    fc, cfg = inp.forecast, inp.cfg
    names = list(fc.input_names)
    faulty = [u for u, f in fc.units.items() if f.root_cause != "healthy"]
    shown = faulty or list(fc.units)
    fig = figs.new(4.6 * len(names) + 0.6, 2.9 * len(shown) + 0.7)
    axes = np.atleast_2d(fig.subplots(len(shown), len(names), squeeze=False))
    cmap = matplotlib.colormaps["viridis"]
    for i, unit in enumerate(shown):
        u = fc.units[unit]
        yrs = _selected_years(np.asarray(u.years_future))
        for j, name in enumerate(names):
            ax = axes[i, j]
            for k, y in enumerate(yrs):
                idx = int(np.flatnonzero(u.years_future == y)[0])
                x = u.samples[idx, :, j]
                col = cmap(k / max(len(yrs) - 1, 1) * 0.85)
                ax.hist(x, bins=40, density=True, histtype="stepfilled", alpha=0.3, color=col)
                ax.hist(x, bins=40, density=True, histtype="step", lw=1.3, color=col,
                        label=f"year {y}")
                if u.has_truth and u.true_inputs is not None:
                    ax.axvline(u.true_inputs[name][idx], color=col, ls="--", lw=1)
            spec = cfg.model.inputs.get(name)
            if spec is not None:
                x0, x1 = ax.get_xlim()
                if x0 < spec.low:
                    ax.axvspan(x0, spec.low, color="grey", alpha=0.15, lw=0)
                if x1 > spec.high:
                    ax.axvspan(spec.high, x1, color="grey", alpha=0.15, lw=0)
                ax.set_xlim(x0, x1)
            ax.set_xlabel(_input_label(cfg, name))
            ax.set_ylabel("probability density")
            state = "healthy" if u.root_cause == "healthy" else f"{u.root_cause} fault"
            ax.set_title(f"{unit} ({state}): {name}", color=colours[unit], fontsize=10)
            ax.grid(alpha=0.3)
            if j == 0:
                if u.has_truth:
                    ax.plot([], [], "k--", lw=1, label="true value")
                ax.legend(fontsize=8)
    fig.suptitle("Forecast distributions of the degradation inputs"
                 + (" (units with a detected fault)" if faulty else "")
                 + "\ngrey background: outside the surrogate's training box (the FMU is run "
                 "there)")
    figs.save(fig, "fig8_marginals", "forecast", "Marginal distributions of the forecast inputs",
              "Monte Carlo samples of each input for the next year, three years on and the end "
              "of the horizon, drawn from the trend's predictive distribution; they are "
              "propagated through the twin to get the t90 distribution of Figure 9.")
    return shown


def fig_t90_forecast(figs: _Figures, inp: _Inputs, colours: dict,
                     observed_t90: Optional[dict]) -> None:
    """Figure 9: t90 distribution per year per unit, P(unsafe), failure year."""
    fc, safety = inp.forecast, inp.cfg.safety
    units = list(fc.units)
    record = float(inp.cfg.model.output.times.stop)
    cap = record * 1.04                                    # "never reached" drawn here
    fig = figs.new(11, 3.1 * len(units) + 0.6)
    axes = np.atleast_1d(fig.subplots(len(units), 1, sharex=True, squeeze=False)[:, 0])
    limit = safety.failure_probability
    for ax, unit in zip(axes, units):
        u = fc.units[unit]
        c = colours[unit]
        yo, yf = np.asarray(u.years_observed), np.asarray(u.years_future)
        data_o = [np.clip(np.nan_to_num(r, nan=np.inf), None, cap) for r in u.t90_observed]
        data_f = [np.clip(np.nan_to_num(r, nan=np.inf), None, cap) for r in u.t90]
        kw = dict(widths=0.6, whis=(5, 95), showfliers=False, patch_artist=True,
                  medianprops={"color": "k"})
        bo = ax.boxplot(data_o, positions=yo, **kw)
        bf = ax.boxplot(data_f, positions=yf, **kw)
        for b in bo["boxes"]:
            b.set(facecolor=c, alpha=0.35)
        for b in bf["boxes"]:
            b.set(facecolor=c, alpha=0.8)
        if observed_t90 is not None and unit in observed_t90:
            oy, ot90 = observed_t90[unit]
            ax.plot(oy, np.clip(ot90, None, cap), "D", color="k", ms=4, mfc="white",
                    label="measured t90", zorder=5)
        ax.axhline(safety.max_time, color=LIMIT_COLOUR, ls="--", lw=1.2,
                   label=f"{safety.max_time:g} s limit")
        # The P(unsafe) labels sit at a fixed height of the axes, whatever its range.
        lab = ax.get_xaxis_transform()
        for y, p in zip(yf, u.p_unsafe):
            ax.text(y, 0.97, _pct(p), ha="center", va="top", fontsize=8, transform=lab,
                    color=LIMIT_COLOUR if p > limit else "k")
        if u.failure_year is not None:
            ax.axvspan(u.failure_year - 0.45, u.failure_year + 0.45, color=LIMIT_COLOUR,
                       alpha=0.12, lw=0, label=f"failure year {u.failure_year}")
        if u.has_truth and u.true_failure_year is not None:
            ax.plot([u.true_failure_year], [0.86], "v", color="k", ms=8, transform=lab,
                    label=f"true failure year {u.true_failure_year}")
        ax.axvline(yo[-1] + 0.5, color="grey", ls=":", lw=1)
        # Zoom on the boxes (narrow ones vanish on a 0-50 s axis); keep the limit in view,
        # and the "never reached" level when some draw never reached it.
        allv = np.concatenate([np.ravel(d) for d in data_o + data_f])
        lo_v = float(np.quantile(allv, 0.01))
        hi_v = float(max(np.quantile(np.concatenate([np.ravel(d) for d in data_f]), 0.95),
                         np.max([np.quantile(d, 0.95) for d in data_o + data_f])))
        top = cap * 1.02 if hi_v >= cap else max(safety.max_time, hi_v) * 1.12 + 1.0
        ax.set_ylim(max(0.0, min(lo_v, safety.max_time) * 0.85 - 1.0), top * 1.08)
        ax.set_ylabel("t90 (s)")
        state = "healthy" if u.root_cause == "healthy" else f"{u.root_cause} fault"
        ax.set_title(f"{unit} ({state}): " + (
            f"fails in year {u.failure_year}" if u.failure_year is not None
            else f"no failure by year {int(yf[-1])}") + "; numbers: P(unsafe) per future year",
            color=c, fontsize=10, loc="left")
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8, loc="upper left")
    axes[-1].set_xlabel("year of service (light boxes: observed years from the posterior; "
                        "dark boxes: forecast)")
    ticks = np.arange(min(int(fc.units[u].years_observed[0]) for u in units),
                      max(int(fc.units[u].years_future[-1]) for u in units) + 1)
    axes[-1].set_xticks(ticks)
    axes[-1].set_xticklabels([str(t) for t in ticks])
    fig.suptitle(f"Time to {100 * safety.fraction:g} % of nominal flow: distribution per year "
                 f"(box 25-75 %, whiskers 5-95 %); values at the top never reached it in "
                 f"{record:g} s")
    figs.save(fig, "fig9_t90_forecast", "forecast", "t90 distribution per year",
              "The forecast inputs pushed through the twin give a t90 distribution per year. "
              f"The unit fails in the first year whose probability of exceeding "
              f"{safety.max_time:g} s (or leaving the physical domain) passes "
              f"{100 * limit:g} % (shaded).")


# ---------------------------------------------------------------------------------------
# Diagnose figures
# ---------------------------------------------------------------------------------------
def _gap_title(g) -> str:
    if g.verdict == "effect":
        eff = " / ".join(g.group) if len(g.group) > 1 else ", ".join(g.effects)
        return f"effect {eff}" + (f" from year {g.onset}" if g.onset is not None else "")
    if g.verdict == "unexplained":
        return "gap not explained by any candidate"
    return "no significant gap"


def fig_residual_map(figs: _Figures, inp: _Inputs, colours: dict) -> None:
    """Residual (observation - twin) / noise by year and time, before and after the effect."""
    from matplotlib.colors import TwoSlopeNorm
    gap = inp.gap
    units = list(gap.units)
    fig = figs.new(max(4.2 * len(units) + 1.2, 9.0), 7.2)
    axes = fig.subplots(2, len(units), squeeze=False, sharex=True)
    allr = np.concatenate([np.abs(np.concatenate([g.residual_before, g.residual_after]).ravel())
                           for g in gap.units.values()])
    allr = allr[np.isfinite(allr)]
    vmax = float(max(np.quantile(allr, 0.99) if allr.size else 3.0, 3.0))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-vmax, vmax=vmax)
    t = np.asarray(gap.time)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    im = None
    for i, unit in enumerate(units):
        g = gap.units[unit]
        yrs = np.asarray(g.years)
        for r, (res, label) in enumerate(((g.residual_before, "base twin"),
                                          (g.residual_after, "final twin"))):
            ax = axes[r, i]
            im = ax.imshow(res, aspect="auto", origin="lower", cmap="RdBu_r", norm=norm,
                           extent=(t[0] - dt / 2, t[-1] + dt / 2, yrs[0] - 0.5, yrs[-1] + 0.5),
                           interpolation="nearest")
            for k, (name, (a, b)) in enumerate(zip(gap.windows, gap.window_bounds)):
                if t[0] < a < t[-1]:
                    ax.axvline(a, color="k", lw=1, ls="--")
                if r == 0:
                    mid = (max(a, t[0] - dt / 2) + min(b, t[-1] + dt / 2)) / 2
                    ax.text(mid, yrs[-1] + 0.45, name, ha="center", va="top", fontsize=8,
                            bbox={"fc": "white", "alpha": 0.7, "lw": 0, "pad": 1})
            if r == 0:
                for y in yrs[np.asarray(g.significant_years, bool)]:
                    ax.plot(t[-1] + dt / 2, y, "<", color="k", ms=6, clip_on=False)
                ax.set_title(f"{unit}: {_gap_title(g)}\nbase twin", color=colours[unit],
                             fontsize=10)
            else:
                ax.set_title(f"after ({', '.join(g.effects) if g.effects else 'no effect added'}"
                             f"): RMS {g.rms_before:.2f} -> {g.rms_after:.2f}", fontsize=9)
                ax.set_xlabel("time since start (s)")
            if i == 0:
                ax.set_ylabel(f"year of service ({label})")
            ax.yaxis.get_major_locator().set_params(integer=True)
    cb = fig.colorbar(im, ax=axes, shrink=0.85, pad=0.01)
    cb.set_label("standardised residual (observed - twin) / noise std (-)")
    fig.suptitle("Where the twin misses the plant: flow residual by year and time\n"
                 "(dashed: window boundaries; arrow: year with a significant gap)")
    figs.save(fig, "diag_residual_map", "diagnose", "Residual map",
              "Top row: residual of the base twin (degradation inputs fitted year by year); "
              "bottom row: after adding the diagnosed effect. Red: the plant flows more than "
              "the twin, blue: less. A structured band that starts in some year points at an "
              "unmodelled effect.")


def fig_candidates(figs: _Figures, inp: _Inputs, colours: dict) -> None:
    """Candidate effects ranked by BIC gain, one panel per unit, group highlighted."""
    from matplotlib.ticker import FuncFormatter
    gap, cfg = inp.gap, inp.cfg
    units = list(gap.units)
    n_c = max(len(g.candidates) for g in gap.units.values())
    fig = figs.new(max(4.0 * len(units) + 1.0, 8.0), 0.38 * n_c + 2.0)
    axes = fig.subplots(1, len(units), squeeze=False)[0]
    thr = cfg.diagnose.bic_gain
    for ax, unit in zip(axes, units):
        g = gap.units[unit]
        cands = list(g.candidates)
        vals = np.asarray(g.delta_bic, float)
        y = np.arange(len(cands))[::-1]
        cols = [colours[unit] if c in g.group and g.verdict == "effect"
                else ("#555555" if c in g.effects else "#bbbbbb") for c in cands]
        ax.barh(y, np.nan_to_num(vals, nan=0.0), color=cols, edgecolor="k", lw=0.5)
        ax.set_yticks(y)
        ax.set_yticklabels(cands, fontsize=8)
        ax.axvline(thr, color=LIMIT_COLOUR, ls="--", lw=1.2, label=f"acceptance ({thr:g})")
        ax.axvline(0, color="k", lw=0.8)
        # symlog: gains span from about -10 (a useless extra parameter) to thousands.
        ax.set_xscale("symlog", linthresh=10)
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        fin = vals[np.isfinite(vals)]
        hi = max(thr * 3, float(fin.max()) * 3 if fin.size else thr * 3)
        lo = min(-thr * 2, float(fin.min()) * 1.5 if fin.size else -thr)
        ax.set_xlim(lo, hi)
        for yy, v in zip(y, vals):
            if np.isfinite(v):
                # Gains right of the bar's end; losses inside the bar, clear of the names.
                ax.text(v if v >= 0 else 0.0, yy,
                        f" {v:.0f} " if abs(v) >= 10 else f" {v:.1f} ", va="center",
                        ha="left" if v >= 0 else "right", fontsize=7)
        ax.set_xlabel("BIC gain over the base twin (-)")
        ax.set_title(f"{unit}: {_gap_title(g)}", color=colours[unit], fontsize=10)
        ax.grid(alpha=0.3, axis="x")
        if g.verdict == "effect":
            ax.bar([0], [0], color=colours[unit],
                   label="diagnosed effect" if len(g.group) <= 1
                   else "best group (indistinguishable)")
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle("Candidate unmodelled effects ranked by BIC gain (higher explains more)")
    figs.save(fig, "diag_candidates", "diagnose", "Candidate ranking",
              "Each candidate effect is fitted with the degradation inputs through the FMU; the "
              "BIC gain says how much better the twin explains the observations with it. "
              f"A gain above {thr:g} is accepted; candidates within "
              f"{cfg.diagnose.group_bic:g} of the best cannot be told apart from the flow alone.")


def fig_overlay(figs: _Figures, inp: _Inputs, colours: dict) -> bool:
    """One affected year per unit with a gap: observation, base twin, augmented twin."""
    gap = inp.gap
    hit = [u for u, g in gap.units.items() if g.verdict != "none"]
    if not hit:
        return False
    t = np.asarray(gap.time)
    fig = figs.new(max(4.6 * len(hit) + 0.6, 8.0), 6.2)
    axes = fig.subplots(2, len(hit), squeeze=False, sharex=True, height_ratios=[2.2, 1])
    for i, unit in enumerate(hit):
        g = gap.units[unit]
        yrs = np.asarray(g.years)
        cand = [int(y) for y in g.where_years] or [int(y) for y in yrs[g.significant_years]]
        rows = [int(np.flatnonzero(yrs == y)[0]) for y in cand if y in yrs] or list(range(len(yrs)))
        k = max(rows, key=lambda r: g.chi2_before[r])
        ax, axr = axes[0, i], axes[1, i]
        ax.plot(t, g.observed[k], "o", color="k", ms=4, label="observed")
        ax.plot(t, g.predicted_before[k], "-", color="grey", lw=1.6, label="base twin")
        ax.plot(t, g.predicted_after[k], "-", color=colours[unit], lw=1.6,
                label=f"twin + {', '.join(g.effects)}" if g.effects else "final twin")
        ax.set_ylabel("mass flow (kg/s)")
        ax.set_title(f"{unit}, year {int(yrs[k])}: {_gap_title(g)}", color=colours[unit],
                     fontsize=10)
        ax.legend(fontsize=8, loc="lower right")
        ax.grid(alpha=0.3)
        axr.axhline(0, color="k", lw=0.8)
        axr.plot(t, g.residual_before[k], ".-", color="grey", label="base")
        axr.plot(t, g.residual_after[k], ".-", color=colours[unit], label="final")
        axr.set_xlabel("time since start (s)")
        axr.set_ylabel("residual / noise (-)")
        axr.legend(fontsize=7, loc="upper right", ncol=2)
        axr.grid(alpha=0.3)
    fig.suptitle("Before and after: the most affected year against the twin")
    figs.save(fig, "diag_overlay", "diagnose", "Before/after overlay",
              "Observed start-up of the most affected year (dots) against the base twin and the "
              "twin with the diagnosed effect; below, the standardised residuals.")
    return True


# ---------------------------------------------------------------------------------------
# Plain-language summary per unit
# ---------------------------------------------------------------------------------------
def _faulty_components(uf) -> list[str]:
    return sorted({t.component or name for name, t in uf.trends.items() if t.rejects})


def _unit_summary(unit: str, inp: _Inputs, observed_t90: dict) -> UnitSummary:
    cfg = inp.cfg
    s = UnitSummary(unit)
    limit = cfg.safety.failure_probability
    if unit in observed_t90:
        yrs, t90 = observed_t90[unit]
        s.last_year, s.last_t90 = int(yrs[-1]), float(t90[-1])
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
        comps = _faulty_components(uf)
        s.root_cause = uf.root_cause
        s.health = "healthy" if not comps else "degrading: " + " and ".join(comps)
        s.failure_year = uf.failure_year
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
                        else "no action; re-check at next year's start-up")
        for name, t in uf.trends.items():
            if t.rejects:
                lo, hi = t.slope_ci
                why.append(f"{name} drifts {t.slope:+.3g}/yr (90 % CI {lo:+.3g} to {hi:+.3g}) "
                           f"against normal ageing {t.normal_rate:+.3g} +- {t.tolerance:.3g}/yr "
                           f"(one-sided t test, p = {t.p_value:.1g})")
        if not comps:
            pmin = min(t.p_value for t in uf.trends.values())
            why.append(f"every input drifts within normal ageing (one-sided t tests of the "
                       f"slopes, all p >= {np.floor(pmin * 100) / 100:.2f})")
        why.append(f"P(unsafe) from {uf.t90.shape[1]} Monte Carlo draws per year through "
                   f"the twin; failure = first year above {100 * limit:g} %")
    elif post is not None:
        s.action = "run `twinmon forecast` for a trend and a time to failure"
    else:
        s.action = "run `twinmon calibrate` and `twinmon forecast` for a diagnosis"
        if s.last_t90 is not None and s.last_t90 > cfg.safety.max_time:
            s.action = (f"unsafe at the last start-up (t90 {_fmt_t90(s.last_t90)}): inspect "
                        "the unit; " + s.action)

    if post is not None:
        cc = cfg.calibrate
        rmax, emin = float(np.nanmax(post.rhat)), float(np.nanmin(post.ess))
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
            "absorbed_share": _plain(float(gap.absorbed_share)),
            "closed_percent": _plain(float(gap.closed_percent)),
            "rms_before": _plain(float(gap.rms_before)), "rms_after": _plain(float(gap.rms_after)),
            "separating_channel": gap.separating_channel or None,
            "failure_year_before": gap.failure_year_before,
            "failure_year_after": gap.failure_year_after,
            "estimate": {k: {"mean": _plain(float(v[0])), "q05": _plain(float(v[1])),
                             "q95": _plain(float(v[2]))} for k, v in gap.estimate.items()},
        }
        if gap.verdict == "effect":
            group = gap.group if len(gap.group) > 1 else gap.effects
            eff = " or ".join(group)
            s.action += (f"; the twin misses the plant from year {gap.onset}: check {eff}"
                         if gap.onset is not None else f"; the twin misses the plant: check {eff}")
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
            if uf is not None and np.isfinite(share) and share > 0.1:
                why.append(f"the calibrated twin lacks this effect and its degradation inputs "
                           f"absorb {100 * share:.0f} % of its signature, so the root cause and "
                           "time to failure above may be biased")
            if gap.failure_year_before != gap.failure_year_after:
                why.append(f"with the effect in the twin the projected failure year moves from "
                           f"{gap.failure_year_before or 'none'} to "
                           f"{gap.failure_year_after or 'none'}")
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


# ---------------------------------------------------------------------------------------
# HTML
# ---------------------------------------------------------------------------------------
_CSS = """
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


def _e(x: Any) -> str:
    return html.escape(str(x))


def _e_p(text: str) -> str:
    return f"<p>{_e(text)}</p>"


def _figure_html(item: dict) -> str:
    data = base64.b64encode(item["_path"].read_bytes()).decode("ascii")
    return (f'<figure id="{_e(item["name"])}"><img alt="{_e(item["title"])}" '
            f'src="data:image/png;base64,{data}"><figcaption><b>{_e(item["title"])}.</b> '
            f'{_e(item["caption"])}</figcaption></figure>')


def _html(cfg: Config, summary: ReportSummary, figs: list[dict], extra: dict) -> str:
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           "<title>twinmon health report</title>", f"<style>{_CSS}</style></head><body>",
           "<h1>twinmon health report</h1>",
           f'<p class="meta">Generated {_e(artifacts.utc_now())} by twinmon from config '
           f"<code>{_e(cfg.source)}</code>.</p>"]
    out.append("<h2>Summary per unit</h2>")
    if summary.units:
        out.append("<table><tr><th>Unit</th><th>Health</th><th>Time to failure</th>"
                   "<th>What to do</th><th>What this rests on</th></tr>")
        for u, s in summary.units.items():
            cls = ("ok" if s.root_cause == "healthy" else "bad" if s.failure_year is not None
                   else "warn" if s.root_cause else "")
            ttf = s.time_to_failure
            if s.failure_year is not None and s.last_year is not None:
                n = s.failure_year - s.last_year
                ttf = (f"year {s.failure_year} of service: {n} year{'s' if n != 1 else ''} "
                       f"after the last observation (year {s.last_year}); P(unsafe) "
                       f"{_pct(s.p_unsafe)} in year {s.failure_year}")
            out.append(f'<tr><td class="unit">{_e(u)}</td><td class="{cls}">{_e(s.health)}</td>'
                       f"<td>{_e(ttf)}</td><td>{_e(s.action)}</td><td>{_e(s.confidence)}</td></tr>")
        out.append("</table>")
        plans = [(u, s.plan) for u, s in summary.units.items() if s.plan]
        if plans:
            out.append("<p>Maintenance plans from the forecast:</p><ul>")
            out += [f"<li><b>{_e(u)}</b>: {_e(p)}</li>" for u, p in plans]
            out.append("</ul>")
        est = [(u, s) for u, s in summary.units.items() if s.estimates]
        if est:
            names = list(est[0][1].estimates)
            out.append("<p>Latest estimates (posterior mean, 90 % interval):</p><table><tr>"
                       "<th>Unit</th><th>Year</th>" + "".join(
                           f"<th>{_e(_input_label(cfg, n))}</th>" for n in names) + "</tr>")
            for u, s in est:
                cells = "".join(
                    f"<td>{s.estimates[n]['mean']:.4g} [{s.estimates[n]['q05']:.4g}, "
                    f"{s.estimates[n]['q95']:.4g}]</td>" for n in names if n in s.estimates)
                year = next(iter(s.estimates.values()))["year"]
                out.append(f"<tr><td class='unit'>{_e(u)}</td><td>{year}</td>{cells}</tr>")
            out.append("</table>")
    else:
        out.append('<p class="note">No units: no artifact with units was given.</p>')
    for note in summary.notes:
        out.append(f'<p class="note">{_e(note)}</p>')

    for sec in SECTIONS:
        out.append(f'<h2 id="{sec}">{_e(_SECTION_TITLES[sec])}</h2>')
        state = summary.sections[sec]
        if state != "rendered":
            out.append(f'<p class="note">Section {_e(state)}.</p>')
            continue
        out += extra.get(sec, [])
        for item in figs:
            if item["section"] == sec:
                out.append(_figure_html(item))

    out.append("<h2>Artifacts</h2><table><tr><th>Role</th><th>Path</th><th>Schema</th>"
               "<th>Created</th></tr>")
    for role, path in summary.artifacts.items():
        prov = extra["provenance"].get(role, {})
        out.append(f"<tr><td>{_e(role)}</td><td><code>{_e(path)}</code></td>"
                   f"<td>{_e(prov.get('schema', ''))}</td><td>{_e(prov.get('created', ''))}"
                   "</td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out)


def _calibration_table(cfg: Config, inp: _Inputs, diag: dict) -> list[str]:
    rows = ["<table><tr><th>Unit</th><th>Years</th><th>max R-hat</th><th>min ESS</th>"
            "<th>acceptance</th><th>noise std (kg/s)</th></tr>"]
    for u, d in diag["units"].items():
        bad = d["max_rhat"] > cfg.calibrate.rhat_warn or d["min_ess"] < cfg.calibrate.ess_warn
        rows.append(f"<tr><td class='unit'>{_e(u)}</td><td>{d['years'][0]}-{d['years'][-1]}</td>"
                    f"<td class='{'warn' if bad else 'ok'}'>{d['max_rhat']:.3f}</td>"
                    f"<td>{d['min_ess']:.0f}</td><td>{d['acceptance'][0]:.2f}-"
                    f"{d['acceptance'][1]:.2f}</td><td>{d['noise_std']:.3g} "
                    f"({_e(d['noise_source'])})</td></tr>")
    rows.append("</table>")
    if diag["warnings"]:
        rows.append("<p class='warn'>Sampling warnings:</p><ul>"
                    + "".join(f"<li>{_e(w)}</li>" for w in diag["warnings"]) + "</ul>")
    else:
        rows.append(_e_p(f"No sampling warning (R-hat <= {cfg.calibrate.rhat_warn:g}, "
                         f"ESS >= {cfg.calibrate.ess_warn:g} everywhere)."))
    return rows


def _calibration_diagnostics(inp: _Inputs) -> dict:
    from .calibrate import diagnostics_warnings
    post, cfg = inp.posterior, inp.cfg
    units = {}
    for u, p in post.units.items():
        units[u] = {"years": [int(y) for y in p.years],
                    "max_rhat": float(np.nanmax(p.rhat)), "min_ess": float(np.nanmin(p.ess)),
                    "acceptance": [float(np.min(p.acceptance)), float(np.max(p.acceptance))],
                    "noise_std": float(np.asarray(p.noise_std)[0]),
                    "noise_source": p.noise_source}
    return {"units": units,
            "warnings": diagnostics_warnings(post.units, list(post.input_names), cfg)}


# ---------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------
def _check_consistency(cfg: Config, inp: _Inputs) -> None:
    names = cfg.model.input_names
    for role, obj in (("posterior", inp.posterior), ("forecast", inp.forecast),
                      ("surrogate", inp.surrogate)):
        if obj is not None and list(obj.input_names) != names:
            raise ArtifactError(f"{inp.paths[role]}: inputs are {list(obj.input_names)}, the "
                                f"config's are {names}")
    if inp.sims is not None and list(inp.sims.input_names) != names:
        raise ArtifactError(f"{inp.paths['simulations']}: inputs are {inp.sims.input_names}, "
                            f"the config's are {names}")


def report(cfg: Config, output_dir: str | os.PathLike, *,
           observations: str | os.PathLike | None = None,
           simulations: str | os.PathLike | None = None,
           surrogate: str | os.PathLike | None = None,
           posterior: str | os.PathLike | None = None,
           forecast: str | os.PathLike | None = None,
           gap: str | os.PathLike | None = None,
           truth: str | os.PathLike | None = None) -> ReportSummary:
    """Make the health report from whichever artifacts are given.

    Parameters
    ----------
    cfg : Config
    output_dir : path-like
        Folder to write ``index.html`` (self-contained), ``figures/*.png`` and
        ``summary.json`` into; created if needed. Files of an earlier report are replaced.
    observations, simulations, surrogate, posterior, forecast, gap, truth : path-like, optional
        Artifacts (``twinmon.<kind>/1``); ``None`` skips the sections that need it. The
        surrogate figure needs both ``simulations`` (the test runs) and ``surrogate``.

    Returns
    -------
    ReportSummary
        ``.terminal()`` is a short text, ``.as_dict()`` the content of ``summary.json``.

    Raises
    ------
    ArtifactError
        An artifact is missing, of the wrong schema or made for other inputs than the
        config's; nothing is written then.
    """
    import matplotlib
    paths = {"observations": observations, "simulations": simulations, "surrogate": surrogate,
             "posterior": posterior, "forecast": forecast, "gap": gap, "truth": truth}
    inp = _load(cfg, paths)
    _check_consistency(cfg, inp)
    provenance = {role: artifacts.read_provenance(p) for role, p in inp.paths.items()}

    out = Path(output_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.{os.getpid()}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "figures").mkdir(parents=True)
    try:
        with matplotlib.rc_context({"font.size": 10, "axes.titlesize": 11,
                                    "figure.titlesize": 12, "legend.framealpha": 0.85}):
            summary = _render(cfg, inp, tmp, out, provenance)
        _install(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return summary


def _render(cfg: Config, inp: _Inputs, tmp: Path, out: Path, provenance: dict) -> ReportSummary:
    figs = _Figures(tmp / "figures")
    units = inp.unit_names()
    colours = {u: UNIT_COLOURS[i % len(UNIT_COLOURS)] for i, u in enumerate(units)}
    sections: dict[str, str] = {}
    notes: list[str] = []
    extra: dict[str, list[str]] = {"provenance": provenance}
    surrogate_info = calibration_info = None

    observed_t90: dict = {}
    if inp.obs is not None:
        fig_last_transients(figs, inp, colours)
        t90s = fig_t90_history(figs, inp, colours)
        observed_t90 = {u: (np.asarray(o.years), t90s[u]) for u, o in inp.obs.units.items()}
        sections["observations"] = "rendered"
    else:
        sections["observations"] = f"skipped: {_SKIP_HINTS['observations']}"

    if inp.surrogate is not None and inp.sims is not None and inp.sims.ok["test"].any():
        surrogate_info = fig_surrogate(figs, inp)
        surrogate_info["stored_validation"] = inp.validation
        surrogate_info["modes"] = int(inp.surrogate.n_modes)
        surrogate_info["variance_ratio"] = inp.surrogate.variance_ratio
        si = surrogate_info
        extra["surrogate"] = [_e_p(
            f"{si['modes']} Karhunen-Loeve modes kept ({100 * si['variance_ratio']:.4f} % of "
            f"the training variance). On {si['n_test']} held-out FMU runs: max relative error "
            f"{100 * si['max_rel_error']:.3f} %, mean {100 * si['mean_rel_error']:.4f} % (paper: "
            f"{100 * PAPER_SURROGATE_ERROR[0]:g} % / {100 * PAPER_SURROGATE_ERROR[1]:g} %); "
            f"{100 * si['coverage_90']:.0f} % of the FMU values lie in the 90 % predictive band.")]
        sections["surrogate"] = "rendered"
    elif inp.surrogate is not None:
        v = inp.validation or {}
        surrogate_info = {"stored_validation": v, "modes": int(inp.surrogate.n_modes)}
        sections["surrogate"] = ("skipped: the surrogate figure needs the simulations artifact "
                                 "(its test runs); stored validation: max relative error "
                                 f"{100 * (v.get('max_rel_error') or float('nan')):.3f} %, "
                                 f"mean {100 * (v.get('mean_rel_error') or float('nan')):.4f} %")
    else:
        sections["surrogate"] = f"skipped: {_SKIP_HINTS['surrogate']}"

    if inp.posterior is not None:
        errors = fig_estimates(figs, inp, colours)
        calibration_info = _calibration_diagnostics(inp)
        if errors:
            calibration_info["truth_check"] = errors
        extra["calibration"] = _calibration_table(cfg, inp, calibration_info)
        sections["calibration"] = "rendered"
    else:
        sections["calibration"] = f"skipped: {_SKIP_HINTS['calibration']}"

    if inp.forecast is not None:
        fig_trends(figs, inp, colours)
        fig_marginals(figs, inp, colours)
        fig_t90_forecast(figs, inp, colours, observed_t90 or None)
        sections["forecast"] = "rendered"
    else:
        sections["forecast"] = f"skipped: {_SKIP_HINTS['forecast']}"

    if inp.gap is not None:
        if inp.gap_other_source is not None:
            lines = [f"{u}: {_gap_title(g)}" + (f" ({', '.join(g.effects)}, "
                                                 f"{g.closed_percent:.0f} % of the gap closed)"
                                                 if g.verdict == "effect" else "")
                     for u, g in inp.gap.units.items()]
            extra["diagnose"] = [_e_p(
                f"This section diagnoses {inp.gap_other_source}, not the observations above; "
                "its units are not merged into the unit summaries. " + "; ".join(lines) + ".")]
        fig_residual_map(figs, inp, colours)
        fig_candidates(figs, inp, colours)
        if not fig_overlay(figs, inp, colours):
            notes.append("Diagnose found no gap in any unit: no before/after overlay.")
        sections["diagnose"] = "rendered"
    else:
        sections["diagnose"] = f"skipped: {_SKIP_HINTS['diagnose']}"

    if inp.truth is not None and inp.posterior is None and inp.forecast is None:
        notes.append("A truth file was given but no posterior or forecast to compare it with.")
    if inp.forecast is not None and inp.posterior is None:
        notes.append("The forecast is shown without its posterior: Figure 6 is skipped.")

    unit_summaries = {u: _unit_summary(u, inp, observed_t90) for u in units}
    summary = ReportSummary(
        output_dir=str(out), index=str(out / "index.html"), units=unit_summaries,
        sections=sections,
        figures=[{**{k: v for k, v in f.items() if not k.startswith("_")},
                  "path": str(out / f["file"])} for f in figs.items],
        surrogate=_plain(surrogate_info), calibration=_plain(calibration_info),
        artifacts=dict(inp.paths), notes=notes)
    (tmp / "summary.json").write_text(json.dumps(_plain(summary.as_dict()), indent=2,
                                                 allow_nan=False))
    (tmp / "index.html").write_text(_html(cfg, summary, figs.items, extra), encoding="utf-8")
    return summary


def _install(tmp: Path, out: Path) -> None:
    """Move a finished report into ``out``: figures, then summary.json, index.html last."""
    out.mkdir(parents=True, exist_ok=True)
    figures = out / "figures"
    old = out / f".figures.{os.getpid()}.old"
    if figures.exists():
        os.replace(figures, old)
    os.replace(tmp / "figures", figures)
    shutil.rmtree(old, ignore_errors=True)
    os.replace(tmp / "summary.json", out / "summary.json")
    os.replace(tmp / "index.html", out / "index.html")
