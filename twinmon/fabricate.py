"""Stage ``fabricate``: synthetic plant data, as the paper made its own.

Each unit follows true yearly trajectories of the degradation inputs (linear trend, optional
curvature, year-to-year jitter); optionally an unmodelled effect (an FMU parameter outside the
calibrated inputs) is switched on from an onset year, or an additive disturbance outside the
candidate list is added. A maintenance event (``events: [{year, component}]``) puts
that component's inputs back on their trajectory from its ``start``, as a new part, and is
recorded in both files. Every unit-year is simulated through the real FMU and measurement
noise is added. The observations file carries only what a plant would record; the truth file
(``twinmon.truth/1``) holds the true inputs and effects and is read by evaluation only.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from . import artifacts
from .config import Config, Disturbance, TrajectorySpec
from .errors import ArtifactError, ConfigError, SimulationError
from .observations import (Event, Observations, UnitObservations, put_events, read_events,
                           write_observations)
from .simulate import run_batch, spec_for


@dataclass
class FabricateSummary:
    units: int
    years: int
    observations: str
    truth: str

    def as_dict(self) -> dict:
        return {"units": self.units, "years": self.years, "observations": self.observations,
                "truth": self.truth}


def true_inputs(cfg: Config, rng: np.random.Generator,
                years: np.ndarray | dict | None = None) -> dict[str, dict[str, np.ndarray]]:
    """True degradation inputs per unit and year.

    Parameters
    ----------
    years : ndarray of int, shape [n], or dict unit -> ndarray, optional
        Years of service (1 = the first), the same for every unit or each unit's own;
        default ``1 .. fabricate.years``.

    Returns
    -------
    dict unit -> dict input name -> ndarray, shape [n]
        Values in each input's units.

    Notes
    -----
    The trajectory is a function of the part's age, ``year - 1`` for the original part and
    ``year - event year`` after a replacement of its component (recorded or not), so a
    replaced part starts again from ``start`` and ages as the first did
    (:func:`trajectory_path`). The jitter draws do not depend on the events nor on the
    trajectory's shape: one draw per unit, input and year, in that order.
    """
    fab = cfg.fabricate
    out = {}
    for unit, spec in fab.units.items():
        yrs = years.get(unit) if isinstance(years, dict) else years
        year = (np.arange(fab.years, dtype=float) if yrs is None
                else np.asarray(yrs, float) - 1)
        vals = {}
        for name, ispec in cfg.model.inputs.items():
            # (Every input has a trajectory and no other: checked as the config loads.)
            tr = spec.trajectories[name]
            installed = np.zeros_like(year)
            for ev in sorted(spec.events, key=lambda e: e.year):
                if ev.component == (ispec.component or name):
                    installed = np.where(year >= ev.year - 1, ev.year - 1.0, installed)
            det = np.empty_like(year)
            for inst in np.unique(installed):
                on = installed == inst
                det[on] = trajectory_path(tr, year[on] - inst, inst)
            vals[name] = det + tr.jitter * rng.standard_normal(year.size)
        out[unit] = vals
    return out


def trajectory_path(tr: TrajectorySpec, age: np.ndarray, installed: float = 0.0,
                    n_changes: int | None = None) -> np.ndarray:
    """A trajectory without its jitter.

    Parameters
    ----------
    tr : TrajectorySpec
    age : ndarray, shape [n]
        Ages of the part, years (0 in its first year of service).
    installed : float
        Years of service before the part was fitted (0: the original part). A change dated
        before then happened to an older part and is left out.
    n_changes : int, optional
        Apply only the first ``n_changes`` changes (all by default).

    Returns
    -------
    ndarray, shape [n]
        ``start + slope * g(age) + curvature * age**2`` with ``g(a) = a`` (linear) or
        ``expm1(growth * a) / growth`` (exponential), then each change: from its year the
        value jumps by ``size`` and, with a ``slope``, goes on from the value it had reached
        at that rate.
    """
    age = np.asarray(age, float)
    g = age if tr.growth == 0 else np.expm1(tr.growth * age) / tr.growth
    out = tr.start + tr.slope * g + tr.curvature * age ** 2
    changes = tr.changes if n_changes is None else tr.changes[:n_changes]
    for k, c in enumerate(changes):
        at = c.year - 1 - installed
        if at < 0:
            continue
        after = age >= at
        if c.slope is not None:
            ref = float(trajectory_path(tr, np.array([at]), installed, k)[0])
            out = np.where(after, ref + c.slope * (age - at), out)
        out = np.where(after, out + c.size, out)
    return out


def recorded_years(cfg: Config, unit: str) -> np.ndarray:
    """The years of ``unit`` the plant recorded, shape [n_y]: ``1 .. last_year`` without
    its ``missing_years``."""
    fab = cfg.fabricate
    spec = fab.units[unit]
    end = spec.last_year or fab.years
    return np.array([y for y in range(1, end + 1) if y not in spec.missing_years])


def future_inputs(cfg: Config) -> tuple[dict[str, np.ndarray], dict[str, dict[str, np.ndarray]]]:
    """The units' true inputs in the ``forecast.horizon`` years after each unit's record,
    jitter included: what a unit's inputs will really be, the truth a forecast of the unit's
    *state* is scored against (a line through the recorded true values has no year-to-year
    variation, so intervals that rightly carry it look too wide against it).

    Drawn from their own stream (``fabricate.seed`` and 1), so the observations and the
    recorded years' truth are the same as without them.

    Returns
    -------
    years : dict unit -> ndarray of int, shape [h]
    inputs : dict unit -> dict input name -> ndarray, shape [h]
    """
    fab = cfg.fabricate
    years = {u: int(recorded_years(cfg, u)[-1]) + np.arange(1, cfg.forecast.horizon + 1)
             for u in fab.units}
    return years, true_inputs(cfg, np.random.default_rng([fab.seed, 1]), years)


def disturbance_signal(d: Disturbance, time: np.ndarray) -> np.ndarray:
    """Additive output disturbance (output units) at the sample times, shape [n_t]."""
    if d.shape == "sine":
        return d.amplitude * np.sin(2 * np.pi * time / d.period)
    return d.amplitude * np.exp(-((time - d.period) / 4.0) ** 2)


def fabricate(cfg: Config, observations: str | os.PathLike, truth: str | os.PathLike,
              executor=None) -> FabricateSummary:
    """Simulate the fleet of ``cfg.fabricate`` and write observations and truth files.

    Parameters
    ----------
    cfg : Config
        Must have a ``fabricate`` section.
    observations, truth : path-like
        Files to write (``twinmon.observations/1`` and ``twinmon.truth/1``).
    """
    fab = cfg.fabricate
    if fab is None:
        raise ConfigError(f"{cfg.source}: fabricate: section is missing")
    rng = np.random.default_rng(fab.seed)
    inputs = true_inputs(cfg, rng)
    from .simulate import check_model
    check_model(cfg)
    channels = list(cfg.model.channels) if fab.record_channels else []
    out_var, out_name = cfg.model.output.variable, cfg.model.output.name
    outputs = list(dict.fromkeys([out_var, *fab.truth_variables, *channels]))
    spec = spec_for(cfg, outputs=outputs)
    time = spec.times
    years = np.arange(1, fab.years + 1)

    # One batch for the whole fleet: the FMU defaults stand for "effect off" before onset.
    params, keys = [], []
    for unit, spec_u in fab.units.items():
        for k, yr in enumerate(years):
            p = {cfg.model.inputs[n].variable: float(v[k]) for n, v in inputs[unit].items()}
            for var, eff in spec_u.effects.items():
                if yr >= eff.onset:
                    p[var] = eff.value
            params.append(p)
            keys.append((unit, k))
    batch = run_batch(spec, params, executor)
    if not batch.ok.all():
        i = int(np.flatnonzero(~batch.ok)[0])
        unit, k = keys[i]
        raise SimulationError(f"{cfg.source}: fabricate.units.{unit}: year {years[k]} failed "
                              f"to simulate: {batch.messages[i]}")

    # Noise levels: the output's in its units (noise_std) or relative to the range the
    # healthy unit's output spans over the record; other channels relative to their own
    # healthy range (so 1 % means the same thing on every channel).
    healthy = run_batch(spec, [{s.variable: s.nominal for s in cfg.model.inputs.values()}])
    if not healthy.ok.all():
        raise SimulationError(f"{cfg.source}: the healthy unit (every input at its nominal "
                              f"value) failed to simulate: {healthy.messages[0]}")

    def healthy_range(var: str) -> float:
        x = healthy.outputs[var][0]
        return float(x.max() - x.min()) or float(abs(x).max())

    out_std = (fab.noise_std if fab.noise_std is not None
                else fab.noise_fraction * healthy_range(out_var))
    ch_std = {c: fab.channel_noise_fraction * healthy_range(c) for c in channels}

    obs_units, truth_rows = {}, {}
    for unit, spec_u in fab.units.items():
        rows = [i for i, key in enumerate(keys) if key[0] == unit]
        clean = batch.outputs[out_var][rows]
        if spec_u.disturbance is not None:
            d = spec_u.disturbance
            clean = clean + np.where(years[:, None] >= d.onset,
                                     disturbance_signal(d, time)[None, :], 0.0)
        chans = {out_name: clean + out_std * rng.standard_normal(clean.shape)}
        for c in channels:
            x = batch.outputs[c][rows]
            chans[c] = x + ch_std[c] * rng.standard_normal(x.shape)
        # Every year is simulated and its noise drawn (the streams stay the same), then the
        # years the plant did not record are left out and lost samples blanked.
        kept = np.isin(years, recorded_years(cfg, unit))
        chans = {c: x[kept] for c, x in chans.items()}
        if spec_u.nan_fraction > 0:
            lost = (np.random.default_rng([fab.seed, 2, list(fab.units).index(unit)])
                    .random(chans[out_name].shape) < spec_u.nan_fraction)
            chans[out_name] = np.where(lost, np.nan, chans[out_name])
        # Noise-free data (noise_fraction 0) record no level: zero is not a usable std.
        noise = ({k: v for k, v in {out_name: out_std, **ch_std}.items() if v > 0}
                 if fab.record_noise else {})
        obs_units[unit] = UnitObservations(years[kept], chans, noise, unit_events(spec_u))
        truth_rows[unit] = ([r for r, k in zip(rows, kept) if k], clean[kept], kept)

    section = cfg.section_yaml("model", "fabricate")
    fmu_inputs = [spec.fmu]
    write_observations(observations,
                       Observations(time, obs_units, Path(observations), out_name),
                       config=section, inputs=fmu_inputs, seed=fab.seed,
                       units=cfg.model.channel_units)
    _write_truth(truth, cfg, inputs, truth_rows, batch, spec, time, years, out_std,
                 section, fmu_inputs, future_inputs(cfg))
    return FabricateSummary(len(fab.units), fab.years, str(observations), str(truth))


def unit_events(spec_u, recorded_only: bool = True) -> list[Event]:
    """A fabricated unit's events as the plant records them (``recorded_only``) or as they
    happened, sorted by year."""
    return sorted((Event(e.year, e.component, e.action, e.note) for e in spec_u.events
                   if e.recorded or not recorded_only), key=lambda e: e.year)


def _write_truth(path, cfg, inputs, truth_rows, batch, spec, time, years, out_std, section,
                 fmu_inputs, future) -> None:
    fab = cfg.fabricate
    future_years, future = future
    with artifacts.write_artifact(path, "truth", config=section, inputs=fmu_inputs,
                                  seed=fab.seed) as f:
        artifacts.put(f, "time", time, "s", "sample times")
        f.attrs["noise_std"] = out_std
        for unit, spec_u in fab.units.items():
            rows, clean, kept = truth_rows[unit]
            g = f.create_group(f"units/{unit}")
            artifacts.put(g, "years", years[kept], "year", "year of service")
            for name, v in inputs[unit].items():
                artifacts.put(g, f"inputs/{name}", v[kept], cfg.model.inputs[name].units,
                              f"true {name} ({cfg.model.inputs[name].variable}) per year")
            for var, eff in spec_u.effects.items():
                on = years[kept] >= eff.onset
                spec = cfg.model.effects.get(var)
                artifacts.put(g, f"effects/{var}", np.where(on, eff.value, np.nan),
                              spec.units if spec is not None else "",
                              f"injected value of {var} per year; NaN = off (FMU default)")
                g[f"effects/{var}"].attrs["onset"] = eff.onset
            if spec_u.disturbance is not None:
                d = spec_u.disturbance
                g.attrs["disturbance"] = artifacts.json_attr(
                    {"amplitude": d.amplitude, "period": d.period, "onset": d.onset,
                     "shape": d.shape})
            artifacts.put(g, "future/years", future_years[unit], "year",
                          "years after the record (forecast.horizon of them)")
            for name, v in future[unit].items():
                artifacts.put(g, f"future/inputs/{name}", v, cfg.model.inputs[name].units,
                              f"true {name} in the years after the record, jitter included")
            if spec_u.events:
                put_events(g, unit_events(spec_u, recorded_only=False))
                hidden = [{"year": e.year, "component": e.component}
                          for e in spec_u.events if not e.recorded]
                if hidden:
                    g.attrs["unrecorded_events"] = artifacts.json_attr(hidden)
            out = cfg.model.output
            artifacts.put(g, f"{out.name}_clean", clean, out.units,
                          f"noise-free {out.label} (with effects and disturbance)")
            for var in fab.truth_variables:
                artifacts.put(g, f"clean/{var}", batch.outputs[var][rows],
                              cfg.model.variable_words(var)[1], f"noise-free {var}")


@dataclass
class Truth:
    """A loaded truth file: per unit, years [n_y], inputs {name: [n_y]}, effects {var: [n_y]},
    maintenance events (sorted by year; ``[]`` when none), and the true inputs of the years
    after the record, ``future_years`` [h] and ``future_inputs`` {name: [h]} (absent from
    units of truth files written before they were recorded)."""

    years: dict[str, np.ndarray]
    inputs: dict[str, dict[str, np.ndarray]]
    effects: dict[str, dict[str, np.ndarray]]
    disturbance: dict[str, dict]
    noise_std: float
    events: dict[str, list[Event]] = field(default_factory=dict)
    future_years: dict[str, np.ndarray] = field(default_factory=dict)
    future_inputs: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    #: Per unit, the events the plant did not record, ``[(year, component)]``.
    unrecorded: dict[str, list[tuple[int, str]]] = field(default_factory=dict)


def read_truth(path: str | os.PathLike, units: Optional[Sequence[str]] = None) -> Truth:
    """Load a ``twinmon.truth/1`` file; with ``units``, the units of it among them only, in
    the file's order (a report shows the truth of the few units it draws: a 1000-unit
    fleet's whole truth took 1.4 s to read)."""
    import json
    path = Path(path)
    with artifacts.open_artifact(path, "truth") as f:
        years, inputs, effects, dist, events, hidden = {}, {}, {}, {}, {}, {}
        fut_years, fut_inputs = {}, {}
        every = f["units"]
        wanted = None if units is None else set(units)
        for unit in every:
            if wanted is not None and unit not in wanted:
                continue
            g = every[unit]
            if "future" in g:
                fut_years[unit] = artifacts.get(g, "future/years", path)
                if "inputs" not in g["future"]:
                    raise ArtifactError(f"{path}: group {g.name}/future/inputs is missing")
                fut_inputs[unit] = {k: v[()] for k, v in g["future/inputs"].items()}
                for k, v in fut_inputs[unit].items():
                    if v.shape != fut_years[unit].shape:
                        raise ArtifactError(
                            f"{path}: {g.name}/future/inputs/{k} has shape {v.shape}, "
                            f"{g.name}/future/years {fut_years[unit].shape}")
            years[unit] = artifacts.get(g, "years", path)
            events[unit] = read_events(g, path)
            inputs[unit] = {k: v[()] for k, v in g["inputs"].items()}
            effects[unit] = {k: v[()] for k, v in g["effects"].items()} if "effects" in g else {}
            if "disturbance" in g.attrs:
                dist[unit] = json.loads(g.attrs["disturbance"])
            hidden[unit] = [(int(e["year"]), str(e["component"]))
                            for e in json.loads(g.attrs.get("unrecorded_events", "[]"))]
        return Truth(years, inputs, effects, dist, float(f.attrs["noise_std"]), events,
                     fut_years, fut_inputs, hidden)
