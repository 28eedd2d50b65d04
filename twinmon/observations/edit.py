"""In-place edits of an observations file: :func:`add_events` (``twinmon events add``) and
:func:`remove_events` (``twinmon events remove``), atomic, recorded in the file's ``edits``
attribute."""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Mapping, Sequence

import h5py

from .. import artifacts
from ..errors import ArtifactError, InputDataError
from .events import put_events
from .file import read_observations, validate_observations
from .records import EVENTS, Event, Observations


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
    path = Path(path)
    _writable(path)
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
        _rewrite(path, obs, events, "events add")
    obs.path = path
    return obs


def remove_events(path: str | os.PathLike, unit: str, year: int,
                  component: str) -> Observations:
    """Remove one maintenance event (``unit``, ``year``, ``component``) from an observations
    file, in place and atomically as :func:`add_events` adds one (an event recorded by
    mistake: without this the file had to be imported again). The root attribute ``edits``
    records the removal.

    Raises
    ------
    InputDataError
        An unknown unit, or no such event (the message lists the unit's events).
    """
    path = Path(path)
    _writable(path)
    with artifacts.output_lock(path, "twinmon events remove"):
        obs = read_observations(path)
        u = obs.units.get(unit)
        if u is None:
            raise InputDataError(f"{path}: no unit {unit!r} (units: {', '.join(obs.units)})")
        gone = [e for e in u.events if (e.year, e.component) == (year, component)]
        if not gone:
            have = ", ".join(f"year {e.year} {e.component}" for e in u.events) or "none"
            raise InputDataError(f"{path}: /units/{unit}/{EVENTS}: no event for {component!r} "
                                 f"in year {year} (the unit's events: {have})")
        u.events = [e for e in u.events if e not in gone]
        _rewrite(path, obs, {unit: gone}, "events remove")
    obs.path = path
    return obs


def _writable(path: Path) -> None:
    if path.exists() and not os.access(path, os.W_OK):
        # Replaced by a rename, a read-only file would be rewritten all the same.
        raise OSError(13, "cannot write: the file is read-only (not writable by you)",
                      str(path))


def _rewrite(path: Path, obs: Observations, changed: Mapping[str, Sequence[Event]],
             command: str) -> None:
    """Write ``obs``'s events of the units in ``changed`` into ``path``: into a copy beside
    it, read back, then renamed over it (on any error the original is untouched); the
    change is appended to the root attribute ``edits``."""
    import shutil
    validate_observations(obs)
    with artifacts.replacing(path) as tmp:
        shutil.copyfile(path, tmp)
        # The copy keeps the original's permissions (plant data is not made readable by
        # others by an edit).
        shutil.copymode(path, tmp)
        with h5py.File(tmp, "r+") as f:
            for unit in changed:
                g = f[f"units/{unit}"]
                if EVENTS in g:
                    del g[EVENTS]
                if obs.units[unit].events:          # none: no dataset, as files without
                    put_events(g, obs.units[unit].events)
            raw = f.attrs.get("edits", "[]")
            edits = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
            edits.append({"time": artifacts.utc_now(), "command": command,
                          "events": {u: [dataclasses.asdict(e) for e in evs]
                                     for u, evs in changed.items()}})
            f.attrs["edits"] = json.dumps(edits)
        back = read_observations(tmp, obs.output or None)
        if any(back.units[u].events != obs.units[u].events for u in changed):
            raise ArtifactError(f"{path}: the events read back differ from those written")
