"""``twinmon calibrate``: posterior of the degradation inputs per unit and year."""
from __future__ import annotations

import click
import numpy as np

from .app import main
from .common import (config_options, emit_json, json_option, load, progress_bar,
                     refuse_overwrite, say)

#: Warning lines printed; the rest are counted (all are in the --json summary).
MAX_WARNINGS = 12


@main.command()
@config_options
@click.option("--surrogate", default="out/surrogate.h5", show_default=True,
              type=click.Path(), help="Surrogate artifact (from reduce).")
@click.option("--observations", required=True, type=click.Path(),
              help="Observations artifact (twinmon.observations/1).")
@click.option("--truth", type=click.Path(), default=None,
              help="Truth file (from fabricate): print errors and interval coverage.")
@click.option("-o", "--output", default="out/posterior.h5", show_default=True,
              type=click.Path(), help="Posterior artifact to write.")
@click.option("--update", is_flag=True,
              help="Keep the years already in the output posterior; sample only the years "
                   "(and units) added to the observations since. Same result as a full run.")
@json_option
def calibrate(config_path, overrides, surrogate, observations, truth, output, update, as_json):
    """Bayesian posterior of each unit's degradation inputs, every recorded year.

    calibrate.method (default auto): a fleet the forecast can pool is drawn jointly over
    each unit's years with its trend (a line, accelerating wear or a change, averaged by
    their evidence; unrecorded repairs found restart it) by the laplace method; a few units
    are sampled by MCMC year by year (sequential), each year's prior from the last.
    """
    from ..calibrate import calibrate as run
    from ..repairs import FoundRepair
    refuse_overwrite({"-o": output}, {"--surrogate": surrogate, "--observations": observations,
                                      "--truth": truth, "-c": config_path})
    cfg = load(config_path, overrides)
    with progress_bar(lambda: _count_years(observations), "calibrate") as tick:
        s = run(cfg, surrogate, observations, output, truth_path=truth, progress=tick,
                update=update)
    # Warnings go to stderr even with --json or -q: they say the numbers may be wrong.
    for w in s.warnings[:MAX_WARNINGS]:
        click.echo(f"twinmon: warning: {w}", err=True)
    if len(s.warnings) > MAX_WARNINGS:
        click.echo(f"twinmon: warning: ... and {len(s.warnings) - MAX_WARNINGS} more warnings "
                   "(all in --json)", err=True)
    if as_json:
        emit_json(s.as_dict())
        return
    d = s.as_dict()
    if s.method_reason:
        say(f"calibrate: {s.method_reason}")
    if s.update is not None:
        u = s.update
        # The laplace method keeps the years' sites, not their draws (docs/calibration.md).
        kept, done = (("sites of ", "summarised, each unit with a new year drawn again")
                      if s.method == "laplace" else ("", "sampled"))
        say(f"calibrate --update: {kept}{u['kept_years']} unit-year(s) kept from "
            f"{u['from'] or 'nothing (no earlier posterior)'}, {u['new_years']} {done}"
            + "".join(f"; {what}: {', '.join(u[key])}" for key, what in
                      (("new_units", "new units"), ("redone_units", "redone (data changed)"),
                       ("dropped_units", "no longer observed")) if u[key]))
    for unit, nz in d["noise"].items():
        p = s.posterior[unit]
        say(f"calibrate: {unit}: {len(p.years)} years, noise std {nz['std']:.3g} "
            f"{cfg.model.output.units} "
            f"({_SOURCE[nz['source']]}), R-hat <= {p.rhat.max():.3f}, ESS >= {p.ess.min():.0f}, "
            + (f"acceptance {np.nanmin(p.acceptance):.2f}-{np.nanmax(p.acceptance):.2f}"
               if np.isfinite(p.acceptance).any() else _drawn(p)))
        if p.channels:
            units = cfg.model.channel_units
            say("  channels: " + ", ".join(
                f"{ch} (noise std {c['std']:.3g} {units.get(ch, '')}, {c['source']})"
                for ch, c in p.channels.items()))
        for r in p.found_repairs:
            say(f"  {FoundRepair(**r).headline()}: a trend segment starts there (forecast's "
                "plan says how to record it)")
        last = {n: p.mean[-1, j] for j, n in enumerate(s.input_names)}
        say("  last year: " + ", ".join(
            f"{n} {v:.4g} [{p.q05[-1, j]:.4g}, {p.q95[-1, j]:.4g}]"
            for j, (n, v) in enumerate(last.items())))
    if s.truth_check:
        say("relative error of the posterior mean against the truth:")
        for name, tc in s.truth_check.items():
            say(f"  {name}: max {100 * tc['max_rel_error']:.1f} %, mean "
                f"{100 * tc['mean_rel_error']:.2f} %; 90 % interval coverage "
                f"{100 * tc['coverage_90']:.0f} %")
    say(f"calibrate: {len(s.warnings)} warning(s) -> {output}")


_SOURCE = {"file": "from the observations file", "config": "from the config",
           "estimated": "estimated from the residuals",
           "differences": "estimated from the residuals' second differences (the residuals "
                          "hold more than noise)"}


def _drawn(p) -> str:
    """How a unit's draws without a chain per year were made (the laplace method): weighted,
    or weighted then moved by a Markov chain (its trend moves' acceptance recorded)."""
    from ..calibrate.rejuvenate import moved_by_chain
    trend = (p.trend or {}).get("acceptance")
    if moved_by_chain(p.acceptance, trend):
        return ("weighted draws moved by a Markov chain (trend moves accepted "
                f"{np.nanmean(trend):.2f})")
    return "weighted independent draws"


def _count_years(observations) -> int:
    """Unit-years in the file (for the progress bar); 0 when unreadable (the stage itself
    then raises the proper error)."""
    from ..errors import TwinmonError
    from ..observations import read_observations
    try:
        return sum(len(u.years) for u in read_observations(observations).units.values())
    except TwinmonError:
        return 0
