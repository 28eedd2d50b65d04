"""Building FMUs from C sources, describing them, and running them fast, many times.

An FMU source folder holds ``modelDescription.xml`` and ``sources/*.c|*.h`` (FMI 2.0 or 3.0);
:func:`build_fmu` compiles it with the system C compiler into a ``.fmu`` cached under
``<src_dir>/.build/<hash>/`` (the hash covers the model description, the sources and the
build recipe), so an unchanged model is compiled once.  :func:`describe_fmu` reads what an
FMU offers (its parameters, outputs, types and units) for config checks and ``twinmon init``.
:class:`FMUModel` extracts an FMU once, keeps one instance and resets it between runs: an
FMI 2.0 or 3.0 Co-Simulation run costs a few dozen direct C calls.
"""
from __future__ import annotations

import ctypes
import difflib
import hashlib
import os
import shutil
import subprocess
import tempfile
import weakref
import xml.etree.ElementTree as ET
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from .errors import SimulationError

__all__ = ["source_hash", "build_fmu", "resolve_fmu", "FMUModel", "VariableInfo", "FMUInfo",
           "describe_fmu", "closest_names"]

# Part of the hash: changing how the binary is built must invalidate the cache.
_BUILD_RECIPE = b"twinmon-build/1: cc -O2 -shared -fPIC <sources/*.c> -lm"
_ZIP_DATE = (2020, 1, 1, 0, 0, 0)   # fixed, so that the same build gives the same bytes
_FMU_MODE = 0o644                   # a built .fmu is a shareable file, not a private one

FLOAT_TYPES = frozenset({"Real", "Float64", "Float32"})
INTEGER_TYPES = frozenset({"Integer", "Enumeration", "Int8", "UInt8", "Int16", "UInt16",
                           "Int32", "UInt32", "Int64", "UInt64"})
NUMERIC_TYPES = FLOAT_TYPES | INTEGER_TYPES | {"Boolean"}


def _one_line(exc: BaseException, limit: int = 300) -> str:
    """An exception's message on one line (fmpy's span several: a heading, then one
    ``- problem`` line each), cut to ``limit`` characters."""
    lines = [ln.strip().lstrip("- ").strip() for ln in str(exc).splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        return type(exc).__name__
    text = lines[0]
    for ln in lines[1:]:
        text += (" " if text.endswith(":") else "; ") + ln
    return text if len(text) <= limit else text[:limit - 3] + "..."


# --------------------------------------------------------------------------------------
# building

def _source_files(src_dir: Path) -> list[Path]:
    sources = src_dir / "sources"
    files = [src_dir / "modelDescription.xml"]
    if sources.is_dir():
        # is_file() and read_bytes() follow symbolic links: a source shared with another
        # FMU folder through a link is hashed and packed by its content.
        files += sorted(p for p in sources.rglob("*") if p.is_file())
    return files


def source_hash(src_dir: Path) -> str:
    """SHA-256 over ``modelDescription.xml`` and every file under ``sources/``.

    Parameters
    ----------
    src_dir : Path
        FMU source folder.

    Returns
    -------
    str
        Hex digest; covers each file's relative path and content (sorted; symbolic links
        are followed) and the build recipe.
    """
    src_dir = Path(src_dir)
    h = hashlib.sha256(_BUILD_RECIPE)
    for f in _source_files(src_dir):
        h.update(f.relative_to(src_dir).as_posix().encode() + b"\0")
        h.update(f.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def _model_head(md_path: Path) -> tuple[str, str]:
    """``(fmiVersion, modelIdentifier)`` of a source folder's model description."""
    try:
        root = ET.parse(md_path).getroot()
    except (OSError, ET.ParseError) as e:
        raise SimulationError(f"cannot read {md_path}: {_one_line(e)}") from None
    version = root.get("fmiVersion", "")
    if not (version == "2.0" or version.startswith("3.")):
        raise SimulationError(f"{md_path}: fmiVersion {version!r} is not supported "
                              "(FMI 2.0 or 3.0)")
    for kind in ("CoSimulation", "ModelExchange"):
        el = root.find(kind)
        if el is not None and el.get("modelIdentifier"):
            return version, el.get("modelIdentifier")
    raise SimulationError(f"{md_path} declares no modelIdentifier")


def _fmi_headers() -> Path:
    import fmpy
    return Path(os.path.dirname(fmpy.__file__)) / "c-code"


def _binary_dir(fmi_version: str) -> str:
    """Folder of the shared library inside the FMU: FMI 3 names platforms by a tuple."""
    import fmpy
    return f"binaries/{fmpy.platform_tuple if fmi_version.startswith('3') else fmpy.platform}"


def build_fmu(src_dir: Path | str, force: bool = False) -> Path:
    """Compile an FMU source folder (FMI 2.0 or 3.0) into a ``.fmu`` (cached by :func:`source_hash`).

    Parameters
    ----------
    src_dir : Path or str
        Folder with ``modelDescription.xml`` and ``sources/``.  The FMI version is read from
        the model description: FMI 2.0 binaries go to ``binaries/linux64/``, FMI 3.0 ones to
        ``binaries/x86_64-linux/`` (fmpy's platform names).
    force : bool
        Rebuild even when the cached ``.fmu`` exists.

    Returns
    -------
    Path
        ``<src_dir>/.build/<hash[:16]>/<modelIdentifier>.fmu``, mode 0644.

    Raises
    ------
    SimulationError
        The sources are missing or do not compile (names the folder and the first error line).
    """
    import fmpy

    src_dir = Path(src_dir).resolve()
    md = src_dir / "modelDescription.xml"
    if not md.is_file():
        raise SimulationError(f"{src_dir} has no modelDescription.xml")
    fmi_version, identifier = _model_head(md)
    c_files = sorted((src_dir / "sources").glob("*.c"))
    if not c_files:
        raise SimulationError(f"{src_dir / 'sources'} holds no C sources")
    digest = source_hash(src_dir)
    out_dir = src_dir / ".build" / digest[:16]
    out = out_dir / f"{identifier}.fmu"
    if out.is_file() and not force:
        if out.stat().st_mode & 0o777 != _FMU_MODE:
            try:    # cached by an older twinmon that left it private (0600)
                os.chmod(out, _FMU_MODE)
            except OSError:
                pass
        return out

    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="twinmon-build-") as tmp:
        lib_rel = f"{_binary_dir(fmi_version)}/{identifier}{fmpy.sharedLibraryExtension}"
        lib = Path(tmp) / lib_rel
        lib.parent.mkdir(parents=True)
        cmd = ["cc", "-O2", "-shared", "-fPIC", "-I", str(_fmi_headers()),
               "-I", str(src_dir / "sources"), *map(str, c_files), "-o", str(lib), "-lm"]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True)
        except OSError as e:
            raise SimulationError(f"cannot compile FMU sources in {src_dir}: {e}") from None
        if proc.returncode != 0:
            lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
            first = next((ln for ln in lines if "error" in ln.lower()),
                         lines[0] if lines else f"cc exited with code {proc.returncode}")
            raise SimulationError(f"cannot compile FMU sources in {src_dir}: {first.strip()}")

        entries = [("modelDescription.xml", md), (lib_rel, lib)]
        entries += [(p.relative_to(src_dir).as_posix(), p)
                    for p in _source_files(src_dir)[1:]]
        fd, tmp_fmu = tempfile.mkstemp(suffix=".fmu.tmp", dir=out_dir)
        try:
            with os.fdopen(fd, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as zf:
                for name, path in entries:
                    info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
                    info.compress_type = zipfile.ZIP_DEFLATED
                    info.external_attr = 0o644 << 16
                    zf.writestr(info, path.read_bytes())
            os.chmod(tmp_fmu, _FMU_MODE)      # mkstemp creates 0600
            os.replace(tmp_fmu, out)
        except BaseException:
            if os.path.exists(tmp_fmu):
                os.unlink(tmp_fmu)
            raise
    return out


def resolve_fmu(path) -> Path:
    """The ``.fmu`` to run for ``path``: a source folder is built (cached), a ``.fmu`` is used as is.

    Raises
    ------
    SimulationError
        ``path`` is neither an FMU source folder nor a ``.fmu`` file.
    """
    p = Path(path)
    if p.is_dir() and (p / "modelDescription.xml").is_file() and (p / "sources").is_dir():
        return build_fmu(p)
    if p.is_file() and p.suffix.lower() == ".fmu":
        return p
    raise SimulationError(f"{p} is neither a .fmu file nor an FMU source folder "
                          "(modelDescription.xml + sources/)")


# --------------------------------------------------------------------------------------
# describing

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


def _unit(v) -> str:
    if v.unit:
        return v.unit
    dt = getattr(v, "declaredType", None)
    return (getattr(dt, "unit", None) or "") if dt is not None else ""


def _is_tunable(v) -> bool:
    # Parameters of variability fixed or tunable, and inputs (held constant over a run):
    # what FMUModel sets before initialisation.
    return (v.type in FLOAT_TYPES and not v.dimensions
            and (v.causality == "input"
                 or (v.causality == "parameter" and v.variability in ("fixed", "tunable"))))


def _is_recordable(v) -> bool:
    return v.type in NUMERIC_TYPES and not v.dimensions and v.causality in ("output", "local")


@dataclass(frozen=True)
class VariableInfo:
    """One scalar FMU variable as the model description declares it.

    ``type`` is the FMI type name (``Real``, ``Integer``, ``Boolean``... in FMI 2.0;
    ``Float64``, ``Int32``... in FMI 3.0); ``start`` is its start value as a float
    (Boolean: 0/1), or None when it has none; ``unit`` is "" when undeclared.
    ``shape`` is () for a scalar (FMI 3.0 arrays have their dimensions there).
    """

    name: str
    causality: str
    variability: str
    type: str
    start: float | None
    unit: str
    description: str
    shape: tuple[int, ...] = ()

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

    def recordable(self) -> list[VariableInfo]:
        """Numeric outputs and locals, outputs first: what :class:`FMUModel` can record."""
        vs = [v for v in self.variables.values()
              if v.is_numeric and v.causality in ("output", "local")]
        return [v for v in vs if v.causality == "output"] + \
               [v for v in vs if v.causality == "local"]


def describe_fmu(path) -> FMUInfo:
    """Read an FMU's model description: its version, interfaces and variables.

    Parameters
    ----------
    path : Path or str
        A ``.fmu`` file, or an FMU source folder (built and cached first, see
        :func:`resolve_fmu`).

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
    fmu = resolve_fmu(p) if p.is_dir() else p
    md = _read_model_description(fmu)
    variables = {}
    for v in md.modelVariables:
        variables[v.name] = VariableInfo(
            name=v.name, causality=v.causality or "local", variability=v.variability or "",
            type=v.type, start=_start_value(v) if not v.dimensions else None, unit=_unit(v),
            description=v.description or "",
            shape=tuple(d.start if d.start is not None else -1 for d in v.dimensions))
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


def closest_names(name: str, candidates: Iterable[str], n: int = 3) -> list[str]:
    """The ``n`` candidates most like ``name`` (difflib ratio, case-insensitive), best first.

    Every candidate that shares something with ``name`` may be returned, so that an error
    message can always point at what exists; an empty list only when there are none.
    """
    key = name.lower()
    scored = []
    for c in dict.fromkeys(candidates):
        r = difflib.SequenceMatcher(None, key, c.lower()).ratio()
        if r > 0:
            scored.append((-r, c))
    return [c for _, c in sorted(scored)[:max(n, 0)]]


def _a(word: str) -> str:
    return ("an " if word[:1].lower() in "aeiou" else "a ") + word


def _closest_hint(name: str, candidates: Iterable[str]) -> str:
    near = closest_names(name, candidates)
    return f"; closest: {', '.join(near)}" if near else ""


# --------------------------------------------------------------------------------------
# running

_c_int, _c_void_p, _c_double, _c_size_t = ctypes.c_int, ctypes.c_void_p, ctypes.c_double, ctypes.c_size_t
_c_bool, _c_float = ctypes.c_bool, ctypes.c_float
_PROTOS = {
    "fmi2Reset": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi2SetupExperiment": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_int, _c_double, _c_double,
                                            _c_int, _c_double),
    "fmi2EnterInitializationMode": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi2ExitInitializationMode": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi2SetReal": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p),
    "fmi2GetReal": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p),
    "fmi2GetInteger": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p),
    "fmi2GetBoolean": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p),
    "fmi2DoStep": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_double, _c_double, _c_int),
    "fmi2FreeInstance": ctypes.CFUNCTYPE(None, _c_void_p),
}
_GET_ARRAY = ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p, _c_size_t)
_PROTOS3 = {
    "fmi3Reset": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi3EnterInitializationMode": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_bool, _c_double,
                                                    _c_double, _c_bool, _c_double),
    "fmi3ExitInitializationMode": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi3DoStep": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_double, _c_double, _c_bool,
                                   _c_void_p, _c_void_p, _c_void_p, _c_void_p),
    "fmi3FreeInstance": ctypes.CFUNCTYPE(None, _c_void_p),
    "fmi3SetFloat64": _GET_ARRAY, "fmi3SetFloat32": _GET_ARRAY,
    **{f"fmi3Get{t}": _GET_ARRAY for t in ("Float64", "Float32", "Int8", "UInt8", "Int16",
                                           "UInt16", "Int32", "UInt32", "Int64", "UInt64",
                                           "Boolean")},
}
# FMI 2.0 output getters by type (value arrays of fmi2Integer / fmi2Boolean, both C int)
_GETTERS2 = {"Integer": ("fmi2GetInteger", ctypes.c_int),
             "Enumeration": ("fmi2GetInteger", ctypes.c_int),
             "Boolean": ("fmi2GetBoolean", ctypes.c_int)}
_GETTERS3 = {"Float32": ctypes.c_float, "Int8": ctypes.c_int8, "UInt8": ctypes.c_uint8,
             "Int16": ctypes.c_int16, "UInt16": ctypes.c_uint16, "Int32": ctypes.c_int32,
             "UInt32": ctypes.c_uint32, "Int64": ctypes.c_int64, "UInt64": ctypes.c_uint64,
             "Enumeration": ctypes.c_int64, "Boolean": ctypes.c_bool}
_STATUS = ["ok", "warning", "discard", "error", "fatal", "pending"]


def _fmt_params(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.6g}" for k, v in values.items()) or "defaults"


class FMUModel:
    """One FMU instance, reset and rerun for each parameter set.

    Parameters
    ----------
    fmu_path : Path or str
        The ``.fmu`` file, FMI 2.0 or 3.0 (use :func:`resolve_fmu` for a source folder).
    outputs : sequence of str
        Numeric variables to record (outputs or locals; Real/Float64/Float32, any integer
        type, Enumeration or Boolean; all are returned as float).
    times : ndarray, shape [n_t]
        Sorted sample times (s), all > 0; the run starts at 0.
    fmi_type : str
        ``"CoSimulation"`` (fast path: direct C calls) or ``"ModelExchange"`` (fmpy's
        CVode, slow; for checks).
    start_values : mapping, optional
        Parameter values applied on every run before the run's own.

    Notes
    -----
    Use as a context manager or call :meth:`close`: the extracted FMU lives in a temporary
    folder until then.  Parameters are the float parameters and inputs of
    :meth:`FMUInfo.tunable_parameters`.
    """

    def __init__(self, fmu_path, outputs: Sequence[str], times: np.ndarray,
                 fmi_type: str = "CoSimulation",
                 start_values: Mapping[str, float] | None = None):
        import fmpy

        self._fmu_path = Path(fmu_path)
        if fmi_type not in ("CoSimulation", "ModelExchange"):
            raise SimulationError(f"fmi_type must be CoSimulation or ModelExchange, got {fmi_type!r}")
        self._fmi_type = fmi_type
        self._times = np.asarray(times, dtype=float).ravel()
        if self._times.size == 0 or not np.all(np.isfinite(self._times)) \
                or self._times[0] <= 0 or np.any(np.diff(self._times) <= 0):
            raise SimulationError(f"output times for {self._fmu_path} must be finite, > 0 and "
                                  f"strictly increasing; got {self._times!r}")
        self._fmu = None
        self._component = None
        self._tmpdir = None
        md = _read_model_description(self._fmu_path)
        self._md = md
        self._v3 = md.fmiVersion.startswith("3")
        if not (self._v3 or md.fmiVersion == "2.0"):
            raise SimulationError(f"{self._fmu_path}: FMI {md.fmiVersion} is not supported "
                                  "(FMI 2.0 or 3.0)")
        kind = md.coSimulation if fmi_type == "CoSimulation" else md.modelExchange
        if kind is None:
            raise SimulationError(f"{self._fmu_path} does not support {fmi_type}")
        self._vars = {v.name: v for v in md.modelVariables}
        self._params = {v.name: v.valueReference for v in md.modelVariables if _is_tunable(v)}
        self._param_type = {v.name: v.type for v in md.modelVariables if _is_tunable(v)}
        self._outputs = tuple(outputs)
        for name in self._outputs:
            v = self._vars.get(name)
            if v is None:
                raise SimulationError(
                    f"{self._fmu_path} has no variable {name!r} to record"
                    f"{_closest_hint(name, [w.name for w in md.modelVariables if _is_recordable(w)])}")
            if not _is_recordable(v):
                what = (f"{_a(v.type)} variable" if v.type not in NUMERIC_TYPES or v.dimensions
                        else f"{_a(v.causality)} variable")
                raise SimulationError(f"{self._fmu_path}: {name!r} is {what}, not a numeric "
                                      "output or local that can be recorded")
        self._start = dict(start_values or {})
        self._check_names(self._start)

        self._tmpdir = tempfile.mkdtemp(prefix="twinmon-fmu-")
        self._finalizer = weakref.finalize(self, shutil.rmtree, self._tmpdir, True)
        try:
            fmpy.extract(str(self._fmu_path), unzipdir=self._tmpdir)
        except Exception as e:
            self.close()
            raise SimulationError(f"cannot extract FMU {self._fmu_path}: {_one_line(e)}") from None

        # Output columns: the block read by fmi2GetReal / fmi3GetFloat64 straight into the
        # buffer rows first (the only block for an all-float FMU: the fast path), then one
        # group per other type, copied in after each step.
        main_type = "Float64" if self._v3 else "Real"
        main = [n for n in self._outputs if self._vars[n].type == main_type]
        others: dict[str, list[str]] = {}
        for n in self._outputs:
            if self._vars[n].type != main_type:
                others.setdefault(self._vars[n].type, []).append(n)
        order = main + [n for names in others.values() for n in names]
        self._col = {n: order.index(n) for n in self._outputs}
        n_main, n_out = len(main), len(order)
        self._n_main = n_main
        self._out_vr = (ctypes.c_uint32 * max(n_main, 1))(*[self._vars[n].valueReference
                                                            for n in main])
        self._others = others
        self._groups: list = []          # (getter, vr array, value array, first column), set later
        self._buf = np.empty((self._times.size, n_out))
        self._dt = np.diff(np.concatenate(([0.0], self._times)))
        self._log: list[str] = []
        if fmi_type == "CoSimulation":
            try:
                if self._v3:
                    self._open_cs3(kind.modelIdentifier)
                else:
                    self._open_cs(kind.modelIdentifier)
            except SimulationError:
                self.close()
                raise
            except Exception as e:  # e.g. a missing binary for this platform
                self.close()
                raise SimulationError(f"cannot load FMU {self._fmu_path}: {_one_line(e)}") from None

    # -- set-up -------------------------------------------------------------------------

    def _bind(self, protos: Mapping[str, ctypes.CFUNCTYPE], optional: Iterable[str] = ()) -> None:
        dll = self._fmu.dll
        self._fn = {}
        for name, proto in protos.items():
            try:
                self._fn[name] = proto(ctypes.cast(getattr(dll, name), _c_void_p).value)
            except AttributeError:
                if name not in optional:
                    raise SimulationError(f"{self._fmu_path}: the binary lacks {name}") from None

    def _make_groups(self, getter_for) -> None:
        col = self._n_main
        for typ, names in self._others.items():
            fname, ctype = getter_for(typ)
            if fname not in self._fn:
                raise SimulationError(f"{self._fmu_path}: the binary lacks {fname} to read "
                                      f"{', '.join(names)}")
            vr = (ctypes.c_uint32 * len(names))(*[self._vars[n].valueReference for n in names])
            val = (ctype * len(names))()
            self._groups.append((self._fn[fname], vr, val, col, len(names), fname))
            col += len(names)

    def _logger_list(self):
        log = self._log

        def push(message) -> None:
            if len(log) > 20:
                del log[:10]
            log.append(message.decode("utf-8", "replace") if message else "")
        return push

    def _open_cs(self, identifier: str) -> None:
        from fmpy import fmi2

        self._fmu = fmi2.FMU2Slave(guid=self._md.guid, unzipDirectory=self._tmpdir,
                                   modelIdentifier=identifier,
                                   instanceName=identifier)
        self._bind(_PROTOS, optional=("fmi2GetInteger", "fmi2GetBoolean"))
        self._make_groups(lambda typ: _GETTERS2[typ])
        push = self._logger_list()

        def logger(env, instance, status, category, message):
            push(message)

        cb = fmi2.fmi2CallbackFunctions()
        cb.logger = fmi2.fmi2CallbackLoggerTYPE(logger)
        cb.allocateMemory = fmi2.fmi2CallbackAllocateMemoryTYPE(fmi2.calloc)
        cb.freeMemory = fmi2.fmi2CallbackFreeMemoryTYPE(fmi2.free)
        # No fmpy.logging.addLoggerProxy here: it keeps ONE process-wide Python logger, so a
        # second instance would redirect (and later dangle) this one's.  Messages arrive
        # unformatted, which is enough for the FMUs we build (they pre-format them).
        self._callbacks = cb          # must outlive the instance
        self._logger_ref = logger
        self._instantiate()

    def _open_cs3(self, identifier: str) -> None:
        from fmpy import fmi3

        self._fmu = fmi3.FMU3Slave(guid=self._md.guid, unzipDirectory=self._tmpdir,
                                   modelIdentifier=identifier, instanceName=identifier)
        self._bind(_PROTOS3, optional=[n for n in _PROTOS3 if n.startswith("fmi3Get")
                                       or n == "fmi3SetFloat32"])
        if "fmi3GetFloat64" not in self._fn and self._n_main:
            raise SimulationError(f"{self._fmu_path}: the binary lacks fmi3GetFloat64")
        self._make_groups(lambda typ: (f"fmi3Get{'Int64' if typ == 'Enumeration' else typ}",
                                       _GETTERS3[typ]))
        push = self._logger_list()

        def logger(env, status, category, message):
            push(message)

        self._logger_ref = logger     # fmpy keeps the ctypes callback on the FMU object
        self._ev = (ctypes.c_bool * 3)()
        self._last = ctypes.c_double()
        self._instantiate()

    def _instantiate(self) -> None:
        try:
            if self._v3:
                self._fmu.instantiate(logMessage=self._logger_ref)
            else:
                self._fmu.instantiate(callbacks=self._callbacks)
        except Exception as e:
            raise SimulationError(f"cannot instantiate FMU {self._fmu_path}: "
                                  f"{_one_line(e)}") from None
        self._component = _c_void_p(self._fmu.component)

    def _check_names(self, values: Mapping[str, float]) -> None:
        for name in values:
            if name in self._params:
                continue
            v = self._vars.get(name)
            hint = _closest_hint(name, self._params)
            if v is None:
                raise SimulationError(f"{self._fmu_path} has no parameter {name!r}{hint}")
            raise SimulationError(f"{self._fmu_path}: {name!r} is {_a(v.causality)} {v.type} "
                                  f"variable, not a float parameter that can be set{hint}")

    # -- public -------------------------------------------------------------------------

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the FMU's float parameters (and inputs) that :meth:`run` accepts."""
        return tuple(self._params)

    @property
    def output_names(self) -> tuple[str, ...]:
        """Names of the recorded variables, in the order given."""
        return self._outputs

    @property
    def fmi_version(self) -> str:
        """The FMU's FMI version ("2.0", "3.0")."""
        return self._md.fmiVersion

    @property
    def times(self) -> np.ndarray:
        """Sample times (s), shape [n_t]."""
        return self._times.copy()

    def run(self, params: Mapping[str, float]) -> dict[str, np.ndarray]:
        """Simulate from 0 to ``times[-1]`` with the given parameters.

        Parameters
        ----------
        params : mapping of str to float
            Parameter values for this run (on top of ``start_values`` and the FMU defaults).

        Returns
        -------
        dict of str to ndarray, shape [n_t]
            Each recorded output at ``times`` (integer and Boolean outputs as float).

        Raises
        ------
        SimulationError
            Unknown parameter, FMI error status or non-finite output (the message names the
            parameter values).  The instance stays usable.
        """
        if self._fmi_type == "ModelExchange":
            return self._run_me(params)
        if self._component is None:
            if self._fmu is None:
                raise SimulationError(f"FMUModel for {self._fmu_path} is closed")
            self._instantiate()
        self._check_names(params)
        values = {**self._start, **params}
        try:
            floats = [float(v) for v in values.values()]
        except (TypeError, ValueError):
            raise SimulationError(f"{self._fmu_path}: parameter values must be numbers, "
                                  f"got {_fmt_params(values)}") from None
        self._log.clear()
        if self._v3:
            self._run_cs3(values, floats)
        else:
            self._run_cs2(values, floats)
        buf = self._buf
        if not np.isfinite(buf).all():
            bad = [n for n in self._outputs if not np.isfinite(buf[:, self._col[n]]).all()]
            raise SimulationError(f"{self._fmu_path}: non-finite {', '.join(bad)} for "
                                  f"{_fmt_params(values)}")
        col = self._col
        return {name: buf[:, col[name]].copy() for name in self._outputs}

    def close(self) -> None:
        """Free the instance and remove the extracted FMU."""
        if self._fmu is not None:
            try:
                if self._component is not None:
                    self._fn["fmi3FreeInstance" if self._v3 else "fmi2FreeInstance"](
                        self._component)
                self._fmu.freeLibrary()
            except Exception:
                pass
            self._fmu = None
            self._component = None
        if self._tmpdir is not None:
            self._finalizer()
            self._tmpdir = None

    def __enter__(self) -> "FMUModel":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ----------------------------------------------------------------------

    def _run_cs2(self, values: Mapping[str, float], floats: list[float]) -> None:
        fn, c = self._fn, self._component
        if fn["fmi2Reset"](c) > 1:
            self._reinstantiate()
            c = self._component
        if values:
            vr = (ctypes.c_uint32 * len(values))(*[self._params[k] for k in values])
            val = (ctypes.c_double * len(values))(*floats)
            if fn["fmi2SetReal"](c, vr, len(values), val) > 1:
                self._fail("fmi2SetReal", values)
        if fn["fmi2SetupExperiment"](c, 0, 0.0, 0.0, 0, 0.0) > 1:
            self._fail("fmi2SetupExperiment", values)
        if fn["fmi2EnterInitializationMode"](c) > 1:
            self._fail("fmi2EnterInitializationMode", values)
        if fn["fmi2ExitInitializationMode"](c) > 1:
            self._fail("fmi2ExitInitializationMode", values)

        do_step, get_real = fn["fmi2DoStep"], fn["fmi2GetReal"]
        out_vr, n_main = self._out_vr, self._n_main
        buf = self._buf
        addr, stride = buf.ctypes.data, buf.strides[0]
        groups = self._groups
        t = 0.0
        if not groups:    # the fast path: every output is Real
            for i, (t_next, dt) in enumerate(zip(self._times.tolist(), self._dt.tolist())):
                if do_step(c, t, dt, 1) > 1:
                    self._fail(f"fmi2DoStep from t={t:g} s", values)
                t = t_next
                if get_real(c, out_vr, n_main, addr + i * stride) > 1:
                    self._fail(f"fmi2GetReal at t={t:g} s", values)
            return
        for i, (t_next, dt) in enumerate(zip(self._times.tolist(), self._dt.tolist())):
            if do_step(c, t, dt, 1) > 1:
                self._fail(f"fmi2DoStep from t={t:g} s", values)
            t = t_next
            if n_main and get_real(c, out_vr, n_main, addr + i * stride) > 1:
                self._fail(f"fmi2GetReal at t={t:g} s", values)
            for getter, vr, val, j0, n, fname in groups:
                if getter(c, vr, n, val) > 1:
                    self._fail(f"{fname} at t={t:g} s", values)
                buf[i, j0:j0 + n] = val[:]

    def _run_cs3(self, values: Mapping[str, float], floats: list[float]) -> None:
        fn, c = self._fn, self._component
        if fn["fmi3Reset"](c) > 1:
            self._reinstantiate()
            c = self._component
        f64 = [k for k in values if self._param_type[k] != "Float32"]
        f32 = [k for k in values if self._param_type[k] == "Float32"]
        for names, fname, ctype in ((f64, "fmi3SetFloat64", ctypes.c_double),
                                    (f32, "fmi3SetFloat32", ctypes.c_float)):
            if not names:
                continue
            if fname not in fn:
                self._fail(f"{fname} (missing from the binary)", values)
            vr = (ctypes.c_uint32 * len(names))(*[self._params[k] for k in names])
            val = (ctype * len(names))(*[float(values[k]) for k in names])
            if fn[fname](c, vr, len(names), val, len(names)) > 1:
                self._fail(fname, values)
        if fn["fmi3EnterInitializationMode"](c, False, 0.0, 0.0, False, 0.0) > 1:
            self._fail("fmi3EnterInitializationMode", values)
        if fn["fmi3ExitInitializationMode"](c) > 1:
            self._fail("fmi3ExitInitializationMode", values)

        do_step = fn["fmi3DoStep"]
        get_f64 = fn.get("fmi3GetFloat64")
        out_vr, n_main = self._out_vr, self._n_main
        buf = self._buf
        addr, stride = buf.ctypes.data, buf.strides[0]
        ev = self._ev
        p_ev, p_term, p_early = (ctypes.addressof(ev) + k * ctypes.sizeof(ctypes.c_bool)
                                 for k in range(3))
        p_last = ctypes.addressof(self._last)
        groups = self._groups
        t = 0.0
        for i, (t_next, dt) in enumerate(zip(self._times.tolist(), self._dt.tolist())):
            if do_step(c, t, dt, True, p_ev, p_term, p_early, p_last) > 1:
                self._fail(f"fmi3DoStep from t={t:g} s", values)
            if ev[1] or ev[2]:
                self._fail(f"fmi3DoStep from t={t:g} s (the FMU "
                           f"{'asked to terminate' if ev[1] else 'returned early'} at "
                           f"t={self._last.value:g} s)", values)
            t = t_next
            if n_main and get_f64(c, out_vr, n_main, addr + i * stride, n_main) > 1:
                self._fail(f"fmi3GetFloat64 at t={t:g} s", values)
            for getter, vr, val, j0, n, fname in groups:
                if getter(c, vr, n, val, n) > 1:
                    self._fail(f"{fname} at t={t:g} s", values)
                buf[i, j0:j0 + n] = val[:]

    def _reinstantiate(self) -> None:
        if self._component is not None:
            self._fn["fmi3FreeInstance" if self._v3 else "fmi2FreeInstance"](self._component)
            self._component = None
        self._instantiate()

    def _fail(self, what: str, values: Mapping[str, float]):
        detail = f" ({self._log[-1]})" if self._log else ""
        # An instance in an error state must not leak into the next run.
        reset = self._fn["fmi3Reset" if self._v3 else "fmi2Reset"]
        if reset(self._component) > 1:
            try:
                self._reinstantiate()
            except SimulationError:
                self._component = None
        raise SimulationError(f"{self._fmu_path}: {what} failed for "
                              f"{_fmt_params(values)}{detail}")

    def _run_me(self, params: Mapping[str, float]) -> dict[str, np.ndarray]:
        import fmpy

        self._check_names(params)
        values = {**self._start, **params}
        interval = float(np.min(self._dt))
        try:
            res = fmpy.simulate_fmu(self._tmpdir, model_description=self._md,
                                    fmi_type="ModelExchange", start_time=0.0,
                                    stop_time=float(self._times[-1]), output_interval=interval,
                                    relative_tolerance=1e-8, start_values=dict(values),
                                    output=list(self._outputs))
        except Exception as e:
            raise SimulationError(f"{self._fmu_path}: ModelExchange run failed for "
                                  f"{_fmt_params(values)}: {_one_line(e)}") from None
        out = {n: np.interp(self._times, res["time"], np.asarray(res[n], dtype=float))
               for n in self._outputs}
        if not all(np.isfinite(v).all() for v in out.values()):
            raise SimulationError(f"{self._fmu_path}: non-finite output for {_fmt_params(values)}")
        return out
