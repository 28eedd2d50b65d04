"""Stage ``simulate``: a design of experiments run through the FMU.

The training and test designs are drawn by OpenTURNS over the config's input box; every run
goes through the real FMU by fmpy, one extracted FMU and one instance per worker. A run that
fails is recorded (status and message) and does not stop the batch. Results are flushed to
``<output>.partial`` chunk by chunk, so an interrupted ``simulate`` resumes where it stopped;
the partial file is renamed to the final name only once every run has been attempted.
"""
from __future__ import annotations

import os
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import h5py
import numpy as np

from . import artifacts
from .config import Config
from .errors import ArtifactError, ConfigError, Interrupted, SimulationError
from .executors import Executor, InterruptGuard, SimulationSpec, check_workers, make_executor

SPLITS = ("train", "test")
#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "simulate", "seed")
STATUS_PENDING, STATUS_OK, STATUS_FAILED = -1, 0, 1


def draw_design(cfg: Config, size: int, seed: int) -> np.ndarray:
    """Space-filling design over the input box.

    Parameters
    ----------
    cfg : Config
    size : int
        Number of points.
    seed : int
        Seed of OpenTURNS' generator (so the design is reproducible).

    Returns
    -------
    ndarray, shape [size, n_inputs]
        Points in each input's own units.
    """
    import openturns as ot
    if size == 0:
        return np.empty((0, len(cfg.model.inputs)))
    ot.RandomGenerator.SetSeed(int(seed))
    marginals = [ot.Uniform(s.low, s.high) for s in cfg.model.inputs.values()]
    dist = ot.JointDistribution(marginals)
    kind = cfg.simulate.design
    if kind == "lhs":
        exp = ot.LHSExperiment(dist, size)
        exp.setAlwaysShuffle(True)
        # A few hundred annealing steps buy a much better space filling (lower C2 discrepancy)
        # than a plain LHS at no visible cost for a few hundred points.
        space = ot.SpaceFillingC2()
        sample = ot.SimulatedAnnealingLHS(exp, space, ot.GeometricProfile()).generate()
    else:
        seq = ot.SobolSequence(dist.getDimension()) if kind == "sobol" \
            else ot.HaltonSequence(dist.getDimension())
        sample = ot.LowDiscrepancyExperiment(seq, dist, size, True).generate()
    return np.array(sample)


def twin_outputs(cfg: Config) -> list[str]:
    """FMU variables a twin run records: the output, the indicator's variable (when it is
    another one) and the non-physical flag."""
    outputs = [cfg.model.output.variable, cfg.indicator_variable]
    if cfg.model.nonphysical:
        outputs.append(cfg.model.nonphysical)
    return list(dict.fromkeys(outputs))


def design_outputs(cfg: Config) -> list[str]:
    """FMU variables a design run records: the twin's (:func:`twin_outputs`) and the further
    channels (``model.channels``), which ``reduce`` may learn for a multi-channel likelihood."""
    return list(dict.fromkeys(twin_outputs(cfg) + list(cfg.model.channels)))


def check_model(cfg: Config):
    """Check every FMU variable the config names against the FMU's model description, and
    return that description (:class:`~twinmon.fmu.FMUInfo`).

    Done once, before any run and in this process, so that a typo or a foreign FMU ends the
    command with one line instead of failing in every worker.

    Raises
    ------
    SimulationError
        The FMU cannot be read, does not support ``model.fmi_type``, or lacks a named
        variable (the message names the config path, the name and the closest names the
        FMU has).
    """
    from .fmu import closest_names, describe_fmu, why_not_settable
    from .fmu.common import _a
    src = cfg.source
    try:
        info = describe_fmu(cfg.model.fmu)
    except SimulationError as exc:
        raise SimulationError(f"{src}: model.fmu: {exc.message}") from None
    kind_ok = info.co_simulation if cfg.model.fmi_type == "CoSimulation" else info.model_exchange
    if not kind_ok:
        raise SimulationError(f"{src}: model.fmi_type: {info.path} does not support "
                              f"{cfg.model.fmi_type}")
    params = {v.name for v in info.settable()}
    values = {v.name for v in info.recordable()}

    def need(where: str, name: str, pool: set, what: str) -> None:
        if name in pool:
            return
        near = closest_names(name, sorted(pool))
        hint = f"; closest: {', '.join(near)}" if near else ""
        found = info.variables.get(name)
        if found is None:
            why = f"is not a variable of {info.path.name}"
        elif pool is params:
            why = why_not_settable(found)
        else:
            why = f"is {_a(found.causality)} {found.type}, not {what}"
        raise SimulationError(f"{src}: {where}: {name!r} {why}{hint}")

    for key, spec in cfg.model.inputs.items():
        need(f"model.inputs.{key}.variable", spec.variable, params, "a settable parameter")
        v = info.variables[spec.variable]
        if v.min is not None and spec.low < v.min:
            raise SimulationError(f"{src}: model.inputs.{key}.low: {spec.low:g} is below the "
                                  f"min {v.min:g} {info.path.name} declares for {v.name}")
        if v.max is not None and spec.high > v.max:
            raise SimulationError(f"{src}: model.inputs.{key}.high: {spec.high:g} is above "
                                  f"the max {v.max:g} {info.path.name} declares for {v.name}")
    need("model.output.variable", cfg.model.output.variable, values, "a recordable output")
    for ch in cfg.model.channels:
        need(f"model.channels.{ch}", ch, values, "a recordable output")
    if cfg.model.nonphysical:
        need("model.nonphysical", cfg.model.nonphysical, values, "a recordable output")
    if cfg.safety.indicator.variable:
        need("safety.indicator.variable", cfg.safety.indicator.variable, values,
             "a recordable output")
    for name in cfg.model.fixed:
        need(f"model.fixed.{name}", name, params, "a settable parameter")
    for name in cfg.model.effects:
        need(f"model.effects.{name}", name, params, "a settable parameter")
    fab = cfg.fabricate
    if fab is not None:
        for name in fab.truth_variables:
            need(f"fabricate.truth_variables.{name}", name, values, "a recordable output")
    return info


def unit_mismatches(cfg: Config, info=None) -> list[str]:
    """Where the config's units differ from those the FMU declares for the same variable
    (inputs, output, channels), one line each; variables the FMU declares no unit for are
    not compared. Spellings are compared after removing blanks, ``.`` and ``*`` between
    symbols and case (``N.m`` = ``N*m`` = ``n m``): a unit written another way is not
    flagged, a different unit is (``W`` against ``kW`` would label kilowatts as watts).
    ``info``: the FMU's description when already read (:func:`check_model` returns it)."""
    if info is None:
        from .fmu import describe_fmu
        info = describe_fmu(cfg.model.fmu)

    def norm(u: str) -> str:
        return "".join(ch for ch in u.lower() if ch not in " .*")
    pairs = [(f"model.inputs.{k}.units", s.variable, s.units)
             for k, s in cfg.model.inputs.items()]
    pairs.append(("model.output.units", cfg.model.output.variable, cfg.model.output.units))
    pairs += [(f"model.channels.{k}.units", k, c.units) for k, c in cfg.model.channels.items()]
    out = []
    for where, var, units in pairs:
        v = info.variables.get(var)
        if v is None or not v.unit or not units or norm(v.unit) == norm(units):
            continue
        out.append(f"{cfg.source}: {where}: {units!r}, but {info.path.name} declares "
                   f"{v.unit!r} for {var}: the report labels its values with the config's")
    return out


def spec_for(cfg: Config, outputs: Sequence[str] | None = None,
             times: np.ndarray | None = None) -> SimulationSpec:
    """Simulation spec of the config's FMU (built from sources if need be)."""
    from .fmu import resolve_fmu
    if outputs is None:
        outputs = twin_outputs(cfg)
    return SimulationSpec(fmu=resolve_fmu(cfg.model.fmu), outputs=tuple(outputs),
                          times=cfg.model.output.times.times if times is None else times,
                          fmi_type=cfg.model.fmi_type, fixed=dict(cfg.model.fixed))


def declared_range(cfg: Config, build: bool = True) -> np.ndarray:
    """The range the FMU's model description declares for each input (``min``, ``max``),
    shape [d, 2], -inf / inf where it declares none: beyond it a value is not a state of
    the model (FMI forbids setting it; a hand-written FMU may run it anyway, slowly or to a
    failure). ``build``: as :func:`~twinmon.fmu.describe_fmu`'s."""
    from .fmu import describe_fmu
    info = describe_fmu(cfg.model.fmu, build=build)
    out = np.tile([-np.inf, np.inf], (len(cfg.model.inputs), 1))
    for i, spec in enumerate(cfg.model.inputs.values()):
        v = info.variables.get(spec.variable)
        if v is not None:
            out[i] = (-np.inf if v.min is None else v.min, np.inf if v.max is None else v.max)
    return out


def as_parameters(cfg: Config, X: np.ndarray) -> list[dict[str, float]]:
    """Design rows [n, n_inputs] as FMU parameter mappings (config names -> FMU names)."""
    variables = [s.variable for s in cfg.model.inputs.values()]
    return [dict(zip(variables, map(float, row))) for row in np.atleast_2d(X)]


@dataclass
class BatchResult:
    """Outputs of a batch of runs.

    Attributes
    ----------
    outputs : dict of str to ndarray, each shape [n, n_t]
        NaN rows for failed runs.
    ok : ndarray of bool, shape [n]
    messages : list of str
        Failure message per run ("" when it succeeded).
    """

    outputs: dict[str, np.ndarray]
    ok: np.ndarray
    messages: list[str]


def run_batch(spec: SimulationSpec, params: Sequence[Mapping[str, float]],
              executor: Executor | None = None,
              on_result: Callable[[int], None] | None = None) -> BatchResult:
    """Run parameter sets through the FMU and gather their outputs in order.

    Parameters
    ----------
    spec : SimulationSpec
    params : sequence of mapping
        FMU parameter values per run.
    executor : Executor, optional
        Defaults to a serial executor.
    on_result : callable, optional
        Called with the number of runs finished so far, for progress bars.
    """
    from .executors import SerialExecutor
    executor = executor or SerialExecutor()
    n, n_t = len(params), len(spec.times)
    outputs = {o: np.full((n, n_t), np.nan) for o in spec.outputs}
    ok = np.zeros(n, bool)
    messages = [""] * n
    for done, res in enumerate(executor.map(spec, list(enumerate(params))), start=1):
        if res.ok:
            ok[res.index] = True
            for o in spec.outputs:
                outputs[o][res.index] = res.outputs[o]
        else:
            messages[res.index] = res.message
        if on_result:
            on_result(done)
    return BatchResult(outputs, ok, messages)


@dataclass
class SimulateSummary:
    runs: int
    failures: int
    resumed: int
    wall_time: float
    workers: int
    output: str
    #: Plain-words warnings about the design (a criterion no run meets, failed runs).
    warnings: list = field(default_factory=list)

    @property
    def runs_per_second(self) -> float:
        return self.runs / self.wall_time if self.wall_time > 0 else float("inf")

    def as_dict(self) -> dict:
        return {"runs": self.runs, "failures": self.failures, "resumed": self.resumed,
                "wall_time": round(self.wall_time, 3), "workers": self.workers,
                "runs_per_s": round(self.runs_per_second, 1), "output": self.output,
                "warnings": list(self.warnings)}


def criterion_warnings(cfg: Config, sims: "Simulations") -> list[str]:
    """Warn when the safety criterion is met by no training run, or by every one.

    Either way the forecast cannot tell units apart inside the design box: the limit is
    probably in the wrong place, in the wrong direction, or in other units."""
    from .safety import Indicator
    ind = Indicator.from_config(cfg)
    ok = sims.ok["train"]
    if not ok.any():
        return []
    series = sims.indicator_series["train"][ok]
    values = ind(sims.time, series)
    unsafe = ind.unsafe(values, sims.nonphysical["train"][ok])
    finite = values[np.isfinite(values)]
    span = (f"{ind.fmt(finite.min())} to {ind.fmt(finite.max())}" if finite.size
            else "never finite")
    if unsafe.all():
        return [f"every training run is already unsafe ({ind.rule}; {ind.name} over the design "
                f"box: {span}): every unit will be judged unsafe; check safety.unsafe_if and "
                "safety.indicator"]
    if not unsafe.any():
        return [f"no training run is unsafe ({ind.rule}; {ind.name} over the design box: "
                f"{span}): the twin cannot predict a failure inside the box; check "
                "safety.unsafe_if, safety.indicator and the input ranges"]
    return []


def simulate(cfg: Config, output: str | os.PathLike, *, workers: int | None = None,
             progress: Callable[[int, int], None] | None = None) -> SimulateSummary:
    """Run the training and test designs through the FMU and write ``simulations.h5``.

    Parameters
    ----------
    cfg : Config
    output : path-like
        The artifact to write. ``<output>.partial`` holds work in progress.
    workers : int, optional
        Overrides ``simulate.workers``.
    progress : callable, optional
        ``progress(done, total)`` after each run.
    """
    output = Path(output)
    # Before the lock and the partial file: a bad count leaves nothing behind.
    check_workers(cfg.simulate.workers if workers is None else workers)
    check_model(cfg)
    output.parent.mkdir(parents=True, exist_ok=True)
    # One writer per output: a second 'simulate' into the same file must not take the
    # first one's partial file for a corrupt one and delete it.
    with artifacts.output_lock(output, "twinmon simulate"):
        return _simulate_locked(cfg, output, workers, progress)


def _simulate_locked(cfg: Config, output: Path, workers, progress) -> SimulateSummary:
    spec = spec_for(cfg, outputs=design_outputs(cfg))
    section = cfg.section_yaml(*SECTIONS)
    designs = {"train": draw_design(cfg, cfg.simulate.train_size, cfg.seed),
               "test": draw_design(cfg, cfg.simulate.test_size, cfg.seed + 1)}
    partial = output.with_name(output.name + ".partial")
    resumed = _open_partial(partial, section, spec, cfg, designs)
    executor = make_executor(cfg.simulate.executor,
                             cfg.simulate.workers if workers is None else workers,
                             dask=cfg.dask)
    total = sum(len(x) for x in designs.values())
    start = _time.perf_counter()
    done = resumed
    try:
        # One pool for the whole design (workers fork once, not once per chunk); Ctrl-C is
        # taken between runs, where the partial file is consistent.
        with InterruptGuard() as guard, executor, h5py.File(partial, "a") as f:
            for split in SPLITS:
                g = f[split]
                pending = np.flatnonzero(g["status"][()] == STATUS_PENDING)
                for lo in range(0, len(pending), cfg.simulate.chunk_size):
                    idx = pending[lo:lo + cfg.simulate.chunk_size]
                    params = as_parameters(cfg, designs[split][idx])
                    base = done

                    def on_result(k, b=base):
                        guard.check()
                        if progress:
                            progress(b + k, total)
                    batch = run_batch(spec, params, executor, on_result)
                    _store_chunk(g, idx, batch, spec, cfg)
                    done += len(idx)
                    f.flush()
        failures = 0
        with h5py.File(partial, "a") as f:
            for split in SPLITS:
                failures += int(np.sum(f[split]["status"][()] == STATUS_FAILED))
            if failures == total:
                first = f["train"]["message"][0] if len(f["train"]["message"]) else b""
                first = first.decode() if isinstance(first, bytes) else str(first)
                raise SimulationError(f"{output}: all {total} runs failed; first: {first} "
                                      f"({partial} kept for inspection)")
            f.attrs["created"] = artifacts.utc_now()
        os.replace(partial, output)
    except KeyboardInterrupt:
        raise Interrupted(f"{output}: interrupted; {partial} keeps the finished runs and "
                          "the next 'twinmon simulate' resumes from it") from None
    except (SimulationError, ConfigError):      # ConfigError: dask.address out of reach
        if done == 0 and partial.exists():
            partial.unlink()          # nothing to resume: leave no empty partial file behind
        raise
    wall = _time.perf_counter() - start
    warnings = criterion_warnings(cfg, read_simulations(output))
    if failures:
        warnings.insert(0, f"{failures} of {total} runs failed (their messages are in "
                           f"{output}, /train/message and /test/message)")
    return SimulateSummary(runs=total - resumed, failures=failures, resumed=resumed,
                           wall_time=wall, workers=executor.workers, output=str(output),
                           warnings=warnings)


def _open_partial(partial: Path, section: str, spec: SimulationSpec, cfg: Config,
                  designs: Mapping[str, np.ndarray]) -> int:
    """Reuse a partial file made by the same config and FMU; else start a fresh one.

    Returns the number of runs already done."""
    fmu_hash = artifacts.file_sha256(spec.fmu)
    if partial.exists():
        try:
            with h5py.File(partial, "r") as f:
                same = (f.attrs.get("config") == section
                        and f.attrs.get("fmu_sha256") == fmu_hash)
                done = sum(int(np.sum(f[s]["status"][()] != STATUS_PENDING)) for s in SPLITS)
        except (OSError, KeyError):
            same = False
        if same:
            return done
        partial.unlink()
    times = spec.times
    with h5py.File(partial, "w") as f:
        artifacts.set_provenance(f, "simulations", config=section,
                                 records=[{"path": str(spec.fmu), "sha256": fmu_hash}],
                                 seed=cfg.seed)
        f.attrs["fmu_sha256"] = fmu_hash
        f.attrs["input_names"] = artifacts.json_attr(cfg.model.input_names)
        f.attrs["input_variables"] = artifacts.json_attr(
            [s.variable for s in cfg.model.inputs.values()])
        f.attrs["output_variable"] = cfg.model.output.variable
        artifacts.put(f, "time", times, "s", "sample times of the output")
        artifacts.put(f, "bounds", cfg.model.bounds, "input units",
                      "design box, one row (low, high) per input")
        for split in SPLITS:
            X = designs[split]
            g = f.create_group(split)
            artifacts.put(g, "X", X, "input units",
                          f"{split} design, one row per run, columns = input_names")
            artifacts.put(g, "Y", np.full((len(X), times.size), np.nan),
                          cfg.model.output.units,
                          f"{cfg.model.output.variable} at the sample times; NaN if the run failed")
            if cfg.indicator_variable != cfg.model.output.variable:
                artifacts.put(g, "Y_indicator", np.full((len(X), times.size), np.nan),
                              cfg.model.variable_words(cfg.indicator_variable)[1],
                              f"{cfg.indicator_variable} (the health indicator's variable) at "
                              "the sample times; NaN if the run failed")
            for ch in _design_channels(cfg):
                artifacts.put(g, f"channels/{ch}", np.full((len(X), times.size), np.nan),
                              cfg.model.variable_words(ch)[1],
                              f"{ch} (a further channel) at the sample times; NaN if the run "
                              "failed")
            artifacts.put(g, "nonphysical", np.zeros(len(X), np.int8), "1",
                          "1 when the twin ended in its non-physical mode")
            artifacts.put(g, "status", np.full(len(X), STATUS_PENDING, np.int8), "1",
                          "-1 not run yet, 0 ok, 1 failed")
            artifacts.put(g, "message", np.array([""] * len(X), dtype=h5py.string_dtype()),
                          "", "failure message of the run, empty when it succeeded")
    return 0


def _design_channels(cfg: Config) -> list[str]:
    """The further channels stored under ``<split>/channels`` (not the output itself)."""
    return [ch for ch in cfg.model.channels if ch != cfg.model.output.variable]


def _store_chunk(g: h5py.Group, idx: np.ndarray, batch: BatchResult, spec: SimulationSpec,
                 cfg: Config) -> None:
    # Write only this chunk's rows (idx is increasing, as h5py's point selection needs).
    rows = idx.tolist()
    g["Y"][rows] = batch.outputs[cfg.model.output.variable]
    for ch in _design_channels(cfg):
        # A partial file begun before channels were recorded has no room for them.
        if f"channels/{ch}" in g and ch in batch.outputs:
            g[f"channels/{ch}"][rows] = batch.outputs[ch]
    if "Y_indicator" in g:
        g["Y_indicator"][rows] = batch.outputs[cfg.indicator_variable]
    if cfg.model.nonphysical:
        flag = batch.outputs[cfg.model.nonphysical][:, -1]
        g["nonphysical"][rows] = np.where(batch.ok, flag > 0.5, 0).astype(np.int8)
    g["status"][rows] = np.where(batch.ok, STATUS_OK, STATUS_FAILED).astype(np.int8)
    g["message"][rows] = np.array(batch.messages, dtype=h5py.string_dtype())


@dataclass
class Simulations:
    """A loaded ``simulations.h5``.

    Attributes
    ----------
    time : ndarray, shape [n_t], s
    input_names : list of str
    bounds : ndarray, shape [n_inputs, 2]
    X, Y, ok, nonphysical : dict split -> arrays [n, n_inputs], [n, n_t], [n], [n]
    indicator_series : dict split -> array [n, n_t]
        The health indicator's variable (``Y`` itself when it is the output).
    channels : dict split -> dict FMU variable -> array [n, n_t]
        Further channels the design recorded (empty for files written before they were).
    """

    path: Path
    time: np.ndarray
    input_names: list[str]
    bounds: np.ndarray
    X: dict[str, np.ndarray]
    Y: dict[str, np.ndarray]
    ok: dict[str, np.ndarray]
    nonphysical: dict[str, np.ndarray]
    indicator_series: dict[str, np.ndarray] = field(default_factory=dict)
    channels: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


def read_simulations(path: str | os.PathLike) -> Simulations:
    """Load a simulations artifact (schema checked)."""
    import json
    path = Path(path)
    with artifacts.open_artifact(path, "simulations") as f:
        names = json.loads(f.attrs["input_names"])
        X, Y, ok, nph, ind, chans = {}, {}, {}, {}, {}, {}
        for split in SPLITS:
            if split not in f:
                raise ArtifactError(f"{path}: group /{split} is missing")
            g = f[split]
            X[split] = artifacts.get(g, "X", path)
            Y[split] = artifacts.get(g, "Y", path)
            status = artifacts.get(g, "status", path)
            ok[split] = status == STATUS_OK
            nph[split] = artifacts.get(g, "nonphysical", path).astype(bool)
            ind[split] = artifacts.get(g, "Y_indicator", path) if "Y_indicator" in g else Y[split]
            chans[split] = ({ch: artifacts.get(g["channels"], ch, path) for ch in g["channels"]}
                            if "channels" in g else {})
        return Simulations(path, artifacts.get(f, "time", path), names,
                           artifacts.get(f, "bounds", path), X, Y, ok, nph, ind, chans)
