"""Commands that make data: ``simulate``, ``fabricate``, ``import-csv``, ``events``."""
from __future__ import annotations

import dataclasses

import click

from .app import main
from .common import (config_options, emit_json, json_option, load, progress_bar,
                     refuse_overwrite, say, warn)


@main.command()
@config_options
@click.option("-o", "--output", default="out/simulations.h5", show_default=True,
              type=click.Path(), help="Simulations artifact to write.")
@click.option("-j", "--workers", type=int, default=None,
              help="Worker processes (default: simulate.workers, 0 = one per core).")
@json_option
def simulate(config_path, overrides, output, workers, as_json):
    """Run the design of experiments through the FMU."""
    from ..simulate import simulate as run
    refuse_overwrite({"-o": output}, {"-c": config_path})
    cfg = load(config_path, overrides)
    total = cfg.simulate.train_size + cfg.simulate.test_size
    with progress_bar(total, "simulate") as update:
        summary = run(cfg, output, workers=workers, progress=update)
    if as_json:
        emit_json(summary.as_dict())
    else:
        say(f"simulate: {summary.runs} runs ({summary.resumed} resumed), {summary.failures} "
            f"failed, {summary.wall_time:.2f} s on {summary.workers} workers "
            f"({summary.runs_per_second:.0f} runs/s) -> {output}")
    for w in summary.warnings:
        warn(f"simulate: {w}")


@main.command()
@config_options
@click.option("-o", "--output", default="data/fleet.h5", show_default=True,
              type=click.Path(), help="Observations file to write.")
@click.option("--truth", "truth", default=None, type=click.Path(),
              help="Truth file to write [default: OUTPUT with _truth before .h5].")
@json_option
def fabricate(config_path, overrides, output, truth, as_json):
    """Synthetic observations (simulation + noise) and their withheld truth."""
    from ..fabricate import fabricate as run
    truth = truth or (output[:-3] if output.endswith(".h5") else output) + "_truth.h5"
    refuse_overwrite({"-o": output, "--truth": truth}, {"-c": config_path})
    cfg = load(config_path, overrides)
    summary = run(cfg, output, truth)
    if as_json:
        emit_json(summary.as_dict())
    else:
        say(f"fabricate: {summary.units} units x {summary.years} years -> {output} "
            f"(truth: {truth})")


@main.command("import-csv")
@click.argument("csv_file", type=click.Path())
@config_options
@click.option("-o", "--output", required=True, type=click.Path(),
              help="Observations file to write.")
@click.option("--noise-std", type=float, default=None,
              help="Known noise standard deviation of the output, in its units.")
@click.option("--events", "events", default=None, type=click.Path(),
              help="Maintenance events CSV: unit,year,component[,action,note].")
@json_option
def import_csv(csv_file, config_path, overrides, output, noise_std, events, as_json):
    """Convert long CSV measurements (unit,year,time,<output>[,<channel>...]) to observations.

    Column names are the config's: model.output.name and the FMU variables of
    model.channels. Events (--events) name a unit, the year whose recording is the first
    after the work, and a component of model.inputs, e.g. "U-7,6,<component>,replaced,WO 4711"."""
    import math

    from ..errors import InputDataError
    from ..observations import import_csv as run
    refuse_overwrite({"-o": output}, {"CSV_FILE": csv_file, "--events": events,
                                      "-c": config_path})
    cfg = load(config_path, overrides)
    if noise_std is not None and not (math.isfinite(noise_std) and noise_std > 0):
        raise InputDataError(f"--noise-std: expected a positive number, got {noise_std!r}")
    from ..artifacts import output_lock
    with output_lock(output, "twinmon import-csv"):     # from reading to the rename
        obs = run(csv_file, output, cfg.model.output.name, noise_std,
                  channels=list(cfg.model.channels), units=cfg.model.channel_units,
                  events=events, components=list(cfg.model.components))
    n_events = sum(len(o.events) for o in obs.units.values())
    summary = {"units": {u: {"years": o.years.tolist(), "channels": sorted(o.channels),
                             "events": [dataclasses.asdict(e) for e in o.events]}
                         for u, o in obs.units.items()},
               "samples_per_year": int(obs.time.size), "output": output}
    if as_json:
        emit_json(summary)
    else:
        n_units = len(obs.units)
        say(f"import-csv: {n_units} unit{'s' * (n_units != 1)}, {obs.time.size} samples per "
            "start-up" + (f", {n_events} event{'s' * (n_events != 1)}" if events is not None
                          else "") + f" -> {output}")


@main.group()
def events():
    """Maintenance events of an observations file (a part replaced in a given year)."""


@events.command("add")
@click.argument("observations", type=click.Path())
@config_options
@click.option("--unit", required=True, help="Unit name, as in the file.")
@click.option("--year", required=True, type=int,
              help="Year of service whose recording is the first after the work.")
@click.option("--component", required=True, help="A component of the config's model.inputs.")
@click.option("--action", default="replaced", show_default=True, help="What was done.")
@click.option("--note", default="", help="Free text, e.g. the work order.")
@json_option
def events_add(observations, config_path, overrides, unit, year, component, action, note,
               as_json):
    """Add one event to OBSERVATIONS in place (atomic: on any error the file is unchanged)."""
    from ..observations import Event, add_events
    cfg = load(config_path, overrides)
    obs = add_events(observations, {unit: [Event(year, component.strip(), action.strip(),
                                                  note.strip())]},
                     components=list(cfg.model.components))
    _print_events(obs, as_json, f"events add: {unit} year {year}: {component} {action} -> "
                                f"{observations}")


@events.command("remove")
@click.argument("observations", type=click.Path())
@click.option("--unit", required=True, help="Unit name, as in the file.")
@click.option("--year", required=True, type=int, help="Year of the event to remove.")
@click.option("--component", required=True, help="Its component.")
@json_option
def events_remove(observations, unit, year, component, as_json):
    """Remove one event from OBSERVATIONS in place (atomic: on any error the file is
    unchanged), e.g. one recorded by mistake."""
    from ..observations import remove_events
    obs = remove_events(observations, unit, year, component.strip())
    _print_events(obs, as_json, f"events remove: {unit} year {year}: {component} -> "
                                f"{observations}")


@events.command("list")
@click.argument("observations", type=click.Path())
@json_option
def events_list(observations, as_json):
    """Print the events recorded in OBSERVATIONS, by unit."""
    from ..observations import read_observations
    _print_events(read_observations(observations), as_json, None)


def _print_events(obs, as_json, headline):
    if as_json:
        emit_json({u: [dataclasses.asdict(e) for e in o.events] for u, o in obs.units.items()})
        return
    if headline:
        say(headline)
        return
    for u, o in obs.units.items():
        line = "; ".join(f"year {e.year}: {e.component} {e.action}"
                         + (f" ({e.note})" if e.note else "") for e in o.events)
        click.echo(f"{u}: {line or 'no events'}")


@main.command("build-fmu")
@click.argument("source", type=click.Path(file_okay=False))
@click.option("--force", is_flag=True, help="Rebuild even if the cached binary is current.")
@click.option("--validate/--no-validate", default=True, show_default=True,
              help="Check the built FMU with fmpy.validate_fmu.")
def build_fmu(source, force, validate):
    """Build a hand-written FMU from its C sources (cached by a hash of the sources)."""
    from ..errors import SimulationError
    from ..fmu import build_fmu as build
    path = build(source, force=force)
    if validate:
        from fmpy.validation import validate_fmu
        problems = validate_fmu(str(path))
        if problems:
            raise SimulationError(f"{path}: fmpy.validate_fmu found {len(problems)} problems, "
                                  f"first: {problems[0]}")
    say(f"build-fmu: {path}" + (" (validated)" if validate else ""))
