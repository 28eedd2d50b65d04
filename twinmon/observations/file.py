"""The observations file (``twinmon.observations/1``): :func:`write_observations`,
:func:`read_observations` and :func:`validate_observations`.

:func:`read_observations` is the one function through which every stage reads
observations; it validates shapes and values (:func:`validate_observations`) so a stage
never meets a malformed array.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .. import artifacts
from ..errors import ArtifactError, InputDataError
from .events import _validate_events, put_events, read_events
from .records import EVENTS, Observations, UnitObservations



def write_observations(path: str | os.PathLike, obs: Observations, *, config: str = "",
                       inputs: Sequence[str | os.PathLike] = (), seed: int | None = None,
                       units: Mapping[str, str] | None = None) -> None:
    """Write observations atomically (validated first, so a bad array is never written).

    Parameters
    ----------
    units : mapping of channel name to units, optional
        Recorded as each dataset's ``units`` attribute (from the config's channels).
    """
    validate_observations(obs)
    units = dict(units or {})
    with artifacts.write_artifact(path, "observations", config=config, inputs=inputs,
                                  seed=seed) as f:
        if obs.output:
            f.attrs["output"] = obs.output
        artifacts.put(f, "time", obs.time, "s", "time since start of the transient")
        for name, u in obs.units.items():
            g = f.create_group(f"units/{name}")
            artifacts.put(g, "years", np.asarray(u.years, dtype=np.int64), "year",
                          "observation year (1 = first year of service)")
            for ch, arr in u.channels.items():
                artifacts.put(g, ch, np.asarray(arr, dtype=np.float64),
                              units.get(ch, ""), f"measured {ch}; NaN = missing sample")
            if u.noise_std:
                g.attrs["noise_std"] = json.dumps(u.noise_std)
            if u.events:
                put_events(g, u.events)


def read_observations(path: str | os.PathLike, output: str | None = None) -> Observations:
    """Read and validate an observations file.

    Parameters
    ----------
    path : path-like
    output : str, optional
        Name of the measured output's channel (``model.output.name``); every unit must hold
        it. Defaults to the name the file records.

    Raises
    ------
    ArtifactError
        Wrong schema or missing datasets.
    InputDataError
        Wrong shapes, infinite values, unsorted or duplicate years, a unit with no output,
        a malformed ``noise_std`` attribute.
    """
    path = Path(path)
    with artifacts.open_artifact(path, "observations") as f:
        recorded = f.attrs.get("output")
        recorded = recorded.decode() if isinstance(recorded, bytes) else recorded
        output = output or recorded or ""
        time = artifacts.get(f, "time", path).astype(float)
        if "units" not in f or len(f["units"]) == 0:
            raise ArtifactError(f"{path}: group /units is missing or empty")
        units = {}
        for name, g in f["units"].items():
            if not hasattr(g, "items"):
                raise ArtifactError(f"{path}: /units/{name} is a dataset, expected a group")
            years = artifacts.get(g, "years", path).astype(np.int64)
            channels = {}
            for ch, ds in g.items():
                if ch in ("years", EVENTS):
                    continue
                if not hasattr(ds, "dtype") or ds.dtype.kind not in "fiu":
                    raise InputDataError(f"{path}: /units/{name}/{ch} is not a numeric array")
                channels[ch] = np.asarray(ds[()], dtype=float)
            if output and output not in channels:
                have = ", ".join(sorted(channels)) or "none"
                raise ArtifactError(f"{path}: dataset /units/{name}/{output} (the config's "
                                    f"model.output.name) is missing; channels here: {have}")
            noise = _noise_attr(g.attrs.get("noise_std"), output, path, name)
            events = read_events(g, path) if EVENTS in g else []
            units[name] = UnitObservations(years, channels, noise, events)
    obs = Observations(time, units, path, output)
    validate_observations(obs)
    return obs


def _noise_attr(raw, output: str, path: Path, unit: str) -> dict:
    """``noise_std`` as written by twinmon (JSON mapping) or by hand (a bare number: the
    output's noise)."""
    if raw is None:
        return {}
    if isinstance(raw, bytes):
        raw = raw.decode("utf-8", "replace")
    value = raw
    if isinstance(raw, str):
        try:
            value = json.loads(raw)
        except ValueError:
            raise InputDataError(f"{path}: /units/{unit} attribute noise_std is {raw!r}, "
                                 "expected a number or a JSON mapping {channel: std}") from None
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.item()
    if isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
        if not output:
            raise InputDataError(f"{path}: /units/{unit} attribute noise_std is a bare number "
                                 f"({value!r}) but the output channel is not known")
        return {output: float(value)}
    if isinstance(value, dict):
        return value
    raise InputDataError(f"{path}: /units/{unit} attribute noise_std is {value!r}, expected a "
                         "number or a mapping {channel: std}")


def validate_observations(obs: Observations) -> None:
    """Check shapes and values; raise :class:`InputDataError` naming file, place and value."""
    p = obs.path
    t = np.asarray(obs.time)
    if t.ndim != 1 or t.size == 0:
        raise InputDataError(f"{p}: /time must be a non-empty 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputDataError(f"{p}: /time[{bad}] is {t[bad]}, expected a finite time")
    if np.any(np.diff(t) <= 0):
        bad = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise InputDataError(f"{p}: /time[{bad}] = {t[bad]} is not after {t[bad - 1]}")
    for name, u in obs.units.items():
        y = np.asarray(u.years)
        if y.ndim != 1 or y.size == 0:
            raise InputDataError(f"{p}: /units/{name}/years must be a non-empty 1-D array, "
                                 f"got shape {y.shape}")
        if np.any(np.diff(y) <= 0):
            bad = int(np.flatnonzero(np.diff(y) <= 0)[0]) + 1
            raise InputDataError(f"{p}: /units/{name}/years[{bad}] = {y[bad]} is not after "
                                 f"{y[bad - 1]} (years must increase)")
        for ch, arr in u.channels.items():
            if arr.shape != (y.size, t.size):
                raise InputDataError(f"{p}: /units/{name}/{ch} has shape {arr.shape}, "
                                     f"expected ({y.size}, {t.size}) = (years, time)")
            if np.any(np.isinf(arr)):
                i, j = np.argwhere(np.isinf(arr))[0]
                raise InputDataError(f"{p}: /units/{name}/{ch}[{i}, {j}] is {arr[i, j]}, "
                                     "expected a finite value or NaN for missing")
        out = u.channels.get(obs.output) if obs.output else None
        if out is not None and np.all(np.isnan(out), axis=1).any():
            i = int(np.flatnonzero(np.all(np.isnan(out), axis=1))[0])
            raise InputDataError(f"{p}: /units/{name}/{obs.output} year {y[i]} has no sample")
        for ch, s in u.noise_std.items():
            if not (isinstance(s, (int, float)) and not isinstance(s, bool)
                    and math.isfinite(s) and s > 0):
                raise InputDataError(f"{p}: /units/{name} attribute noise_std[{ch!r}] is {s!r}, "
                                     "expected a positive number")
        if EVENTS in u.channels:
            raise InputDataError(f"{p}: /units/{name}: a channel may not be called {EVENTS!r} "
                                 "(the name of the unit's maintenance events)")
        _validate_events(u.events, y, f"{p}: /units/{name}/{EVENTS}")
