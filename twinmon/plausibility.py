"""Plausibility of observations: one check for every stage that reads them.

:func:`~twinmon.observations.read_observations` checks that a file is well formed (shapes,
finite values, increasing years). This module checks that it can be what the config's
machine recorded, before a stage spends minutes on it:

- years are positive whole numbers (a year of service counts from 1), strictly increasing
  and at most :data:`MAX_YEAR` (a fractional year in a float dataset used to be truncated
  without a word);
- the time grid is the config's (``model.output.times``);
- the measured output lies where the twin can put it: within the range of the FMU's output
  over the corners and the centre of the design box (:func:`output_envelope`), widened by
  the range's own width at each sample time plus a tenth of its overall width (measurement
  noise at samples where every run agrees). A record most of whose samples lie outside is
  refused: an output of 1e30, a negated one, one in other units (grams for kilograms), all zeros.

Every stage that reads observations calls :func:`check_observations` (calibrate, diagnose,
backtest, report).
"""
from __future__ import annotations

import itertools
import os

import numpy as np

from .config import Config
from .errors import InputDataError

#: Highest plausible year of service.
MAX_YEAR = 1000

#: Fraction of a record's samples that may lie outside the envelope (noise, a start-up
#: delayed a sample): above it the record is refused.
OUTSIDE_LIMIT = 0.5

#: Box corners used up to this many inputs; above it, the centre and each face's centre.
MAX_CORNER_INPUTS = 6


def check_observations(cfg: Config, obs, path: str | os.PathLike | None = None) -> None:
    """Refuse observations that cannot be the config's machine's record.

    Parameters
    ----------
    cfg : Config
    obs : Observations
        As read by :func:`~twinmon.observations.read_observations`.
    path : path-like, optional
        The file (for the message and for the years' stored type); defaults to ``obs.path``.

    Raises
    ------
    InputDataError
        Naming the file, the place and the value.
    """
    path = path if path is not None else obs.path
    _check_years(obs, path)
    expected = cfg.model.output.times.times
    if obs.time.shape != expected.shape or not np.allclose(obs.time, expected):
        raise InputDataError(f"{path}: /time: time grid ({obs.time[0]:g}..{obs.time[-1]:g} s, "
                             f"{obs.time.size} samples) is not the config's output grid "
                             f"model.output.times ({expected[0]:g}..{expected[-1]:g} s, "
                             f"{expected.size} samples)")
    lo, hi = output_envelope(cfg)
    width = hi - lo
    slack = width + 0.1 * float(np.max(hi) - np.min(lo))
    low, high = lo - slack, hi + slack
    name = obs.output or cfg.model.output.name
    units = cfg.model.output.units
    _check_noise(obs, path, name, float(np.max(hi) - np.min(lo)), units)
    for unit in obs.units:
        y = obs.output_of(unit)
        outside = (y < low) | (y > high)
        share = outside.mean(axis=1)
        if np.any(share > OUTSIDE_LIMIT):
            k = int(np.argmax(share))
            year = int(obs.units[unit].years[k])
            j = int(np.flatnonzero(outside[k])[len(np.flatnonzero(outside[k])) // 2])
            raise InputDataError(
                f"{path}: /units/{unit}/{name} year {year}: {100 * share[k]:.0f} % of the "
                f"samples lie outside what the twin gives over the design box (e.g. "
                f"{y[k, j]:.4g} {units} at t = {obs.time[j]:g} s, plausible "
                f"{low[j]:.4g}..{high[j]:.4g}); wrong units, sign or channel?")


def _check_noise(obs, path, name: str, span: float, units: str) -> None:
    """A recorded noise level must be a positive finite number; the output's at most the
    span of the output over the design box (1e300 overflowed the likelihood)."""
    for unit, u in obs.units.items():
        for ch, std in (u.noise_std or {}).items():
            try:
                value = float(std)
            except (TypeError, ValueError):
                value = float("nan")
            limit = span if ch == name and np.isfinite(span) and span > 0 else np.inf
            if not (np.isfinite(value) and 0 < value <= limit):
                what = (f"a positive number at most {limit:.4g} {units} (the output's span "
                        "over the design box)" if np.isfinite(limit) else
                        "a positive finite number")
                raise InputDataError(f"{path}: /units/{unit} attribute noise_std: {ch} is "
                                     f"{std!r}, expected {what}")


def _check_years(obs, path) -> None:
    import h5py
    stored = {}
    try:
        with h5py.File(path, "r") as f:
            for unit in obs.units:
                ds = f.get(f"units/{unit}/years")
                if ds is not None:
                    stored[unit] = np.asarray(ds[()])
    except (OSError, TypeError):
        stored = {}
    for unit, u in obs.units.items():
        raw = stored.get(unit, np.asarray(u.years))
        where = f"{path}: /units/{unit}/years"
        if raw.dtype.kind == "f":
            frac = np.flatnonzero(raw != np.round(raw))
            if frac.size:
                raise InputDataError(f"{where}[{frac[0]}] = {raw[frac[0]]!r} is not a whole "
                                     "year of service")
        years = np.asarray(u.years)
        bad = np.flatnonzero((years < 1) | (years > MAX_YEAR))
        if bad.size:
            raise InputDataError(f"{where}[{bad[0]}] = {years[bad[0]]}: years of service count "
                                 f"from 1 and are at most {MAX_YEAR}")
        if np.any(np.diff(years) <= 0):
            k = int(np.flatnonzero(np.diff(years) <= 0)[0]) + 1
            raise InputDataError(f"{where}[{k}] = {years[k]} is not after {years[k - 1]}")


def output_envelope(cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest output of the FMU over the design box, per sample time.

    Runs the FMU at the box's corners and centre (at most ``2**d + 1`` runs; above
    :data:`MAX_CORNER_INPUTS` inputs, the centre and the centre of each face).

    Returns
    -------
    lo, hi : ndarray, shape [n_t]
        In the output's units. Failed runs are left out; if every run fails, the envelope is
        unbounded (nothing refused here: the stage reports the FMU's failure itself).
    """
    key = (str(cfg.model.fmu), cfg.model.fmi_type, cfg.model.output.variable,
           tuple((s.variable, s.low, s.high) for s in cfg.model.inputs.values()),
           tuple(sorted(cfg.model.fixed.items())),
           tuple(np.asarray(cfg.model.output.times.times).tolist()))
    return _envelope(key, cfg)


#: Envelopes computed in this process, by FMU, box and grid.
_cache: dict = {}


def _envelope(key, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    if key in _cache:
        return _cache[key]
    from .simulate import as_parameters, run_batch, spec_for
    specs = list(cfg.model.inputs.values())
    low = np.array([s.low for s in specs])
    high = np.array([s.high for s in specs])
    mid = (low + high) / 2
    if len(specs) <= MAX_CORNER_INPUTS:
        points = [np.array(c) for c in itertools.product(*zip(low, high))]
    else:
        points = []
        for j in range(len(specs)):
            for v in (low[j], high[j]):
                p = mid.copy()
                p[j] = v
                points.append(p)
    X = np.vstack(points + [mid])
    spec = spec_for(cfg, outputs=[cfg.model.output.variable])
    batch = run_batch(spec, as_parameters(cfg, X))
    Y = batch.outputs[cfg.model.output.variable][batch.ok]
    n_t = len(spec.times)
    if Y.size == 0:
        out = (np.full(n_t, -np.inf), np.full(n_t, np.inf))
    else:
        out = (Y.min(axis=0), Y.max(axis=0))
    _cache[key] = out
    return out


#: Observed values beyond the twin's range by more than this many times its width are taken
#: for a unit or scale mistake (or a broken sensor), not for a degraded machine.
RANGE_FACTOR = 1.0


def refuse_far_values(obs, path, name: str, units: str, lo: float, hi: float,
                      what: str) -> None:
    """Refuse a single value of channel ``name`` further than :data:`RANGE_FACTOR` times the
    range ``lo``..``hi`` (``what`` produced it, for the message) from it.

    Raises
    ------
    InputDataError
        Naming the file, unit, year, time and value."""
    width = max(hi - lo, abs(hi), 1e-300)
    low, high = lo - RANGE_FACTOR * width, hi + RANGE_FACTOR * width
    for unit in obs.units:
        y = obs.units[unit].channels[name]
        with np.errstate(invalid="ignore"):
            bad = (y < low) | (y > high)
        if bad.any():
            k, j = np.argwhere(bad)[0]
            raise InputDataError(
                f"{path}: /units/{unit}/{name} year {obs.units[unit].years[k]} at "
                f"t = {obs.time[j]:g} s is {y[k, j]:g} {units}, far outside anything {what} "
                f"({lo:.4g} to {hi:.4g} {units}); check the units and the channel")
