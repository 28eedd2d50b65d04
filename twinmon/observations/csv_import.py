"""A user's own measurements as CSV: :func:`import_csv` turns long-form rows (one per
sample) into an observations file, with maintenance events from a second CSV
(:func:`read_events_csv`, a CMMS export trimmed to its columns). Every error names the
file, the line and the value.
"""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from ..errors import InputDataError
# The largest year of service, the limit every reader checks: a larger one is a calendar year
# or a typo.
from ..plausibility import MAX_YEAR
from .file import validate_observations, write_observations
from .records import Event, Observations, UnitObservations


KEY_COLUMNS = ("unit", "year", "time")


def _header_hint(header: list) -> str:
    """What a header that misses a column probably is: semicolon-separated (a spreadsheet
    in a locale with decimal commas), or names carrying their units."""
    if len(header) == 1 and ";" in header[0]:
        return ("; the file is separated by semicolons: save it as CSV with commas between "
                "fields and points as decimal marks")
    if any("[" in h or "(" in h for h in header):
        return "; write the bare names (units go in the config, not the header)"
    return ""


def _calendar_hint(year: int) -> str:
    """A hint for a year that looks like a calendar year."""
    return (" (a calendar year? write the year of service: 1 for the first year the unit "
            "ran)" if 1900 <= year <= 2200 else "")


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
                                 f"(header is {','.join(header)})" + _header_hint(header))
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
            # To 12 significant digits: an export's float noise (0.30000000000000004) is the
            # same time as another unit's 0.3.
            time = _parse_float(row[col["time"]], csv_path, lineno, "time", allow_empty=False)
            time = float(f"{time:.12g}")
            if not 1 <= year <= MAX_YEAR:
                raise InputDataError(f"{csv_path}: line {lineno}: column 'year' is {year}, "
                                     f"expected a year of service from 1 to {MAX_YEAR}"
                                     + _calendar_hint(year))
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
            this = f"unit {key[0]!r} year {key[1]}"
            other = f"unit {ref_key[0]!r} year {ref_key[1]}"
            if extra in rows[key]:
                raise InputDataError(
                    f"{csv_path}: line {rows[key][extra][0]}: {this} has a row at time "
                    f"{extra:g} that {other} has not (its time grid differs)")
            own = sorted(line for line, _ in rows[key].values())
            raise InputDataError(
                f"{csv_path}: lines {own[0]}-{own[-1]}: {this} has no row at time {extra:g}, "
                f"which {other} has (line {rows[ref_key][extra][0]}; its time grid differs)")
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
                                 f"(header is {','.join(header)})" + _header_hint(header))
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
                                     f"expected a year of service from 1 to {MAX_YEAR}"
                                     + _calendar_hint(year))
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
