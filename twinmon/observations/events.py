"""Maintenance events of a unit: their rules, their compound dataset ``/units/<unit>/events``
(written by :func:`put_events`, read by :func:`read_events`) and the check of their
components against the config (:func:`check_events`).

The file alone can check the events' years (:func:`_validate_events`, called by
:func:`~twinmon.observations.file.validate_observations`); only the config knows the
components.
"""
from __future__ import annotations

import os
from typing import TYPE_CHECKING, Sequence

import h5py
import numpy as np

from ..errors import InputDataError
from .records import EVENTS, Event, Observations

if TYPE_CHECKING:
    from ..config import Config


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
