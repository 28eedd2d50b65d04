"""The ``forecast`` command: trends, failure probability, root cause and plan per unit."""
from __future__ import annotations

import click

from .app import main
from ..errors import TwinmonError
from .common import (config_options, emit_json, json_option, load, progress_bar,
                     refuse_overwrite, say, warn)


@main.command()
@config_options
@click.option("--posterior", default="out/posterior.h5", show_default=True,
              type=click.Path(), help="Posterior artifact of calibrate.")
@click.option("--surrogate", default="out/surrogate.h5", show_default=True,
              type=click.Path(), help="Surrogate artifact of reduce.")
@click.option("-o", "--output", default="out/forecast.h5", show_default=True,
              type=click.Path(), help="Forecast artifact to write.")
@click.option("--truth", "truth", default=None, type=click.Path(),
              help="Truth file of fabricate: also give each unit's true failure year.")
@click.option("-j", "--workers", type=int, default=None,
              help="Worker processes over units (default: simulate.workers, 0 = one per core).")
@click.option("--force-prognosis", is_flag=True,
              help="Give a failure year and root cause even for units whose twin misses the "
                   "plant (labelled FORCED).")
@json_option
def forecast(config_path, overrides, posterior, surrogate, output, truth, workers,
             force_prognosis, as_json):
    """Trend of each input, P(unsafe) per future year, failure year, root cause and plan.

    Each input's trend (the posterior's own for a fleet calibrated jointly, with its
    shape; else lines through the yearly posterior means) extended over the horizon, the
    future states propagated by Monte Carlo through the twin (surrogate inside its training
    box, a learnt limit-state model or the FMU outside it); degradation detected on the
    health indicator's drift and the inputs' slopes against normal ageing, then attributed
    to components with probabilities; a unit whose trend the history does not follow, or
    whose twin misses the plant, is marked unreliable with the reason.
    """
    from ..forecast import forecast as run
    refuse_overwrite({"-o": output}, {"--posterior": posterior, "--surrogate": surrogate,
                                      "--truth": truth, "-c": config_path})
    if force_prognosis:
        overrides = (*overrides, "forecast.force_prognosis=true")
    from ..calibrate import read_posterior
    cfg = load(config_path, overrides)
    # The unit count is a look at the file's index (its units are read lazily); a missing or
    # foreign file is reported by the stage itself.
    try:
        n_units = len(read_posterior(posterior).units)
    except TwinmonError:
        n_units = 0
    with progress_bar(n_units, "forecast") as update:
        s = run(cfg, posterior, surrogate, output, truth_path=truth, workers=workers,
                progress=update)
    if as_json:
        emit_json(s.as_dict())
        return
    limit = cfg.safety.failure_probability
    for unit, u in s.units.items():
        tests = ", ".join(f"{n} {t.slope:+.3g}/yr p={t.p_value:.2g}"
                          for n, t in u.trends.items())
        fy = u.failure_year if u.failure_year is not None else f"none by {u.years_future[-1]}"
        # The year to act by is a low quantile of the time to failure; the median year is the
        # point forecast (benchmarks/prognosis.py scores both): show it where it differs.
        med = u.median_failure_year
        if u.failure_year is not None and med != u.failure_year:
            fy = f"{fy}, median {med if med is not None else 'after ' + str(u.years_future[-1])}"
        true = ""
        if u.has_truth:
            tf = u.true_failure_year
            true = f" (true: {tf if tf is not None else 'none by ' + str(u.years_future[-1])})"
        if u.status == "withheld" and not u.forced:
            say(f"{unit}: WITHHELD; {u.status_reason}")
            continue
        label = {"withheld": " [FORCED: the twin misses the plant]",
                 "unreliable": " [UNRELIABLE]"}.get(u.status, "")
        cause = (" and ".join(u.attribution.named) if u.root_cause == "both" and
                 u.attribution is not None and u.attribution.named else u.root_cause)
        say(f"{unit}: {cause}{label}; failure year (P(unsafe) > {limit:g}) {fy}{true}; "
            f"{tests}; FMU share {100 * u.fmu_fraction:.1f} %"
            + (f", limit-state model {100 * u.model_fraction:.1f} %" if u.model_fraction else ""))
        say(f"  plan: {u.plan}")
        if u.fmu_failures:
            say(f"  warning: {u.fmu_failures} FMU run(s) failed and were counted unsafe")
    for w in s.warnings:
        warn(f"forecast: {w}")
    if s.pooling.get("pooled"):
        med = ", ".join(f"{n} {v:.3g}" for n, v in s.pooling["median"].items())
        say(f"forecast: year-to-year sd pooled over {s.pooling['units']} jointly calibrated "
            f"units (fleet median: {med})")
    if s.limit_state.get("used"):
        say(f"forecast: outside the design box, a limit-state model learnt from "
            f"{s.limit_state['runs']} FMU runs answered the points it is sure are unsafe")
    say(f"forecast: {len(s.units)} units in {s.wall_time:.1f} s -> {output}")
