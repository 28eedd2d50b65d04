"""The stage itself: load every artifact, draw the figures of each section, write the page,
``summary.json`` and the PNGs into a temporary folder, then move them into place."""
from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path
from typing import Optional, Sequence

from .. import artifacts
from ..config import Config
from ..jsontext import to_json
from .common import SKIP_HINTS, UNIT_COLOURS, Figures, plain
from .fig_calibration import fig_estimates
from .fig_backtest import fig_backtest
from .fig_diagnose import fig_candidates, fig_overlay, fig_residual_map, gap_title
from .fig_fleet import fig_fleet_failure
from .fig_forecast import fig_indicator_forecast, fig_marginals, fig_trends
from .fig_observations import fig_indicator_history, fig_last_transients
from .fig_surrogate import fig_surrogate
from .fleet import check_requested, fleet_view, is_fleet
from .html import (calibration_table, diagnose_table, e_p, fleet_overview, page,
                   stored_validation_text, surrogate_text)
from .load import (Inputs, check_consistency, fleet_statistics, load, observed_indicator,
                   start_fleet_statistics, with_truth_of)
from .summary import ReportSummary, calibration_diagnostics, unit_summary, words_dict

#: Units per figure when a large fleet's units are drawn in detail (Figures 6 and 7 give
#: each unit a column: more would not read).
GROUP = 4
#: The config sections a report reads (the others reach it through the artifacts, which
#: are fingerprinted): recorded in ``summary.json`` (``made_from``).
CONFIG_SECTIONS = ("model", "safety", "seed", "calibrate", "forecast", "backtest",
                   "diagnose", "report")


def made_from(cfg: Config, paths: dict, units: Sequence[str] = ()) -> dict:
    """What a report is made from, as ``summary.json`` records it (``made_from``): this
    twinmon's version, the config sections it reads (:data:`CONFIG_SECTIONS`, without the
    processes that draw), the SHA-256 of each artifact by its role, the units asked for."""
    from .. import __version__
    return {"twinmon_version": __version__, "config": cfg.section_yaml(*CONFIG_SECTIONS),
            "inputs": {role: artifacts.file_sha256(p)
                       for role, p in sorted(paths.items()) if p is not None},
            "units": sorted(units)}


def is_up_to_date(cfg: Config, output_dir: str | os.PathLike, paths: dict,
                  units: Sequence[str] = ()) -> Optional[dict]:
    """The content of ``output_dir``'s ``summary.json`` when that report is whole (the
    page, the summary and every figure it lists) and was made from the same artifacts,
    config and version (:func:`made_from`); ``None`` when it must be made again. Used by
    ``twinmon run``."""
    import json
    out = Path(output_dir)
    try:
        done = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    figures = done.get("figures") if isinstance(done, dict) else None
    if not isinstance(figures, list) or not (out / "index.html").is_file() or not all(
            isinstance(f, dict) and (out / str(f.get("file", ""))).is_file() for f in figures):
        return None
    # The artifacts are hashed last (0.5 s for a 1000-unit fleet's): a report that is not
    # there whole is stale without them.
    try:
        return done if done.get("made_from") == made_from(cfg, paths, units) else None
    except OSError:
        return None


def report(cfg: Config, output_dir: str | os.PathLike, *args, **kwargs):
    """Write the report (:func:`_report`) without numpy's RuntimeWarnings: the report
    summarises arrays that may hold NaN (an unreliable year, a failed run), and "All-NaN
    slice encountered" lines on stderr say nothing to the user (a real problem ends the
    command with its one-line error)."""
    import warnings

    import numpy as np
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        return _report(cfg, output_dir, *args, **kwargs)


def _report(cfg: Config, output_dir: str | os.PathLike, *,
           observations: str | os.PathLike | None = None,
           simulations: str | os.PathLike | None = None,
           surrogate: str | os.PathLike | None = None,
           posterior: str | os.PathLike | None = None,
           forecast: str | os.PathLike | None = None,
           gap: str | os.PathLike | None = None,
           backtest: str | os.PathLike | None = None,
           truth: str | os.PathLike | None = None,
           units: Sequence[str] = ()) -> ReportSummary:
    """Make the health report from whichever artifacts are given.

    Parameters
    ----------
    cfg : Config
        Names everything the report shows: the output's label and units, the health
        indicator's name, label, units and limit, the inputs' components.
    output_dir : path-like
        Folder to write ``index.html`` (self-contained), ``figures/*.png`` and
        ``summary.json`` into; created if needed. Files of an earlier report are replaced.
    observations, simulations, surrogate, posterior, forecast, gap, backtest, truth : path-like, optional
        Artifacts (``twinmon.<kind>/1``); ``None`` skips the sections that need it. The
        surrogate figure needs both ``simulations`` (the test runs) and ``surrogate``.
    units : sequence of str
        Units to draw in detail whatever their state (``report --unit``). A fleet of more
        than ``report.detail_units`` units opens on a fleet overview and draws per-unit
        figures only for these and the units at risk (see :mod:`~twinmon.report.fleet`).

    Returns
    -------
    ReportSummary
        ``.terminal()`` is a short text, ``.as_dict()`` the content of ``summary.json``.

    Raises
    ------
    ArtifactError
        An artifact is missing, of the wrong schema or made for other inputs than the
        config's; nothing is written then.
    ConfigError
        A unit of ``units`` is in none of the artifacts.
    """
    import matplotlib
    paths = {"observations": observations, "simulations": simulations, "surrogate": surrogate,
             "posterior": posterior, "forecast": forecast, "gap": gap, "truth": truth,
             "backtest": backtest}
    out = Path(output_dir)
    with matplotlib.rc_context({"font.size": 10, "axes.titlesize": 11,
                                "figure.titlesize": 12, "legend.framealpha": 0.85}):
        # Forked inside the context: the workers draw with the same settings. Forked before
        # the artifacts are loaded: the workers read the fleet's statistics meanwhile.
        with _figure_pool(cfg, out) as pool:
            started = start_fleet_statistics(paths, pool, _workers(cfg))
            inp = load(cfg, paths)
            check_consistency(cfg, inp)
            provenance = {role: artifacts.read_provenance(p) for role, p in inp.paths.items()}
            record = made_from(cfg, paths, units)
            out.parent.mkdir(parents=True, exist_ok=True)
            # One writer per report folder; folders left by a killed report are removed
            # first.
            with artifacts.output_lock(out, "twinmon report"):
                artifacts.remove_stale_temporaries(out)
                tmp = out.parent / f".{out.name}.{os.getpid()}.tmp"
                shutil.rmtree(tmp, ignore_errors=True)
                (tmp / "figures").mkdir(parents=True)
                try:
                    summary = _render(cfg, inp, tmp, out, provenance, list(units), pool,
                                      started, record)
                    _install(tmp, out)
                finally:
                    shutil.rmtree(tmp, ignore_errors=True)
    return summary


def _figure_pool(cfg: Config, out: Path):
    """A pool of ``report.workers`` processes (none with one worker or one core) for the
    fleet's statistics (:func:`~.load.start_fleet_statistics`) then :class:`Figures`, shut
    down with the report, ended at once on an error or a Ctrl-C."""
    from contextlib import nullcontext

    from ..errors import Interrupted, TwinmonError
    from ..executors import closing_pool, start_pool
    workers = _workers(cfg)
    if workers <= 1:
        return nullcontext(None)
    from .common import freeze_inherited

    # Imported before the fork, once: each worker would otherwise import them to unpickle
    # its first figure (0.25 s of CPU each, against 0.004 s to unpickle a small figure).
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401
    return closing_pool(start_pool(workers, freeze_inherited), TwinmonError(
        f"{out}: a worker process died while reading the fleet or drawing the figures (out "
        "of memory?); nothing was written; re-run with --set report.workers=1"),
        Interrupted("report: interrupted; nothing was written"))


def _workers(cfg: Config) -> int:
    """Processes drawing the figures: ``report.workers``, or one per core."""
    return cfg.report.workers or len(os.sched_getaffinity(0))


def _render(cfg: Config, inp: Inputs, tmp: Path, out: Path, provenance: dict,
            requested: list, pool=None, started: Optional[dict] = None,
            record: Optional[dict] = None) -> ReportSummary:
    figs = Figures(tmp / "figures", pool)
    w = inp.words
    units = inp.unit_names()
    sections: dict[str, str] = {}
    notes: list[str] = []
    extra: dict[str, list[str]] = {"provenance": provenance}
    surrogate_info = calibration_info = None

    observed = observed_indicator(inp)
    # The summaries read each unit's figures, not its Monte Carlo arrays (a fleet's forecast
    # holds ~0.4 MB of them per unit; only the drawn units' figures need them) nor its
    # posterior draws.
    light = fleet_statistics(inp, started or {})
    summaries = {u: unit_summary(u, light, observed) for u in units}
    fleet = None
    if is_fleet(cfg, len(units)):
        # A large fleet: the overview first, per-unit figures for a few units only.
        fleet = fleet_view(cfg, summaries, requested)
        drawn = fleet.detail
        groups = _groups(drawn, GROUP)
        if fig_fleet_failure(figs, inp, summaries):
            extra["fleet_figure"] = [figs.items[-1]]
    else:
        check_requested(summaries, requested)
        drawn, groups = units, [units]
    inp = with_truth_of(inp, drawn)
    colours = {u: UNIT_COLOURS[i % len(UNIT_COLOURS)] for i, u in enumerate(drawn)}
    views = _views(inp, groups, fleet is not None)

    if inp.obs is not None:
        # Figures 2 and 3 draw every unit on one axis: as many as there are colours.
        obs_views = views if fleet is None else _views(inp, _groups(drawn, len(UNIT_COLOURS)),
                                                       True)
        for group, sub, suffix in _drawing(figs, obs_views, fleet):
            seen = {u: observed[u] for u in group if u in observed}
            if sub.obs.units:
                fig_last_transients(figs, sub, colours, seen)
            if seen:
                fig_indicator_history(figs, sub, colours, seen)
        if not observed:
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
        surrogate_info = {"stored_validation": v, "modes": int(inp.surrogate.n_modes),
                          "max_range_error": v.get("max_range_error"),
                          "n_test": v.get("n_test")}
        sections["surrogate"] = ("skipped: the surrogate figure needs the simulations artifact "
                                 f"(its test runs); {stored_validation_text(v)}")
    else:
        sections["surrogate"] = f"skipped: {SKIP_HINTS['surrogate']}"
    if inp.surrogate is not None:
        from ..reduce import cap_warning, error_warning
        capped = cap_warning(inp.surrogate, cfg.reduce, surrogate_info.get("max_range_error"),
                             w.out_label)
        capped = capped or error_warning(surrogate_info.get("max_range_error"),
                                         (inp.validation or {}).get("mean_range_error"),
                                         w.out_label)
        if capped:
            surrogate_info["warning"] = capped
            notes.append(capped[0].upper() + capped[1:] + ".")

    if inp.posterior is not None:
        errors = []
        for group, sub, suffix in _drawing(figs, views, fleet):
            if sub.posterior.units:
                errors.append((len(sub.posterior.units), fig_estimates(figs, sub, colours)))
        calibration_info = calibration_diagnostics(light)
        note = _method_note(provenance.get("posterior", {}), len(inp.posterior.units))
        if note:
            notes.append(note)
        check = _pooled_truth_check(errors)
        if check:
            calibration_info["truth_check"] = check
        extra["calibration"] = calibration_table(cfg, _only(calibration_info, drawn)
                                                 if fleet else calibration_info, fleet)
        sections["calibration"] = "rendered"
    else:
        sections["calibration"] = f"skipped: {SKIP_HINTS['calibration']}"

    if inp.forecast is not None:
        for group, sub, suffix in _drawing(figs, views, fleet):
            if sub.forecast.units:
                seen = {u: observed[u] for u in group if u in observed}
                fig_trends(figs, sub, colours)
                fig_marginals(figs, sub, colours)
                fig_indicator_forecast(figs, sub, colours, seen or None)
        sections["forecast"] = "rendered"
    else:
        sections["forecast"] = f"skipped: {SKIP_HINTS['forecast']}"

    if inp.backtest is not None:
        fig_backtest(figs, inp, colours)
        sections["backtest"] = "rendered"
        if not inp.backtest.all_in_band:
            # The forecast's own check on this history failed: said at the top, not only
            # under a figure.
            notes += [w[0].upper() + w[1:] + "." for w in inp.backtest.warnings
                      if w.startswith("back-test")]
    else:
        sections["backtest"] = f"skipped: {SKIP_HINTS['backtest']}"

    if inp.gap is not None:
        if inp.gap_other_source is not None:
            lines = [f"{u}: {gap_title(g)}" + (f" ({', '.join(g.effects)}, "
                                                f"{g.closed_percent:.0f} % of the gap closed)"
                                                if g.verdict == "effect" else "")
                     for u, g in inp.gap.units.items()]
            extra["diagnose"] = [e_p(
                f"This section diagnoses {inp.gap_other_source}, not the observations above; "
                "its units are not merged into the unit summaries. " + "; ".join(lines) + ".")]
        gap_views = views
        if fleet is not None and inp.gap_other_source is not None:
            # Other machines than the fleet's: the first of them, a group at a time.
            other = list(inp.gap.units)[:cfg.report.detail_units]
            chunks = _groups(other, GROUP)
            gap_views = [(g, _subset(inp, g, gap_only=True),
                          f"_{k + 1}" if len(chunks) > 1 else "") for k, g in enumerate(chunks)]
        if inp.gap_other_source is not None:
            # Other machines than the fleet's may be units the fleet does not have.
            for i, u in enumerate(inp.gap.units):
                colours.setdefault(u, UNIT_COLOURS[i % len(UNIT_COLOURS)])
        # Each unit's named effects, groups and hidden candidates (a large fleet's: those
        # drawn in detail).
        tabled = (list(inp.gap.units) if fleet is None else
                  [u for g, _, _ in gap_views for u in g if u in inp.gap.units])
        extra["diagnose"] = (extra.get("diagnose", [])
                             + diagnose_table(cfg, {u: inp.gap.units[u] for u in tabled}))
        overlay = ranked = False
        for group, sub, suffix in _drawing(figs, gap_views, fleet):
            if sub.gap.units:
                fig_residual_map(figs, sub, colours)
                ranked = fig_candidates(figs, sub, colours) or ranked
                overlay = fig_overlay(figs, sub, colours) or overlay
        if not ranked and any(g.verdict != "none" for g in inp.gap.units.values()):
            from ..diagnose import no_candidates_hint
            notes.append("Diagnose located a gap but could not name it: "
                         + no_candidates_hint(cfg) + ".")
        if not overlay:
            notes.append("Diagnose found no gap in any unit"
                         + (" drawn in detail" if fleet else "") + ": no before/after overlay.")
        sections["diagnose"] = "rendered"
    else:
        sections["diagnose"] = f"skipped: {SKIP_HINTS['diagnose']}"

    if inp.truth is not None and inp.posterior is None and inp.forecast is None:
        notes.append("A truth file was given but no posterior or forecast to compare it with.")
    if inp.forecast is not None and inp.posterior is None:
        notes.append("The forecast is shown without its posterior: Figure 6 is skipped.")
    pooling = getattr(inp.forecast, "sigma_pooling", None) or {}
    if pooling.get("pooled"):
        med = ", ".join(f"{n} {v:.3g} {_units(cfg, n)}".rstrip()
                        for n, v in pooling["median"].items())
        notes.append(f"The year-to-year variation of the inputs was pooled over the "
                     f"{pooling['units']} jointly calibrated units (fleet median sd: {med}): "
                     "each unit's trend and forecast use the fleet's estimate of it.")
    shaped = getattr(inp.forecast, "shape_pooling", None) or {}
    if shaped.get("pooled"):
        prior = shaped["fleet"]
        acc = sum(v for k, v in prior.items() if k not in ("line", "change"))
        forms = ", ".join(f"{k} {v:.2f}" for k, v in prior.items()
                          if k not in ("line", "change"))
        steady = shaped.get("steady") or {}
        still = (f" Units whose slopes stay within normal ageing take those of the "
                 f"{steady['units']} such units: a straight line "
                 f"{steady['fleet']['line']:.2f}, a change {steady['fleet']['change']:.2f}."
                 if steady.get("pooled") else "")
        notes.append(f"The trend shapes' prior probabilities were learnt from the fleet's "
                     f"{shaped['units']} units: a straight line {prior['line']:.2f}, "
                     f"accelerating {acc:.2f} ({forms}), a change {prior['change']:.2f}; "
                     f"each unit's forecast weighs its shapes by them.{still}")

    figs.finish()
    output_words, indicator_words = words_dict(inp)
    summary = ReportSummary(
        output_dir=str(out), index=str(out / "index.html"),
        units=summaries,
        sections=sections,
        figures=[{**{k: v for k, v in f.items() if not k.startswith("_")},
                  "path": str(out / f["file"])} for f in figs.items],
        surrogate=plain(surrogate_info), calibration=plain(calibration_info),
        artifacts=dict(inp.paths), notes=notes, output=output_words,
        indicator=plain(indicator_words), fleet=fleet.as_dict() if fleet else None,
        made_from=record or {})
    if fleet is not None:
        extra["fleet"] = fleet_overview(cfg, summary, fleet, extra.pop("fleet_figure", []))
    (tmp / "summary.json").write_text(to_json(summary.as_dict()))
    (tmp / "index.html").write_text(page(cfg, w, summary, figs.items, extra, fleet),
                                    encoding="utf-8")
    return summary


def _groups(units: list, most: int) -> list[list]:
    """``units`` cut into the fewest groups of at most ``most``, of near-equal sizes (a
    group of 1 beside groups of 4 would be drawn at another scale)."""
    if not units:
        return []
    n = -(-len(units) // most)
    size = -(-len(units) // n)
    return [units[i:i + size] for i in range(0, len(units), size)]


def _views(inp: Inputs, groups: list, subset: bool) -> list:
    """``(units, inputs restricted to them, figure-name suffix)`` per group."""
    return [(g, _subset(inp, g) if subset else inp, f"_{k + 1}" if len(groups) > 1 else "")
            for k, g in enumerate(groups)]


def _drawing(figs: Figures, views: list, fleet):
    """Yield ``(units, inputs, suffix)`` per group of units, with the figure names and
    titles of the group set on ``figs`` (a large fleet's figures name their units)."""
    for group, sub, suffix in views:
        figs.suffix, figs.units = suffix, (list(group) if fleet is not None else [])
        yield group, sub, suffix
    figs.suffix, figs.units = "", []


def _subset(inp: Inputs, units: list, gap_only: bool = False) -> Inputs:
    """The inputs restricted to ``units`` (the figures of a group draw every unit they get);
    the units are read from their artifacts here."""
    def keep(obj, own: bool = True):
        if obj is None or not own:
            return obj
        return dataclasses.replace(obj, units={u: obj.units[u] for u in units
                                               if u in obj.units})
    if gap_only:
        return dataclasses.replace(inp, gap=keep(inp.gap))
    return dataclasses.replace(
        inp, obs=keep(inp.obs), posterior=keep(inp.posterior), forecast=keep(inp.forecast),
        gap=keep(inp.gap, inp.gap_other_source is None))


def _warned_unit(warning: str) -> str:
    """The unit a calibration warning names (``U year 3: ...``, ``U years 1-10: ...``)."""
    import re
    return re.split(r" years? ", warning, maxsplit=1)[0]


def _only(diag: dict, units: list) -> dict:
    """Calibration diagnostics of ``units`` only, with the fleet's figures beside them."""
    keep = set(units)
    per_unit = diag["units"]
    out = {**diag, "units": {u: d for u, d in per_unit.items() if u in keep},
           "warnings": [x for x in diag["warnings"] if _warned_unit(x) in keep]}
    if per_unit:
        out["fleet"] = {"units": len(per_unit),
                        "max_rhat": max(d["max_rhat"] for d in per_unit.values()),
                        "min_ess": min(d["min_ess"] for d in per_unit.values()),
                        "warned_units": len({_warned_unit(x) for x in diag["warnings"]})}
    return out


def _method_note(posterior_provenance: dict, n_units: int) -> str:
    """Which calibration method the posterior was sampled with (``calibrate.method: auto``
    picks it by the fleet's size, so the reader is told), from its provenance attributes;
    "" for a posterior made before it was recorded."""
    method = posterior_provenance.get("method", "")
    if method == "joint":
        return (f"Calibrated with the joint method: each of the {n_units} units' whole "
                "history in one posterior, its trend inside.")
    if method == "laplace":
        return (f"Calibrated with the laplace method: each of the {n_units} units' whole "
                "history in one posterior, its trend inside, each year's likelihood "
                "summarised once and the draws weighted to the exact one.")
    if method == "sequential":
        return ("Calibrated with the sequential (paper's) method: each year in turn, its "
                "prior centred on the year before.")
    return ""


def _pooled_truth_check(errors: list) -> dict:
    """The truth errors of the groups drawn, pooled (max of maxima, unit-weighted means)."""
    errors = [(n, e) for n, e in errors if e]
    if not errors:
        return {}
    if len(errors) == 1:
        return errors[0][1]
    out = {}
    for name in errors[0][1]:
        got = [(n, e[name]) for n, e in errors if name in e]
        total = sum(n for n, _ in got)
        out[name] = {"max_rel_error": max(e["max_rel_error"] for _, e in got),
                     "mean_rel_error": sum(n * e["mean_rel_error"] for n, e in got) / total,
                     "coverage_90": sum(n * e["coverage_90"] for n, e in got) / total}
    return out


def _install(tmp: Path, out: Path) -> None:
    """Move a finished report into ``out``: figures, then index.html, summary.json last (it
    records what the report was made from: a report cut short between the two is made
    again by ``twinmon run``, not taken as up to date with the old page)."""
    from ..interrupts import raise_if_interrupted
    raise_if_interrupted()          # a Ctrl-C swallowed while rendering: nothing installed
    out.mkdir(parents=True, exist_ok=True)
    figures = out / "figures"
    old = out / f".figures.{os.getpid()}.old"
    if figures.exists():
        os.replace(figures, old)
    os.replace(tmp / "figures", figures)
    shutil.rmtree(old, ignore_errors=True)
    os.replace(tmp / "index.html", out / "index.html")
    os.replace(tmp / "summary.json", out / "summary.json")


def _units(cfg: Config, name: str) -> str:
    """An input's units from the config, "" for a dimensionless one ("1") or one it does not
    list."""
    spec = cfg.model.inputs.get(name)
    return spec.units if spec is not None and spec.units != "1" else ""
