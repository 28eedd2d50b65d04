"""forecast on the shipped fleet, end to end through the real stages (seeded).

fabricate (configs/fleet.yaml) -> simulate -> reduce -> calibrate -> forecast --truth.
Targets: root cause Park healthy, Colt pump, Monk motor; predicted failure
years within one year of the true ones (the truth file's recorded future through the FMU).
"""
from __future__ import annotations

import copy
import time

import numpy as np
import pytest

from twinmon.forecast import forecast, read_forecast



@pytest.fixture(scope="module")
def fleet(calibrated_fleet):
    cfg, tmp, _ = calibrated_fleet
    start = time.perf_counter()
    summary = forecast(cfg, tmp / "post.h5", tmp / "sur.h5", tmp / "fc.h5",
                       truth_path=tmp / "truth.h5")
    wall = time.perf_counter() - start
    print(f"\nforecast wall time {wall:.2f} s")
    for unit, u in summary.units.items():
        print(unit, u.root_cause, {n: round(t.p_value, 6) for n, t in u.trends.items()},
              "predicted", u.failure_year, "true", u.true_failure_year)
    return cfg, tmp, summary


def test_root_causes_match_the_fabricated_faults(fleet):
    cfg, _, s = fleet
    assert {u: f.root_cause for u, f in s.units.items()} == \
        {"Park": "healthy", "Colt": "pump", "Monk": "motor"}
    alpha = cfg.forecast.alpha
    faulty = {"Colt": "pump_coef", "Monk": "motor_damping"}
    for unit, f in s.units.items():
        for name, t in f.trends.items():
            if faulty.get(unit) == name:
                assert t.p_value < alpha / 10, (unit, name, t.p_value)
            else:
                assert t.p_value > 0.1, (unit, name, t.p_value)


def test_predicted_failure_years_within_one_year_of_truth(fleet):
    _, _, s = fleet
    for unit, f in s.units.items():
        if f.true_failure_year is None:
            # A unit that stays safe in truth must not be given an early failure.
            assert f.failure_year is None, unit
        else:
            assert f.failure_year is not None, unit
            assert abs(f.failure_year - f.true_failure_year) <= 1, \
                (unit, f.failure_year, f.true_failure_year)
    assert s.units["Park"].true_failure_year is None
    assert s.units["Colt"].true_failure_year is not None
    assert s.units["Monk"].true_failure_year is not None


def test_true_inputs_mostly_inside_the_prediction_intervals(fleet):
    # The paper: "the parameters' true values lie in the confidence interval". The
    # calibrated damping of a unit can carry a bias (damping and pump coefficient trade
    # off), so the check is on the share over all units, inputs and years.
    # (A strict xfail until forecast drew the unit's true state -- forecast.predictive:
    # state -- instead of a new yearly estimate: 67 % then, 83 % after, against the true
    # lines extended; 32/42 = 76 % against the truth file's recorded future, jitter
    # included: Monk's damping, estimated low along the ridge, misses all 7 years.)
    _, tmp, s = fleet
    f = read_forecast(tmp / "fc.h5")
    inside = [(f.units[u].pred_lo[n] <= f.units[u].true_inputs[n])
              & (f.units[u].true_inputs[n] <= f.units[u].pred_hi[n])
              for u in f.units for n in f.input_names]
    assert np.mean(inside) >= 0.75


def test_truth_is_the_recorded_future(fleet):
    """The true future inputs are the truth file's recorded ones (jitter included), not a
    line; a truth file without them falls back to the line and says so."""
    cfg, tmp, s = fleet
    from twinmon.fabricate import read_truth
    truth = read_truth(tmp / "truth.h5")
    for unit, u in s.units.items():
        assert u.truth_source == "recorded future"
        pos = np.searchsorted(truth.future_years[unit], u.years_future)
        for n in cfg.model.input_names:
            assert np.array_equal(u.true_inputs[n], truth.future_inputs[unit][n][pos])
    assert read_forecast(tmp / "fc.h5").units["Colt"].truth_source == "recorded future"
    from twinmon.forecast.chunk import _add_truth
    from twinmon.simulate import spec_for
    old = copy.copy(s.units["Colt"])        # the fixture's forecast stays as it is
    _add_truth(cfg, old, "Colt", (truth.years["Colt"], truth.inputs["Colt"], None, None),
               tmp / "truth.h5", spec_for(cfg), None)
    assert old.truth_source == "trend line"
    slope, icpt = np.polyfit(truth.years["Colt"], truth.inputs["Colt"]["pump_coef"], 1)
    assert np.allclose(old.true_inputs["pump_coef"], icpt + slope * old.years_future)
    # A forecast made from the first years of the record (a backtest's cut): its future
    # is the truth's recorded years, then its recorded future.
    cut = copy.copy(s.units["Colt"])
    ty = np.asarray(truth.years["Colt"])
    cut.years_future = np.arange(ty[-1] - 1, ty[-1] + 4)
    _add_truth(cfg, cut, "Colt", (ty, truth.inputs["Colt"], truth.future_years["Colt"],
                                  truth.future_inputs["Colt"]), tmp / "truth.h5",
               spec_for(cfg), None)
    assert cut.truth_source == "recorded future"
    for n in cfg.model.input_names:
        want = np.concatenate([np.asarray(truth.inputs["Colt"][n])[-2:],
                               np.asarray(truth.future_inputs["Colt"][n])[:3]])
        assert np.array_equal(cut.true_inputs[n], want)


def test_unsafe_probability_rises_towards_failure(fleet):
    cfg, _, s = fleet
    for unit in ("Colt", "Monk"):
        f = s.units[unit]
        assert np.all(np.diff(f.p_unsafe) >= -0.02), (unit, f.p_unsafe)
        assert f.p_unsafe[-1] > 0.5
        # Ten observed years all safe, as the fabricated fleet was.
        assert np.all(f.p_unsafe_observed <= cfg.safety.failure_probability)
    assert np.all(s.units["Park"].p_unsafe <= cfg.safety.failure_probability)
