"""Reading the artifacts, all of them before anything is drawn.

A bad artifact (missing, wrong schema, made for other inputs than the config's) fails the
report before a single file is written.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from .. import artifacts, lineage
from ..config import Config
from ..errors import ArtifactError
from ..plausibility import check_observations
from .common import Words, indicator_rows


@dataclass
class Inputs:
    """Everything the report is made from: the config, its words and the loaded artifacts."""

    cfg: Config
    words: Words
    obs: Any = None
    sims: Any = None
    surrogate: Any = None
    validation: Optional[dict] = None
    posterior: Any = None
    forecast: Any = None
    backtest: Any = None
    gap: Any = None
    truth: Any = None
    paths: dict = field(default_factory=dict)
    #: The observations file the gap artifact diagnosed, when it is not ``obs``: its units are
    #: then other machines (or other records) and must not be merged into the unit summaries.
    gap_other_source: Optional[str] = None

    def unit_names(self) -> list[str]:
        """Units in order of first appearance: observations, posterior, forecast, gap."""
        names: list[str] = []
        for src in (self.obs, self.posterior, self.forecast):
            if src is not None:
                names += [u for u in src.units if u not in names]
        if self.gap is not None and self.gap_other_source is None:
            names += [u for u in gap_units(self.gap) if u not in names]
        return names


def gap_units(gap) -> list[str]:
    units = getattr(gap, "units", None)
    return list(units) if units is not None else []


def load(cfg: Config, paths: dict) -> Inputs:
    """Load (and schema-check) every artifact given in ``paths`` ({role: path or None})."""
    inp = Inputs(cfg=cfg, words=Words.from_config(cfg),
                 paths={k: str(v) for k, v in paths.items() if v is not None})
    # A report of artifacts from different runs would put one run's forecast beside
    # another's posterior: refused, naming the two files.
    lineage.check_chain(paths)
    if paths.get("observations") is not None:
        from ..observations import read_observations
        inp.obs = read_observations(paths["observations"], cfg.model.output.name)
        check_observations(cfg, inp.obs)
    if paths.get("simulations") is not None:
        from ..simulate import read_simulations
        inp.sims = read_simulations(paths["simulations"])
    if paths.get("surrogate") is not None:
        from ..reduce import read_surrogate, read_validation
        inp.surrogate = read_surrogate(paths["surrogate"])
        inp.validation = read_validation(paths["surrogate"])
    if paths.get("posterior") is not None:
        from ..calibrate import read_posterior
        inp.posterior = read_posterior(paths["posterior"])
    if paths.get("forecast") is not None:
        from ..forecast import read_forecast
        inp.forecast = read_forecast(paths["forecast"])
    if paths.get("backtest") is not None:
        from ..backtest import read_backtest
        inp.backtest = read_backtest(paths["backtest"])
    if paths.get("gap") is not None:
        inp.gap = read_gap(paths["gap"])
        diagnosed = artifacts.read_provenance(paths["gap"]).get("inputs", [])
        if diagnosed and paths.get("observations") is not None:
            same = diagnosed[0]["sha256"] == artifacts.file_sha256(paths["observations"])
            if not same:
                inp.gap_other_source = diagnosed[0]["path"]
        elif diagnosed and paths.get("posterior") is not None:
            # No observations given: the posterior records those it was calibrated from.
            calibrated = lineage.recorded_inputs(paths["posterior"])
            if calibrated and all(r["sha256"] != diagnosed[0]["sha256"] for r in calibrated):
                inp.gap_other_source = diagnosed[0]["path"]
    if paths.get("truth") is not None:
        # Checked here, its units read for the units drawn (:func:`with_truth_of`).
        from ..fabricate import read_truth
        inp.truth = read_truth(paths["truth"], units=())
    return inp


def with_truth_of(inp: Inputs, units: list) -> Inputs:
    """``inp`` with the truth of ``units`` (the units drawn: only their figures show it),
    when a truth file was given; :func:`load` read none of its units."""
    if inp.truth is None:
        return inp
    import dataclasses

    from ..fabricate import read_truth
    return dataclasses.replace(inp, truth=read_truth(inp.paths["truth"], units=units))


def start_fleet_statistics(paths: dict, pool=None, parts: int = 1) -> dict:
    """Start reading every unit's figures that the fleet's summaries and diagnostics need:
    the forecast's units without their Monte Carlo arrays (~0.4 MB a unit left on disk) and
    the posterior's without their draws (the years' and the trend's), a few kB a unit either
    way; :func:`fleet_statistics` collects them.

    ``paths``: {role: path or None}, as :func:`load` takes it. With a ``pool``, each
    artifact is read in ``parts`` runs of its units side by side while this process loads
    the other artifacts: reading is most of a large fleet's own cost (1000 units: 4.5 s of
    CPU for the forecast, 1 s for the posterior), and the workers are idle until the first
    figure comes. Without one, nothing is read here. An artifact that does not open is left
    to :func:`load`, which says what is wrong with it.
    """
    from pathlib import Path

    from ..errors import TwinmonError
    started = {}
    for kind in ("forecast", "posterior"):
        path = paths.get(kind)
        if path is None or not Path(path).is_file():
            continue
        try:
            head = _slim(kind, path)
        except TwinmonError:
            continue
        names = list(head.units)
        size = -(-len(names) // max(parts, 1))
        runs = []
        if pool is not None and size < len(names):
            runs = [pool.submit(read_units, kind, str(path), names[i:i + size])
                    for i in range(0, len(names), size)]
        started[kind] = (head, runs)
    return started


def fleet_statistics(inp: Inputs, started: dict) -> Inputs:
    """``inp`` with the statistics :func:`start_fleet_statistics` started reading (those it
    did not, read here: each artifact in one opening of its file)."""
    import dataclasses
    from pathlib import Path
    out = inp
    for kind, obj in (("forecast", inp.forecast), ("posterior", inp.posterior)):
        if obj is None or not Path(obj.path).is_file():
            continue
        head, runs = started.get(kind) or (_slim(kind, obj.path), [])
        units: dict = {}
        for run in runs:
            units.update(run.result())
        if not runs:
            units = dict(head.units.each())
        if kind == "forecast":
            out = dataclasses.replace(out, forecast=dataclasses.replace(head, units=units))
        else:
            from ..calibrate import Posterior
            out = dataclasses.replace(out, posterior=Posterior(
                head.input_names, units, head.path, head.fit_windows))
    return out


def _slim(kind: str, path):
    """The forecast (without Monte Carlo arrays) or the posterior (without draws) at
    ``path``, its units read on demand."""
    if kind == "forecast":
        from ..forecast import read_forecast
        return read_forecast(path, arrays=False)
    from ..calibrate import read_posterior
    return read_posterior(path, draws=False, trend=False)


def read_units(kind: str, path: str, names: list) -> dict:
    """Pool task of :func:`start_fleet_statistics`: the units ``names`` of the forecast or the
    posterior at ``path``, {unit: its statistics}, in one opening of the file."""
    return dict(_slim(kind, path).units.each(names))


def read_gap(path):
    try:
        from ..diagnose import read_gap as _read
    except ImportError:  # diagnose not installed in this build: still check the schema
        with artifacts.open_artifact(path, "gap"):
            pass
        raise ArtifactError(f"{path}: this twinmon has no diagnose module to read it") from None
    return _read(path)


def check_consistency(cfg: Config, inp: Inputs) -> None:
    """Every artifact must be made for the config's inputs."""
    names = cfg.model.input_names
    for role, obj in (("posterior", inp.posterior), ("forecast", inp.forecast),
                      ("surrogate", inp.surrogate)):
        if obj is not None and list(obj.input_names) != names:
            raise ArtifactError(f"{inp.paths[role]}: inputs are {list(obj.input_names)}, the "
                                f"config's are {names}")
    if inp.sims is not None and list(inp.sims.input_names) != names:
        raise ArtifactError(f"{inp.paths['simulations']}: inputs are {inp.sims.input_names}, "
                            f"the config's are {names}")


def indicator_channel(inp: Inputs, unit: str) -> Optional[np.ndarray]:
    """The recorded variable the indicator is computed from, [n_y, n_t], or None when the
    observations do not hold it (an indicator on a variable the plant does not record)."""
    w, obs = inp.words, inp.obs
    if w.on_output:
        return obs.output_of(unit)
    return obs.units[unit].channels.get(w.ind.variable)


def observed_indicator(inp: Inputs) -> dict:
    """The health indicator of every recorded transient: {unit: (years [n_y], values [n_y])},
    for the units whose observations hold the indicator's variable."""
    out = {}
    if inp.obs is None:
        return out
    for unit, u in inp.obs.units.items():
        values = indicator_channel(inp, unit)
        if values is not None:
            out[unit] = (np.asarray(u.years), indicator_rows(inp.words.ind, inp.obs.time, values))
    return out


def truth_at(truth, unit: str, name: str, years) -> Optional[np.ndarray]:
    """True values of an input at the given years (NaN where the truth has no such year)."""
    if truth is None or unit not in truth.inputs or name not in truth.inputs[unit]:
        return None
    ty = np.asarray(truth.years[unit])
    tv = np.asarray(truth.inputs[unit][name], float)
    out = np.full(len(years), np.nan)
    for k, y in enumerate(years):
        hit = np.flatnonzero(ty == y)
        if hit.size:
            out[k] = tv[hit[0]]
    return out
