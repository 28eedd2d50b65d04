"""Options and small functions shared by the commands."""
from __future__ import annotations

import sys
from contextlib import contextmanager

import click

from ..config import Config, load_config


def config_options(f):
    """``-c/--config`` and repeated ``--set KEY=VALUE``."""
    f = click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
                     help="Override a config value (YAML syntax), e.g. --set seed=3.")(f)
    f = click.option("-c", "--config", "config_path", required=True,
                     type=click.Path(),
                     help="YAML config file.")(f)
    return f


def refuse_overwrite(outputs: dict, inputs: dict) -> None:
    """Exit 2 (one line) when an output is one of the command's inputs: first thing a
    writing command does, before reading anything."""
    from ..artifacts import check_outputs_not_inputs
    check_outputs_not_inputs(outputs, inputs)


def json_option(f):
    return click.option("--json", "as_json", is_flag=True,
                        help="Print a machine-readable JSON summary on stdout.")(f)


def load(config_path: str, overrides) -> Config:
    return load_config(config_path, overrides)


def quiet() -> bool:
    ctx = click.get_current_context()
    return bool(ctx.obj and ctx.obj.get("quiet"))


def say(text: str = "") -> None:
    """Human output, on stderr so that stdout stays clean for --json."""
    if not quiet():
        click.echo(text, err=True)


def warn(text: str) -> None:
    """A warning on stderr, shown even with --quiet (it may change what the user does)."""
    click.echo(f"twinmon: warning: {text}", err=True)


def emit_json(obj) -> None:
    """``--json`` output: strict JSON (``null`` for NaN and infinities, see
    :mod:`twinmon.jsontext`), whatever the command."""
    from ..jsontext import to_json
    click.echo(to_json(obj))


@contextmanager
def progress_bar(total, label: str):
    """Yields ``update(done, total)``; a bar on stderr only for a terminal and not --quiet.

    ``total``: an int, or a callable giving it, called only when the bar is shown (counting
    a fleet's unit-years reads its observations: 1-2 s for 1000 units, wasted in a batch
    run)."""
    show = sys.stderr.isatty() and not quiet()
    if show and callable(total):
        total = total()
    show = show and total > 0
    if not show:
        yield lambda done, total=total: None
        return
    with click.progressbar(length=total, label=label, file=sys.stderr) as bar:
        state = {"done": 0}

        def update(done, total=total):
            bar.update(done - state["done"])
            state["done"] = done
        yield update
