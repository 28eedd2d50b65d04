"""The stage itself: load every artifact, draw the figures of each section, write the page,
``summary.json`` and the PNGs into a temporary folder, then move them into place."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from .. import artifacts
from ..config import Config
from .common import SKIP_HINTS, UNIT_COLOURS, Figures, plain
from .fig_calibration import fig_estimates
from .fig_diagnose import fig_candidates, fig_overlay, fig_residual_map, gap_title
from .fig_forecast import fig_indicator_forecast, fig_marginals, fig_trends
from .fig_observations import fig_indicator_history, fig_last_transients
from .fig_surrogate import fig_surrogate
from .html import (calibration_table, e_p, page, stored_validation_text, surrogate_text)
from .load import Inputs, check_consistency, load, observed_indicator
from .summary import ReportSummary, calibration_diagnostics, unit_summary, words_dict


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
        Names everything the report shows: the output's label and units, the health
        indicator's name, label, units and limit, the inputs' components.
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
    inp = load(cfg, paths)
    check_consistency(cfg, inp)
    provenance = {role: artifacts.read_provenance(p) for role, p in inp.paths.items()}

    out = Path(output_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    # One writer per report folder; folders left by a killed report are removed first.
    with artifacts.output_lock(out, "twinmon report"):
        artifacts.remove_stale_temporaries(out)
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


def _render(cfg: Config, inp: Inputs, tmp: Path, out: Path, provenance: dict) -> ReportSummary:
    figs = Figures(tmp / "figures")
    w = inp.words
    units = inp.unit_names()
    colours = {u: UNIT_COLOURS[i % len(UNIT_COLOURS)] for i, u in enumerate(units)}
    sections: dict[str, str] = {}
    notes: list[str] = []
    extra: dict[str, list[str]] = {"provenance": provenance}
    surrogate_info = calibration_info = None

    observed = observed_indicator(inp)
    if inp.obs is not None:
        fig_last_transients(figs, inp, colours, observed)
        if observed:
            fig_indicator_history(figs, inp, colours, observed)
        else:
            extra["observations"] = [e_p(
                f"The observations do not record the {w.var_label} ({w.ind.variable}), the "
                f"variable the "
                f"{w.ind.name} is computed from: no observed {w.ind.name} history.")]
        sections["observations"] = "rendered"
    else:
        sections["observations"] = f"skipped: {SKIP_HINTS['observations']}"

    if inp.surrogate is not None and inp.sims is not None and inp.sims.ok["test"].any():
        surrogate_info = fig_surrogate(figs, inp)
        surrogate_info["stored_validation"] = inp.validation
        surrogate_info["modes"] = int(inp.surrogate.n_modes)
        surrogate_info["variance_ratio"] = inp.surrogate.variance_ratio
        extra["surrogate"] = [e_p(surrogate_text(surrogate_info, w))]
        sections["surrogate"] = "rendered"
    elif inp.surrogate is not None:
        v = inp.validation or {}
        surrogate_info = {"stored_validation": v, "modes": int(inp.surrogate.n_modes)}
        sections["surrogate"] = ("skipped: the surrogate figure needs the simulations artifact "
                                 f"(its test runs); {stored_validation_text(v)}")
    else:
        sections["surrogate"] = f"skipped: {SKIP_HINTS['surrogate']}"

    if inp.posterior is not None:
        errors = fig_estimates(figs, inp, colours)
        calibration_info = calibration_diagnostics(inp)
        if errors:
            calibration_info["truth_check"] = errors
        extra["calibration"] = calibration_table(cfg, calibration_info)
        sections["calibration"] = "rendered"
    else:
        sections["calibration"] = f"skipped: {SKIP_HINTS['calibration']}"

    if inp.forecast is not None:
        fig_trends(figs, inp, colours)
        fig_marginals(figs, inp, colours)
        fig_indicator_forecast(figs, inp, colours, observed or None)
        sections["forecast"] = "rendered"
    else:
        sections["forecast"] = f"skipped: {SKIP_HINTS['forecast']}"

    if inp.gap is not None:
        if inp.gap_other_source is not None:
            lines = [f"{u}: {gap_title(g)}" + (f" ({', '.join(g.effects)}, "
                                                f"{g.closed_percent:.0f} % of the gap closed)"
                                                if g.verdict == "effect" else "")
                     for u, g in inp.gap.units.items()]
            extra["diagnose"] = [e_p(
                f"This section diagnoses {inp.gap_other_source}, not the observations above; "
                "its units are not merged into the unit summaries. " + "; ".join(lines) + ".")]
        fig_residual_map(figs, inp, colours)
        fig_candidates(figs, inp, colours)
        if not fig_overlay(figs, inp, colours):
            notes.append("Diagnose found no gap in any unit: no before/after overlay.")
        sections["diagnose"] = "rendered"
    else:
        sections["diagnose"] = f"skipped: {SKIP_HINTS['diagnose']}"

    if inp.truth is not None and inp.posterior is None and inp.forecast is None:
        notes.append("A truth file was given but no posterior or forecast to compare it with.")
    if inp.forecast is not None and inp.posterior is None:
        notes.append("The forecast is shown without its posterior: Figure 6 is skipped.")

    output_words, indicator_words = words_dict(inp)
    summary = ReportSummary(
        output_dir=str(out), index=str(out / "index.html"),
        units={u: unit_summary(u, inp, observed) for u in units},
        sections=sections,
        figures=[{**{k: v for k, v in f.items() if not k.startswith("_")},
                  "path": str(out / f["file"])} for f in figs.items],
        surrogate=plain(surrogate_info), calibration=plain(calibration_info),
        artifacts=dict(inp.paths), notes=notes, output=output_words,
        indicator=plain(indicator_words))
    (tmp / "summary.json").write_text(json.dumps(plain(summary.as_dict()), indent=2,
                                                 allow_nan=False))
    (tmp / "index.html").write_text(page(cfg, w, summary, figs.items, extra), encoding="utf-8")
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
