"""Tests of twinmon.fmu and of the PumpCircuit FMU against an independent scipy integration.

The reference below is written from the equations of docs/model.md (not ported from
the C sources): same equations, same guards, integrated with scipy's DOP853 at rtol 1e-10.
"""
from __future__ import annotations

import math
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from twinmon.artifacts import file_sha256
from twinmon.errors import SimulationError
from twinmon.fmu import FMUModel, build_fmu, resolve_fmu, source_hash

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "fmus" / "PumpCircuit"
TIMES = np.arange(2.0, 50.0 + 1e-9, 2.0)
OUTPUTS = ["sensor.m_flow", "pump.m_flow", "motor.w", "pump.dp", "motor.I", "nonphysical"]

DEFAULTS = {
    "motor.D": 10.0, "pump.b2": 3.61, "sensor.tau": 0.0, "sensor.gain": 1.0,
    "valve.opening_time": 0.0, "pipe.fouling": 0.0, "pump.leak": 0.0,
    "motor.start_delay": 0.0, "motor.supply_ratio": 1.0, "valve.opening": 0.16425,
}
EFFECTS_ON = {
    "sensor.tau": 2.0, "sensor.gain": 0.95, "valve.opening_time": 8.0, "pipe.fouling": 0.3,
    "pump.leak": 5e-5, "motor.start_delay": 3.0, "motor.supply_ratio": 0.9,
}
EFFECTS_OFF = {"sensor.tau": 0.0, "sensor.gain": 1.0, "valve.opening_time": 0.0,
               "pipe.fouling": 0.0, "pump.leak": 0.0, "motor.start_delay": 0.0,
               "motor.supply_ratio": 1.0}
DESIGN_POINTS = [(10.0, 3.61), (5.0, 3.0), (25.0, 2.6), (15.0, 3.9)]


# ----------------------------------------------------------------------------------------
# independent reference model (docs/model.md)

UALIM, VROT, LM, RM, KI, JM, JP = 380.0, 1400.0, 1.0, 1e-5, 1.0, 4.0, 10.0
A1, A2, A3 = -88.67, 0.0, 43.15
B1, B3, RHMIN, CF0 = -3.7751, -0.0075464, 0.05, 10.0
RHO, G = 998.0, 9.80665
L, DP, LAM = 10.0, 0.2, 0.03
AREA = math.pi * DP ** 2 / 4
KV, CVMAX = 1.733e12, 8005.42
WN = VROT * math.pi / 30
KM = 30 * UALIM / (math.pi * VROT)
WEPS = 1e-3   # rad/s


def _head(qi, R):
    return A1 * qi * abs(qi) + A2 * qi * R + A3 * R * abs(R)


def _impeller_flow(Q, R, leak):
    """qi = Q/rho + leak*sqrt(max(dp(qi), 0)), solved with brentq."""
    q0 = Q / RHO
    if leak == 0.0:
        return q0

    def f(q):
        return q - q0 - leak * math.sqrt(max(RHO * G * _head(q, R), 0.0))

    hi = q0 + leak * math.sqrt(max(RHO * G * _head(q0, R), 0.0))
    if hi == q0:
        return q0
    return brentq(f, q0, hi, xtol=1e-300, rtol=8.9e-16, maxiter=500)


def _algebraic(t, x, p):
    w, I, Q, y = x
    R = w / WN
    qi = _impeller_flow(Q, R, p["pump.leak"])
    hn = _head(qi, R)
    if abs(R) < 1e-6:
        rh_raw = B3
    else:
        rh_raw = B1 * (qi / R) ** 2 + p["pump.b2"] * (qi / R) + B3
    rh = max(rh_raw, RHMIN)
    Ch = RHO * G * qi * hn * w / (rh * (w * w + WEPS ** 2))   # regularised at w = 0
    return R, qi, hn, rh_raw, rh, Ch


def _opening(t, p):
    T = p["valve.opening_time"]
    if T > 0:
        return p["valve.opening"] * max(min(t / T, 1.0), 0.01)
    return p["valve.opening"]


def _rhs(t, x, p, motor_on):
    w, I, Q, y = x
    R, qi, hn, _, _, Ch = _algebraic(t, x, p)
    Cf = CF0 * (1 - abs(R)) if abs(R) < 1 else 0.0
    Um = p["motor.supply_ratio"] * UALIM if motor_on else 0.0
    kf = 1 + p["pipe.fouling"]
    Cv = _opening(t, p) * CVMAX
    dP_pipe = kf * LAM * L / DP * Q * abs(Q) / (2 * AREA ** 2 * RHO)
    dP_valve = kf * KV * Q * abs(Q) / (RHO ** 2 * Cv ** 2)
    tau = p["sensor.tau"]
    return [
        (KI * I - p["motor.D"] * w - Ch - Cf) / (JM + JP),
        (Um - KM * w - RM * I) / LM,
        (RHO * G * hn - dP_pipe - dP_valve) / (L / AREA),
        (Q - y) / tau if tau > 0 else 0.0,
    ]


def _nonphysical_now(x, p):
    R, qi, _, rh_raw, _, _ = _algebraic(0.0, x, p)
    return R > 0.1 and rh_raw <= RHMIN and qi / R > p["pump.b2"] / (2 * abs(B1))


def reference(params, times=TIMES):
    """Outputs of the documented model at ``times`` (scipy DOP853, rtol 1e-10)."""
    p = {**DEFAULTS, **params}
    t_end = float(times[-1])
    cuts = {0.0, t_end}
    if p["motor.start_delay"] > 0:
        cuts.add(p["motor.start_delay"])
    if p["valve.opening_time"] > 0:
        cuts |= {0.01 * p["valve.opening_time"], p["valve.opening_time"]}
    cuts = sorted(c for c in cuts if c <= t_end)
    x = np.zeros(4)
    ts, xs = [], []
    for a, b in zip(cuts[:-1], cuts[1:]):
        on = a >= p["motor.start_delay"]
        grid = np.linspace(a, b, max(2, int(math.ceil((b - a) / 0.01)) + 1))
        keep = [t for t in times if a < t <= b]
        t_eval = np.unique(np.concatenate([grid, keep]))
        sol = solve_ivp(_rhs, (a, b), x, method="DOP853", t_eval=t_eval, args=(p, on),
                        rtol=1e-10, atol=[1e-8, 1e-7, 1e-8, 1e-8], max_step=0.05)
        assert sol.success, sol.message
        ts.append(sol.t)
        xs.append(sol.y.T)
        x = sol.y[:, -1]
    ts = np.concatenate(ts)
    xs = np.concatenate(xs)
    flag = np.maximum.accumulate([1.0 if _nonphysical_now(xi, p) else 0.0 for xi in xs])
    out = {k: [] for k in OUTPUTS}
    for t in times:
        i = int(np.flatnonzero(np.isclose(ts, t, rtol=0, atol=1e-9))[-1])
        w, I, Q, y = xs[i]
        _, qi, hn, _, _, _ = _algebraic(t, xs[i], p)
        out["sensor.m_flow"].append(p["sensor.gain"] * (y if p["sensor.tau"] > 0 else Q))
        out["pump.m_flow"].append(Q)
        out["motor.w"].append(w)
        out["pump.dp"].append(RHO * G * hn)
        out["motor.I"].append(I)
        out["nonphysical"].append(flag[i])
    return {k: np.asarray(v) for k, v in out.items()}


def rel_err(fmu, ref):
    scale = np.max(np.abs(ref))
    return float(np.max(np.abs(fmu - ref) / np.maximum(np.abs(ref), 1e-3 * scale)))


# ----------------------------------------------------------------------------------------
# fixtures

@pytest.fixture(scope="session")
def fmu_path() -> Path:
    return build_fmu(SRC)


@pytest.fixture(scope="module")
def model(fmu_path):
    with FMUModel(fmu_path, OUTPUTS, TIMES) as m:
        yield m


# ----------------------------------------------------------------------------------------
# tests

def test_validate_fmu(fmu_path):
    from fmpy.validation import validate_fmu
    assert validate_fmu(str(fmu_path)) == []


CASES = [dict(zip(("motor.D", "pump.b2"), pt)) for pt in DESIGN_POINTS] + \
        [{"motor.D": 12.0, "pump.b2": 3.3, name: value} for name, value in EFFECTS_ON.items()] + \
        [{"motor.D": 10.0, "pump.b2": 1.6}]   # non-physical run


@pytest.mark.parametrize("params", CASES, ids=lambda p: ",".join(f"{k}={v:g}" for k, v in p.items()))
def test_matches_scipy_reference(model, params):
    got = model.run(params)
    ref = reference(params)
    for name in OUTPUTS:
        if name == "nonphysical":
            np.testing.assert_array_equal(got[name], ref[name])
        else:
            assert rel_err(got[name], ref[name]) < 1e-4, (name, rel_err(got[name], ref[name]))


def test_nonphysical_triggers_for_low_b2(model):
    assert model.run({"pump.b2": 1.6})["nonphysical"][-1] == 1.0
    assert model.run({})["nonphysical"].max() == 0.0


@pytest.mark.parametrize("name", sorted(EFFECTS_OFF))
def test_effect_off_gives_base_model(model, name):
    for base in ({}, {"motor.D": 18.0, "pump.b2": 2.9}):
        a = model.run(base)
        b = model.run({**base, name: EFFECTS_OFF[name]})
        for k in OUTPUTS:
            np.testing.assert_allclose(b[k], a[k], rtol=1e-12, atol=0)


def test_effects_change_the_output(model):
    base = model.run({})["sensor.m_flow"]
    for name, value in EFFECTS_ON.items():
        assert np.max(np.abs(model.run({name: value})["sensor.m_flow"] - base)) > 1.0, name


def test_model_exchange_agrees_with_cosimulation(fmu_path, model):
    import fmpy
    for params in ({}, {"motor.D": 20.0, "pump.b2": 2.8, "motor.start_delay": 3.0,
                        "valve.opening_time": 8.0, "sensor.tau": 2.0},
                   {"pump.b2": 1.6, "pump.leak": 5e-5}):
        res = fmpy.simulate_fmu(str(fmu_path), fmi_type="ModelExchange", stop_time=50.0,
                                output_interval=2.0, relative_tolerance=1e-8,
                                start_values=params, output=OUTPUTS)
        cs = model.run(params)
        for name in OUTPUTS:
            me = np.interp(TIMES, res["time"], res[name])
            if name == "nonphysical":
                np.testing.assert_array_equal(me, cs[name])
            else:
                assert rel_err(me, cs[name]) < 1e-3, (name, rel_err(me, cs[name]))


def test_build_cache(tmp_path, fmu_path):
    src = tmp_path / "PumpCircuit"
    shutil.copytree(SRC / "sources", src / "sources")
    shutil.copy(SRC / "modelDescription.xml", src / "modelDescription.xml")
    first = build_fmu(src)
    mtime = first.stat().st_mtime_ns
    time.sleep(0.01)
    assert build_fmu(src) == first
    assert first.stat().st_mtime_ns == mtime
    assert resolve_fmu(src) == first
    h = source_hash(src)
    with open(src / "sources" / "model.c", "a") as fh:
        fh.write("\n/* changed */\n")
    assert source_hash(src) != h
    second = build_fmu(src)
    assert second != first and second.parent.name == source_hash(src)[:16]
    assert file_sha256(first) != file_sha256(second)


def test_build_error_names_folder(tmp_path):
    src = tmp_path / "Broken"
    shutil.copytree(SRC / "sources", src / "sources")
    shutil.copy(SRC / "modelDescription.xml", src / "modelDescription.xml")
    (src / "sources" / "model.c").write_text("this is not C;\n")
    with pytest.raises(SimulationError, match="Broken") as e:
        build_fmu(src)
    assert "\n" not in str(e.value)


def test_resolve_fmu(fmu_path, tmp_path):
    assert resolve_fmu(fmu_path) == fmu_path
    with pytest.raises(SimulationError, match="nowhere"):
        resolve_fmu(tmp_path / "nowhere")


def test_fmumodel_reuse_and_errors(model):
    a = model.run({"motor.D": 14.0, "pump.b2": 3.1})
    b = model.run({"motor.D": 14.0, "pump.b2": 3.1})
    for k in OUTPUTS:
        np.testing.assert_array_equal(a[k], b[k])
    with pytest.raises(SimulationError, match="no_such_param"):
        model.run({"no_such_param": 1.0})
    assert set(model.output_names) == set(OUTPUTS)
    assert "motor.D" in model.parameter_names and "pump.b2" in model.parameter_names


def test_a_parameter_value_that_is_not_a_number_is_a_simulation_error(model):
    # The message formatting every value as a number raised a TypeError of its own.
    with pytest.raises(SimulationError, match="must be numbers.*pump.b2='fast'"):
        model.run({"motor.D": 14.0, "pump.b2": "fast"})
    with pytest.raises(SimulationError, match="must be numbers.*motor.D=.*start"):
        model.run({"motor.D": {"start": 14.0}})


def test_fmumodel_recovers_after_failure(model):
    ok = model.run({})
    with pytest.raises(SimulationError, match="motor.D=nan|pump.b2"):
        model.run({"motor.D": float("nan"), "pump.b2": 3.0})
    again = model.run({})
    np.testing.assert_array_equal(again["sensor.m_flow"], ok["sensor.m_flow"])


def test_start_values_apply_to_every_run(fmu_path):
    with FMUModel(fmu_path, ["sensor.m_flow"], TIMES, start_values={"sensor.gain": 0.5}) as m:
        half = m.run({})["sensor.m_flow"]
        full = m.run({"sensor.gain": 1.0})["sensor.m_flow"]
    np.testing.assert_allclose(half, 0.5 * full, rtol=1e-15)


def test_fmumodel_close_removes_extraction(fmu_path):
    m = FMUModel(fmu_path, ["pump.m_flow"], TIMES)
    tmp = m._tmpdir
    assert os.path.isdir(tmp)
    m.close()
    assert not os.path.exists(tmp)


def test_fmumodel_speed(model):
    n = 200
    t0 = time.perf_counter()
    for i in range(n):
        model.run({"motor.D": 10.0 + 0.05 * i, "pump.b2": 3.61 - 0.005 * i})
    rate = n / (time.perf_counter() - t0)
    assert rate > 300   # >= 1000/s on an idle core; loose bound for loaded CI machines


def test_step_guard_fails_cleanly_instead_of_hanging(model):
    # a 1 ns flowmeter lag is far too stiff for the explicit integrator: the FMU must give up
    t0 = time.perf_counter()
    with pytest.raises(SimulationError, match=r"sensor.tau=1e-09.*internal steps"):
        model.run({"sensor.tau": 1e-9})
    assert time.perf_counter() - t0 < 5.0
    assert model.run({})["nonphysical"].max() == 0.0


def test_fmumodel_model_exchange(fmu_path, model):
    with FMUModel(fmu_path, OUTPUTS, TIMES, fmi_type="ModelExchange") as me:
        a = me.run({"motor.D": 14.0})
    b = model.run({"motor.D": 14.0})
    for name in OUTPUTS:
        assert rel_err(a[name], b[name]) < 1e-3 if name != "nonphysical" else \
            np.array_equal(a[name], b[name])


def test_model_exchange_instance_is_reused_and_reset(fmu_path):
    # One instance serves every run (reset between them): a run repeated after others, and
    # after a run the FMU refused, gives the first run's arrays bit for bit.
    with FMUModel(fmu_path, OUTPUTS, TIMES, fmi_type="ModelExchange") as me:
        a = me.run({"motor.D": 14.0})
        first = me._me
        me.run({"motor.D": 20.0, "pump.b2": 3.2})
        assert me._me is first
        with pytest.raises(SimulationError, match=r"ModelExchange run failed for motor.D=nan"):
            me.run({"motor.D": float("nan")})
        b = me.run({"motor.D": 14.0})
    assert me._me is None
    for name in OUTPUTS:
        assert np.array_equal(a[name], b[name])


def test_fmumodel_rejects_bad_construction(fmu_path):
    with pytest.raises(SimulationError, match="no_such_output"):
        FMUModel(fmu_path, ["no_such_output"], TIMES)
    with pytest.raises(SimulationError, match="times"):
        FMUModel(fmu_path, ["pump.m_flow"], np.array([0.0, 1.0]))
    with pytest.raises(SimulationError, match="bogus"):
        FMUModel(fmu_path, ["pump.m_flow"], TIMES, start_values={"bogus": 1.0})


# ----------------------------------------------------------------------------------------
# FMI 3.0, introspection, broken files (the DC drive FMUs: fmus/DCDrive, fmus/DCDrive3)

from twinmon.fmu import (FMUInfo, VariableInfo, closest_names, describe_fmu,  # noqa: E402
                         why_not_settable)

DC2 = ROOT / "fmus" / "DCDrive"
DC3 = ROOT / "fmus" / "DCDrive3"
DC_TIMES = np.round(np.arange(0.1, 3.0 + 1e-9, 0.1), 10)


@pytest.fixture(scope="session")
def dc2_fmu() -> Path:
    return build_fmu(DC2)


@pytest.fixture(scope="session")
def dc3_fmu() -> Path:
    return build_fmu(DC3)


def test_built_fmu_is_world_readable(fmu_path, dc3_fmu, tmp_path):
    assert fmu_path.stat().st_mode & 0o777 == 0o644
    assert dc3_fmu.stat().st_mode & 0o777 == 0o644
    # a cached file left private by an older build is fixed on the next call
    src = tmp_path / "PumpCircuit"
    shutil.copytree(SRC / "sources", src / "sources")
    shutil.copy(SRC / "modelDescription.xml", src / "modelDescription.xml")
    out = build_fmu(src)
    os.chmod(out, 0o600)
    assert build_fmu(src) == out and out.stat().st_mode & 0o777 == 0o644


def test_fmi3_build_layout(dc2_fmu, dc3_fmu):
    import zipfile

    import fmpy
    with zipfile.ZipFile(dc3_fmu) as zf:
        names = set(zf.namelist())
    assert f"binaries/{fmpy.platform_tuple}/DCDrive3{fmpy.sharedLibraryExtension}" in names
    assert "sources/buildDescription.xml" in names
    with zipfile.ZipFile(dc2_fmu) as zf:
        assert f"binaries/{fmpy.platform}/DCDrive{fmpy.sharedLibraryExtension}" in zf.namelist()


def test_describe_fmu_fields(fmu_path, dc3_fmu):
    info = describe_fmu(DC3)                       # a source folder: built, then described
    assert isinstance(info, FMUInfo) and info.path == dc3_fmu
    assert (info.fmi_version, info.model_name) == ("3.0", "DCDrive3")
    assert info.co_simulation and info.model_exchange and "DC motor" in info.description
    b = info.variables["bearing.b"]
    assert b == VariableInfo(name="bearing.b", causality="parameter", variability="fixed",
                             type="Float64", start=0.001, unit="N.m.s/rad",
                             description=b.description, initial="exact", min=0.0)
    assert b.is_float and b.is_numeric and "bearing" in b.description
    stalled = info.variables["stalled"]
    assert (stalled.type, stalled.causality, stalled.is_float, stalled.is_numeric) == \
        ("Int32", "output", False, True)
    assert info.variables["time"].causality == "independent"
    tunable = [v.name for v in info.tunable_parameters()]
    assert tunable == ["bearing.b", "winding.R", "tacho.tau", "tacho.gain", "supply.ratio",
                       "load.extra", "supply.delay", "fan.c"]
    recordable = [v.name for v in info.recordable()]
    assert recordable[:5] == ["tacho.w", "shaft.w", "armature.i", "shaft.torque", "stalled"]
    assert "state.w" in recordable and "time" not in recordable and "bearing.b" not in recordable

    pump = describe_fmu(fmu_path)
    assert (pump.fmi_version, pump.model_name) == ("2.0", "PumpCircuit")
    d = pump.variables["motor.D"]
    assert (d.type, d.start, d.unit, d.variability) == ("Real", 10.0, "N.m.s/rad", "fixed")
    # The declared range: a damping has min 0, the pump coefficient no declared bound.
    assert (d.min, d.max) == (0.0, None)
    assert (pump.variables["pump.b2"].min, pump.variables["pump.b2"].max) == (None, None)
    assert {v.name for v in pump.tunable_parameters()} == set(DEFAULTS)
    assert [v.name for v in pump.recordable()][:6] == OUTPUTS


def test_closest_names():
    pool = ["bearing.b", "winding.R", "tacho.w", "tacho.tau", "shaft.w"]
    assert closest_names("winding.r", pool)[0] == "winding.R"
    assert closest_names("tacho_w", pool, n=2) == ["tacho.w", "tacho.tau"]
    assert len(closest_names("x", pool, n=10)) <= len(pool)
    assert closest_names("anything", []) == []


def _broken_fmus(good: Path, folder: Path) -> dict[str, Path]:
    import zipfile
    data = good.read_bytes()
    files = {"empty": b"", "truncated": data[: len(data) // 2], "text": b"not a zip\n"}
    corrupt = bytearray(data)
    mid = len(corrupt) // 3
    corrupt[mid:mid + 200] = bytes(x ^ 0xFF for x in corrupt[mid:mid + 200])
    files["corrupt"] = bytes(corrupt)
    out = {}
    for name, content in files.items():
        out[name] = folder / f"{name}.fmu"
        out[name].write_bytes(content)
    out["no_model_description"] = folder / "no_md.fmu"
    with zipfile.ZipFile(out["no_model_description"], "w") as zf:
        zf.writestr("binaries/readme.txt", "nothing here")
    out["bad_xml"] = folder / "bad_xml.fmu"
    with zipfile.ZipFile(out["bad_xml"], "w") as zf:
        zf.writestr("modelDescription.xml", '<fmiModelDescription fmiVersion="2.0"><oops')
    return out


@pytest.mark.parametrize("kind", ["empty", "truncated", "text", "corrupt",
                                  "no_model_description", "bad_xml"])
def test_broken_fmu_is_one_line_simulation_error(kind, dc2_fmu, tmp_path):
    path = _broken_fmus(dc2_fmu, tmp_path)[kind]
    for call in (lambda: describe_fmu(path), lambda: FMUModel(path, ["tacho.w"], DC_TIMES)):
        with pytest.raises(SimulationError) as e:
            call()
        msg = str(e.value)
        assert "\n" not in msg and str(path) in msg, msg
        assert "Traceback" not in msg and len(msg) < 500


def test_missing_fmu_is_simulation_error(tmp_path):
    with pytest.raises(SimulationError, match="nowhere.fmu"):
        describe_fmu(tmp_path / "nowhere.fmu")


def test_unknown_names_suggest_closest(dc2_fmu):
    with pytest.raises(SimulationError, match=r"'tacho_w'.*closest: tacho\.w"):
        FMUModel(dc2_fmu, ["tacho_w"], DC_TIMES)
    with FMUModel(dc2_fmu, ["tacho.w"], DC_TIMES) as m:
        with pytest.raises(SimulationError, match=r"'bearing_b'.*closest: bearing\.b"):
            m.run({"bearing_b": 2e-3})
        with pytest.raises(SimulationError, match=r"'tacho.w' is an output Real the FMU "
                           r"calculates \(initial=\"calculated\".*FMI lets no tool set it"):
            m.run({"tacho.w": 1.0})


def test_fmi3_cosimulation_run(dc3_fmu, dc2_fmu):
    outs = ["tacho.w", "armature.i", "stalled"]
    with FMUModel(dc3_fmu, outs, DC_TIMES) as m3, FMUModel(dc2_fmu, outs, DC_TIMES) as m2:
        assert m3.fmi_version == "3.0" and m2.fmi_version == "2.0"
        assert "bearing.b" in m3.parameter_names
        for params in ({}, {"winding.R": 4.0}, {"bearing.b": 5e-3, "supply.delay": 0.3}):
            a, b = m3.run(params), m2.run(params)
            for k in outs:
                np.testing.assert_allclose(a[k], b[k], rtol=1e-9, atol=0)
        assert m3.run({"winding.R": 4.0})["stalled"][-1] == 1.0      # Int32 read as float
        # the instance survives a failed run (non-finite parameter rejected by the FMU)
        with pytest.raises(SimulationError, match="fmi3SetFloat64 failed"):
            m3.run({"winding.R": float("nan")})
        np.testing.assert_array_equal(m3.run({})["tacho.w"], m2.run({})["tacho.w"])
        # start values and output order as given
        with FMUModel(dc3_fmu, ["stalled", "tacho.w"], DC_TIMES,
                      start_values={"tacho.gain": 0.5}) as half:
            r = half.run({})
            assert list(r) == ["stalled", "tacho.w"]
            np.testing.assert_allclose(r["tacho.w"], 0.5 * m2.run({})["tacho.w"], rtol=1e-15)


def test_fmi3_model_exchange_run(dc3_fmu, dc2_fmu):
    with FMUModel(dc3_fmu, ["tacho.w", "stalled"], DC_TIMES, fmi_type="ModelExchange") as me, \
            FMUModel(dc2_fmu, ["tacho.w", "stalled"], DC_TIMES) as cs:
        for params in ({"bearing.b": 3e-3}, {"winding.R": 4.0}):
            a, b = me.run(params), cs.run(params)
            np.testing.assert_allclose(a["tacho.w"], b["tacho.w"], rtol=1e-4)
            np.testing.assert_array_equal(a["stalled"], b["stalled"])


def test_fmi2_integer_output_is_read(tmp_path):
    """An FMI 2.0 Integer output goes through fmi2GetInteger (the Real-only fast path is not
    used): the DC drive's stall flag declared as an Integer."""
    src = tmp_path / "DCDriveInt"
    shutil.copytree(DC2 / "sources", src / "sources")
    md = (DC2 / "modelDescription.xml").read_text()
    md = md.replace('(latched)"><Real unit="1"/>', '(latched)"><Integer/>')
    assert "<Integer/>" in md
    (src / "modelDescription.xml").write_text(md)
    c = (src / "sources" / "fmi2.c").read_text()
    c = c.replace(
        "fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])\n"
        "{ (void)c; (void)vr; (void)value; return nvr == 0 ? fmi2OK : fmi2Error; }",
        "fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer value[])\n"
        "{ for (size_t k = 0; k < nvr; ++k) { if (vr[k] != VR_STALLED) return fmi2Error;"
        " value[k] = ((inst_t *)c)->s.stalled; } return fmi2OK; }")
    assert "value[k] = ((inst_t *)c)->s.stalled" in c
    (src / "sources" / "fmi2.c").write_text(c)
    fmu = build_fmu(src)
    with FMUModel(fmu, ["stalled", "tacho.w"], DC_TIMES) as m:
        r = m.run({"winding.R": 4.0})
        assert r["stalled"][-1] == 1.0 and r["stalled"][0] == 0.0
        assert m.run({})["stalled"].max() == 0.0
    assert describe_fmu(fmu).variables["stalled"].type == "Integer"


# ----------------------------------------------------------------------------------------
# start values: a state's initial value set like a parameter, before initialisation

def test_start_values_are_listed_with_their_fmi_attributes(dc2_fmu, dc3_fmu):
    for fmu in (dc2_fmu, dc3_fmu):
        info = describe_fmu(fmu)
        starts = [v.name for v in info.start_values()]
        # the three states (initial="exact", start="0"); not their derivatives (no start),
        # not the outputs (initial="calculated")
        assert starts == ["state.i", "state.w", "tacho.y"], fmu
        assert info.variables["state.w"].initial == "exact"
        assert [v.name for v in info.settable()][-3:] == starts
        assert not info.variables["tacho.w"].is_settable
        assert not info.variables["der(state.w)"].is_settable
        assert why_not_settable(info.variables["state.w"]) == ""
        assert why_not_settable(info.variables["bearing.b"]) == ""
        assert "FMI lets no tool set it" in why_not_settable(info.variables["tacho.w"])


@pytest.mark.parametrize("which", ["dc2", "dc3"])
def test_a_start_value_sets_the_initial_state_and_does_not_leak(which, dc2_fmu, dc3_fmu):
    """The shaft already turning at 150 rad/s when the supply switches on (state.w's start
    value): faster at first than from rest, and the next run from rest is the same as the
    first one (the reset restores the model description's start value)."""
    fmu = dc2_fmu if which == "dc2" else dc3_fmu
    with FMUModel(fmu, ["shaft.w"], DC_TIMES) as m:
        assert "state.w" in m.parameter_names
        rest = m.run({})["shaft.w"]
        spun = m.run({"state.w": 150.0})["shaft.w"]
        again = m.run({})["shaft.w"]
    assert np.array_equal(rest, again)
    assert spun[0] > rest[0] + 50.0                       # 0.1 s in: still well ahead
    # the same settled speed (the start is forgotten after a few time constants)
    assert abs(spun[-1] - rest[-1]) < 1e-3 * rest[-1]
    # against the documented equations (test_dcdrive's reference) started from w = 150 rad/s
    ref = _dc_reference_from(150.0)
    np.testing.assert_allclose(spun, ref, rtol=1e-4)


def _dc_reference_from(w0: float) -> np.ndarray:
    """shaft.w of the documented DC drive (docs/dcdrive.md, default parameters, supply on at
    t = 0) started from i = 0, w = w0, integrated by scipy (DOP853, rtol 1e-10)."""
    V, KE, KT, L, J, R, B, C, TC, WC = 48.0, 0.1, 0.1, 5e-3, 5e-3, 1.0, 1e-3, 7e-6, 1.0, 0.5

    def rhs(t, x):
        i, w = x
        load = B * w + C * w * abs(w) + TC * math.tanh(w / WC)
        return [(V - R * i - KE * w) / L, (KT * i - load) / J]
    sol = solve_ivp(rhs, (0.0, float(DC_TIMES[-1])), [0.0, w0], method="DOP853",
                    t_eval=DC_TIMES, rtol=1e-10, atol=1e-9)
    assert sol.success
    return sol.y[1]


def test_a_variable_fmi_forbids_to_set_is_refused_with_the_reason(dc2_fmu):
    with FMUModel(dc2_fmu, ["shaft.w"], DC_TIMES) as m:
        with pytest.raises(SimulationError, match=r"'der\(state.w\)' is a local Real the FMU "
                           r"calculates.*FMI lets no tool set it before initialisation"):
            m.run({"der(state.w)": 1.0})
