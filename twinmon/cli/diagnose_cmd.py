"""Command ``diagnose``: the sim-to-real gap of each unit (where, which effect, how far it
shrinks)."""
from __future__ import annotations

import click

from .app import main
from .common import (config_options, emit_json, json_option, load, progress_bar,
                     refuse_overwrite, say, warn)


@main.command()
@config_options
@click.option("--observations", required=True, type=click.Path(),
              help="Observations artifact (twinmon.observations/1).")
@click.option("--posterior", default=None, type=click.Path(),
              help="Optional posterior.h5: standardise the residual map against it.")
@click.option("-o", "--output", default="out/gap.h5", show_default=True,
              type=click.Path(), help="Gap artifact to write.")
@click.option("-j", "--workers", type=int, default=None,
              help="Worker processes over units (default: diagnose.workers, 0 = one per core).")
@click.option("--update", is_flag=True,
              help="Keep the per-year base fits and screening of the output gap.h5; fit and "
                   "screen only the years (and units) added to the observations since, "
                   "recompute the rest. Same result as a full run.")
@json_option
def diagnose(config_path, overrides, observations, posterior, output, workers, update,
             as_json):
    """Locate the sim-to-real gap, name the unmodelled effect, show how far it shrinks."""
    from ..diagnose import candidate_names, diagnose as run, no_candidates_hint
    from ..diagnose.text import hidden_line, summary_line
    from ..errors import TwinmonError
    from ..observations import read_observations
    from ..executors import check_workers
    refuse_overwrite({"-o": output}, {"--observations": observations,
                                      "--posterior": posterior, "-c": config_path})
    cfg = load(config_path, overrides)
    check_workers(workers if workers is not None else cfg.diagnose.workers)
    hint = "" if candidate_names(cfg) else no_candidates_hint(cfg)
    if hint:
        warn(hint)

    def n_units() -> int:
        # For the bar only; an unreadable file is reported by the stage itself.
        try:
            return len(read_observations(observations).units)
        except TwinmonError:
            return 0
    with progress_bar(n_units, "diagnose") as tick:
        s = run(cfg, observations, output, workers=workers, progress=tick,
                posterior=posterior, update=update)
    if as_json:
        out = {"units": {u: g.as_dict() for u, g in s.units.items()},
               "output": s.output, "wall_time": round(s.wall_time, 3)}
        if s.update is not None:
            out["update"] = s.update
        emit_json(out)
    if s.update is not None:
        say(update_line(s.update))
    # Candidates hidden alike on every unit (a fleet recording the same channels) are said
    # once, after the units.
    hidden = {hidden_line(g.hidden) if g.hidden else "" for g in s.units.values()}
    shared = next(iter(hidden)) if len(s.units) > 1 and len(hidden) == 1 else ""
    for u, g in s.units.items():
        say(summary_line(u, g, hint, hidden=not shared))
    if shared:
        say(f"every unit: {shared}")
    say(f"diagnose: {len(s.units)} unit{'s' if len(s.units) != 1 else ''} in "
        f"{s.wall_time:.1f} s on {s.workers} worker{'s' if s.workers != 1 else ''} "
        f"-> {output}")


def update_line(u: dict) -> str:
    """What ``--update`` kept and recomputed, in one line."""
    return (f"diagnose --update: {u['kept_years']} unit-year(s) of base fits and screening "
            f"kept from {u['from'] or 'nothing (no earlier gap.h5)'}, {u['new_years']} run; "
            "tests, confirmation fits and shrink recomputed"
            + "".join(f"; {what}: {', '.join(u[key])}" for key, what in
                      (("new_units", "new units"), ("redone_units", "redone (data changed)"),
                       ("dropped_units", "no longer observed")) if u[key]))
