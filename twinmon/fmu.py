"""Building FMUs from C sources and running them fast, many times.

An FMU source folder holds ``modelDescription.xml`` and ``sources/*.c|*.h``; :func:`build_fmu`
compiles it with the system C compiler into a ``.fmu`` cached under
``<src_dir>/.build/<hash>/`` (the hash covers the model description, the sources and the
build recipe), so an unchanged model is compiled once.  :class:`FMUModel` extracts an FMU
once, keeps one instance and resets it between runs: a run costs a few dozen direct C calls.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import weakref
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .errors import SimulationError

__all__ = ["source_hash", "build_fmu", "resolve_fmu", "FMUModel"]

# Part of the hash: changing how the binary is built must invalidate the cache.
_BUILD_RECIPE = b"twinmon-build/1: cc -O2 -shared -fPIC <sources/*.c> -lm"
_ZIP_DATE = (2020, 1, 1, 0, 0, 0)   # fixed, so that the same build gives the same bytes


# --------------------------------------------------------------------------------------
# building

def _source_files(src_dir: Path) -> list[Path]:
    sources = src_dir / "sources"
    files = [src_dir / "modelDescription.xml"]
    if sources.is_dir():
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
        Hex digest; covers each file's relative path and content (sorted) and the build recipe.
    """
    src_dir = Path(src_dir)
    h = hashlib.sha256(_BUILD_RECIPE)
    for f in _source_files(src_dir):
        h.update(f.relative_to(src_dir).as_posix().encode() + b"\0")
        h.update(f.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def _model_identifier(md_path: Path) -> str:
    try:
        root = ET.parse(md_path).getroot()
    except (OSError, ET.ParseError) as e:
        raise SimulationError(f"cannot read {md_path}: {e}") from None
    for kind in ("CoSimulation", "ModelExchange"):
        el = root.find(kind)
        if el is not None and el.get("modelIdentifier"):
            return el.get("modelIdentifier")
    raise SimulationError(f"{md_path} declares no modelIdentifier")


def _fmi_headers() -> Path:
    import fmpy
    return Path(os.path.dirname(fmpy.__file__)) / "c-code"


def build_fmu(src_dir: Path | str, force: bool = False) -> Path:
    """Compile an FMU source folder into a ``.fmu`` (cached by :func:`source_hash`).

    Parameters
    ----------
    src_dir : Path or str
        Folder with ``modelDescription.xml`` and ``sources/``.
    force : bool
        Rebuild even when the cached ``.fmu`` exists.

    Returns
    -------
    Path
        ``<src_dir>/.build/<hash[:16]>/<modelIdentifier>.fmu``.

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
    identifier = _model_identifier(md)
    c_files = sorted((src_dir / "sources").glob("*.c"))
    if not c_files:
        raise SimulationError(f"{src_dir / 'sources'} holds no C sources")
    digest = source_hash(src_dir)
    out_dir = src_dir / ".build" / digest[:16]
    out = out_dir / f"{identifier}.fmu"
    if out.is_file() and not force:
        return out

    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="twinmon-build-") as tmp:
        lib_rel = f"binaries/{fmpy.platform}/{identifier}{fmpy.sharedLibraryExtension}"
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
# running

_c_int, _c_void_p, _c_double, _c_size_t = ctypes.c_int, ctypes.c_void_p, ctypes.c_double, ctypes.c_size_t
_PROTOS = {
    "fmi2Reset": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi2SetupExperiment": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_int, _c_double, _c_double,
                                            _c_int, _c_double),
    "fmi2EnterInitializationMode": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi2ExitInitializationMode": ctypes.CFUNCTYPE(_c_int, _c_void_p),
    "fmi2SetReal": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p),
    "fmi2GetReal": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_void_p, _c_size_t, _c_void_p),
    "fmi2DoStep": ctypes.CFUNCTYPE(_c_int, _c_void_p, _c_double, _c_double, _c_int),
    "fmi2FreeInstance": ctypes.CFUNCTYPE(None, _c_void_p),
}
_STATUS = ["ok", "warning", "discard", "error", "fatal", "pending"]


def _fmt_params(values: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.6g}" for k, v in values.items()) or "defaults"


class FMUModel:
    """One FMU instance, reset and rerun for each parameter set.

    Parameters
    ----------
    fmu_path : Path or str
        The ``.fmu`` file (use :func:`resolve_fmu` for a source folder).
    outputs : sequence of str
        Real variables to record.
    times : ndarray, shape [n_t]
        Sorted sample times (s), all > 0; the run starts at 0.
    fmi_type : str
        ``"CoSimulation"`` (fast path) or ``"ModelExchange"`` (fmpy's CVode, slow; for checks).
    start_values : mapping, optional
        Parameter values applied on every run before the run's own.

    Notes
    -----
    Use as a context manager or call :meth:`close`: the extracted FMU lives in a temporary
    folder until then.
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
        try:
            md = fmpy.read_model_description(str(self._fmu_path))
        except Exception as e:  # fmpy raises plain exceptions for bad files
            raise SimulationError(f"cannot read FMU {self._fmu_path}: {e}") from None
        self._md = md
        kind = md.coSimulation if fmi_type == "CoSimulation" else md.modelExchange
        if kind is None:
            raise SimulationError(f"{self._fmu_path} does not support {fmi_type}")
        self._vars = {v.name: v for v in md.modelVariables}
        self._params = {v.name: v.valueReference for v in md.modelVariables
                        if v.causality in ("parameter", "input") and v.type == "Real"}
        self._outputs = tuple(outputs)
        for name in self._outputs:
            v = self._vars.get(name)
            if v is None or v.type != "Real":
                raise SimulationError(f"{self._fmu_path} has no Real variable {name!r} to record")
        self._start = dict(start_values or {})
        self._check_names(self._start)

        self._tmpdir = tempfile.mkdtemp(prefix="twinmon-fmu-")
        self._finalizer = weakref.finalize(self, shutil.rmtree, self._tmpdir, True)
        try:
            fmpy.extract(str(self._fmu_path), unzipdir=self._tmpdir)
        except Exception as e:
            self.close()
            raise SimulationError(f"cannot extract FMU {self._fmu_path}: {e}") from None

        n_out = len(self._outputs)
        self._out_vr = (ctypes.c_uint32 * n_out)(*[self._vars[n].valueReference for n in self._outputs])
        self._buf = np.empty((self._times.size, n_out))
        self._dt = np.diff(np.concatenate(([0.0], self._times)))
        self._log: list[str] = []
        if fmi_type == "CoSimulation":
            self._open_cs(kind.modelIdentifier)

    # -- set-up -------------------------------------------------------------------------

    def _open_cs(self, identifier: str) -> None:
        from fmpy import fmi2

        self._fmu = fmi2.FMU2Slave(guid=self._md.guid, unzipDirectory=self._tmpdir,
                                   modelIdentifier=identifier,
                                   instanceName=identifier)
        self._fn = {name: proto(ctypes.cast(getattr(self._fmu.dll, name), _c_void_p).value)
                    for name, proto in _PROTOS.items()}

        log = self._log

        def logger(env, instance, status, category, message):
            if len(log) > 20:
                del log[:10]
            log.append(message.decode("utf-8", "replace") if message else "")

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

    def _instantiate(self) -> None:
        try:
            self._fmu.instantiate(callbacks=self._callbacks)
        except Exception as e:
            raise SimulationError(f"cannot instantiate FMU {self._fmu_path}: {e}") from None
        self._component = _c_void_p(self._fmu.component)

    def _check_names(self, values: Mapping[str, float]) -> None:
        for name in values:
            if name not in self._params:
                raise SimulationError(f"{self._fmu_path} has no parameter {name!r} "
                                      f"(known: {', '.join(sorted(self._params))})")

    # -- public -------------------------------------------------------------------------

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the FMU's Real parameters (and inputs) that :meth:`run` accepts."""
        return tuple(self._params)

    @property
    def output_names(self) -> tuple[str, ...]:
        """Names of the recorded variables, in the order given."""
        return self._outputs

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
            Each recorded output at ``times``.

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
        fn, c = self._fn, self._component
        self._log.clear()

        if fn["fmi2Reset"](c) > 1:
            self._reinstantiate()
            c = self._component
        if values:
            vr = (ctypes.c_uint32 * len(values))(*[self._params[k] for k in values])
            try:
                val = (ctypes.c_double * len(values))(*[float(v) for v in values.values()])
            except (TypeError, ValueError):
                raise SimulationError(f"{self._fmu_path}: parameter values must be numbers, "
                                      f"got {_fmt_params(values)}") from None
            if fn["fmi2SetReal"](c, vr, len(values), val) > 1:
                self._fail("fmi2SetReal", values)
        if fn["fmi2SetupExperiment"](c, 0, 0.0, 0.0, 0, 0.0) > 1:
            self._fail("fmi2SetupExperiment", values)
        if fn["fmi2EnterInitializationMode"](c) > 1:
            self._fail("fmi2EnterInitializationMode", values)
        if fn["fmi2ExitInitializationMode"](c) > 1:
            self._fail("fmi2ExitInitializationMode", values)

        do_step, get_real = fn["fmi2DoStep"], fn["fmi2GetReal"]
        out_vr, n_out = self._out_vr, len(self._outputs)
        buf = self._buf
        addr, stride = buf.ctypes.data, buf.strides[0]
        t = 0.0
        for i, (t_next, dt) in enumerate(zip(self._times.tolist(), self._dt.tolist())):
            if do_step(c, t, dt, 1) > 1:
                self._fail(f"fmi2DoStep from t={t:g} s", values)
            t = t_next
            if get_real(c, out_vr, n_out, addr + i * stride) > 1:
                self._fail(f"fmi2GetReal at t={t:g} s", values)
        if not np.isfinite(buf).all():
            bad = [n for j, n in enumerate(self._outputs) if not np.isfinite(buf[:, j]).all()]
            raise SimulationError(f"{self._fmu_path}: non-finite {', '.join(bad)} for "
                                  f"{_fmt_params(values)}")
        return {name: buf[:, j].copy() for j, name in enumerate(self._outputs)}

    def close(self) -> None:
        """Free the instance and remove the extracted FMU."""
        if self._fmu is not None:
            try:
                if self._component is not None:
                    self._fn["fmi2FreeInstance"](self._component)
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

    def _reinstantiate(self) -> None:
        if self._component is not None:
            self._fn["fmi2FreeInstance"](self._component)
            self._component = None
        self._instantiate()

    def _fail(self, what: str, values: Mapping[str, float]):
        detail = f" ({self._log[-1]})" if self._log else ""
        # An instance in an error state must not leak into the next run.
        if self._fn["fmi2Reset"](self._component) > 1:
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
                                  f"{_fmt_params(values)}: {e}") from None
        out = {n: np.interp(self._times, res["time"], res[n]) for n in self._outputs}
        if not all(np.isfinite(v).all() for v in out.values()):
            raise SimulationError(f"{self._fmu_path}: non-finite output for {_fmt_params(values)}")
        return out
