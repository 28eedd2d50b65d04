"""``twinmon init``: a starter config for a new FMU."""
from __future__ import annotations

from pathlib import Path

import click

from .app import main
from .common import emit_json, json_option, say


@main.command("init")
@click.argument("model", type=click.Path())
@click.option("-o", "--output", default=None, type=click.Path(),
              help="YAML file to write [default: MODEL's name + .yaml, here].")
@click.option("--force", is_flag=True, help="Overwrite OUTPUT if it exists.")
@json_option
def init_cmd(model, output, force, as_json):
    """Write a starter config for MODEL (a .fmu file or an FMU source folder).

    It lists the FMU's tunable parameters as candidate inputs and effects and its recordable
    variables for the output and channels; fill in every <fill in> and uncomment what you
    use: until then loading it fails, naming the first missing key."""
    from ..fmu import describe_fmu
    from ..init import write_starter_config
    out = Path(output) if output else Path((Path(model).resolve().stem or "twinmon") + ".yaml")
    path = write_starter_config(model, out, force=force)
    info = describe_fmu(model)
    summary = {"output": str(path), "fmu": str(info.path), "fmi_version": info.fmi_version,
               "model_name": info.model_name,
               "parameters": [v.name for v in info.tunable_parameters()],
               "start_values": [v.name for v in info.start_values()],
               "recordable": [v.name for v in info.recordable()]}
    if as_json:
        emit_json(summary)
    else:
        say(f"init: {path}: {len(summary['parameters'])} candidate inputs, "
            f"{len(summary['recordable'])} recordable variables of {info.model_name} "
            f"(FMI {info.fmi_version}); fill in every <fill in> and uncomment what you use")
