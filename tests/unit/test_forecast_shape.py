"""forecast's trend shapes: wear that accelerates makes a prognosis unreliable, and a jump
back towards nominal that no event records is found and restarts the trend."""
from __future__ import annotations

import numpy as np
import pytest

from twinmon.calibrate import calibrate
from twinmon.config import load_config
from twinmon.fabricate import fabricate
from twinmon.forecast import forecast
from twinmon.repairs import fall_test
from twinmon.forecast.trend import acceleration_test
from twinmon.reduce import reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml


def test_acceleration_test_is_one_sided_in_the_degrading_direction():
    rng = np.random.default_rng(3)
    years = np.arange(1, 11)
    noise = 0.02 * rng.standard_normal(10)
    bend = 1.0 + 0.02 * years + 0.02 * years ** 2 + noise
    assert acceleration_test(years, bend, +1) < 1e-4
    assert acceleration_test(years, bend, -1) > 0.99        # it bends away from failure
    assert acceleration_test(years[:4], bend[:4], +1) == 1.0  # too few years to tell
    # On straight lines its p-values are uniform: 5 % of them below 0.05.
    p = [acceleration_test(years, 1.0 + 0.1 * years + 0.02 * rng.standard_normal(10), +1)
         for _ in range(600)]
    assert 0.03 < np.mean(np.array(p) < 0.05) < 0.075


def _fall(years, values, direction, sd=0.02):
    """fall_test on one input whose yearly errors have sd ``sd``."""
    cov = np.full((len(years), 1, 1), sd ** 2)
    return fall_test(years, np.asarray(values, float)[:, None], cov, 0, direction)


def test_fall_test_finds_a_repair_and_nothing_else():
    rng = np.random.default_rng(5)
    years = np.arange(1, 11)
    wear = lambda age: 1.0 + 0.1 * age                                  # noqa: E731
    noise = 0.02 * rng.standard_normal(10)
    repaired = np.where(years < 6, wear(years - 1), wear(years - 6)) + noise
    p, year, step, tried = _fall(years, repaired, +1)
    assert p < 1e-4 and year == 6 and step < -0.3 and tried == 7
    # One-sided: a jump in the degrading direction (a step of wear) is no repair.
    stepped = wear(years - 1) + 0.5 * (years >= 6) + noise
    p, _, _, tried = _fall(years, stepped, +1)
    assert p * tried > 0.5
    assert _fall(years, -repaired, -1)[1] == 6                         # falling inputs too
    assert _fall(years[:4], repaired[:4], +1) == (1.0, -1, 0.0, 0)
    assert _fall(years, repaired, 0)[3] == 0                            # direction unknown
    # Flat and straight lines and accelerating wear: after Bonferroni over the years tried,
    # at most alpha of them are read as a repair.
    for shape in (lambda y: 1.0 + 0.0 * y, lambda y: 1.0 + 0.1 * y,
                  lambda y: 1.0 + 0.01 * y + 0.01 * y ** 2):
        hits = 0
        for _ in range(300):
            p, _, _, tried = _fall(years, shape(years) + 0.02 * rng.standard_normal(10), +1)
            hits += p * tried < 0.05
        assert hits / 300 <= 0.05


def test_fall_test_without_error_variance_tests_nothing_quietly():
    """Estimates known exactly (zero error covariance) give no test, and no numpy warning."""
    import warnings
    years = np.arange(1, 11)
    est = np.random.default_rng(2).standard_normal((10, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fall_test(years, est, np.zeros((10, 2, 2)), 0, +1) == (1.0, -1, 0.0, 0)


def test_fall_test_weighs_inputs_that_trade_off():
    """Two inputs whose yearly errors run along a ridge (correlation -0.95): the second's
    steady line tells the first's fall from a slide along the ridge."""
    rng = np.random.default_rng(8)
    years = np.arange(1, 11)
    sd = np.array([0.1, 0.1])
    cov1 = np.diag(sd) @ np.array([[1.0, -0.95], [-0.95, 1.0]]) @ np.diag(sd)
    cov = np.repeat(cov1[None], 10, axis=0)
    truth = np.column_stack([np.where(years < 6, 0.06 * (years - 1), 0.06 * (years - 6)),
                             0.01 * years])
    found = 0
    for _ in range(100):
        est = truth + rng.multivariate_normal([0, 0], cov1, 10)
        p, year, _, tried = fall_test(years, est, cov, 0, +1)
        alone = _fall(years, est[:, 0], +1, sd=0.1)
        found += (p * tried < 0.01 and year == 6) - (alone[0] * alone[3] < 0.01
                                                    and alone[1] == 6)
    assert found > 30           # the joint weighting finds many more


def _ridge(rng, truth):
    """Yearly estimates of two inputs whose errors run along a ridge (sd 0.1 each,
    correlation -0.95): the truth [10, 2] plus those errors, and a year-to-year scatter of
    sd 0.005 on the first input."""
    cov1 = 0.01 * np.array([[1.0, -0.95], [-0.95, 1.0]])
    jitter = np.column_stack([0.005 * rng.standard_normal(10), np.zeros(10)])
    return truth + rng.multivariate_normal([0, 0], cov1, 10) + jitter, \
        np.repeat(cov1[None], 10, axis=0)


def test_fall_test_fits_the_year_to_year_variance_under_the_ridge():
    """The year-to-year variances fitted under the errors' whole covariance: with errors
    along a ridge, a variance taken from each input's own scatter is noise of the ridge's
    size and hides falls (a fall of 0.18 was found 194 times in 300 that way)."""
    rng = np.random.default_rng(8)
    years = np.arange(1, 11)
    truth = np.column_stack([np.where(years < 5, 0.06 * (years - 1), 0.06 * (years - 5)),
                             0.01 * years])
    found = 0
    for _ in range(300):
        est, cov = _ridge(rng, truth)
        p, year, _, tried = fall_test(years, est, cov, 0, +1)
        found += p * tried < 0.05 and year == 5
    assert found / 300 > 0.85


def test_fall_test_reads_no_fall_into_wear_that_bends():
    """Wear that speeds up after year 3 on one of two inputs that trade off: a line plus a
    step reads the bend as a fall (34 units of 300 had a finding that way); the scan's
    trends carry a curvature."""
    rng = np.random.default_rng(8)
    years = np.arange(1, 11)
    bend = np.column_stack([0.01 * years + 0.012 * np.maximum(years - 3, 0) ** 2,
                            0.01 * years])
    findings = 0
    for _ in range(300):
        est, cov = _ridge(rng, bend)
        findings += any(p * tried * 2 < 0.05 for p, _, _, tried in
                        (fall_test(years, est, cov, i, +1) for i in (0, 1)))
    assert findings / 300 <= 0.05


def test_fall_test_reads_no_fall_into_estimates_that_rise_every_year(monkeypatch):
    """Exponential wear on one input: the scan's quadratic plus a step fits a fall where the
    curve outruns the quadratic, though the estimates rise every year; the estimates' own
    means across the year must fall too."""
    import twinmon.repairs as R
    rng = np.random.default_rng(5)
    years = np.arange(1, 12)
    cov = np.full((11, 1, 1), 0.01 ** 2)
    runs = [1 + 0.02 * np.exp(0.3 * (years - 1)) + 0.01 * rng.standard_normal(11)
            for _ in range(200)]

    def findings():
        return sum(p * tried < 0.05 for p, _, _, tried in
                   (fall_test(years, x[:, None], cov, 0, +1) for x in runs))
    assert findings() == 0
    # Without the estimates' own check the same runs give findings (the check is what
    # keeps them out).
    monkeypatch.setattr(R, "_falls", lambda *a: True)
    assert findings() >= 5


def test_shape_gate_tests_every_input_when_none_drifts():
    """A part that ages normally, then wears fast from year 7: its slope over the record is
    within normal ageing (no input drifts), and the gate names its acceleration; beside an
    input that drifts it is not tested."""
    from dataclasses import replace
    from twinmon.forecast.trend import Trend, shape_gate
    cfg = load_config(CONFIGS / "pump.yaml")
    rng = np.random.default_rng(2)
    years = np.arange(1, 11)
    pump = 3.65 - 0.02 * years - 0.2 * np.maximum(years - 6, 0) + 0.01 * rng.standard_normal(10)
    motor = 10.0 + 0.05 * rng.standard_normal(10)
    mean = np.column_stack([motor, pump])
    base = Trend(intercept=0.0, slope=0.0, slope_se=1.0, slope_ci=(0.0, 0.0), residual_std=0.0,
                 n=10, x_mean=5.5, sxx=82.5, normal_rate=0.0, tolerance=0.0, direction=+1,
                 p_value=1.0, test="t", rejects=False, component="motor")
    trends = {"motor_damping": base,
              "pump_coef": replace(base, direction=-1, component="pump")}
    since = {"motor_damping": 1, "pump_coef": 1}
    reason, name = shape_gate(cfg, since, years, mean, trends)
    assert name == "pump_coef" and reason.startswith("pump_coef's yearly estimates accelerate")
    trends["motor_damping"] = replace(base, rejects=True)
    assert shape_gate(cfg, since, years, mean, trends) == ("", None)


@pytest.fixture(scope="module")
def dcdrive_fleet(tmp_path_factory):
    """A DC drive (not the pump) fleet: a bearing whose friction grows exponentially, one
    that wears at a steady faulty rate, a faulty bearing replaced in year 6 with no event
    recorded, a healthy unit; calibrated year by year."""
    from twinmon.fmu import build_fmu
    from ..conftest import ROOT
    build_fmu(ROOT / "fmus" / "DCDrive")
    tmp = tmp_path_factory.mktemp("shape")
    steady = {"winding_resistance": {"start": 1.0, "slope": 0.003, "jitter": 0.002}}
    cfg_path = write_yaml(tmp / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "simulate": {"train_size": 48, "test_size": 8},
        "calibrate": {"method": "sequential"},
        "forecast": {"samples": 400, "observed_samples": 100},
        "fabricate": {"years": 10, "noise_std": 1.5, "seed": 7, "units": {
            "Acc": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 1.5e-5,
                                                          "growth": 0.35, "jitter": 5e-6},
                                     **steady}},
            "Lin": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 1.5e-4,
                                                          "jitter": 5e-6}, **steady}},
            "Ok": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 0.0,
                                                         "jitter": 5e-6}, **steady}},
            "Rep": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 2.5e-4,
                                                          "jitter": 5e-6}, **steady},
                    "events": [{"year": 6, "component": "bearing", "recorded": False}]}}}})
    cfg = load_config(cfg_path)
    fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
    simulate(cfg, tmp / "sim.h5")
    reduce(cfg, tmp / "sim.h5", tmp / "sur.h5")
    calibrate(cfg, tmp / "sur.h5", tmp / "obs.h5", tmp / "post.h5")
    return cfg_path, tmp


def test_accelerating_wear_is_unreliable_and_a_line_is_not(dcdrive_fleet):
    cfg_path, tmp = dcdrive_fleet
    s = forecast(load_config(cfg_path), tmp / "post.h5", tmp / "sur.h5", tmp / "fc.h5")
    acc, lin, ok = (s.units[u] for u in ("Acc", "Lin", "Ok"))
    assert acc.root_cause != "healthy" and acc.status == "unreliable"
    assert "bearing_friction's yearly estimates accelerate" in acc.status_reason
    assert acc.status_reason in acc.plan
    assert lin.root_cause != "healthy" and lin.status == "ok"
    assert ok.root_cause == "healthy" and ok.status == "ok"
    # The gate off: the same forecast says ok.
    off = forecast(load_config(cfg_path, ["forecast.shape_alpha=0"]), tmp / "post.h5",
                   tmp / "sur.h5", tmp / "fc_off.h5")
    assert off.units["Acc"].status == "ok"
    assert off.units["Acc"].failure_year == acc.failure_year


def test_an_unrecorded_repair_is_found_and_restarts_the_trend(dcdrive_fleet):
    cfg_path, tmp = dcdrive_fleet
    s = forecast(load_config(cfg_path), tmp / "post.h5", tmp / "sur.h5", tmp / "fc_rep.h5",
                 truth_path=tmp / "truth.h5")
    rep = s.units["Rep"]
    assert [(r["year"], r["components"]) for r in rep.repairs] == [(6, ["bearing"])]
    assert rep.repairs[0]["steps"]["bearing_friction"] < 0
    assert "--unit Rep --year 6 --component bearing" in rep.plan
    assert "its trend restarts there" in rep.plan
    # The new bearing's trend: its five years, wearing at the faulty rate again.
    t = rep.trends["bearing_friction"]
    assert t.n == 5 and t.rejects and abs(t.slope - 2.5e-4) < 1e-4
    assert rep.root_cause == "bearing" and rep.status == "ok"
    assert rep.failure_year is not None and rep.true_failure_year is not None
    assert abs(rep.failure_year - rep.true_failure_year) <= 1
    assert any("Rep (bearing year 6)" in w for w in s.warnings)
    for u in ("Acc", "Lin", "Ok"):
        assert s.units[u].repairs == [], u
    from twinmon.forecast import read_forecast
    back = read_forecast(tmp / "fc_rep.h5").units["Rep"]
    assert back.repairs == rep.repairs
    # The report says it where a user looks: the unit's action and what it rests on (the
    # summary of every unit; figures for one).
    import json

    from twinmon.report import report
    report(load_config(cfg_path, ["report.detail_units=1"]), tmp / "report",
           posterior=tmp / "post.h5", forecast=tmp / "fc_rep.h5")
    text = json.dumps(json.loads((tmp / "report" / "summary.json").read_text())["units"]["Rep"])
    assert "record the year-6 repair of the bearing" in text
    assert "fell back towards nominal in year 6" in text
    # Turned off: no finding, and the line through the whole history.
    off = forecast(load_config(cfg_path, ["forecast.repair_alpha=0"]), tmp / "post.h5",
                   tmp / "sur.h5", tmp / "fc_rep_off.h5")
    assert off.units["Rep"].repairs == [] and off.units["Rep"].trends["bearing_friction"].n == 10


def test_the_fleet_method_starts_a_segment_at_an_unrecorded_repair(dcdrive_fleet):
    """The method a fleet is calibrated with (laplace, which shares the repair scan of the
    years' sites with the joint method: calibrate.trend.with_found_repairs) restarts the
    bearing's trend at its hidden replacement, and the forecast says so."""
    cfg_path, tmp = dcdrive_fleet
    from twinmon.calibrate import read_posterior
    cfg = load_config(cfg_path, ["calibrate.method=laplace"])
    summary = calibrate(cfg, tmp / "sur.h5", tmp / "obs.h5", tmp / "post_joint.h5")
    assert summary.as_dict()["units"]["Rep"]["found_repairs"][0]["year"] == 6
    post = read_posterior(tmp / "post_joint.h5")
    rep = post.units["Rep"]
    assert [(r["year"], r["components"]) for r in rep.found_repairs] == [(6, ["bearing"])]
    i = cfg.model.input_names.index("bearing_friction")
    assert list(rep.trend["start"][:, i]) == [1, 6]
    for u in ("Acc", "Lin", "Ok"):
        assert post.units[u].found_repairs == [], u
    s = forecast(cfg, tmp / "post_joint.h5", tmp / "sur.h5", tmp / "fc_joint.h5",
                 truth_path=tmp / "truth.h5")
    u = s.units["Rep"]
    assert [(r["year"], r["components"]) for r in u.repairs] == [(6, ["bearing"])]
    assert "--unit Rep --year 6 --component bearing" in u.plan
    assert u.root_cause == "bearing" and u.status == "ok"
    assert abs(u.failure_year - u.true_failure_year) <= 1
    assert u.trends["bearing_friction"].n == 5
    # The wear before the repair is tested with the wear since (pooled over the segments);
    # a unit without a repair has no such test.
    assert np.isfinite(u.drift.p_history) and u.drift.abnormal
    assert "across its repairs" in u.plan
    for other in ("Acc", "Lin", "Ok"):
        assert np.isnan(s.units[other].drift.p_history), other
