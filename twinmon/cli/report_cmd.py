"""The ``report`` command: figures, a self-contained HTML report and ``summary.json``."""
from __future__ import annotations

from pathlib import Path

import click

from .app import main
from .common import config_options, emit_json, json_option, load, refuse_overwrite, say

#: Artifacts looked up in ``--workdir`` when not given explicitly.
_WORKDIR_ARTIFACTS = ("simulations", "surrogate", "posterior", "forecast", "backtest", "gap")


def _from_workdir(workdir: Path, given: dict, explicit: bool) -> None:
    """Fill ``given`` with the artifacts found in ``workdir``.

    Raises
    ------
    ArtifactError
        ``workdir`` does not exist, or holds none of the artifacts while no other artifact
        was given: the report would be empty (most likely a mistyped folder).
    """
    from ..errors import ArtifactError
    if not workdir.is_dir():
        raise ArtifactError(f"{workdir}: --workdir folder does not exist")
    found = []
    for name in _WORKDIR_ARTIFACTS:
        candidate = workdir / f"{name}.h5"
        if candidate.exists():
            found.append(name)
            if given[name] is None:
                given[name] = str(candidate)
    if not found and not explicit:
        names = ", ".join(f"{n}.h5" for n in _WORKDIR_ARTIFACTS)
        raise ArtifactError(f"{workdir}: --workdir folder holds no artifact (looked for {names}); "
                            "nothing to report")


def _artifact_option(name: str, help_text: str):
    return click.option(f"--{name}", name, default=None, type=click.Path(),
                        help=help_text)


@main.command()
@config_options
@click.option("--workdir", default=None, type=click.Path(file_okay=False),
              help="Folder of the pipeline's artifacts: simulations.h5, surrogate.h5, "
                   "posterior.h5, forecast.h5 and gap.h5 are used when they exist there.")
@_artifact_option("observations", "Observations file (e.g. data/fleet.h5).")
@_artifact_option("simulations", "Simulations artifact (its test runs validate the surrogate).")
@_artifact_option("surrogate", "Surrogate artifact of reduce.")
@_artifact_option("posterior", "Posterior artifact of calibrate.")
@_artifact_option("forecast", "Forecast artifact of forecast.")
@_artifact_option("gap", "Gap artifact of diagnose.")
@_artifact_option("truth", "Truth file of fabricate: true values drawn on the figures.")
@click.option("-o", "--output", default=None, type=click.Path(file_okay=False),
              help="Report folder to write  [default: <workdir>/report, or out/report].")
@click.option("--unit", "units", multiple=True, metavar="UNIT",
              help="Draw this unit's figures whatever its state (repeatable). A fleet of more "
                   "than report.detail_units units otherwise draws only the units at risk.")
@json_option
def report(config_path, overrides, workdir, observations, simulations, surrogate, posterior,
           forecast, gap, truth, output, units, as_json):
    """Health report: figures, index.html (self-contained), summary.json.

    Every section is optional: it is drawn when its artifact is given (or found in
    --workdir) and skipped with a note otherwise, so a report can follow any prefix of the
    pipeline.
    """
    from ..report import report as run
    given = {"simulations": simulations, "surrogate": surrogate, "posterior": posterior,
             "forecast": forecast, "backtest": None, "gap": gap}
    if workdir is not None:
        _from_workdir(Path(workdir), given, explicit=any(
            v is not None for v in (*given.values(), observations, truth)))
    if output is None:
        output = str(Path(workdir) / "report") if workdir is not None else "out/report"
    refuse_overwrite({"-o": output}, {f"--{k}": v for k, v in
                                      {**given, "observations": observations,
                                       "truth": truth}.items()} | {"-c": config_path})
    cfg = load(config_path, overrides)
    s = run(cfg, output, observations=observations, truth=truth, units=units, **given)
    if as_json:
        emit_json(s.as_dict())
        return
    say(s.terminal())
    say(f"report: {len(s.figures)} figures -> {s.index}")
