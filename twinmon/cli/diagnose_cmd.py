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
    for u, g in s.units.items():
        say(summary_line(u, g, hint))
    say(f"diagnose: {len(s.units)} units in {s.wall_time:.1f} s on {s.workers} workers "
        f"-> {output}")


def update_line(u: dict) -> str:
    """What ``--update`` kept and recomputed, in one line."""
    return (f"diagnose --update: {u['kept_years']} unit-year(s) of base fits and screening "
            f"kept from {u['from'] or 'nothing (no earlier gap.h5)'}, {u['new_years']} run; "
            "tests, confirmation fits and shrink recomputed"
            + "".join(f"; {what}: {', '.join(u[key])}" for key, what in
                      (("new_units", "new units"), ("redone_units", "redone (data changed)"),
                       ("dropped_units", "no longer observed")) if u[key]))


def summary_line(unit: str, g, no_candidates: str = "") -> str:
    """One human line per unit: verdict, effect (group) with its estimate, where, shrink;
    ``no_candidates``: what to do when the config lists no candidate effect."""
    if g.verdict == "none":
        return (f"{unit}: no significant gap (p = {g.p_gap:.2g}, residual RMS "
                f"{g.rms_before:.2f} x noise)")
    where = (f"years {g.where_years[0]}-{g.where_years[-1]}" if g.where_years else "")
    if g.where_windows:
        where += f", {', '.join(g.where_windows)}"
    if g.verdict == "unexplained" and not g.candidates:
        return (f"{unit}: UNEXPLAINED gap from year {g.onset} ({where}); residual RMS "
                f"{g.rms_before:.2f} x noise; "
                + (no_candidates or "no candidate effects to test (model.effects)"))
    if g.verdict == "unexplained":
        best = g.candidates[0]
        return (f"{unit}: UNEXPLAINED gap from year {g.onset} ({where}); residual RMS "
                f"{g.rms_before:.2f} x noise; best candidate {best} would close only "
                f"{g.closed_percent:.0f} %")
    if len(g.groups) > 1:
        # Several effects: each with the effects the data cannot tell from it.
        text = " + ".join(group_text(grp) for grp in g.groups)
        seps = sorted({grp["separating_channel"] for grp in g.groups
                       if len(grp["members"]) > 1 and grp["separating_channel"]})
        sep = f"; {', '.join(seps)} would separate the groups" if seps else ""
    else:
        parts = []
        for e in g.effects:
            est = g.estimate.get(e)
            parts.append(f"{e} = {est[0]:.4g} [{est[1]:.4g}, {est[2]:.4g}]" if est else e)
        text = " or ".join(parts[:len(g.group)]) if len(g.group) > 1 else parts[0]
        extra = [p for p, e in zip(parts, g.effects) if e not in g.group]
        if extra:
            text += " + " + " + ".join(extra)
        sep = (f"; {g.separating_channel} would separate the group" if g.separating_channel
               else "")
    fy = ""
    if g.failure_year_before != g.failure_year_after:
        fy = (f"; projected failure year {g.failure_year_before or 'none'} -> "
              f"{g.failure_year_after or 'none'}")
    return (f"{unit}: {text} from year {g.onset} ({where}); residual RMS "
            f"{g.rms_before:.2f} -> {g.rms_after:.2f} x noise, {g.closed_percent:.0f} % of "
            f"the excess gap closed, BIC gain {g.delta_bic_final:.0f}{sep}{fy}")


def group_text(grp: dict) -> str:
    """One effect's group of a several-effect twin: ``a = v [q05, q95]`` alone, or
    ``(a = v 62 % or b = w 38 %)`` with each member's evidence share; a failure-year spread
    is named."""
    ms = grp["members"]
    if len(ms) == 1:
        m = ms[0]
        return f"{m['effect']} = {m['value']:.4g} [{m['q05']:.4g}, {m['q95']:.4g}]"
    text = "(" + " or ".join(f"{m['effect']} = {m['value']:.4g} {100 * m['weight']:.0f} %"
                             for m in ms) + ")"
    if grp.get("failure_year_spread"):
        lo, hi = grp["failure_year_range"]
        text += f" [failure year {lo or 'none'}-{hi or 'none'} across the group]"
    return text
