"""The observations format (``twinmon.observations/1``) and the CSV importer.

Layout (DESIGN.md section 3); channel names are the config's (``model.output.name`` for the
measured output, FMU variable names for further channels)::

    /time                    float64 [n_t]       seconds since start
    /units/<unit>/years      int64   [n_y]       observation year (1 = first year of service)
    /units/<unit>/<output>   float64 [n_y, n_t]  the measured output; NaN = missing sample
    /units/<unit>/<channel>  float64 [n_y, n_t]  optional further channels
    /units/<unit>/events     compound [n_e]      maintenance events (optional; absent = none):
                             year int64, component, action, note (UTF-8 strings), by year
    /units/<unit>.attrs      noise_std: JSON {channel: std}, or a bare number (the output's)
    /.attrs                  output: name of the output channel (files written since 0.2)
                             edits: JSON [{time, command, ...}] of in-place edits (events add)

A user's own measurements reach twinmon through :func:`import_csv`; everything downstream
reads :func:`read_observations`, which validates shapes and values so a stage never meets a
malformed array. Maintenance events (a part replaced in a given year) ride along per unit; the
file alone can check their years, the config their components (:func:`check_events`).
"""
from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import h5py
import numpy as np

from . import artifacts

if TYPE_CHECKING:
    from .config import Config
from .errors import ArtifactError, InputDataError

#: Name of a unit's events dataset: not a channel, so no channel may be called so.
EVENTS = "events"


@dataclass(frozen=True)
class Event:
    """A maintenance event of one unit.

    The recording of ``year`` is the first one after the work: from it on, the inputs of
    ``component`` describe the new (or repaired) part.

    Attributes
    ----------
    year : int
        Year of service of the event (after the unit's first recorded year, at most its last).
    component : str
        A component of the config's inputs (``model.inputs[*].component``).
    action : str
        What was done, ``"replaced"`` by default.
    note : str
        Free text (work order, reason), kept as written.
    """

    year: int
    component: str
    action: str = "replaced"
    note: str = ""


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
    events : list of Event
        Maintenance events sorted by year (stable within a year); empty when none.
    """

    years: np.ndarray
    channels: dict[str, np.ndarray]
    noise_std: dict[str, float] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)


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

    def up_to(self, last_year: int, units=None) -> "Observations":
        """The records of ``units`` (default: all) up to ``last_year``, as if nothing later
        had been recorded (later events dropped too); units with no such year left out."""
        out = {}
        for name in (self.units if units is None else units):
            u = self.units[name]
            keep = np.asarray(u.years) <= last_year
            if keep.any():
                out[name] = dataclasses.replace(
                    u, years=np.asarray(u.years)[keep],
                    channels={c: np.asarray(v)[keep] for c, v in u.channels.items()},
                    events=[e for e in u.events if e.year <= last_year])
        return dataclasses.replace(self, units=out)


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


# ---------------------------------------------------------------------------------------
# Maintenance events
# ---------------------------------------------------------------------------------------
_EVENT_DTYPE = np.dtype([("year", np.int64), ("component", h5py.string_dtype()),
                         ("action", h5py.string_dtype()), ("note", h5py.string_dtype())])


def _validate_events(events: Sequence[Event], years: np.ndarray, where: str) -> None:
    """Events need only the unit's years: each lies in (first, last] recorded year, sorted,
    at most one per (year, component). The components are the config's
    (:func:`check_events`)."""
    seen = set()
    prev = None
    for e in events:
        what = f"year {e.year} ({e.component} {e.action})"
        if isinstance(e.year, bool) or not isinstance(e.year, (int, np.integer)):
            raise InputDataError(f"{where}: year {e.year!r} is not an integer year of service")
        if not (isinstance(e.component, str) and e.component.strip()):
            raise InputDataError(f"{where}: year {e.year}: component is {e.component!r}, "
                                 "expected a component name")
        if not (isinstance(e.action, str) and e.action.strip()):
            raise InputDataError(f"{where}: year {e.year}: action is {e.action!r}, expected "
                                 "what was done (e.g. replaced)")
        if e.year <= years[0]:
            raise InputDataError(f"{where}: {what} is not after the first recorded year "
                                 f"{years[0]}: an event needs recordings before it (the history "
                                 "it ends)")
        if e.year > years[-1]:
            raise InputDataError(f"{where}: {what} is after the last recorded year "
                                 f"{years[-1]}: add it with that year's measurements")
        if prev is not None and e.year < prev:
            raise InputDataError(f"{where}: {what} comes after year {prev} (events must be "
                                 "sorted by year)")
        if (e.year, e.component) in seen:
            raise InputDataError(f"{where}: {what}: a second event for {e.component!r} in "
                                 f"year {e.year}")
        seen.add((e.year, e.component))
        prev = e.year


def check_events(cfg: "Config", obs: Observations) -> None:
    """Check that every event names a component of the config's inputs.

    The file cannot know the model's components, so :func:`read_observations` checks only
    the events' years; stages that use events (calibrate, forecast) call this with their
    config.

    Raises
    ------
    InputDataError
        Naming the file, the unit, the year, the unknown component and the valid ones.
    """
    comps = cfg.model.components
    for name, u in obs.units.items():
        for e in u.events:
            if e.component not in comps:
                raise InputDataError(
                    f"{obs.path}: /units/{name}/{EVENTS}: year {e.year}: component "
                    f"{e.component!r} is not a component of the config's model.inputs "
                    f"(components: {', '.join(comps)})")


def put_events(group: h5py.Group, events: Sequence[Event]) -> h5py.Dataset:
    """Write ``events`` as the compound dataset ``<group>/events`` (year, component, action,
    note)."""
    arr = np.array([(int(e.year), e.component, e.action, e.note) for e in events],
                   dtype=_EVENT_DTYPE)
    ds = group.create_dataset(EVENTS, data=arr)
    ds.attrs["units"] = "year"
    ds.attrs["description"] = ("maintenance events: year of service (its recording is the "
                               "first after the work), component, action, note")
    return ds


def read_events(group: h5py.Group, path: str | os.PathLike) -> list[Event]:
    """The events of a unit's group (``[]`` when it has none), sorted by year.

    Accepts a hand-written compound dataset with the fields ``year`` and ``component`` and
    optionally ``action`` (empty: ``replaced``) and ``note``.
    """
    if EVENTS not in group:
        return []
    ds = group[EVENTS]
    where = f"{path}: {group.name}/{EVENTS}"
    names = (ds.dtype.names or ()) if isinstance(ds, h5py.Dataset) else ()
    if (not isinstance(ds, h5py.Dataset) or ds.ndim != 1
            or not {"year", "component"} <= set(names)):
        found = ", ".join(names) or "none"
        raise InputDataError(f"{where}: expected a 1-D compound dataset with fields year, "
                             f"component[, action, note]; found fields {found}")
    if ds.dtype["year"].kind not in "iu":
        raise InputDataError(f"{where}: field year has type {ds.dtype['year']}, expected "
                             "integer years of service")

    def text(row, field: str) -> str:
        if field not in names:
            return ""
        v = row[field]
        return (v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)).strip()

    events = [Event(int(row["year"]), text(row, "component"),
                    text(row, "action") or "replaced", text(row, "note")) for row in ds[()]]
    return sorted(events, key=lambda e: e.year)


# ---------------------------------------------------------------------------------------
# CSV import
# ---------------------------------------------------------------------------------------
KEY_COLUMNS = ("unit", "year", "time")
#: Years are small integers; a larger one is a typo (and would overflow int64 on writing).
MAX_YEAR = 10_000


def import_csv(csv_path: str | os.PathLike, out_path: str | os.PathLike, output: str,
               noise_std: float | None = None, channels: Sequence[str] | None = None,
               units: Mapping[str, str] | None = None, events: str | os.PathLike | None = None,
               components: Sequence[str] | None = None) -> Observations:
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
    events : path-like, optional
        Maintenance events CSV (:func:`read_events_csv`); each names a unit and a year of
        the measurements.
    components : sequence of str, optional
        Components an event may name (the config's, ``model.components``); None: any.

    Raises
    ------
    InputDataError
        Missing columns, non-numeric values, duplicate rows, unequal time grids, events of
        an unknown unit or component or outside the unit's years; the message names the
        file and line.
    """
    csv_path = Path(csv_path)
    required = KEY_COLUMNS + (output,)
    text = _read_text(csv_path)
    event_rows = read_events_csv(events, components) if events is not None else []
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
    if event_rows:
        _attach_events(per_unit, event_rows, Path(events), csv_path)
    obs = Observations(time, per_unit, csv_path, output)
    validate_observations(obs)
    write_observations(out_path, obs, units=units,
                       inputs=[csv_path] + ([events] if events is not None else []))
    obs.path = Path(out_path)
    return obs


def _read_text(path: Path) -> str:
    """A CSV file's text, UTF-8 with an optional byte-order mark."""
    if not path.exists():
        raise InputDataError(f"{path}: file not found")
    try:
        return path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b"\n") + 1
        raise InputDataError(f"{path}: line {line}: not UTF-8 text (byte "
                             f"0x{exc.object[exc.start]:02x}); save the CSV as UTF-8") from None


EVENT_COLUMNS = ("unit", "year", "component", "action", "note")


def read_events_csv(path: str | os.PathLike, components: Sequence[str] | None = None
                    ) -> list[tuple[int, str, Event]]:
    """Read maintenance events from a CSV, as a CMMS export trimmed to these columns.

    Header ``unit,year,component`` and optionally ``action`` (empty: ``replaced``) and
    ``note``; one row per event, e.g. ``U-7,6,<component>,replaced,WO 4711``. UTF-8.

    Parameters
    ----------
    path : path-like
    components : sequence of str, optional
        Components an event may name; None: any.

    Returns
    -------
    list of (line, unit, Event)
        In file order; the line numbers let later checks name the row.

    Raises
    ------
    InputDataError
        A missing or unknown column, an empty cell, a year that is not an integer, an
        unknown component; naming the file, line and value.
    """
    import io
    path = Path(path)
    text = _read_text(path)
    out = []
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputDataError(f"{path}: line 1: file is empty, expected a header "
                                 "unit,year,component[,action,note]") from None
        missing = [c for c in EVENT_COLUMNS[:3] if c not in header]
        if missing:
            raise InputDataError(f"{path}: line 1: missing column {missing[0]!r} "
                                 f"(header is {','.join(header)})")
        unknown = [h for h in header if h not in EVENT_COLUMNS]
        if unknown:
            raise InputDataError(f"{path}: line 1: unknown column {unknown[0]!r} (columns: "
                                 f"{', '.join(EVENT_COLUMNS)})")
        if len(set(header)) != len(header):
            dup = next(h for h in header if header.count(h) > 1)
            raise InputDataError(f"{path}: line 1: column {dup!r} appears twice")
        col = {h: i for i, h in enumerate(header)}
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputDataError(f"{path}: line {lineno}: {len(row)} fields, expected "
                                     f"{len(header)}")
            cell = {c: row[col[c]].strip() if c in col else "" for c in EVENT_COLUMNS}
            for c in EVENT_COLUMNS[:3]:
                if not cell[c]:
                    raise InputDataError(f"{path}: line {lineno}: column {c!r} is empty")
            year = _parse_int(cell["year"], path, lineno, "year")
            if not 1 <= year <= MAX_YEAR:
                raise InputDataError(f"{path}: line {lineno}: column 'year' is {year}, "
                                     f"expected a year of service from 1 to {MAX_YEAR}")
            if components is not None and cell["component"] not in components:
                raise InputDataError(f"{path}: line {lineno}: component {cell['component']!r} "
                                     "is not a component of the config's model.inputs "
                                     f"(components: {', '.join(components)})")
            out.append((lineno, cell["unit"], Event(year, cell["component"],
                                                    cell["action"] or "replaced", cell["note"])))
    return out


def _attach_events(per_unit: dict[str, UnitObservations], rows, path: Path,
                   data_path: Path) -> None:
    """Give each unit its events, checking unit and year against the measurements so the
    error names the events file's line."""
    seen: dict[tuple[str, int, str], int] = {}
    for lineno, unit, e in rows:
        u = per_unit.get(unit)
        if u is None:
            raise InputDataError(f"{path}: line {lineno}: unit {unit!r} has no measurements "
                                 f"in {data_path} (units: {', '.join(per_unit)})")
        first, last = int(u.years[0]), int(u.years[-1])
        if not first < e.year <= last:
            raise InputDataError(f"{path}: line {lineno}: year {e.year} of unit {unit!r} is "
                                 f"outside its measured years ({first}, {last}]: an event must "
                                 "come after the first recording and at most in the last")
        key = (unit, e.year, e.component)
        if key in seen:
            raise InputDataError(f"{path}: line {lineno}: a second event for {e.component!r} "
                                 f"of unit {unit!r} in year {e.year} (first on line {seen[key]})")
        seen[key] = lineno
        u.events.append(e)
    for u in per_unit.values():
        u.events.sort(key=lambda e: e.year)


def add_events(path: str | os.PathLike, events: Mapping[str, Sequence[Event]],
               components: Sequence[str] | None = None) -> Observations:
    """Add maintenance events to an existing observations file, in place and atomically.

    The file is copied beside itself, the events written into the copy, the copy read back
    and validated, and only then renamed over the original: on any error the original is
    untouched. Everything else in the file (measurements, provenance) is kept byte for
    byte; the root attribute ``edits`` records the addition.

    Parameters
    ----------
    path : path-like
        A ``twinmon.observations/1`` file.
    events : mapping of unit to sequence of Event
    components : sequence of str, optional
        Components an event may name (the config's); None: any.

    Returns
    -------
    Observations
        The file as it now reads.

    Raises
    ------
    InputDataError
        An unknown unit or component, a year outside the unit's (first, last] recorded
        years, an event already recorded.
    """
    import shutil
    path = Path(path)
    with artifacts.output_lock(path, "twinmon events add"):
        obs = read_observations(path)
        for unit, evs in events.items():
            u = obs.units.get(unit)
            if u is None:
                raise InputDataError(f"{path}: no unit {unit!r} (units: {', '.join(obs.units)})")
            for e in evs:
                if components is not None and e.component not in components:
                    raise InputDataError(
                        f"{path}: /units/{unit}/{EVENTS}: year {e.year}: component "
                        f"{e.component!r} is not a component of the config's model.inputs "
                        f"(components: {', '.join(components)})")
                if any((o.year, o.component) == (e.year, e.component) for o in u.events):
                    raise InputDataError(f"{path}: /units/{unit}/{EVENTS}: year {e.year}: an "
                                         f"event for {e.component!r} is already recorded")
            u.events = sorted([*u.events, *evs], key=lambda e: e.year)
        validate_observations(obs)
        artifacts.remove_stale_temporaries(path)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            shutil.copyfile(path, tmp)
            with h5py.File(tmp, "r+") as f:
                for unit in events:
                    g = f[f"units/{unit}"]
                    if EVENTS in g:
                        del g[EVENTS]
                    put_events(g, obs.units[unit].events)
                raw = f.attrs.get("edits", "[]")
                edits = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
                added = {u: [dataclasses.asdict(e) for e in evs] for u, evs in events.items()}
                edits.append({"time": artifacts.utc_now(), "command": "events add",
                              "events": added})
                f.attrs["edits"] = json.dumps(edits)
            back = read_observations(tmp, obs.output or None)
            if any(back.units[u].events != obs.units[u].events for u in events):
                raise ArtifactError(f"{path}: the events read back differ from those written")
            os.replace(tmp, path)
        except OSError as exc:
            reason = exc.strerror or str(exc).splitlines()[0]
            raise OSError(exc.errno, f"cannot write: {reason}", str(path)) from None
        finally:
            if tmp.exists():
                tmp.unlink()
    obs.path = path
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
