"""Running an FMU fast, many times: one instance, reset between runs, driven through
direct C calls (FMI 2.0 or 3.0 Co-Simulation), or fmpy's CVode for Model Exchange."""
from __future__ import annotations

import ctypes
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from ..errors import SimulationError
from . import guard
from .common import NUMERIC_TYPES, _a, _closest_hint, _one_line, format_params
from .description import (_is_recordable, _is_settable, _read_model_description,
                          why_not_settable)

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
        CVode at rtol 1e-8 on one instance reset between runs: its derivatives are called
        from Python, a few hundred times a run, about 25 times a Co-Simulation run's cost).
    start_values : mapping, optional
        Parameter values applied on every run before the run's own.

    Notes
    -----
    Use as a context manager or call :meth:`close`: the extracted FMU lives in a temporary
    folder until then.  Parameters are the variables of :meth:`FMUInfo.settable`: float
    parameters, inputs and start values (FMI lets a tool set a local's or an output's start
    value when its ``initial`` is exact or approx), all set before initialisation.
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
        self._me = None            # fmpy's Model Exchange instance, made on the first run
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
        # Parameters, inputs and start values, all set before EnterInitializationMode.
        self._params = {v.name: v.valueReference for v in md.modelVariables if _is_settable(v)}
        self._param_type = {v.name: v.type for v in md.modelVariables if _is_settable(v)}
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

        guard.install()
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
            raise SimulationError(f"{self._fmu_path}: {name!r} {why_not_settable(v)}{hint}")

    # -- public -------------------------------------------------------------------------

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the FMU's float parameters, inputs and start values that :meth:`run`
        accepts."""
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
                                  f"got {format_params(values)}") from None
        self._log.clear()
        with guard.running(self._fmu_path, values, self._tmpdir):
            if self._v3:
                self._run_cs3(values, floats)
            else:
                self._run_cs2(values, floats)
        buf = self._buf
        if not np.isfinite(buf).all():
            bad = [n for n in self._outputs if not np.isfinite(buf[:, self._col[n]]).all()]
            raise SimulationError(f"{self._fmu_path}: non-finite {', '.join(bad)} for "
                                  f"{format_params(values)}")
        col = self._col
        return {name: buf[:, col[name]].copy() for name in self._outputs}

    def close(self) -> None:
        """Free the instance and remove the extracted FMU."""
        self._free_me()
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
                              f"{format_params(values)}{detail}")

    def _run_me(self, params: Mapping[str, float]) -> dict[str, np.ndarray]:
        import fmpy

        self._check_names(params)
        if self._tmpdir is None:
            raise SimulationError(f"FMUModel for {self._fmu_path} is closed")
        values = {**self._start, **params}
        interval = float(np.min(self._dt))
        try:
            # One instance, reset between runs, as the Co-Simulation path keeps one: loading
            # the library's functions and instantiating cost a quarter of a run.
            with guard.running(self._fmu_path, values, self._tmpdir):
                if self._me is None:
                    self._me = fmpy.instantiate_fmu(self._tmpdir, self._md, "ModelExchange")
                else:
                    self._me.reset()
                res = fmpy.simulate_fmu(self._tmpdir, model_description=self._md,
                                        fmi_type="ModelExchange", fmu_instance=self._me,
                                        start_time=0.0, stop_time=float(self._times[-1]),
                                        output_interval=interval, relative_tolerance=1e-8,
                                        start_values=dict(values), output=list(self._outputs))
        except Exception as e:
            # A failed run may leave the instance in an error state: the next one starts
            # from a fresh instance.
            self._free_me()
            raise SimulationError(f"{self._fmu_path}: ModelExchange run failed for "
                                  f"{format_params(values)}: {_one_line(e)}") from None
        out = {n: np.interp(self._times, res["time"], np.asarray(res[n], dtype=float))
               for n in self._outputs}
        if not all(np.isfinite(v).all() for v in out.values()):
            raise SimulationError(f"{self._fmu_path}: non-finite output for {format_params(values)}")
        return out

    def _free_me(self) -> None:
        """Free the Model Exchange instance (and its library), if any."""
        me, self._me = self._me, None
        if me is not None:
            try:
                me.freeInstance()
                me.freeLibrary()
            except Exception:
                pass
