"""The ``backtest`` command: how good the forecasts have been on the user's own history."""
from __future__ import annotations

import click

from .app import main
from .common import config_options, emit_json, json_option, load, refuse_overwrite, say, warn


@main.command()
@config_options
@click.option("--posterior", default="out/posterior.h5", show_default=True,
              type=click.Path(), help="Posterior artifact of calibrate.")
@click.option("--surrogate", default="out/surrogate.h5", show_default=True,
              type=click.Path(), help="Surrogate artifact of reduce.")
@click.option("--observations", default=None, type=click.Path(),
              help="Observations the posterior was calibrated from: with a joint posterior "
                   "(calibrate.method joint), each cut's history is calibrated again from "
                   "them; without, the back-test of a joint posterior is optimistic.")
@click.option("-o", "--output", default="out/backtest.h5", show_default=True,
              type=click.Path(), help="Back-test artifact to write.")
@json_option
def backtest(config_path, overrides, posterior, surrogate, observations, output, as_json):
    """Forecast from each past year and score against what was later observed.

    No truth needed: for each cut year, the forecast from the years up to it is compared with
    the indicator of the later years (coverage of the prediction intervals, indicator error)
    and, for units that reached unsafe, the time to failure (alpha-lambda accuracy, relative
    accuracy, prognostic horizon).
    """
    from ..backtest import backtest as run
    refuse_overwrite({"-o": output}, {"--posterior": posterior, "--surrogate": surrogate,
                                      "--observations": observations, "-c": config_path})
    cfg = load(config_path, overrides)
    s = run(cfg, posterior, surrogate, output, observations_path=observations)
    # Warnings go to stderr with --json too: a coverage outside its band must not pass
    # unseen in a pipeline that reads only stdout.
    for w in s.warnings:
        warn(w)
    if as_json:
        emit_json(s.as_dict())
        return
    from ..safety import Indicator
    ind = Indicator.from_config(cfg)
    c = int(round(100 * s.confidence))
    say(f"coverage of the {c} % prediction intervals of the {ind.name}: "
        f"{100 * s.coverage:.0f} % of {s.n_pairs} later observations; median abs. error "
        f"{ind.fmt(s.indicator_mae)}"
        + (f" ({s.across_repairs} later observation(s) after a recorded repair not scored "
           "against the forecasts made before it)" if s.across_repairs else ""))
    if len(s.by_record) > 1:
        # Short records are where the intervals fail first: each length on its own.
        say("  by years of record at the forecast: " + ", ".join(
            f"{n}: {100 * v['coverage']:.0f} % of {v['pairs']}"
            + ("" if v["in_band"] else " (outside the band)") for n, v in s.by_record.items()))
    if s.ttf:
        bt = cfg.backtest
        say(f"time to failure ({len(s.ttf)} unit(s) reached unsafe): alpha-lambda accuracy "
            f"(alpha {bt.alpha:g}, lambda {bt.lambda_value:g}) {100 * s.alpha_lambda:.0f} %")
        for u, t in s.ttf.items():
            say(f"  {u}: unsafe in year {t.end_of_life}; at cut {t.cut_lambda} predicted RUL "
                f"{int(t.rul_pred[list(t.rul_true).index(t.end_of_life - t.cut_lambda)])} vs "
                f"{t.end_of_life - t.cut_lambda}; relative accuracy {t.relative_accuracy:.2f}; "
                f"prognostic horizon {t.prognostic_horizon:g} yr")
    elif not s.unsafe_before_cuts:
        say("time to failure: no unit reached unsafe in its history")
    early = s.unsafe_before_cuts
    if early:
        # Unsafe before any forecast could have seen it coming: nothing to score, but the
        # user must not read "no unit reached unsafe".
        say("time to failure: not scored for " + ", ".join(
            f"{u} (unsafe from year {y})" for u, y in early.items())
            + ": unsafe already at the first cut, no forecast was made before it")
    if s.cut_posteriors == "recalibrated":
        say("each cut's history calibrated again from its own years")
    say(f"wrote {output}")
