"""The observations format (``twinmon.observations/1``) and the CSV importer.

Layout (DESIGN.md section 3)::

    /time                    float64 [n_t]       seconds since start
    /units/<unit>/years      int64   [n_y]       observation year (1 = first year of service)
    /units/<unit>/m_flow     float64 [n_y, n_t]  measured mass flow (kg/s); NaN = missing
    /units/<unit>/<channel>  float64 [n_y, n_t]  optional further channels
    /units/<unit>.attrs      noise_std (JSON {channel: std}), optional

A user's own measurements reach twinmon through :func:`import_csv`; everything downstream
reads :func:`read_observations`, which validates shapes and values so a stage never meets a
malformed array.
"""
from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from . import artifacts
from .errors import ArtifactError, InputDataError

FLOW = "m_flow"

CHANNEL_UNITS = {FLOW: "kg/s", "motor.w": "rad/s", "pump.dp": "Pa", "motor.I": "A",
                 "pump.m_flow": "kg/s"}


@dataclass
class UnitObservations:
    """One unit's yearly start-up records.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    channels : dict of str to ndarray, each shape [n_y, n_t]
        ``"m_flow"`` (kg/s) always; optional ``"motor.w"`` (rad/s), ``"pump.dp"`` (Pa),
        ``"motor.I"`` (A).
    noise_std : dict of str to float
        Known measurement noise standard deviation per channel (channel units); may be empty.
    """

    years: np.ndarray
    channels: dict[str, np.ndarray]
    noise_std: dict[str, float] = field(default_factory=dict)

    @property
    def m_flow(self) -> np.ndarray:
        return self.channels[FLOW]


@dataclass
class Observations:
    time: np.ndarray
    units: dict[str, UnitObservations]
    path: Path = Path("<memory>")


def write_observations(path: str | os.PathLike, obs: Observations, *, config: str = "",
                       inputs: Sequence[str | os.PathLike] = (), seed: int | None = None) -> None:
    """Write observations atomically (validated first, so a bad array is never written)."""
    validate_observations(obs)
    with artifacts.write_artifact(path, "observations", config=config, inputs=inputs,
                                  seed=seed) as f:
        artifacts.put(f, "time", obs.time, "s", "time since start of the transient")
        for name, u in obs.units.items():
            g = f.create_group(f"units/{name}")
            artifacts.put(g, "years", np.asarray(u.years, dtype=np.int64), "year",
                          "observation year (1 = first year of service)")
            for ch, arr in u.channels.items():
                artifacts.put(g, ch, np.asarray(arr, dtype=np.float64),
                              CHANNEL_UNITS.get(ch, ""), f"measured {ch}; NaN = missing sample")
            if u.noise_std:
                g.attrs["noise_std"] = json.dumps(u.noise_std)


def read_observations(path: str | os.PathLike) -> Observations:
    """Read and validate an observations file.

    Raises
    ------
    ArtifactError
        Wrong schema or missing datasets.
    InputDataError
        Wrong shapes, infinite values, unsorted or duplicate years, a unit with no flow.
    """
    path = Path(path)
    with artifacts.open_artifact(path, "observations") as f:
        time = artifacts.get(f, "time", path).astype(float)
        if "units" not in f or len(f["units"]) == 0:
            raise ArtifactError(f"{path}: group /units is missing or empty")
        units = {}
        for name, g in f["units"].items():
            years = artifacts.get(g, "years", path).astype(np.int64)
            channels = {}
            for ch, ds in g.items():
                if ch != "years":
                    channels[ch] = np.asarray(ds[()], dtype=float)
            if FLOW not in channels:
                raise ArtifactError(f"{path}: dataset /units/{name}/{FLOW} is missing")
            raw = g.attrs.get("noise_std")
            noise = json.loads(raw) if raw is not None else {}
            units[name] = UnitObservations(years, channels, noise)
    obs = Observations(time, units, path)
    validate_observations(obs)
    return obs


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
        if np.all(np.isnan(u.m_flow), axis=1).any():
            i = int(np.flatnonzero(np.all(np.isnan(u.m_flow), axis=1))[0])
            raise InputDataError(f"{p}: /units/{name}/{FLOW} year {y[i]} has no sample")
        for ch, s in u.noise_std.items():
            if not (isinstance(s, (int, float)) and math.isfinite(s) and s > 0):
                raise InputDataError(f"{p}: /units/{name} attribute noise_std[{ch!r}] is {s!r}, "
                                     "expected a positive number")


# ---------------------------------------------------------------------------------------
# CSV import
# ---------------------------------------------------------------------------------------
REQUIRED_COLUMNS = ("unit", "year", "time", FLOW)


def import_csv(csv_path: str | os.PathLike, out_path: str | os.PathLike,
               noise_std: float | None = None) -> Observations:
    """Convert long-form CSV measurements into an observations artifact.

    The CSV has a header with at least ``unit,year,time,m_flow`` and optionally further
    channel columns (``motor.w``, ``pump.dp``, ``motor.I``); one row per sample. Every
    (unit, year) must share one time grid. An empty cell is a missing sample (NaN).

    Parameters
    ----------
    csv_path : path-like
        The CSV file.
    out_path : path-like
        The observations HDF5 file to write.
    noise_std : float, optional
        Known flow noise standard deviation (kg/s), recorded for every unit.

    Raises
    ------
    InputDataError
        Missing columns, non-numeric values, duplicate rows, unequal time grids; the
        message names the file and line.
    """
    csv_path = Path(csv_path)
    if not csv_path.exists():
        raise InputDataError(f"{csv_path}: file not found")
    with open(csv_path, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputDataError(f"{csv_path}: line 1: file is empty, expected a header "
                                 f"{','.join(REQUIRED_COLUMNS)}") from None
        missing = [c for c in REQUIRED_COLUMNS if c not in header]
        if missing:
            raise InputDataError(f"{csv_path}: line 1: missing column {missing[0]!r} "
                                 f"(header is {','.join(header)})")
        if len(set(header)) != len(header):
            dup = next(h for h in header if header.count(h) > 1)
            raise InputDataError(f"{csv_path}: line 1: column {dup!r} appears twice")
        channels = [h for h in header if h not in ("unit", "year", "time")]
        col = {h: i for i, h in enumerate(header)}
        rows: dict[tuple[str, int], dict[float, tuple[int, list[float]]]] = {}
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputDataError(f"{csv_path}: line {lineno}: {len(row)} fields, "
                                     f"expected {len(header)}")
            unit = row[col["unit"]].strip()
            if not unit:
                raise InputDataError(f"{csv_path}: line {lineno}: column 'unit' is empty")
            year = _parse_int(row[col["year"]], csv_path, lineno, "year")
            time = _parse_float(row[col["time"]], csv_path, lineno, "time", allow_empty=False)
            values = [_parse_float(row[col[c]], csv_path, lineno, c, allow_empty=True)
                      for c in channels]
            per = rows.setdefault((unit, year), {})
            if time in per:
                raise InputDataError(f"{csv_path}: line {lineno}: duplicate row for unit "
                                     f"{unit!r} year {year} time {time:g} (first on line "
                                     f"{per[time][0]})")
            per[time] = (lineno, values)
    if not rows:
        raise InputDataError(f"{csv_path}: no data rows after the header")
    grids = {key: sorted(per) for key, per in rows.items()}
    ref_key = next(iter(grids))
    ref = grids[ref_key]
    for key, grid in grids.items():
        if grid != ref:
            extra = sorted(set(grid) ^ set(ref))[0]
            line = rows[key][extra][0] if extra in rows[key] else rows[ref_key][extra][0]
            raise InputDataError(
                f"{csv_path}: line {line}: unit {key[0]!r} year {key[1]} has a time grid "
                f"unlike unit {ref_key[0]!r} year {ref_key[1]} (time {extra:g} in only one)")
    time = np.array(ref)
    units = {}
    for unit in dict.fromkeys(k[0] for k in rows):
        years = sorted(y for (u, y) in rows if u == unit)
        data = {c: np.empty((len(years), time.size)) for c in channels}
        for i, y in enumerate(years):
            for j, t in enumerate(ref):
                for k, c in enumerate(channels):
                    data[c][i, j] = rows[(unit, y)][t][1][k]
        noise = {FLOW: float(noise_std)} if noise_std is not None else {}
        units[unit] = UnitObservations(np.array(years, dtype=np.int64), data, noise)
    obs = Observations(time, units, csv_path)
    validate_observations(obs)
    write_observations(out_path, obs, inputs=[csv_path])
    obs.path = Path(out_path)
    return obs


def _parse_int(text: str, path: Path, lineno: int, column: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise InputDataError(f"{path}: line {lineno}: column {column!r} is {text!r}, "
                             "expected an integer") from None


def _parse_float(text: str, path: Path, lineno: int, column: str, *, allow_empty: bool) -> float:
    text = text.strip()
    if not text and allow_empty:
        return math.nan
    try:
        value = float(text)
    except ValueError:
        raise InputDataError(f"{path}: line {lineno}: column {column!r} is {text!r}, "
                             "expected a number") from None
    if math.isinf(value) or (math.isnan(value) and not allow_empty):
        raise InputDataError(f"{path}: line {lineno}: column {column!r} is {text!r}, "
                             "expected a finite number")
    return value
