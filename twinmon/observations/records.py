"""The observations in memory: a fleet's yearly records (:class:`Observations`), one unit's
(:class:`UnitObservations`) and its maintenance events (:class:`Event`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


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
