"""Commands of the analysis pipeline: ``reduce``, ``calibrate``, ``forecast``, ``report``,
``diagnose`` and ``run``."""
from __future__ import annotations

import click

from .app import main
from .common import config_options, emit_json, json_option, load, refuse_overwrite, say


@main.command()
@config_options
@click.option("--simulations", default="out/simulations.h5", show_default=True,
              type=click.Path(), help="Simulations artifact to learn from.")
@click.option("-o", "--output", default="out/surrogate.h5", show_default=True,
              type=click.Path(), help="Surrogate artifact to write.")
@json_option
def reduce(config_path, overrides, simulations, output, as_json):
    """Karhunen-Loeve reduction + Gaussian-process surrogate of the FMU."""
    from ..reduce import reduce as run
    refuse_overwrite({"-o": output}, {"--simulations": simulations, "-c": config_path})
    cfg = load(config_path, overrides)
    s = run(cfg, simulations, output)
    if as_json:
        emit_json(s.as_dict())
    else:
        v = s.validation
        rel = (f"; relative: max {100 * v.max_rel_error:.3f} %, mean "
               f"{100 * v.mean_rel_error:.4f} %" if v.max_rel_error == v.max_rel_error else "")
        say(f"reduce: {s.modes} modes ({100 * s.variance_ratio:.3f} % of variance), "
            f"{s.train_runs} training runs; on {v.n_test} test runs: error max "
            f"{100 * v.max_range_error:.3f} %, mean {100 * v.mean_range_error:.4f} % of the "
            f"output's range ({v.output_range:.4g} {cfg.model.output.units}){rel}; Q2 per mode "
            f"{', '.join(f'{q:.5f}' for q in v.q2)}, 90 % band coverage "
            f"{100 * v.coverage_90:.1f} % -> {output}")
        for ch, c in s.channels.items():
            t = c["test"]
            say(f"  channel {ch}: {c['modes']} modes, transform {c['transform']}; test error "
                f"max {100 * t['max_range_error']:.3f} %, mean {100 * t['mean_range_error']:.4f} "
                f"% of its range; 90 % band coverage {100 * t['coverage_90']:.1f} %")
    for w in s.warnings:
        click.echo(f"twinmon: warning: {w}", err=True)


@main.command()
@config_options
@click.option("--observations", required=True, type=click.Path(),
              help="Plant observations to calibrate and forecast.")
@click.option("--gap-observations", type=click.Path(), default=None,
              help="Observations to diagnose for a sim-to-real gap [default: --observations].")
@click.option("--truth", type=click.Path(), default=None,
              help="Truth file of fabricated data: adds errors against the truth.")
@click.option("--workdir", default="out", show_default=True, type=click.Path(file_okay=False),
              help="Folder of the artifacts and of report/.")
@click.option("--force", is_flag=True, help="Re-run every stage, even those up to date.")
@click.option("--smoke", is_flag=True,
              help="Every stage with small sizes (design, chains, draws, horizon, diagnose "
                   "screening; twinmon.pipeline.SMOKE, docs/ci.md), to see the chain work in "
                   "about a minute; not for results. --set still overrides.")
@click.option("--update", is_flag=True,
              help="calibrate and diagnose keep the years already in the workdir's "
                   "posterior and gap.h5 and work only on those added since (calibrate "
                   "--update, diagnose --update); forecast and report re-run.")
@json_option
def run(config_path, overrides, observations, gap_observations, truth, workdir, force, update,
        smoke, as_json):
    """Every stage in order, skipping those whose output is up to date."""
    from pathlib import Path

    from ..pipeline import SMOKE, run_pipeline
    # Every artifact the pipeline may write into the workdir.
    refuse_overwrite({f"--workdir {name}": Path(workdir) / name
                      for name in ("simulations.h5", "surrogate.h5", "posterior.h5",
                                   "forecast.h5", "gap.h5", "backtest.h5", "report")},
                     {"--observations": observations, "--gap-observations": gap_observations,
                      "--truth": truth, "-c": config_path})
    if smoke:
        say(f"run --smoke: small sizes ({', '.join(SMOKE)}); for a check of the chain, "
            "not for results")
    cfg = load(config_path, (SMOKE if smoke else ()) + tuple(overrides))
    summary = run_pipeline(cfg, observations, workdir, gap_observations=gap_observations,
                           truth=truth, force=force, update=update, log=say)
    if as_json:
        emit_json(summary.as_dict())
    else:
        say(summary.terminal)
        total = sum(s.seconds for s in summary.stages)
        say(f"run: {total:.1f} s; report: {summary.report}")
