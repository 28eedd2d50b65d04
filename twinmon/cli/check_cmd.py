"""Command ``check``: the config, its FMU, observations and artifacts checked in seconds."""
from __future__ import annotations

import click

from .app import main
from .common import config_options, emit_json, json_option, say, warn


@main.command()
@config_options
@click.option("--observations", default=None, type=click.Path(),
              help="Observations file to check against the config (channels, time grid, "
                   "units).")
@click.option("--workdir", default=None, type=click.Path(),
              help="A `twinmon run` workdir whose artifacts are checked (schema, inputs, "
                   "time grid, fingerprints).")
@click.option("--smoke", is_flag=True,
              help="Check with run --smoke's sizes (a workdir a smoke run wrote then "
                   "matches its settings).")
@json_option
def check(config_path, overrides, observations, workdir, smoke, as_json):
    """Check a config and its FMU in seconds, without running the pipeline (for CI).

    One line per problem on stderr; the exit code is the first problem's family (3 config,
    4 input data, 5 artifact, 6 simulation), 0 when everything passed.
    """
    from ..check import check as run
    from ..pipeline import SMOKE
    res = run(config_path, (SMOKE if smoke else ()) + tuple(overrides),
              observations=observations, workdir=workdir)
    if as_json:
        emit_json(res.as_dict())
    for line in res.checked:
        say(f"check: {line}")
    for w in res.warnings:
        warn(w)
    for p in res.problems:
        click.echo(f"twinmon: {p.family}: {p.message}", err=True)
    if res.ok:
        say(f"check: passed in {res.seconds:.1f} s")
    click.get_current_context().exit(res.exit_code)
