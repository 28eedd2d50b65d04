"""Error families of twinmon.

Every error a user can cause is a :class:`TwinmonError`; the CLI prints its one-line
message on stderr and exits with the family's own code, so a make or CI job can tell a
bad config from a broken artifact without parsing text. Tracebacks are shown only with
``--verbose``.
"""
from __future__ import annotations


class TwinmonError(Exception):
    """Base of every error twinmon raises on purpose.

    Parameters
    ----------
    message : str
        One line saying what is wrong, naming the file, the place and the value.
    """

    exit_code = 1
    family = "error"

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message


class UsageError(TwinmonError):
    """The command line itself is wrong: e.g. an output named as one of the command's inputs.
    Nothing was read or written."""

    exit_code = 2
    family = "usage error"


class ConfigError(TwinmonError):
    """A YAML config or a ``--set`` override is malformed or invalid."""

    exit_code = 3
    family = "config error"


class InputDataError(TwinmonError):
    """A user's data file (CSV, observations) is malformed: shapes, NaN, duplicates."""

    exit_code = 4
    family = "input error"


class ArtifactError(TwinmonError):
    """An HDF5 artifact is missing, unreadable or of the wrong schema."""

    exit_code = 5
    family = "artifact error"


class SimulationError(TwinmonError):
    """The FMU could not be built, loaded, or failed for an input."""

    exit_code = 6
    family = "simulation error"


class CalibrationError(TwinmonError):
    """Posterior sampling or a fit could not be carried out."""

    exit_code = 7
    family = "calibration error"


class ReadError(TwinmonError):
    """An input file exists but cannot be read (permissions, a folder given for a file)."""

    exit_code = 8
    family = "I/O error"


class OutputBusyError(TwinmonError):
    """Another twinmon process is writing the same output; nothing was touched."""

    exit_code = 8
    family = "I/O error"


class Interrupted(TwinmonError):
    """The user interrupted a command (Ctrl-C); the message says what is kept."""

    exit_code = 130
    family = "interrupted"


EXIT_CODES = {cls.family: cls.exit_code for cls in
              (TwinmonError, UsageError, ConfigError, InputDataError, ArtifactError,
               SimulationError, CalibrationError, ReadError, OutputBusyError, Interrupted)}
