"""Tests of the DC drive FMUs (fmus/DCDrive, FMI 2.0; fmus/DCDrive3, FMI 3.0).

The reference below is written from the equations of docs/dcdrive.md (not ported from the C
sources) and integrated with scipy's DOP853 at rtol 1e-10:

    L di/dt = V(t) - R i - Ke w,       V(t) = ratio * 48 V once t >= delay, else 0
    J dw/dt = Kt i - b w - c w|w| - (Tc + extra) tanh(w / 0.5)
    tau dy/dt = w - y (tau > 0),       tacho.w = gain * (y if tau > 0 else w)
    stalled = 1 from t_check = delay + 1 s on when w(t_check) < 48 rad/s
"""
from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from twinmon.fmu import FMUModel, build_fmu, source_hash

ROOT = Path(__file__).resolve().parents[2]
SRC2 = ROOT / "fmus" / "DCDrive"
SRC3 = ROOT / "fmus" / "DCDrive3"
TIMES = np.round(np.arange(0.1, 3.0 + 1e-9, 0.1), 10)          # 30 samples
WINDOW = (TIMES >= 2.0 - 1e-9) & (TIMES <= 3.0 + 1e-9)        # the health indicator's window
OUTPUTS = ["tacho.w", "shaft.w", "armature.i", "shaft.torque", "stalled"]

# documented constants (docs/dcdrive.md)
V_NOM, KE, KT, L_ARM, J_TOT, TC, W_C = 48.0, 0.1, 0.1, 5e-3, 5e-3, 1.0, 0.5
T_CHECK, W_STALL = 1.0, 48.0
DEFAULTS = {"bearing.b": 1e-3, "winding.R": 1.0, "tacho.tau": 0.0, "tacho.gain": 1.0,
            "supply.ratio": 1.0, "load.extra": 0.0, "supply.delay": 0.0, "fan.c": 7e-6}
EFFECTS_ON = {"tacho.tau": 0.2, "tacho.gain": 0.95, "supply.ratio": 0.85, "load.extra": 0.4,
              "supply.delay": 0.35}
EFFECTS_OFF = {"tacho.tau": 0.0, "tacho.gain": 1.0, "supply.ratio": 1.0, "load.extra": 0.0,
               "supply.delay": 0.0}
DESIGN_POINTS = [(1e-3, 1.0), (5e-4, 0.6), (4e-3, 1.8), (6e-3, 3.0), (2e-3, 3.5)]
HEALTHY_INDICATOR = 291.15    # rad/s, mean tacho.w over [2, 3] s (docs/dcdrive.md)
UNSAFE_BELOW = 250.0          # rad/s (configs/dcdrive.yaml)


# ----------------------------------------------------------------------------------------
# independent reference model

def _rhs(t, x, p, on):
    i, w, y = x
    v = p["supply.ratio"] * V_NOM if on else 0.0
    load = (p["bearing.b"] * w + p["fan.c"] * w * abs(w)
            + (TC + p["load.extra"]) * math.tanh(w / W_C))
    tau = p["tacho.tau"]
    return [(v - p["winding.R"] * i - KE * w) / L_ARM,
            (KT * i - load) / J_TOT,
            (w - y) / tau if tau > 0 else 0.0]


def reference(params, times=TIMES):
    """Outputs of the documented model at ``times`` (scipy DOP853, rtol 1e-10)."""
    p = {**DEFAULTS, **params}
    delay = p["supply.delay"]
    t_check = max(delay, 0.0) + T_CHECK
    t_end = float(times[-1])
    cuts = sorted({0.0, t_end} | {c for c in (delay, t_check) if 0 < c <= t_end})
    x = np.zeros(3)
    at, w_check = {}, None
    for a, b in zip(cuts[:-1], cuts[1:]):
        t_eval = sorted({float(t) for t in times if a < t <= b} | {b})
        sol = solve_ivp(_rhs, (a, b), x, method="DOP853", t_eval=t_eval, args=(p, a >= delay),
                        rtol=1e-10, atol=[1e-9, 1e-8, 1e-8])
        assert sol.success, sol.message
        at.update({round(float(t), 9): xs for t, xs in zip(sol.t, sol.y.T)})
        x = sol.y[:, -1]
        if b == t_check:
            w_check = x[1]
    stalled = 1.0 if w_check is not None and w_check < W_STALL else 0.0
    out = {k: [] for k in OUTPUTS}
    for t in times:
        i, w, y = at[round(float(t), 9)]
        out["tacho.w"].append(p["tacho.gain"] * (y if p["tacho.tau"] > 0 else w))
        out["shaft.w"].append(w)
        out["armature.i"].append(i)
        out["shaft.torque"].append(KT * i)
        out["stalled"].append(stalled if t >= t_check - 1e-12 else 0.0)
    return {k: np.asarray(v) for k, v in out.items()}


def rel_err(fmu, ref):
    scale = np.max(np.abs(ref))
    if scale == 0:
        return float(np.max(np.abs(fmu)))
    return float(np.max(np.abs(fmu - ref) / np.maximum(np.abs(ref), 1e-3 * scale)))


# ----------------------------------------------------------------------------------------
# fixtures

@pytest.fixture(scope="session")
def dcdrive_fmu() -> Path:
    return build_fmu(SRC2)


@pytest.fixture(scope="session")
def dcdrive3_fmu() -> Path:
    return build_fmu(SRC3)


@pytest.fixture(scope="module")
def model(dcdrive_fmu):
    with FMUModel(dcdrive_fmu, OUTPUTS, TIMES) as m:
        yield m


@pytest.fixture(scope="module")
def model3(dcdrive3_fmu):
    with FMUModel(dcdrive3_fmu, OUTPUTS, TIMES) as m:
        yield m


# ----------------------------------------------------------------------------------------
# tests

def test_validate_fmus(dcdrive_fmu, dcdrive3_fmu):
    from fmpy.validation import validate_fmu
    assert validate_fmu(str(dcdrive_fmu)) == []
    assert validate_fmu(str(dcdrive3_fmu)) == []


CASES = [{"bearing.b": b, "winding.R": r} for b, r in DESIGN_POINTS] + \
        [{"bearing.b": 2e-3, "winding.R": 1.3, name: value} for name, value in EFFECTS_ON.items()] + \
        [{"winding.R": 4.0}]   # stalled


@pytest.mark.parametrize("params", CASES, ids=lambda p: ",".join(f"{k}={v:g}" for k, v in p.items()))
def test_matches_scipy_reference(model, params):
    got = model.run(params)
    ref = reference(params)
    for name in OUTPUTS:
        if name == "stalled":
            np.testing.assert_array_equal(got[name], ref[name])
        else:
            assert rel_err(got[name], ref[name]) < 1e-5, (name, rel_err(got[name], ref[name]))


def test_stall_flag(model):
    assert model.run({})["stalled"].max() == 0.0
    flag = model.run({"winding.R": 4.0})["stalled"]
    np.testing.assert_array_equal(flag, (TIMES >= 1.0 - 1e-9).astype(float))
    # a late supply moves the check: stalled only from delay + 1 s on
    flag = model.run({"winding.R": 4.0, "supply.delay": 0.5})["stalled"]
    np.testing.assert_array_equal(flag, (TIMES >= 1.5 - 1e-9).astype(float))
    # an extra load at the top of the winding box stalls the drive too
    assert model.run({"winding.R": 3.0, "load.extra": 1.0})["stalled"][-1] == 1.0


@pytest.mark.parametrize("fmu", ["dcdrive_fmu", "dcdrive3_fmu"])
def test_a_sample_a_rounding_error_short_of_the_stall_check(fmu, request):
    # 0.1 + 6 x 0.15 is 0.9999999999999999: the step up to the 1 s breakpoint after it is
    # 1e-16 s long, and the solver once shrank its next step to it and stopped ("step size
    # underflow") at the nominal point.
    t = 0.1 + 0.15 * np.arange(20)
    assert t[6] < 1.0
    with FMUModel(request.getfixturevalue(fmu), ["tacho.w"], t) as m:
        got = m.run({})["tacho.w"]
    assert rel_err(got, reference({}, t)["tacho.w"]) < 1e-5


@pytest.mark.parametrize("name", sorted(EFFECTS_OFF))
def test_effect_off_gives_base_model(model, name):
    for base in ({}, {"bearing.b": 4e-3, "winding.R": 2.2}):
        a = model.run(base)
        b = model.run({**base, name: EFFECTS_OFF[name]})
        for k in OUTPUTS:
            np.testing.assert_array_equal(b[k], a[k])


def test_effects_change_the_output(model):
    base = model.run({})["tacho.w"]
    for name, value in EFFECTS_ON.items():
        assert np.max(np.abs(model.run({name: value})["tacho.w"] - base)) > 1.0, name


def test_health_indicator_and_crossings(model):
    """The indicator (mean tacho.w over [2, 3] s) of the healthy unit, and each degradation
    input alone crossing the unsafe level inside the design box (docs/dcdrive.md)."""
    def indicator(params):
        return float(model.run(params)["tacho.w"][WINDOW].mean())

    healthy = indicator({})
    assert healthy == pytest.approx(HEALTHY_INDICATOR, abs=0.05)
    # settled: the last second moves by less than 0.5 %
    w = model.run({})["tacho.w"]
    assert np.ptp(w[WINDOW]) < 0.005 * healthy
    assert indicator({"bearing.b": 3.0e-3}) > UNSAFE_BELOW > indicator({"bearing.b": 3.9e-3})
    assert indicator({"winding.R": 1.30}) > UNSAFE_BELOW > indicator({"winding.R": 1.40})
    assert indicator({"bearing.b": 6e-3, "winding.R": 3.5}) > 0


def test_fmi3_matches_fmi2(model, model3):
    worst = 0.0
    for params in CASES:
        a, b = model.run(params), model3.run(params)
        for k in OUTPUTS:
            if k == "stalled":
                np.testing.assert_array_equal(a[k], b[k])
            else:
                worst = max(worst, rel_err(b[k], a[k]))
    assert worst < 1e-9


def test_fmi3_integer_output(dcdrive3_fmu, model3):
    import fmpy
    md = fmpy.read_model_description(str(dcdrive3_fmu))
    assert {v.name: v.type for v in md.modelVariables}["stalled"] == "Int32"
    res = fmpy.simulate_fmu(str(dcdrive3_fmu), fmi_type="CoSimulation", stop_time=3.0,
                            output_interval=0.1, start_values={"winding.R": 4.0},
                            output=OUTPUTS)
    assert res["stalled"].dtype == np.int32 and res["stalled"][-1] == 1
    ours = model3.run({"winding.R": 4.0})
    assert ours["stalled"].dtype == float and ours["stalled"][-1] == 1.0
    np.testing.assert_allclose(np.interp(TIMES, res["time"], res["tacho.w"]), ours["tacho.w"],
                               rtol=1e-9)


@pytest.mark.parametrize("which", ["fmi2", "fmi3"])
def test_model_exchange_agrees_with_cosimulation(which, dcdrive_fmu, dcdrive3_fmu, model):
    fmu = dcdrive_fmu if which == "fmi2" else dcdrive3_fmu
    with FMUModel(fmu, OUTPUTS, TIMES, fmi_type="ModelExchange") as me:
        for params in ({"bearing.b": 3e-3, "winding.R": 1.6, "supply.delay": 0.35,
                        "tacho.tau": 0.2}, {"winding.R": 4.0}):
            a, b = me.run(params), model.run(params)
            for k in OUTPUTS:
                if k == "stalled":
                    np.testing.assert_array_equal(a[k], b[k])
                else:
                    assert rel_err(a[k], b[k]) < 1e-4, (k, rel_err(a[k], b[k]))


def test_fmi3_sources_are_the_fmi2_ones(dcdrive3_fmu, tmp_path):
    """model.c/h and cs.c/h of DCDrive3 are links to DCDrive's: the FMU packs their content
    and the source hash follows the link targets."""
    for name in ("model.c", "model.h", "cs.c", "cs.h"):
        link = SRC3 / "sources" / name
        assert link.is_symlink() and link.resolve() == (SRC2 / "sources" / name).resolve()
        with zipfile.ZipFile(dcdrive3_fmu) as zf:
            assert zf.read(f"sources/{name}") == (SRC2 / "sources" / name).read_bytes()
    # copies with the same layout: editing the FMI 2 folder's model.c changes the FMI 3 hash
    import shutil
    shutil.copytree(SRC2, tmp_path / "DCDrive", ignore=shutil.ignore_patterns(".build"))
    shutil.copytree(SRC3, tmp_path / "DCDrive3", symlinks=True,
                    ignore=shutil.ignore_patterns(".build"))
    before = source_hash(tmp_path / "DCDrive3")
    assert before == source_hash(SRC3)
    with open(tmp_path / "DCDrive" / "sources" / "model.c", "a") as fh:
        fh.write("\n/* changed */\n")
    assert source_hash(tmp_path / "DCDrive3") != before
