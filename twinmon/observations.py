"""The observations format (``twinmon.observations/1``) and the CSV importer.

Layout (DESIGN.md section 3); channel names are the config's (``model.output.name`` for the
measured output, FMU variable names for further channels)::

    /time                    float64 [n_t]       seconds since start
    /units/<unit>/years      int64   [n_y]       observation year (1 = first year of service)
    /units/<unit>/<output>   float64 [n_y, n_t]  the measured output; NaN = missing sample
    /units/<unit>/<channel>  float64 [n_y, n_t]  optional further channels
    /units/<unit>.attrs      noise_std: JSON {channel: std}, or a bare number (the output's)
    /.attrs                  output: name of the output channel (files written since 0.2)

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
from typing import Mapping, Sequence

import numpy as np

from . import artifacts
from .errors import ArtifactError, InputDataError


@dataclass
class UnitObservations:
    """One unit's yearly records.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    channels : dict of str to ndarray, each shape [n_y, n_t]
        The measured output under its channel name, and any further channels (their own
        units, named by the config); NaN = missing sample.
    noise_std : dict of str to float
        Known measurement noise standard deviation per channel (channel units); may be empty.
    """

    years: np.ndarray
    channels: dict[str, np.ndarray]
    noise_std: dict[str, float] = field(default_factory=dict)


@dataclass
class Observations:
    """Observations of a fleet on one time grid.

    Attributes
    ----------
    time : ndarray, shape [n_t], s
    units : dict of str to UnitObservations
    path : Path
    output : str
        Name of the measured output's channel ("" when not known).
    """

    time: np.ndarray
    units: dict[str, UnitObservations]
    path: Path = Path("<memory>")
    output: str = ""

    def output_of(self, unit: str) -> np.ndarray:
        """The measured output of ``unit``, shape [n_y, n_t]."""
        return self.units[unit].channels[self.output]


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
                if ch == "years":
                    continue
                if not hasattr(ds, "dtype") or ds.dtype.kind not in "fiu":
                    raise InputDataError(f"{path}: /units/{name}/{ch} is not a numeric array")
                channels[ch] = np.asarray(ds[()], dtype=float)
            if output and output not in channels:
                have = ", ".join(sorted(channels)) or "none"
                raise ArtifactError(f"{path}: dataset /units/{name}/{output} (the config's "
                                    f"model.output.name) is missing; channels here: {have}")
            noise = _noise_attr(g.attrs.get("noise_std"), output, path, name)
            units[name] = UnitObservations(years, channels, noise)
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


# ---------------------------------------------------------------------------------------
# CSV import
# ---------------------------------------------------------------------------------------
KEY_COLUMNS = ("unit", "year", "time")
#: Years are small integers; a larger one is a typo (and would overflow int64 on writing).
MAX_YEAR = 10_000


def import_csv(csv_path: str | os.PathLike, out_path: str | os.PathLike, output: str,
               noise_std: float | None = None, channels: Sequence[str] | None = None,
               units: Mapping[str, str] | None = None) -> Observations:
    """Convert long-form CSV measurements into an observations artifact.

    The CSV has a header with at least ``unit,year,time,<output>`` and optionally further
    channel columns; one row per sample. Every (unit, year) must share one time grid. An
    empty cell is a missing sample (NaN). The file is read as UTF-8 (a byte-order mark is
    dropped).

    Parameters
    ----------
    csv_path : path-like
        The CSV file.
    out_path : path-like
        The observations HDF5 file to write.
    output : str
        Column (channel) name of the measured output (the config's ``model.output.name``).
    noise_std : float, optional
        Known noise standard deviation of the output (its units), recorded for every unit.
    channels : sequence of str, optional
        Further columns allowed (the config's ``model.channels``); None: any.
    units : mapping, optional
        Units per channel, recorded in the file.

    Raises
    ------
    InputDataError
        Missing columns, non-numeric values, duplicate rows, unequal time grids; the
        message names the file and line.
    """
    csv_path = Path(csv_path)
    required = KEY_COLUMNS + (output,)
    if not csv_path.exists():
        raise InputDataError(f"{csv_path}: file not found")
    try:
        text = csv_path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b"\n") + 1
        raise InputDataError(f"{csv_path}: line {line}: not UTF-8 text (byte "
                             f"0x{exc.object[exc.start]:02x}); save the CSV as UTF-8") from None
    import io
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputDataError(f"{csv_path}: line 1: file is empty, expected a header "
                                 f"{','.join(required)}") from None
        missing = [c for c in required if c not in header]
        if missing:
            raise InputDataError(f"{csv_path}: line 1: missing column {missing[0]!r} "
                                 f"(header is {','.join(header)})")
        if len(set(header)) != len(header):
            dup = next(h for h in header if header.count(h) > 1)
            raise InputDataError(f"{csv_path}: line 1: column {dup!r} appears twice")
        chan_cols = [h for h in header if h not in KEY_COLUMNS]
        if channels is not None:
            allowed = {output, *channels}
            extra = [h for h in chan_cols if h not in allowed]
            if extra:
                raise InputDataError(f"{csv_path}: line 1: column {extra[0]!r} is not a channel "
                                     f"of the config (allowed: {', '.join(sorted(allowed))})")
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
            if not 1 <= year <= MAX_YEAR:
                raise InputDataError(f"{csv_path}: line {lineno}: column 'year' is {year}, "
                                     f"expected a year of service from 1 to {MAX_YEAR}")
            values = [_parse_float(row[col[c]], csv_path, lineno, c, allow_empty=True)
                      for c in chan_cols]
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
    per_unit = {}
    for unit in dict.fromkeys(k[0] for k in rows):
        years = sorted(y for (u, y) in rows if u == unit)
        data = {c: np.empty((len(years), time.size)) for c in chan_cols}
        for i, y in enumerate(years):
            for j, t in enumerate(ref):
                for k, c in enumerate(chan_cols):
                    data[c][i, j] = rows[(unit, y)][t][1][k]
        noise = {output: float(noise_std)} if noise_std is not None else {}
        per_unit[unit] = UnitObservations(np.array(years, dtype=np.int64), data, noise)
    obs = Observations(time, per_unit, csv_path, output)
    validate_observations(obs)
    write_observations(out_path, obs, inputs=[csv_path], units=units)
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
