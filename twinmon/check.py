"""``twinmon check``: a config, its FMU, observations and artifacts checked in seconds.

What a CI job runs before (or instead of) the full pipeline: every check that needs no
design of experiments, no surrogate fit and no sampling.

1. the config loads and every name it gives matches the FMU (:func:`twinmon.simulate.check_model`);
2. the FMU runs at the nominal point and at the corners of the design box, with finite
   outputs, and the health indicator is computable there; a warning when its limit is
   reached nowhere among those points (the unsafe side may be out of the box's reach);
3. observations, when given, hold the config's channels on its time grid, in its units;
4. artifacts found in a workdir read with their schema, are made for this config's inputs
   and time grid, and were made from the artifacts beside them (their recorded
   fingerprints); one made with other config settings is a warning (``run`` redoes it).

Each problem is one :class:`~twinmon.errors.TwinmonError` of its family, so that the exit
code says which kind of problem came first.
"""
from __future__ import annotations

import itertools
import os
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import artifacts
from .config import Config, load_config
from .errors import ArtifactError, ConfigError, InputDataError, SimulationError, TwinmonError

__all__ = ["CheckResult", "check", "MAX_CORNERS"]

#: Corners of the design box run at most (all of them up to 6 inputs; beyond, a seeded
#: choice of this many), so that a check stays within seconds.
MAX_CORNERS = 64

#: The artifacts a ``twinmon run`` workdir holds: file name -> (kind, stage module, the
#: workdir artifacts it is made from, in provenance order).
WORKDIR_ARTIFACTS = {
    "simulations.h5": ("simulations", "simulate", ()),
    "surrogate.h5": ("surrogate", "reduce", ("simulations.h5",)),
    "posterior.h5": ("posterior", "calibrate", ("surrogate.h5",)),
    "forecast.h5": ("forecast", "forecast", ("posterior.h5", "surrogate.h5")),
    "gap.h5": ("gap", "diagnose", ()),
}


@dataclass
class CheckResult:
    """What :func:`check` found.

    Attributes
    ----------
    problems : list of TwinmonError
        One per problem, in the order found; empty when everything checked passed.
    warnings : list of str
        What may be intended but deserves a look (an unreachable limit, a stale artifact).
    checked : list of str
        One line per check that ran, for the human and JSON summaries.
    seconds : float
    """

    problems: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    checked: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def exit_code(self) -> int:
        """0 when no problem, else the first problem's family code."""
        return self.problems[0].exit_code if self.problems else 0

    def as_dict(self) -> dict:
        return {"ok": self.ok, "exit_code": self.exit_code,
                "problems": [{"family": p.family, "exit_code": p.exit_code,
                              "message": p.message} for p in self.problems],
                "warnings": list(self.warnings), "checked": list(self.checked),
                "seconds": round(self.seconds, 3)}


def check(config_path: str | os.PathLike, overrides=(), observations=None,
          workdir=None) -> CheckResult:
    """Check a config, its FMU and, when given, observations and a workdir's artifacts.

    Parameters
    ----------
    config_path : path-like
        The YAML config.
    overrides : sequence of str
        ``--set`` items.
    observations : path-like, optional
        An observations file (``twinmon.observations/1``).
    workdir : path-like, optional
        A ``twinmon run`` workdir; the artifacts it holds are checked (none is fine).

    Returns
    -------
    CheckResult
        Never raises a :class:`TwinmonError`: each becomes one of ``problems``.
    """
    start = _time.perf_counter()
    res = CheckResult()
    try:
        cfg = load_config(config_path, overrides)
    except TwinmonError as exc:
        res.problems.append(exc)
        res.seconds = _time.perf_counter() - start
        return res
    res.checked.append(f"config {cfg.source} loads")
    steps = [("model", lambda: _check_model(cfg, res))]
    if observations is not None:
        steps.append(("observations", lambda: _check_observations(cfg, observations, res)))
    if workdir is not None:
        steps.append(("workdir", lambda: _check_workdir(cfg, Path(workdir), res)))
    for _, step in steps:
        try:
            step()
        except TwinmonError as exc:
            res.problems.append(exc)
    res.seconds = _time.perf_counter() - start
    return res


# ---------------------------------------------------------------------------------------
# the model

def box_points(cfg: Config, max_corners: int = MAX_CORNERS) -> list[tuple[str, dict]]:
    """The nominal point and the corners of the design box, as ``(label, {input: value})``
    in each input's units; at most ``max_corners`` corners (a seeded choice beyond)."""
    inputs = cfg.model.inputs
    names = list(inputs)
    points = [("nominal point", {n: float(s.nominal) for n, s in inputs.items()})]
    corners = list(itertools.product((0, 1), repeat=len(names)))
    if len(corners) > max_corners:
        rng = np.random.default_rng(cfg.seed)
        corners = [corners[i] for i in sorted(rng.choice(len(corners), max_corners,
                                                         replace=False))]
    for c in corners:
        values = {n: float(inputs[n].high if hi else inputs[n].low) for n, hi in zip(names, c)}
        label = "corner " + ", ".join(f"{n}={'high' if hi else 'low'}"
                                      for n, hi in zip(names, c))
        points.append((label, values))
    return points


def _check_model(cfg: Config, res: CheckResult) -> None:
    from .fmu import FMUModel
    from .safety import Indicator
    from .simulate import check_model, design_outputs, spec_for, unit_mismatches
    info = check_model(cfg)
    res.checked.append(f"every name in {cfg.source.name} matches the FMU")
    res.warnings += unit_mismatches(cfg, info)
    for name, s in cfg.model.inputs.items():
        if s.normal_rate_tolerance == 0 and s.degrading is not None:
            # Half the draws of a part ageing exactly at its normal rate lie beyond it.
            res.warnings.append(
                f"{cfg.source}: model.inputs.{name}.normal_rate_tolerance: 0, so any drift "
                f"of {name} beyond normal_rate ({s.normal_rate:g} {s.units} a year) counts "
                "as wear: a part ageing normally is then half-way to a fault; give the "
                "spread normal ageing has from unit to unit")
    spec = spec_for(cfg, outputs=design_outputs(cfg))
    ind = Indicator.from_config(cfg)
    points = box_points(cfg)
    values, flags = [], []
    log_refused = False
    with FMUModel(spec.fmu, spec.outputs, spec.times, spec.fmi_type, spec.fixed) as model:
        for label, point in points:
            params = {cfg.model.inputs[n].variable: v for n, v in point.items()}
            try:
                out = model.run(params)
            except SimulationError as exc:
                if label == "nominal point":
                    raise SimulationError(f"{cfg.source}: model.inputs: the FMU fails at the "
                                          f"nominal point: {exc.message}") from None
                res.warnings.append(f"{cfg.source}: model.inputs: the FMU fails at the box's "
                                    f"{label} ({exc.message}); the design runs there fail too")
                continue
            v = float(ind(spec.times, out[cfg.indicator_variable][None, :])[0])
            if label == "nominal point" and not np.isfinite(v) and \
                    not (np.isinf(v) and ind.spec.kind == "time_to_reach"):
                raise SimulationError(
                    f"{cfg.source}: safety.indicator: {ind.name} is not computable at the "
                    f"nominal point (got {v}); check its kind, window and variable")
            values.append(v)
            flags.append(bool(np.any(out[cfg.model.nonphysical] > 0.5))
                         if cfg.model.nonphysical else False)
            if label == "nominal point":
                res.warnings += _direction_warnings(cfg, model, ind, spec, point, v)
            y = np.asarray(out[cfg.model.output.variable], float)
            if cfg.reduce.transform == "log" and np.any(y <= 0) and not log_refused:
                # reduce would stop on it after the whole design has run.
                j = int(np.argmax(y <= 0))
                log_refused = True
                res.problems.append(ConfigError(
                    f"{cfg.source}: reduce.transform: log needs a positive output, but at the "
                    f"{label} {cfg.model.output.name} is {y[j]:g} {cfg.model.output.units} at "
                    f"t = {spec.times[j]:g} s; set reduce.transform: none (or auto)"))
    res.checked.append(f"the FMU runs at the nominal point and {len(points) - 1} box corners")
    vals = np.asarray(values)
    unsafe = ind.unsafe(vals, np.asarray(flags)) if vals.size else np.zeros(0, bool)
    if vals.size and bool(unsafe[0]):
        res.warnings.append(f"{cfg.source}: safety.unsafe_if: the nominal point is already "
                            f"unsafe ({ind.name} {ind.fmt(vals[0])}, {ind.rule})")
    if vals.size and not unsafe.any():
        finite = vals[np.isfinite(vals)]
        span = (f"{ind.fmt(finite.min())} to {ind.fmt(finite.max())}" if finite.size
                else "never defined")
        res.warnings.append(
            f"{cfg.source}: safety.unsafe_if: {ind.rule} is reached nowhere among the nominal "
            f"point and the box's corners ({ind.name} {span}): no unit can be found unsafe "
            "unless the limit lies inside the box")
    # A corner unsafe only as non-physical (a stalled drive) does not reach the limit.
    by_value = ind.unsafe(vals, np.zeros(vals.size, bool)) if vals.size else unsafe
    reach = ("reachable" if by_value.any() else
             f"reached only where the model is non-physical ({cfg.model.nonphysical})"
             if unsafe.any() else "not reached")
    res.checked.append(f"{ind.name} computable; limit {ind.limit:g} {reach} in the box")


def _direction_warnings(cfg: Config, model, ind, spec, nominal: dict, value: float) -> list:
    """A warning for each input whose declared wear direction (``degrading``) moves the
    health indicator away from its limit at the nominal point: its wear alone cannot make a
    unit unsafe by that indicator, which is right for some parts (a slipping belt that
    lowers the power drawn) and a sign error for others (detection and the verdicts trust
    the declared direction: a bearing declared ``down`` made its faults "ambiguous")."""
    out = []
    for name, s in cfg.model.inputs.items():
        if s.degrading is None or not np.isfinite(value):
            continue
        sign = 1.0 if s.degrading == "up" else -1.0
        worn = float(np.clip(nominal[name] + sign * 0.1 * (s.high - s.low), s.low, s.high))
        if worn == nominal[name]:
            continue
        try:
            run = model.run({**{cfg.model.inputs[n].variable: v for n, v in nominal.items()},
                             s.variable: worn})
        except SimulationError:
            continue
        v = float(ind(spec.times, run[cfg.indicator_variable][None, :])[0])
        # Towards unsafe is the indicator's sense; a move within rounding says nothing.
        if np.isfinite(v) and ind.sense * (v - value) < -1e-9 * max(abs(value), 1.0):
            out.append(f"{cfg.source}: model.inputs.{name}.degrading: {s.degrading}, but at "
                       f"the nominal point {name} {worn:.4g} {s.units} moves {ind.name} "
                       f"away from its limit ({ind.fmt(value)} -> {ind.fmt(v)}, {ind.rule}): "
                       "its wear alone cannot make a unit unsafe; check the direction")
    return out


# ---------------------------------------------------------------------------------------
# observations

def _check_observations(cfg: Config, path, res: CheckResult) -> None:
    import h5py

    from .observations import check_events, read_observations
    path = Path(path)
    if not path.is_file():
        raise InputDataError(f"{path}: observations file not found")
    obs = read_observations(path, cfg.model.output.name)
    times = cfg.model.output.times.times
    t = np.asarray(obs.time)
    if t.shape != times.shape or not np.allclose(t, times, rtol=0, atol=1e-6):
        raise InputDataError(
            f"{path}: /time: {t.size} samples {t[0]:g}..{t[-1]:g} s, the config's "
            f"model.output.times has {times.size} ({times[0]:g}..{times[-1]:g} s)")
    want = cfg.model.channel_units
    with h5py.File(path, "r") as f:
        for unit in obs.units:
            for ch, arr in obs.units[unit].channels.items():
                if ch not in want:
                    res.warnings.append(f"{path}: /units/{unit}/{ch} is not a channel of "
                                        f"{cfg.source.name} (model.output / model.channels): "
                                        "ignored")
                    continue
                got = f[f"units/{unit}/{ch}"].attrs.get("units", "")
                got = got.decode() if isinstance(got, bytes) else str(got)
                if got and got != want[ch]:
                    where = ("model.output.units" if ch == cfg.model.output.name
                             else f"model.channels.{ch}.units")
                    raise InputDataError(f"{path}: /units/{unit}/{ch} is in {got!r}, the "
                                         f"config's {where} is {want[ch]!r}")
    check_events(cfg, obs)
    # What calibrate and diagnose refuse at once (years, records far outside what the twin
    # gives, a single value far outside anything it could: calibrate's rule, on the FMU's
    # own envelope over the box since a check needs no surrogate): a check that passes must
    # not be followed by a run that stops on its first step.
    from .plausibility import check_observations, output_envelope, refuse_far_values
    check_observations(cfg, obs, path)
    lo, hi = output_envelope(cfg)
    refuse_far_values(obs, path, cfg.model.output.name, cfg.model.output.units,
                      float(np.min(lo)), float(np.max(hi)), "the twin gives over the design box")
    res.checked.append(f"observations {path.name}: {len(obs.units)} units on the config's "
                       "time grid, channels and units, values within the twin's reach")


# ---------------------------------------------------------------------------------------
# artifacts of a workdir

def _check_workdir(cfg: Config, wd: Path, res: CheckResult) -> None:
    if not wd.is_dir():
        raise ArtifactError(f"{wd}: --workdir is not a folder")
    found = [name for name in WORKDIR_ARTIFACTS if (wd / name).is_file()]
    for name in found:
        try:
            _check_artifact(cfg, wd, name, res)
        except TwinmonError as exc:
            res.problems.append(exc)
        except OSError as exc:
            res.problems.append(ArtifactError(f"{wd / name}: unreadable: "
                                              f"{exc.strerror or exc}"))
    res.checked.append(f"workdir {wd}: {len(found)} artifact(s) read"
                       + (f" ({', '.join(found)})" if found else ""))


def _check_artifact(cfg: Config, wd: Path, name: str, res: CheckResult) -> None:
    import importlib

    from .reduce import check_made_for
    kind, stage, made_from = WORKDIR_ARTIFACTS[name]
    path = wd / name
    with artifacts.open_artifact(path, kind):
        pass
    obj = None
    if kind == "simulations":
        from .simulate import read_simulations
        obj = read_simulations(path)
        check_made_for(cfg, path, obj.input_names, obj.time, obj.bounds, "simulate")
    elif kind == "surrogate":
        from .reduce import read_surrogate
        obj = read_surrogate(path)
        check_made_for(cfg, path, obj.input_names, obj.time, obj.bounds, "simulate and reduce")
    elif kind == "posterior":
        from .calibrate import read_posterior
        obj = read_posterior(path, draws=False)
    elif kind == "forecast":
        from .forecast import read_forecast
        obj = read_forecast(path, arrays=False)
    else:
        from .diagnose import read_gap
        read_gap(path)
    names = getattr(obj, "input_names", None)
    if names is not None and list(names) != cfg.model.input_names:
        raise ArtifactError(f"{path}: inputs are {list(names)}, the config's are "
                            f"{cfg.model.input_names}; re-run {stage}")
    prov = artifacts.read_provenance(path)
    sections = importlib.import_module(f".{stage}", __package__).SECTIONS
    if prov.get("config") != cfg.section_yaml(*sections):
        res.warnings.append(f"{path}: made with other {', '.join(sections)} settings than "
                            f"{cfg.source.name}: `twinmon run` will redo {stage}")
    recorded = prov.get("inputs", [])
    for k, parent in enumerate(made_from):
        if not (wd / parent).is_file() or k >= len(recorded):
            continue
        if recorded[k].get("sha256") != artifacts.file_sha256(wd / parent):
            raise ArtifactError(f"{path}: made from another {parent} than the one beside it "
                                f"(fingerprint {recorded[k].get('sha256', '')[:12]} recorded); "
                                f"re-run {stage}")
