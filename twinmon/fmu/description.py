"""Reading an FMU's model description: what it offers (its variables, their causality,
types, units and start values) for config checks and ``twinmon init``."""
from __future__ import annotations

import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

from ..errors import SimulationError
from .build import resolve_fmu
from .common import FLOAT_TYPES, NUMERIC_TYPES, _a, _one_line


def _read_model_description(path: Path):
    """fmpy's model description of a ``.fmu`` file, checked for the usual ways a file is
    broken; every failure is one :class:`SimulationError` line naming the file."""
    import fmpy

    path = Path(path)
    if path.is_dir():
        if not (path / "modelDescription.xml").is_file():
            raise SimulationError(f"{path}: no modelDescription.xml in this folder")
    else:
        try:
            size = path.stat().st_size
        except OSError as e:
            raise SimulationError(f"{path}: cannot read the FMU: {e.strerror or e}") from None
        if size == 0:
            raise SimulationError(f"{path}: the file is empty, not an FMU")
        if not zipfile.is_zipfile(path):
            raise SimulationError(f"{path}: not a zip archive, so not an FMU "
                                  "(truncated or corrupt file?)")
        try:
            with zipfile.ZipFile(path) as zf:
                if "modelDescription.xml" not in zf.namelist():
                    raise SimulationError(f"{path}: the archive holds no modelDescription.xml, "
                                          "so it is not an FMU")
                bad = zf.testzip()      # CRC of every member: catches a damaged archive now
        except SimulationError:
            raise
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as e:
            raise SimulationError(f"{path}: corrupt FMU archive: {_one_line(e)}") from None
        if bad is not None:
            raise SimulationError(f"{path}: corrupt FMU archive: member {bad} fails its "
                                  "checksum")
    try:
        return fmpy.read_model_description(str(path))
    except Exception as e:  # fmpy raises plain exceptions, often several lines long
        raise SimulationError(f"{path}: invalid modelDescription.xml: {_one_line(e)}") from None


def _start_value(v) -> float | None:
    s = v.start
    if s is None:
        return None
    if v.type == "Boolean":
        return 1.0 if str(s).strip().lower() in ("true", "1") else 0.0
    try:
        return float(s)
    except (TypeError, ValueError):
        return None


def _bound(text) -> float | None:
    """A declared ``min`` / ``max`` as a float (None when absent or not a finite number)."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if value == value and abs(value) != float("inf") else None


def _unit(v) -> str:
    if v.unit:
        return v.unit
    dt = getattr(v, "declaredType", None)
    return (getattr(dt, "unit", None) or "") if dt is not None else ""


def _is_tunable(v) -> bool:
    # Parameters of variability fixed or tunable, and inputs (held constant over a run).
    return (v.type in FLOAT_TYPES and not v.dimensions
            and (v.causality == "input"
                 or (v.causality == "parameter" and v.variability in ("fixed", "tunable"))))


def _is_start_value(v) -> bool:
    # FMI 2.0 (section 3.2.3) and 3.0 let a tool set, before initialisation, the start value
    # of a non-constant variable whose ``initial`` is ``exact`` or ``approx``: a state's
    # initial value, say, or an output's first value.  A start attribute without an
    # ``initial`` on a local or output declares one of these too.
    return (v.type in FLOAT_TYPES and not v.dimensions and v.start is not None
            and v.causality in ("local", "output") and v.variability in ("continuous",
                                                                          "discrete")
            and (v.initial or "exact") in ("exact", "approx"))


def _is_settable(v) -> bool:
    """What :class:`FMUModel` sets before ``EnterInitializationMode``: tunable parameters,
    inputs and start values."""
    return _is_tunable(v) or _is_start_value(v)


def why_not_settable(v) -> str:
    """Why FMI does not let a tool set ``v`` before initialisation (FMU model description
    variable, fmpy's or :class:`VariableInfo`), in words; "" when it does."""
    if _is_settable(v):
        return ""
    shape = getattr(v, "dimensions", None) or getattr(v, "shape", ())
    causality = v.causality or "local"
    if v.type not in FLOAT_TYPES or shape:
        what = "an array" if shape else _a(v.type) + " variable"
        return f"is {what}; twinmon sets scalar float parameters, inputs and start values only"
    if v.variability == "constant":
        return "is a constant: FMI lets no tool change it"
    if causality == "calculatedParameter":
        return "is a calculated parameter: the FMU computes it from other parameters"
    if causality == "independent":
        return "is the independent variable (time)"
    if causality == "structuralParameter":
        return ("is a structural parameter: FMI 3 sets it in configuration mode, which "
                "twinmon does not use")
    initial = getattr(v, "initial", None)
    if initial == "calculated" or v.start is None:
        return (f"is {_a(causality)} {v.type} the FMU calculates (initial=\"calculated\", no "
                "start value): FMI lets no tool set it before initialisation")
    return (f"is {_a(causality)} {v.type} of variability {v.variability or 'continuous'}: "
            "FMI lets no tool set it before initialisation")


def _is_recordable(v) -> bool:
    return v.type in NUMERIC_TYPES and not v.dimensions and v.causality in ("output", "local")


@dataclass(frozen=True)
class VariableInfo:
    """One scalar FMU variable as the model description declares it.

    ``type`` is the FMI type name (``Real``, ``Integer``, ``Boolean``... in FMI 2.0;
    ``Float64``, ``Int32``... in FMI 3.0); ``start`` is its start value as a float
    (Boolean: 0/1), or None when it has none; ``unit`` is "" when undeclared.
    ``shape`` is () for a scalar (FMI 3.0 arrays have their dimensions there);
    ``initial`` is the declared ``initial`` attribute ("" when not given); ``min`` and
    ``max`` the declared range (None where not declared): a value outside it is not a state
    of the model (FMI forbids setting it).
    """

    name: str
    causality: str
    variability: str
    type: str
    start: float | None
    unit: str
    description: str
    shape: tuple[int, ...] = ()
    initial: str = ""
    min: float | None = None
    max: float | None = None

    @property
    def dimensions(self) -> tuple[int, ...]:
        return self.shape

    @property
    def is_settable(self) -> bool:
        """A tunable parameter, an input or a start value: what :class:`FMUModel` sets
        before initialisation (see :func:`why_not_settable` for the others)."""
        return _is_settable(self)

    @property
    def is_start_value(self) -> bool:
        """A local or output whose start value a tool may set (``initial`` exact or
        approx, with a start): a state's initial value, for one."""
        return _is_start_value(self)

    @property
    def is_float(self) -> bool:
        """A scalar floating-point variable (Real, Float64, Float32)."""
        return self.type in FLOAT_TYPES and not self.shape

    @property
    def is_numeric(self) -> bool:
        """A scalar whose value reads as a number (float, integer, enumeration, Boolean)."""
        return self.type in NUMERIC_TYPES and not self.shape


@dataclass(frozen=True)
class FMUInfo:
    """What an FMU offers, read from its model description (see :func:`describe_fmu`).

    ``variables`` keeps the model description's order; ``stop_time`` and ``step_size`` are
    the model description's DefaultExperiment (None when it gives none)."""

    path: Path
    fmi_version: str
    model_name: str
    description: str
    co_simulation: bool
    model_exchange: bool
    variables: dict[str, VariableInfo]
    stop_time: float | None = None
    step_size: float | None = None

    def tunable_parameters(self) -> list[VariableInfo]:
        """Float parameters (variability fixed or tunable) and float inputs: the variables
        :class:`FMUModel` can set for a run, i.e. candidate degradation inputs, effects and
        fixed values."""
        return [v for v in self.variables.values()
                if v.is_float and (v.causality == "input"
                                   or (v.causality == "parameter"
                                       and v.variability in ("fixed", "tunable")))]

    def start_values(self) -> list[VariableInfo]:
        """Float locals and outputs whose start value FMI lets a tool set before
        initialisation (``initial`` exact or approx, with a start): states' initial values,
        for one. :class:`FMUModel` sets them like parameters."""
        return [v for v in self.variables.values() if v.is_start_value]

    def settable(self) -> list[VariableInfo]:
        """:meth:`tunable_parameters` then :meth:`start_values`: every variable a config may
        name as an input, an effect or a fixed value."""
        return self.tunable_parameters() + self.start_values()

    def recordable(self) -> list[VariableInfo]:
        """Numeric outputs and locals, outputs first: what :class:`FMUModel` can record."""
        vs = [v for v in self.variables.values()
              if v.is_numeric and v.causality in ("output", "local")]
        return [v for v in vs if v.causality == "output"] + \
               [v for v in vs if v.causality == "local"]


def describe_fmu(path, build: bool = True) -> FMUInfo:
    """Read an FMU's model description: its version, interfaces and variables.

    Parameters
    ----------
    path : Path or str
        A ``.fmu`` file, or an FMU source folder (built and cached first, see
        :func:`resolve_fmu`).
    build : bool
        False: a source folder's own ``modelDescription.xml`` is read, nothing is built
        (for a reader of the variables alone, such as the report).

    Returns
    -------
    FMUInfo
        ``path`` is the ``.fmu`` file described.

    Raises
    ------
    SimulationError
        One line naming the file and what is wrong: missing, empty, not a zip archive,
        truncated or corrupt, without ``modelDescription.xml``, or an invalid one.
    """
    p = Path(path)
    fmu = resolve_fmu(p) if p.is_dir() and build else p
    md = _read_model_description(fmu)
    variables = {}
    for v in md.modelVariables:
        variables[v.name] = VariableInfo(
            name=v.name, causality=v.causality or "local", variability=v.variability or "",
            type=v.type, start=_start_value(v) if not v.dimensions else None, unit=_unit(v),
            description=v.description or "",
            shape=tuple(d.start if d.start is not None else -1 for d in v.dimensions),
            initial=v.initial or "", min=_bound(getattr(v, "min", None)),
            max=_bound(getattr(v, "max", None)))
    de = md.defaultExperiment

    def number(text) -> float | None:
        try:
            return float(text) if text is not None else None
        except (TypeError, ValueError):
            return None

    return FMUInfo(path=fmu, fmi_version=md.fmiVersion, model_name=md.modelName or "",
                   description=md.description or "",
                   co_simulation=md.coSimulation is not None,
                   model_exchange=md.modelExchange is not None, variables=variables,
                   stop_time=number(de.stopTime) if de is not None else None,
                   step_size=number(de.stepSize) if de is not None else None)
