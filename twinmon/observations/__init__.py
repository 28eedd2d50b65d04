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

Modules: records.py (the objects in memory), events.py (maintenance events: rules, dataset,
check against the config), file.py (write, read and validate a file), csv_import.py (CSV
measurements and events), edit.py (events added to a file in place).
"""
from .csv_import import EVENT_COLUMNS, KEY_COLUMNS, MAX_YEAR, import_csv, read_events_csv
from .edit import add_events, remove_events
from .events import check_events, put_events, read_events
from .file import read_observations, validate_observations, write_observations
from .records import EVENTS, Event, Observations, UnitObservations

__all__ = [
    "EVENTS", "EVENT_COLUMNS", "Event", "KEY_COLUMNS", "MAX_YEAR", "Observations",
    "UnitObservations", "add_events", "check_events", "import_csv", "put_events", "read_events",
    "read_events_csv", "read_observations", "remove_events", "validate_observations",
    "write_observations",
]
