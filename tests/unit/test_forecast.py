"""forecast: Student-t trends, twin propagation (surrogate in the box, FMU outside), root cause."""
from __future__ import annotations

import dataclasses
import json
import re

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

from twinmon import artifacts
from twinmon.calibrate import UnitPosterior, write_posterior
from twinmon.config import load_config
from twinmon.errors import ArtifactError, CalibrationError
from twinmon.forecast import (SOURCE_FAILED, SOURCE_FMU, SOURCE_SURROGATE, TwinResult,
                              degrading_directions, evaluate_twin, fit_trend, forecast,
                              forecast_units, maintenance_plan, read_forecast,
                              residual_correlation,
                              sample_predictive, slope_test, verdict)
from twinmon.reduce import read_surrogate, reduce
from twinmon.safety import Indicator
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml

YEARS = np.arange(1, 11)


# ---------------------------------------------------------------------------------------
# Fixtures
# ---------------------------------------------------------------------------------------
def write_synthetic_posterior(path, cfg, lines: dict, seed: int = 0, n_s: int = 200,
                              scatter=(0.25, 0.03), post_std=(0.3, 0.05), years=YEARS):
    """A posterior artifact (calibrate's writer) whose yearly estimates follow given lines.

    ``lines``: unit -> [(intercept, slope)] per input, or the path itself [n_y, d]. The
    yearly means scatter about it by ``scatter`` (per input); draws scatter about the mean
    by ``post_std``. Every unit has the recorded ``years``.
    """
    rng = np.random.default_rng(seed)
    d = len(cfg.model.inputs)
    units = {}
    years = np.asarray(years)
    for unit, coefs in lines.items():
        n_y = years.size
        centre = (np.array(coefs, float) if np.ndim(coefs) == 2 and len(coefs) == n_y
                  else np.column_stack([a + b * years for a, b in coefs]))
        centre = centre + rng.standard_normal((n_y, d)) * np.asarray(scatter)
        samples = centre[:, None, :] + rng.standard_normal((n_y, n_s, d)) * np.asarray(post_std)
        units[unit] = UnitPosterior(
            years=years.copy(), samples=samples, mean=samples.mean(axis=1),
            median=np.median(samples, axis=1), q05=np.quantile(samples, 0.05, axis=1),
            q95=np.quantile(samples, 0.95, axis=1), rhat=np.ones((n_y, d)),
            ess=np.full((n_y, d), float(n_s)), acceptance=np.full((n_y, 2), 0.3),
            noise_std=np.full(n_y, 4.0), noise_source="file",
            surrogate_var_ratio=np.zeros(n_y))
    write_posterior(path, units, cfg.model.input_names, cfg, [])
    return path


HEALTHY = [(10.0, 0.0), (3.75, -0.02)]
PUMP = [(10.0, 0.0), (3.7, -0.12)]
MOTOR = [(9.0, 1.0), (3.7, -0.02)]
BOTH = [(9.0, 1.0), (3.7, -0.12)]


@pytest.fixture(scope="module")
def setup(tmp_path_factory, fmu_path):
    """A real surrogate, a small-sample config and a four-unit synthetic posterior."""
    tmp = tmp_path_factory.mktemp("forecast")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"executor": "serial"},
        "forecast": {"samples": 300, "observed_samples": 40},
    })
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    post = write_synthetic_posterior(tmp / "post.h5", cfg, {
        "Healthy": HEALTHY, "Pumpy": PUMP, "Motory": MOTOR, "Bothy": BOTH})
    summary = forecast(cfg, post, tmp / "sur.h5", tmp / "fc.h5")
    return cfg, cfg_path, tmp, summary


# ---------------------------------------------------------------------------------------
# Trends and intervals
# ---------------------------------------------------------------------------------------
def test_linear_model_slope_equals_numpy_polyfit():
    rng = np.random.default_rng(1)
    y = 3.7 - 0.08 * YEARS + 0.05 * rng.standard_normal(YEARS.size)
    t, resid = fit_trend(YEARS, y)
    slope, icpt = np.polyfit(YEARS, y, 1)
    assert t.slope == pytest.approx(slope, rel=1e-10)
    assert t.intercept == pytest.approx(icpt, rel=1e-10)
    assert np.allclose(resid, y - (icpt + slope * YEARS), atol=1e-12)
    assert t.residual_std == pytest.approx(np.sqrt(np.sum(resid ** 2) / (YEARS.size - 2)))


def test_prediction_interval_is_student_t_by_hand():
    x = np.array([1.0, 2, 3, 5, 8])
    y = np.array([2.1, 2.9, 4.2, 5.8, 9.1])
    t, _ = fit_trend(x, y)
    x0 = np.array([9.0, 12.0])
    mean, lo, hi, _ = t.predict(x0, 0.90)
    # Hand computation: yhat +- t_{n-2,0.95} s sqrt(1 + 1/n + (x0-xbar)^2/Sxx)
    n = x.size
    b1 = np.sum((x - x.mean()) * (y - y.mean())) / np.sum((x - x.mean()) ** 2)
    b0 = y.mean() - b1 * x.mean()
    s = np.sqrt(np.sum((y - b0 - b1 * x) ** 2) / (n - 2))
    half = stats.t.ppf(0.95, n - 2) * s * np.sqrt(1 + 1 / n + (x0 - x.mean()) ** 2
                                                  / np.sum((x - x.mean()) ** 2))
    assert np.allclose(mean, b0 + b1 * x0)
    assert np.allclose(hi - mean, half) and np.allclose(mean - lo, half)
    # Not the normal quantile: with 3 dof the t interval is much wider.
    assert np.all(hi - mean > 1.3 * stats.norm.ppf(0.95) * s)
    # The slope interval is the t interval of the slope.
    se = s / np.sqrt(np.sum((x - x.mean()) ** 2))
    assert np.allclose(t.slope_ci, (b1 - stats.t.ppf(0.95, n - 2) * se,
                                    b1 + stats.t.ppf(0.95, n - 2) * se))


def test_predictive_samples_follow_the_interval_and_the_correlation():
    rng = np.random.default_rng(2)
    y1 = 10 + 1.0 * YEARS + 0.3 * rng.standard_normal(10)
    y2 = 3.7 - 0.1 * YEARS + 0.05 * rng.standard_normal(10)
    t1, r1 = fit_trend(YEARS, y1)
    t2, r2 = fit_trend(YEARS, y2)
    corr = np.array([[1.0, 0.8], [0.8, 1.0]])
    fut = np.array([11, 15])
    X = sample_predictive([t1, t2], fut, corr, 40000, np.random.default_rng(3))
    assert X.shape == (2, 40000, 2)
    for i, t in enumerate((t1, t2)):
        _, lo, hi, _ = t.predict(fut, 0.90)
        inside = np.mean((X[:, :, i] >= lo[:, None]) & (X[:, :, i] <= hi[:, None]), axis=1)
        assert np.allclose(inside, 0.90, atol=0.01)
    assert np.corrcoef(X[1].T)[0, 1] == pytest.approx(0.8, abs=0.02)
    R = residual_correlation(np.column_stack([r1, r2]))
    assert R.shape == (2, 2) and np.allclose(np.diag(R), 1)
    assert R[0, 1] == pytest.approx(np.corrcoef(r1, r2)[0, 1], abs=1e-6)


@pytest.mark.parametrize("slope, expect", [(-0.5, False), (0.2, False), (0.4, True), (0.9, True)])
def test_slope_test_is_one_sided_against_normal_ageing(slope, expect):
    rng = np.random.default_rng(4)
    y = 10 + slope * YEARS + 0.2 * rng.standard_normal(10)
    t, _ = fit_trend(YEARS, y)
    t = slope_test(t, normal_rate=0.0, tolerance=0.25, direction=+1, alpha=0.01)
    bound = 0.25
    assert t.p_value == pytest.approx(stats.t.sf((t.slope - bound) / t.slope_se, 8))
    assert t.rejects is expect and "one-sided t test" in t.test
    # A falling input whose degrading direction is downwards is tested the other way.
    down, _ = fit_trend(YEARS, 3.7 - slope / 8 * YEARS + 0.02 * rng.standard_normal(10))
    down = slope_test(down, -0.02, 0.03, direction=-1, alpha=0.01)
    assert down.p_value == pytest.approx(
        stats.t.sf((-down.slope - 0.05) / down.slope_se, 8))


def test_degrading_directions_from_the_config_or_inferred_above_the_noise(setup):
    cfg, _, tmp, _ = setup
    sur = read_surrogate(tmp / "sur.h5")
    d = degrading_directions(cfg, sur)
    assert {n: (v.sign, v.source) for n, v in d.items()} == \
        {"motor_damping": (1, "config"), "pump_coef": (-1, "config")}
    # Without the config's word, the same directions are inferred from the twin, each far
    # above the surrogate's own indicator error on the held-out runs.
    free = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, inputs={
        n: dataclasses.replace(s, degrading=None) for n, s in cfg.model.inputs.items()}))
    d = degrading_directions(free, sur)
    assert {n: v.sign for n, v in d.items()} == {"motor_damping": 1, "pump_coef": -1}
    for v in d.values():
        assert v.source == "inferred" and abs(v.effect) > 3 * v.noise and not v.note
    # An input whose effect on the indicator drowns in the surrogate's error is not guessed:
    # held-out runs 50 % off make the surrogate's own t90 error several seconds.
    Y_test = sur.Y_test
    try:
        sur.Y_test = Y_test * 1.5
        d = degrading_directions(free, sur)
    finally:
        sur.Y_test = Y_test
    assert all(v.sign == 0 and "two-sided" in v.note for v in d.values()), d


def test_two_sided_slope_test_when_the_direction_is_unknown():
    rng = np.random.default_rng(5)
    for slope in (+0.5, -0.5):
        t, _ = fit_trend(YEARS, 10 + slope * YEARS + 0.1 * rng.standard_normal(10))
        t = slope_test(t, normal_rate=0.0, tolerance=0.1, direction=0, alpha=0.01)
        assert t.rejects and "two-sided" in t.test and t.direction == 0
    t, _ = fit_trend(YEARS, 10 + 0.05 * YEARS + 0.1 * rng.standard_normal(10))
    assert not slope_test(t, 0.0, 0.1, 0, 0.01).rejects


# ---------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------
def test_root_cause_verdicts_on_synthetic_posteriors(setup):
    _, _, _, s = setup
    causes = {u: f.root_cause for u, f in s.units.items()}
    assert causes == {"Healthy": "healthy", "Pumpy": "pump", "Motory": "motor",
                      "Bothy": "both"}
    alpha = setup[0].forecast.alpha
    for unit, f in s.units.items():
        for name, t in f.trends.items():
            assert (t.p_value < alpha) == t.rejects
    assert verdict(s.units["Bothy"].trends) == "both"


def test_failure_year_and_plan(setup):
    cfg, _, _, s = setup
    for unit, f in s.units.items():
        fy = [int(y) for y, p in zip(f.years_future, f.p_unsafe)
              if p > cfg.safety.failure_probability]
        assert f.failure_year == (fy[0] if fy else None)
    healthy, pump = s.units["Healthy"], s.units["Pumpy"]
    assert healthy.failure_year is None and healthy.plan.startswith("No action")
    # b2 = 3.7 - 0.12 y crosses ~2.2 near year 12.5: the pump unit fails in the horizon.
    assert pump.failure_year is not None and 11 <= pump.failure_year <= 14
    assert "pump" in pump.plan and "motor within normal ageing" in pump.plan
    deadline = "now" if pump.failure_year == 11 else f"year {pump.failure_year - 1}"
    assert deadline in pump.plan
    # The probability of being unsafe grows with the years for a degrading unit.
    assert np.all(np.diff(pump.p_unsafe) >= -0.03)


def test_points_outside_the_box_go_through_the_fmu(setup):
    from twinmon.fmu import FMUModel
    from twinmon.simulate import spec_for
    cfg, _, tmp, s = setup
    sur = read_surrogate(tmp / "sur.h5")
    X = np.array([[10.0, 3.61],     # inside
                  [35.0, 3.61],     # damping above the box
                  [10.0, 2.0],      # pump coefficient below the box, still physical
                  [10.0, 1.5]])     # non-physical
    r = evaluate_twin(cfg, sur, X)
    assert list(r.source) == [SOURCE_SURROGATE, SOURCE_FMU, SOURCE_FMU, SOURCE_FMU]
    spec = spec_for(cfg)
    ind = Indicator.from_config(cfg)
    with FMUModel(spec.fmu, spec.outputs, spec.times) as m:
        for k in (1, 2):
            out = m.run({"motor.D": X[k, 0], "pump.b2": X[k, 1]})
            assert r.value[k] == ind(spec.times, out[ind.variable])
    assert r.value[0] == ind(sur.time, sur.predict(X[:1]))[0]
    assert list(r.nonphysical) == [False, False, False, True]
    assert list(r.unsafe(cfg.safety)) == [False, True, True, True]
    # A degrading unit leaves the box in the later years: those samples used the FMU, or the
    # limit-state model where it is sure they are unsafe. (The summary keeps each unit's
    # figures; its Monte Carlo arrays are in the artifact.)
    f = read_forecast(tmp / "fc.h5").units["Bothy"]
    assert s.units["Bothy"].samples is None
    assert s.units["Bothy"].fmu_fraction == f.fmu_fraction
    assert s.units["Bothy"].model_fraction == f.model_fraction
    outside = ~sur.in_box(f.samples.reshape(-1, 2))
    assert f.fmu_fraction > 0 and f.model_fraction > 0
    assert f.fmu_fraction + f.model_fraction == pytest.approx(outside.mean())
    assert np.all(f.source.ravel()[outside] != SOURCE_SURROGATE)
    assert np.all(f.source.ravel()[~outside] == SOURCE_SURROGATE)


def test_a_repeated_point_is_evaluated_once_with_the_result_of_every_point(setup):
    """Repeats (a joint posterior's points are drawn with replacement) are evaluated once; a
    point's result is the one it gets alone, in the box and outside it, wherever it sits
    in the batch."""
    from twinmon.forecast.twin import distinct_rows
    cfg, _, tmp, _ = setup
    sur = read_surrogate(tmp / "sur.h5")
    rng = np.random.default_rng(5)
    pool = np.column_stack([rng.uniform(5.0, 40.0, 12), rng.uniform(1.5, 4.0, 12)])
    X = pool[rng.integers(0, 12, 40)]
    U, inv = distinct_rows(X)
    assert len(U) < len(X) and np.array_equal(U[inv], X)
    assert len(np.unique(U, axis=0)) == len(U)
    r = evaluate_twin(cfg, sur, X)
    assert (r.source == SOURCE_FMU).any() and (r.source == SOURCE_SURROGATE).any()
    for k in range(len(X)):
        one = evaluate_twin(cfg, sur, X[k:k + 1])
        assert np.array_equal(r.value[k], one.value[0], equal_nan=True)
        assert (r.source[k], r.nonphysical[k]) == (one.source[0], one.nonphysical[0])


def test_distinct_rows_are_numpys_unique_rows_for_two_inputs_and_more():
    """Two inputs take another sort (one complex key) than three (lexsort): both give
    numpy's sorted unique rows and their inverse, ties in the first input included."""
    from twinmon.forecast.twin import distinct_rows
    rng = np.random.default_rng(3)
    for d in (2, 3):
        pool = rng.integers(0, 4, (30, d)).astype(float) + rng.choice([0.0, 0.5], (30, d))
        X = pool[rng.integers(0, 30, 200)]
        U, inv = distinct_rows(X)
        ref, ref_inv = np.unique(X, axis=0, return_inverse=True)
        assert np.array_equal(U, ref) and np.array_equal(inv, ref_inv.ravel())


def test_failed_fmu_runs_count_as_unsafe(setup):
    cfg = setup[0]
    r = TwinResult(value=np.array([10.0, np.nan]), nonphysical=np.zeros(2, bool),
                   source=np.array([SOURCE_FMU, SOURCE_FAILED], np.int8))
    assert list(r.unsafe(cfg.safety)) == [False, True]


def test_same_seed_same_forecast_and_another_seed_differs(setup, tmp_path):
    cfg, _, tmp, s = setup
    again = forecast(cfg, tmp / "post.h5", tmp / "sur.h5", tmp_path / "fc.h5")
    other = forecast(dataclasses.replace(cfg, seed=cfg.seed + 1),
                     tmp / "post.h5", tmp / "sur.h5", tmp_path / "fc2.h5")
    first, second, third = (read_forecast(p) for p in (tmp / "fc.h5", tmp_path / "fc.h5",
                                                       tmp_path / "fc2.h5"))
    for unit in s.units:
        a, b = first.units[unit], second.units[unit]
        assert np.array_equal(a.samples, b.samples)
        assert np.array_equal(a.indicator, b.indicator, equal_nan=True)
        assert np.array_equal(a.p_unsafe, b.p_unsafe)
        assert np.array_equal(again.units[unit].p_unsafe, s.units[unit].p_unsafe)
        assert not np.array_equal(a.samples, third.units[unit].samples)
    with h5py.File(tmp_path / "fc.h5") as f1, h5py.File(tmp / "fc.h5") as f2:
        assert np.array_equal(f1["units/Pumpy/indicator"][()], f2["units/Pumpy/indicator"][()],
                              equal_nan=True)


def test_same_forecast_whatever_the_workers_and_chunks(setup, tmp_path, monkeypatch):
    """Units forecast on a pool of two processes (one chunk of units per task, the FMU in
    each worker) equal those forecast here in chunks of three (the FMU on this process):
    a unit's draws are keyed by its name, a point's prediction is its own."""
    import twinmon.forecast.workers as fworkers
    from twinmon.calibrate import read_posterior
    from twinmon.reduce import read_surrogate
    cfg, _, tmp, s = setup
    pooled = dataclasses.replace(cfg, simulate=dataclasses.replace(cfg.simulate,
                                                                   executor="process"))
    forecast(pooled, tmp / "post.h5", tmp / "sur.h5", tmp_path / "pool.h5", workers=2)
    monkeypatch.setattr(fworkers, "_chunk_size", lambda n, w: 3)
    here, _, _ = forecast_units(cfg, read_posterior(tmp / "post.h5"),
                                read_surrogate(tmp / "sur.h5"), workers=1)
    assert list(here) == list(s.units)
    fc = read_forecast(tmp_path / "pool.h5")
    for unit, b in here.items():
        a = fc.units[unit]
        assert np.array_equal(a.samples, b.samples)
        assert np.array_equal(a.indicator, b.indicator, equal_nan=True)
        assert np.array_equal(a.source, b.source)
        assert np.array_equal(a.indicator_observed, b.indicator_observed, equal_nan=True)
        assert a.root_cause == b.root_cause and a.plan == b.plan
        assert a.as_dict() == b.as_dict()


def test_artifact_round_trip_and_provenance(setup):
    cfg, _, tmp, s = setup
    fc = read_forecast(tmp / "fc.h5")
    assert fc.input_names == cfg.model.input_names and set(fc.units) == set(s.units)
    for unit, u in s.units.items():
        r = fc.units[unit]
        assert r.root_cause == u.root_cause and r.failure_year == u.failure_year
        assert np.array_equal(r.p_unsafe, u.p_unsafe) and r.plan == u.plan
        for name, t in u.trends.items():
            assert r.trends[name].slope == t.slope and r.trends[name].p_value == t.p_value
            assert np.array_equal(r.pred_hi[name], u.pred_hi[name])
        assert r.as_dict() == u.as_dict()
    # Without the Monte Carlo arrays (a fleet's summaries): the same figures.
    light = read_forecast(tmp / "fc.h5", arrays=False)
    for unit, u in s.units.items():
        r = light.units[unit]
        assert r.samples is None and r.indicator is None and r.indicator_observed is None
        assert r.n_samples == fc.units[unit].indicator.shape[1]
        assert r.fmu_fraction == u.fmu_fraction and r.plan == u.plan
        assert np.array_equal(r.p_unsafe, u.p_unsafe)
    prov = artifacts.read_provenance(tmp / "fc.h5")
    assert prov["schema"] == "twinmon.forecast/1" and "seed" in prov
    assert [p["path"] for p in prov["inputs"]] == [str(tmp / "post.h5"), str(tmp / "sur.h5")]
    with h5py.File(tmp / "fc.h5") as f:
        def check(name, obj):
            if isinstance(obj, h5py.Dataset):
                assert "units" in obj.attrs and obj.attrs["description"], name
        f.visititems(check)


def test_packed_arrays_are_what_hdf5_filters_store(tmp_path):
    """The workers compress the Monte Carlo arrays themselves (shuffle, then zlib, one chunk
    per year); HDF5 reads them back bit for bit, NaN and inf included, for every dtype the
    artifact stores."""
    from twinmon.forecast.artifact import _put_per_year, pack_per_year
    rng = np.random.default_rng(3)
    draws = rng.normal(size=(4, 50, 2))
    draws[1, 3, 0], draws[2, 7, 1] = np.nan, np.inf
    arrays = {"draws": draws, "flags": (rng.random((4, 50)) < 0.1).astype(np.int8),
              "codes": rng.integers(0, 4, (3, 20)).astype(np.int8),
              "one_year": rng.normal(size=(1, 7)), "empty": np.zeros((0, 5))}
    with h5py.File(tmp_path / "a.h5", "w") as f:
        for name, a in arrays.items():
            _put_per_year(f, name, pack_per_year(a) if a.size else a, "1", name)
            _put_per_year(f, name + "_here", a, "1", name)
    with h5py.File(tmp_path / "a.h5") as f:
        for name, a in arrays.items():
            for key in (name, name + "_here"):
                assert f[key].dtype == a.dtype and f[key].shape == a.shape
                assert np.array_equal(f[key][()], a, equal_nan=a.dtype.kind == "f"), key
            if a.size:
                assert f[name].chunks == (1,) + a.shape[1:]
                last = (len(a) - 1,) + (0,) * (a.ndim - 1)
                assert f[name].id.read_direct_chunk(last)[1] == \
                    f[name + "_here"].id.read_direct_chunk(last)[1]


def test_a_flipped_byte_in_the_monte_carlo_arrays_is_a_damaged_artifact(setup, tmp_path):
    """Their chunks' zlib checksum finds damage as the checksum of the other datasets does:
    an artifact error naming the file, not numbers read as plausible."""
    import shutil
    _, _, tmp, s = setup
    path = tmp_path / "fc.h5"
    shutil.copy(tmp / "fc.h5", path)
    unit = next(iter(s.units))
    with h5py.File(path, "r") as f:
        offset = f[f"units/{unit}/indicator"].id.get_chunk_info(0).byte_offset + 40
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x10]))
    with pytest.raises(ArtifactError, match=re.escape(str(path))):
        read_forecast(path).units[unit].indicator


def test_json_shape_via_cli(setup, tmp_path):
    from twinmon.cli import main
    _, cfg_path, tmp, _ = setup
    res = CliRunner().invoke(main, ["forecast", "-c", str(cfg_path), "--posterior",
                                    str(tmp / "post.h5"), "--surrogate", str(tmp / "sur.h5"),
                                    "-o", str(tmp_path / "fc.h5"), "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert set(out["units"]) == {"Healthy", "Pumpy", "Motory", "Bothy"}
    for u in out["units"].values():
        assert u["root_cause"] in ("healthy", "pump", "motor", "both")
        assert u["failure_year"] is None or isinstance(u["failure_year"], int)
        assert len(u["years"]) == len(u["p_unsafe"]) == 7
        assert all(isinstance(y, int) for y in u["years"])
        assert len(u["years_observed"]) == len(u["p_unsafe_observed"])
        past = [y for y, p in zip(u["years_observed"], u["p_unsafe_observed"]) if p > 0.05]
        assert u["unsafe_since"] is None if u["p_unsafe_observed"][-1] <= 0.05 \
            else u["unsafe_since"] in past
        assert set(u["trends"]) == {"motor_damping", "pump_coef"}
        assert set(u["trends"]["pump_coef"]) >= {"slope", "slope_ci90", "intercept",
                                                 "p_value", "test", "normal_rate"}
        assert set(u["indicator"]) == {"median", "q05", "q95"} and isinstance(u["plan"], str)
        assert 0 <= u["fmu_fraction"] <= 1 and "true_failure_year" not in u


def test_a_year_the_trend_cannot_follow_is_unreliable_in_the_artifact_and_json(
        setup, tmp_path):
    """A unit whose year 8 lies 6 N.m.s/rad (20 posterior sd) off its line gets status
    unreliable with the trend-fit gate's reason and p-value in forecast.h5 and --json; the
    straight line beside it stays ok. (A sequential posterior: no fleet prior of the
    year-to-year sd, so only a gross miss shows.)"""
    from twinmon.cli import main
    cfg, cfg_path, tmp, _ = setup
    odd = np.column_stack([10.0 + 0 * YEARS, 3.75 - 0.02 * YEARS])
    odd[7, 0] += 6.0
    post = write_synthetic_posterior(tmp_path / "post.h5", cfg, {
        "Steady": HEALTHY, "Odd": odd})
    res = CliRunner().invoke(main, ["forecast", "-c", str(cfg_path), "--posterior", str(post),
                                    "--surrogate", str(tmp / "sur.h5"),
                                    "-o", str(tmp_path / "fc.h5"), "--json"])
    assert res.exit_code == 0, res.output
    units = json.loads(res.stdout)["units"]
    bad, good = units["Odd"], units["Steady"]
    assert bad["status"] == "unreliable"
    assert bad["status_reason"].startswith("prognosis unreliable: the trend missed year(s)")
    assert bad["trend_fit"]["p_value"] < 0.01 and bad["trend_fit"]["missed_years"] == [8]
    assert good["status"] == "ok" and good["trend_fit"]["p_value"] >= 0.01
    assert good["trend_fit"]["years"] == list(range(4, 11))
    stored = read_forecast(tmp_path / "fc.h5").units["Odd"]
    assert stored.status == "unreliable" and stored.status_reason == bad["status_reason"]
    assert stored.trend_fit == bad["trend_fit"]
    assert "(prognosis unreliable: the trend missed" in stored.plan


def test_a_fault_seen_in_three_years_extends_an_unchecked_trend(setup, tmp_path):
    """Three recorded years of a motor wearing 2.0 a year, its estimates close to the line
    (a year-by-year posterior's three years leave the slope's test one degree of freedom):
    the drift is seen and named, but no year could be predicted from three before it, so
    the trend the failure year extends was never checked: unreliable, with the record's
    years in the reason. Four years give the check a year to predict, and that reason
    goes."""
    cfg, _, tmp, _ = setup
    fast = [(9.0, 2.0), (3.7, -0.02)]
    short = forecast(cfg, write_synthetic_posterior(tmp_path / "p3.h5", cfg, {"Short": fast},
                                                    years=YEARS[:3], scatter=(0.02, 0.002)),
                     tmp / "sur.h5", tmp_path / "fc3.h5").units["Short"]
    assert short.root_cause == "motor" and short.trend_fit == {}
    assert short.status == "unreliable"
    assert short.status_reason.startswith(
        "prognosis unreliable: with 3 recorded year(s) (years 1-3) no year could be predicted "
        "from the 3 or more of its trend before it")
    four = forecast(cfg, write_synthetic_posterior(tmp_path / "p4.h5", cfg, {"Four": fast},
                                                   years=YEARS[:4], scatter=(0.02, 0.002)),
                    tmp / "sur.h5", tmp_path / "fc4.h5").units["Four"]
    assert four.root_cause == "motor" and four.trend_fit["years"] == [4]
    assert "no year could be predicted" not in four.status_reason


def test_text_lines_give_the_year_to_act_by_and_the_median_year(setup, tmp_path):
    from twinmon.cli import main
    _, cfg_path, tmp, s = setup
    res = CliRunner().invoke(main, ["forecast", "-c", str(cfg_path), "--posterior",
                                    str(tmp / "post.h5"), "--surrogate", str(tmp / "sur.h5"),
                                    "-o", str(tmp_path / "fc.h5")])
    assert res.exit_code == 0, res.output
    lines = {ln.split(":")[0]: ln for ln in res.stderr.splitlines() if ": " in ln}
    for unit, u in s.units.items():
        if u.status == "withheld":
            assert "WITHHELD" in lines[unit]
            continue
        m = re.search(r"failure year \(P\(unsafe\) > [0-9.]+\) ([^;(]+)", lines[unit])
        said = m.group(1).strip()
        if u.failure_year is None:
            assert said.startswith("none by")
        elif u.median_failure_year == u.failure_year:
            assert said == str(u.failure_year)
        else:
            med = u.median_failure_year
            assert said == f"{u.failure_year}, median " + (
                str(med) if med is not None else f"after {u.years_future[-1]}")


# ---------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------
def test_posterior_for_other_inputs_is_an_artifact_error(setup, tmp_path):
    cfg, cfg_path, tmp, _ = setup
    bad = write_synthetic_posterior(tmp_path / "posterior_other_inputs.h5", cfg,
                                    {"U": HEALTHY})
    with h5py.File(bad, "r+") as f:
        f.attrs["input_names"] = json.dumps(["speed", "pump_coef"])
    with pytest.raises(ArtifactError, match="posterior_other_inputs.h5"):
        forecast(cfg, bad, tmp / "sur.h5", tmp_path / "fc.h5")
    assert not (tmp_path / "fc.h5").exists()
    from twinmon.cli import main
    res = CliRunner().invoke(main, ["forecast", "-c", str(cfg_path), "--posterior", str(bad),
                                    "--surrogate", str(tmp / "sur.h5"),
                                    "-o", str(tmp_path / "fc.h5")])
    assert res.exit_code == ArtifactError.exit_code
    assert "posterior_other_inputs.h5" in res.stderr


def _keep_first_years(path, unit: str, n: int) -> None:
    """Cut a written posterior's unit to its first ``n`` years (every per-year dataset)."""
    with h5py.File(path, "r+") as f:
        g = f["units"][unit]
        for name in list(g):
            data = g[name][()]
            attrs = dict(g[name].attrs)
            del g[name]
            g.create_dataset(name, data=data[:n])
            g[name].attrs.update(attrs)


def test_posterior_with_two_years_is_a_calibration_error(setup, tmp_path):
    cfg, _, tmp, _ = setup
    path = write_synthetic_posterior(tmp_path / "posterior_two_years.h5", cfg, {"U": HEALTHY})
    _keep_first_years(path, "U", 2)
    with pytest.raises(CalibrationError, match="at least 3"):
        forecast(cfg, path, tmp / "sur.h5", tmp_path / "fc.h5")


def test_a_horizon_longer_than_the_record_is_a_warning(setup, tmp_path):
    cfg, cfg_path, tmp, summary = setup
    assert not any("forecast.horizon" in w for w in summary.warnings)
    n = max(len(uf.years_observed) for uf in summary.units.values())
    cfg2 = load_config(cfg_path, [f"forecast.horizon={n + 1}", "forecast.samples=100"])
    post = write_synthetic_posterior(tmp_path / "one.h5", cfg2, {"U": HEALTHY})
    s = forecast(cfg2, post, tmp / "sur.h5", tmp_path / "fc.h5")
    assert any(f"forecast.horizon {n + 1} years is longer than the longest record ({n} "
               "calibrated years)" in w for w in s.warnings)


def test_a_unit_with_too_few_years_is_left_out_and_the_others_forecast(setup, tmp_path):
    """A fleet's unit new in service (2 years) does not stop the others' forecast: it is
    left out with a warning, named in the artifact and in --json, and the report says why
    it has no prognosis."""
    cfg, _, tmp, _ = setup
    path = write_synthetic_posterior(tmp_path / "posterior_new_unit.h5", cfg,
                                     {"Old": HEALTHY, "New": HEALTHY})
    _keep_first_years(path, "New", 2)
    s = forecast(cfg, path, tmp / "sur.h5", tmp_path / "fc.h5")
    assert set(s.units) == {"Old"} and s.too_few_years == {"New": 2}
    assert any("New (2)" in w and "too few for a trend" in w for w in s.warnings)
    assert s.as_dict()["too_few_years"] == {"New": 2}
    back = read_forecast(tmp_path / "fc.h5")
    assert list(back.units) == ["Old"] and back.too_few_years == {"New": 2}
    from twinmon.calibrate import read_posterior
    from twinmon.report.common import Words
    from twinmon.report.load import Inputs
    from twinmon.report.summary import unit_summary
    inp = Inputs(cfg=cfg, words=Words.from_config(cfg), posterior=read_posterior(path),
                 forecast=back)
    u = unit_summary("New", inp, {})
    assert u.short_health == "not judged (too few years)"
    assert u.action.startswith("no prognosis yet: 2 calibrated year(s), a trend needs 3")


def test_a_part_replaced_in_the_last_years_makes_the_prognosis_unreliable(setup, tmp_path):
    """A motor replaced (recorded) in the last year: its trend restarted one year ago, too
    few to show the new part's rate; the unit's prognosis says so. Replaced three years
    before the end, the new part's own years carry its trend."""
    cfg, _, tmp, _ = setup
    # The motor's losses rise 1.0 a year, and the last year's new motor is back at 10.
    late = np.column_stack([9.0 + YEARS, 3.7 - 0.02 * YEARS])
    late[-1, 0] = 10.0
    path = write_synthetic_posterior(tmp_path / "posterior_replaced.h5", cfg,
                                     {"Late": late, "Early": MOTOR})
    last = int(YEARS[-1])
    with h5py.File(path, "r+") as f:
        f["units/Late"].attrs["events"] = json.dumps([[last, "motor", "replaced"]])
        f["units/Early"].attrs["events"] = json.dumps([[last - 2, "motor", "replaced"]])
    s = forecast(cfg, path, tmp / "sur.h5", tmp_path / "fc.h5")
    late, early = s.units["Late"], s.units["Early"]
    assert late.status == "unreliable"
    assert late.status_reason.startswith("prognosis unreliable: the trend restarted after a "
                                         f"repair, of motor_damping in year {last} (1 "
                                         "recorded year(s) since)")
    assert "restarted after a repair" not in early.status_reason
    # The new motor ages normally from its level: finite intervals around it, and no
    # failure (a one-year line has no spread of its own; taking the state's from it gave
    # NaN draws, counted unsafe: "fails next year" at 100 %).
    for name in late.trends:
        assert np.all(np.isfinite(late.pred_lo[name])) and np.all(np.isfinite(late.pred_hi[name]))
    assert late.pred_lo["motor_damping"][0] < 10.5 < late.pred_hi["motor_damping"][0] + 1
    assert late.failure_year is None and float(np.max(late.p_unsafe)) < 0.05


def test_wrong_kind_of_file_names_it(setup, tmp_path):
    cfg, _, tmp, _ = setup
    with pytest.raises(ArtifactError, match="sur.h5"):
        forecast(cfg, tmp / "sur.h5", tmp / "sur.h5", tmp_path / "fc.h5")


def test_plan_says_now_when_already_unsafe(setup):
    cfg, _, _, s = setup
    f = s.units["Pumpy"]
    plan = maintenance_plan(f.trends, f.years_future, np.ones(7), int(f.years_future[0]),
                            10, 0.5, cfg.safety)
    assert "now (already unsafe" in plan and "pump" in plan


@pytest.mark.parametrize("command", [["forecast"], ["diagnose", "--observations", "x.h5"]])
def test_a_negative_worker_count_is_refused_in_one_line(setup, command):
    from twinmon.cli import main
    _, cfg_path, _, _ = setup
    res = CliRunner().invoke(main, [*command, "-c", str(cfg_path), "-j", "-1"])
    assert res.exit_code == 3          # a bad value, as simulate -j -1 (ConfigError)
    assert "workers: expected 0 (one per core) or a positive count, got -1" in res.output


def test_the_drift_is_described_against_what_normal_units_show():
    """A slope inside "+- the band's edge" was called abnormal (p = 0.0064) in the same
    sentence: the edge is reached only when every input ages at its own edge at once. The
    sentence now gives the range 90 % of normal units stay in, then the edge."""
    import numpy as np

    from twinmon.forecast.detection import IndicatorDrift, uniform_sum
    half = np.array([0.2, 0.179])
    d = IndicatorDrift(np.arange(10), np.zeros(10), 0.448, 0.05, 8, 0.0886, half,
                       np.array([1.0, 1.0]), 1, 0.0064, True)
    text = d.describe("t90", "s")
    assert text.startswith("t90 slope +0.448 s/yr vs normal ageing +0.0886 (90 % of normal "
                           "units within +-")
    assert text.endswith("all within +-0.379; p = 0.0064)")
    q = float(text.split("within +-")[1].split(",")[0])
    u, w = uniform_sum(half)
    assert abs(float(w[np.abs(u) <= q].sum()) - 0.9) < 0.02
    assert q < 0.379          # the 90 % range is inside the edge the text used to give alone


def test_the_sequential_estimates_lag_a_drift_where_the_data_are_weak():
    """filter_attenuation: the slope of the expected sequential estimates for a drift of 1 a
    year. Data that fix each year (posterior far inside the prior): no lag. Data that keep
    only a tenth of the prior's precision a year (a 10x noisier record): the estimates show
    under half the drift, and the prognosis says so (describe_lag)."""
    import numpy as np

    from twinmon.config import load_config
    from twinmon.forecast.judge import describe_lag
    from twinmon.forecast.covariance import MIN_ATTENUATION, filter_attenuation
    cfg = load_config(CONFIGS / "pump.yaml")
    years = np.arange(1, 11)
    q0 = (cfg.calibrate.prior_width * np.diff(cfg.model.bounds, axis=1).ravel()) ** 2
    strong = np.array([np.diag(q0 * 1e-4)] * 10)
    assert np.allclose(filter_attenuation(cfg, years, strong, np.array([1, 1])), 1.0,
                       atol=1e-3)
    # P_k = 0.9 Q_k with Q_k = q0 + P_{k-1}: P = 9 q0 at the fixed point.
    weak = np.array([np.diag(9 * q0)] * 10)
    a = filter_attenuation(cfg, years, weak, np.array([1, 1]))
    # The same recursion by hand for one input: m_k = 0.9 m_{k-1} + 0.1 k.
    m, path = 0.0, []
    for k in years:
        m = (0.9 * m + 0.1 * k) if k > 1 else float(k)
        path.append(m)
    assert np.allclose(a, np.polyfit(years, path, 1)[0])
    assert a[0] < MIN_ATTENUATION
    text = describe_lag(cfg.model.input_names, a)
    assert text.startswith("prognosis unreliable: each year's estimate leans on the year "
                           "before") and "motor_damping" in text and "pump_coef" in text
    assert describe_lag(cfg.model.input_names, np.array([0.9, np.nan])) == ""
    # A trend restarted two years ago: no line to judge there.
    assert np.isnan(filter_attenuation(cfg, years, weak, np.array([1, 9]))[1])
