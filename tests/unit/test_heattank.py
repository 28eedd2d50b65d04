"""Tests of the water-heater FMU (fmus/HeatTank, FMI 2.0), the third example machine and the
one with three degradation inputs.

The reference below is written from the equations of docs/heattank.md (not ported from the C
sources) and integrated with scipy's DOP853 at rtol 1e-10:

    Ce dTe/dt = P(t) - hA (Te - Tw),        P(t) = (ratio 230 V)^2 / R once t >= delay, else 0
    Cw dTw/dt = hA (Te - Tw) - UA (Tw - 20) - m_in cp (Tw - 10)
    tau dy/dt = Tw - y (tau > 0),           sensor.T = (y if tau > 0 else Tw) + offset
    cutout = 1 from the first time Te > 250 degC on (latched)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from twinmon.config import load_config
from twinmon.fmu import FMUModel, build_fmu
from twinmon.safety import compute_indicator

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "fmus" / "HeatTank"
CONFIG = ROOT / "configs" / "heattank.yaml"
TIMES = 60.0 * np.arange(1, 26)                                   # 60 s to 1500 s, 25 samples
OUTPUTS = ["sensor.T", "water.T", "element.T", "heater.I", "heater.P", "cutout"]

# documented constants (docs/heattank.md)
V_NOM, C_E, C_W, CP, T_AMB, T_IN, T_CUT = 230.0, 4000.0, 44000.0, 4186.0, 20.0, 10.0, 250.0
DEFAULTS = {"element.R": 26.45, "element.hA": 100.0, "insulation.UA": 1.5, "sensor.tau": 0.0,
            "sensor.offset": 0.0, "supply.ratio": 1.0, "inlet.flow": 0.0, "supply.delay": 0.0}
EFFECTS_ON = {"sensor.tau": 60.0, "sensor.offset": 1.0, "supply.ratio": 0.9,
              "inlet.flow": 0.0015, "supply.delay": 90.0}
EFFECTS_OFF = {"sensor.tau": 0.0, "sensor.offset": 0.0, "supply.ratio": 1.0,
               "inlet.flow": 0.0, "supply.delay": 0.0}
DESIGN_POINTS = [(26.45, 100.0, 1.5), (22.0, 130.0, 0.5), (34.0, 20.0, 10.0),
                 (40.0, 12.0, 30.0), (30.0, 60.0, 25.0)]
HEALTHY_INDICATOR = 888.0     # s, time for sensor.T to reach 55 degC (docs/heattank.md)
UNSAFE_ABOVE = 1000.0         # s (configs/heattank.yaml)


def _rhs(t, x, p, on):
    te, tw, y = x
    v = p["supply.ratio"] * V_NOM if on else 0.0
    power = v * v / p["element.R"]
    q = p["element.hA"] * (te - tw)
    loss = p["insulation.UA"] * (tw - T_AMB) + p["inlet.flow"] * CP * (tw - T_IN)
    tau = p["sensor.tau"]
    return [(power - q) / C_E, (q - loss) / C_W, (tw - y) / tau if tau > 0 else 0.0]


def _too_hot(t, x, p, on):
    return x[0] - T_CUT


_too_hot.direction = 1.0


def reference(params, times=TIMES):
    """Outputs of the documented model at ``times`` (scipy DOP853, rtol 1e-10)."""
    p = {**DEFAULTS, **params}
    delay = p["supply.delay"]
    t_end = float(times[-1])
    cuts = sorted({0.0, t_end} | ({delay} if 0 < delay < t_end else set()))
    x = np.full(3, T_AMB)
    at, t_cut = {}, np.inf
    for a, b in zip(cuts[:-1], cuts[1:]):
        t_eval = sorted({float(t) for t in times if a < t <= b} | {b})
        sol = solve_ivp(_rhs, (a, b), x, method="DOP853", t_eval=t_eval, args=(p, a >= delay),
                        rtol=1e-10, atol=1e-8, events=_too_hot)
        assert sol.success, sol.message
        at.update({round(float(t), 6): xs for t, xs in zip(sol.t, sol.y.T)})
        if sol.t_events[0].size:
            t_cut = min(t_cut, float(sol.t_events[0][0]))
        x = sol.y[:, -1]
    out = {k: [] for k in OUTPUTS}
    for t in times:
        te, tw, y = at[round(float(t), 6)]
        v = p["supply.ratio"] * V_NOM if t >= delay else 0.0
        out["sensor.T"].append((y if p["sensor.tau"] > 0 else tw) + p["sensor.offset"])
        out["water.T"].append(tw)
        out["element.T"].append(te)
        out["heater.I"].append(v / p["element.R"])
        out["heater.P"].append(v * v / p["element.R"])
        out["cutout"].append(1.0 if t >= t_cut else 0.0)
    return {k: np.asarray(v) for k, v in out.items()}


def rel_err(fmu, ref):
    scale = np.max(np.abs(ref))
    if scale == 0:
        return float(np.max(np.abs(fmu)))
    return float(np.max(np.abs(fmu - ref) / np.maximum(np.abs(ref), 1e-3 * scale)))


@pytest.fixture(scope="module")
def heattank_fmu() -> Path:
    return build_fmu(SRC)


@pytest.fixture(scope="module")
def model(heattank_fmu):
    with FMUModel(heattank_fmu, OUTPUTS, TIMES) as m:
        yield m


def test_validate_fmu(heattank_fmu):
    from fmpy.validation import validate_fmu
    assert validate_fmu(str(heattank_fmu)) == []


CASES = [{"element.R": r, "element.hA": h, "insulation.UA": u} for r, h, u in DESIGN_POINTS] + \
        [{"element.R": 28.0, "element.hA": 50.0, name: value}
         for name, value in EFFECTS_ON.items()] + \
        [{"element.R": 22.0, "element.hA": 12.0, "insulation.UA": 0.5}]     # fuse blows


@pytest.mark.parametrize("params", CASES,
                         ids=lambda p: ",".join(f"{k}={v:g}" for k, v in p.items()))
def test_matches_scipy_reference(model, params):
    got, ref = model.run(params), reference(params)
    for name in OUTPUTS:
        if name == "cutout":
            np.testing.assert_array_equal(got[name], ref[name])
        else:
            assert rel_err(got[name], ref[name]) < 1e-6, (name, rel_err(got[name], ref[name]))


def test_the_fuse_latches_only_in_the_scaled_corner(model):
    assert model.run({})["cutout"].max() == 0.0
    flag = model.run({"element.R": 22.0, "element.hA": 12.0, "insulation.UA": 0.5})["cutout"]
    assert flag[-1] == 1.0 and flag[0] == 0.0 and np.all(np.diff(flag) >= 0)
    assert model.run({"element.R": 26.45, "element.hA": 12.0})["cutout"].max() == 0.0


@pytest.mark.parametrize("name", sorted(EFFECTS_OFF))
def test_effect_off_gives_base_model(model, name):
    for base in ({}, {"element.R": 31.0, "element.hA": 30.0, "insulation.UA": 8.0}):
        a = model.run(base)
        b = model.run({**base, name: EFFECTS_OFF[name]})
        for k in OUTPUTS:
            np.testing.assert_array_equal(b[k], a[k])


def test_health_indicator_and_crossings(model):
    """The heat-up time of the healthy unit, and each degradation input alone crossing the
    unsafe level inside the design box (docs/heattank.md)."""
    spec = load_config(CONFIG).safety.indicator

    def indicator(params):
        return float(compute_indicator(TIMES, model.run(params)["sensor.T"], spec))

    assert indicator({}) == pytest.approx(HEALTHY_INDICATOR, abs=0.05)
    assert indicator({"element.R": 29.8}) < UNSAFE_ABOVE < indicator({"element.R": 30.0})
    assert indicator({"element.hA": 25.0}) < UNSAFE_ABOVE < indicator({"element.hA": 24.5})
    assert indicator({"insulation.UA": 13.7}) < UNSAFE_ABOVE < indicator({"insulation.UA": 14.0})
    # the slowest corner never reaches the level within the record: inf, not NaN
    assert indicator({"element.R": 40.0, "element.hA": 12.0, "insulation.UA": 30.0}) == np.inf


def test_the_three_inputs_leave_different_signatures(model):
    """Element resistance tilts the whole ramp (less power from the start), scale shifts it by
    a near constant once the element has warmed, insulation loss bends it late: three
    directions in the transient, not one, though resistance and insulation lie close
    (cosine 0.97 between their changes of the record; 0.89 resistance-scale, 0.77
    scale-insulation)."""
    base = model.run({})["sensor.T"]
    d = np.array([model.run({k: v})["sensor.T"] - base for k, v in
                  (("element.R", 27.2), ("element.hA", 63.0), ("insulation.UA", 6.3))])
    cos = (d @ d.T) / np.outer(np.linalg.norm(d, axis=1), np.linalg.norm(d, axis=1))
    assert np.all(np.abs(cos[np.triu_indices(3, 1)]) < 0.98), cos
    late, early = TIMES >= 900, TIMES <= 300
    assert np.ptp(d[1][TIMES >= 400]) < 0.1 * np.abs(d[1]).max()       # scale: a shift
    assert np.abs(d[2][early]).max() < 0.05 * np.abs(d[2][late]).max()  # insulation: late


def test_model_exchange_agrees_with_cosimulation(heattank_fmu, model):
    with FMUModel(heattank_fmu, OUTPUTS, TIMES, fmi_type="ModelExchange") as me:
        for params in ({"element.R": 31.0, "element.hA": 40.0, "insulation.UA": 6.0,
                        "supply.delay": 90.0, "sensor.tau": 60.0},
                       {"element.R": 22.0, "element.hA": 12.0, "insulation.UA": 0.5}):
            a, b = me.run(params), model.run(params)
            for k in OUTPUTS:
                if k == "cutout":
                    np.testing.assert_array_equal(a[k], b[k])
                else:
                    assert rel_err(a[k], b[k]) < 1e-4, (k, rel_err(a[k], b[k]))
