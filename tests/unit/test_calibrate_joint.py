"""calibrate, joint method: a unit's years and their linear trend in one posterior (the batched
numpy Gibbs sampler, checked against OpenTURNS' Gibbs) through a real surrogate; maintenance
events; the trend in the posterior artifact."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from twinmon import artifacts
from twinmon.calibrate import calibrate, read_posterior, write_posterior
from twinmon.calibrate.methods.joint import JointRun, calibrate_unit_joint
from twinmon.calibrate.posterior import thin_indices
from twinmon.calibrate.samplers.gpbatch import make_predictor
from twinmon.calibrate.samplers.joint_vectorised import run_joint_tasks
from twinmon.calibrate.trend import (TREND_FIELDS, TREND_OPTIONAL, design_matrix,
                                    segment_starts, trend_predictive)
from twinmon.config import load_config
from twinmon.errors import ConfigError
from twinmon.observations import (Observations, UnitObservations, read_observations,
                                  write_observations)
from twinmon.reduce import read_surrogate, reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml

NOISE = 4.0  # kg/s, 1 % of the nominal flow as in the shipped fleet


@pytest.fixture(scope="module")
def setup(tmp_path_factory, fmu_path):
    """A real surrogate (FMU runs + reduce) and a config for short joint chains."""
    tmp = tmp_path_factory.mktemp("joint")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 64, "test_size": 8},
        "calibrate": {"method": "joint", "chains": 3, "samples": 400, "burn_in": 150,
                      "workers": 1, "ess_warn": 100, "max_extensions": 1}})
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    return cfg, cfg_path, tmp, read_surrogate(tmp / "sur.h5")


def _observe(surrogate, X, seed=0):
    """Synthetic flows [n, n_t]: surrogate transients plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    clean = surrogate.predict(np.atleast_2d(X))
    return clean + NOISE * rng.standard_normal(clean.shape)


#: A unit on straight lines: motor damping +0.8 a year from 10, pump coefficient -0.06 a
#: year from 3.75 (years 1..6), with a little year-to-year scatter.
YEARS = np.arange(1, 7)
SLOPES = np.array([0.8, -0.06])


def _trend_unit(seed=2):
    rng = np.random.default_rng(seed)
    X = np.array([10.0, 3.75]) + np.outer(YEARS - 1, SLOPES)
    return X + rng.normal(0.0, [0.1, 0.005], X.shape)


@pytest.fixture(scope="module")
def trend_posterior(setup):
    cfg, _, _, sur = setup
    truth = _trend_unit()
    return truth, calibrate_unit_joint(sur, cfg, YEARS, _observe(sur, truth, seed=3), NOISE,
                                       rng_seed=11)


def test_known_trend_is_recovered(setup, trend_posterior):
    cfg = setup[0]
    truth, p = trend_posterior
    slope = p.trend["slope"][:, 0, :]
    lo, hi = np.quantile(slope, [0.01, 0.99], axis=0)
    assert np.all((lo < SLOPES) & (SLOPES < hi)), (lo, hi)
    # The damping's rise is told apart from no trend at all; the pump's fall (0.3 in five
    # years, against a single year's posterior sd of ~0.1) is only leaned towards.
    assert lo[0] > 0 and np.median(slope[:, 1]) < 0
    assert np.all(np.abs(p.mean - truth) / truth < 0.04), p.mean
    sd = p.samples.std(axis=1)
    assert np.all(np.abs(p.mean - truth) < 3.5 * sd)
    # sigma mixes slowest (rows: intercept, slope, sigma); these chains are short.
    assert np.all(p.rhat < 1.1) and np.all(p.trend["rhat"][:2] < 1.1)
    assert np.all((p.acceptance > 0.1) & (p.acceptance < 0.7))
    assert np.all((p.trend["acceptance"] > 0.1) & (p.trend["acceptance"] < 0.7))
    # A sigma well below the design's year-to-year scale (0.05 of the range) is found.
    span = np.diff(cfg.model.bounds, axis=1).ravel()
    assert np.all(np.median(p.trend["sigma"], axis=0) < cfg.calibrate.prior_width * span)


@pytest.mark.slow
def test_batched_sampler_matches_openturns_gibbs(setup):
    """The numpy sampler (default) and OpenTURNS' Gibbs (the reference) sample one posterior:
    the same unit, data and chain lengths give the same years' means and spreads and the same
    trend, within Monte Carlo error."""
    cfg, cfg_path, _, sur = setup
    truth = _trend_unit()
    flows = _observe(sur, truth, seed=3)
    long = ["calibrate.chains=4", "calibrate.samples=1000", "calibrate.max_extensions=0"]
    vec = calibrate_unit_joint(sur, load_config(cfg_path, long), YEARS, flows, NOISE,
                               rng_seed=11)
    ref = calibrate_unit_joint(sur, load_config(cfg_path, long + ["calibrate.sampler=openturns"]),
                               YEARS, flows, NOISE, rng_seed=11)
    assert not np.array_equal(ref.samples, vec.samples)      # two samplers, two chains
    sd = np.sqrt(ref.var)
    # Monte Carlo error of a mean with ESS >= 300: <= 0.06 sd each. The spreads follow the
    # heavy-tailed sigma, which mixes slowest: at this length they differ by up to ~10 %
    # (0.93 on average here; 0.98 with 5000 draws per chain), so the check is for gross
    # errors (a likelihood weighted by half its weight would widen them by 41 %).
    assert np.all(np.abs(vec.mean - ref.mean) < 0.3 * sd), (vec.mean - ref.mean) / sd
    ratio = np.sqrt(vec.var) / sd
    assert np.all(np.abs(ratio - 1) < 0.25) and abs(ratio.mean() - 1) < 0.15, ratio
    for key in ("slope", "intercept"):
        a, b = vec.trend[key][:, 0], ref.trend[key][:, 0]
        assert np.all(np.abs(np.median(a, 0) - np.median(b, 0)) < 0.35 * b.std(0)), key
        assert np.all(np.abs(a.std(0) / b.std(0) - 1) < 0.25), key


def test_a_chain_does_not_depend_on_its_batch(setup):
    """A chain's draws are the same whether it runs alone or batched with another unit's
    chains (every row its own generator, no arithmetic across rows)."""
    cfg, cfg_path, _, sur = setup
    quick = load_config(cfg_path, ["calibrate.samples=100", "calibrate.burn_in=30",
                                   "calibrate.chains=2"])
    a = JointRun(sur, quick, YEARS[:4], _observe(sur, _trend_unit()[:4], seed=3), NOISE, 5,
                  "file").plan()
    b = JointRun(sur, quick, YEARS[:4], _observe(sur, _trend_unit(seed=7)[:4], seed=8),
                  NOISE, 9, "file").plan()
    predict = make_predictor(sur)[0]
    alone = run_joint_tasks(predict, a)
    mixed = run_joint_tasks(predict, b[:1] + a + b[1:])
    for x, y in zip(alone, mixed[1:3]):
        assert np.array_equal(x[0], y[0]) and np.array_equal(x[1], y[1]) and x[2] == y[2]
    assert not np.array_equal(mixed[0][0], alone[0][0])


def test_the_years_are_shaped_as_the_sequential_methods(setup, trend_posterior):
    cfg, _, _, _ = setup
    _, p = trend_posterior
    n_s = cfg.calibrate.chains * cfg.calibrate.samples
    K = len(YEARS)
    assert p.samples.shape == (K, n_s, 2) and p.mean.shape == (K, 2)
    assert p.acceptance.shape == (K, cfg.calibrate.chains)
    assert np.all(p.q05 < p.median) and np.all(p.median < p.q95)
    assert list(p.status) == ["ok"] * K
    assert len(set(p.fit["extensions"])) == 1       # the unit is lengthened as a whole
    assert p.var.shape == (K, 2) and p.chain_end.shape == (K, cfg.calibrate.chains, 2)
    t = p.trend
    assert t["start"].tolist() == [[1, 1]]
    assert t["intercept"].shape == t["slope"].shape == (n_s, 1, 2)
    assert t["sigma"].shape == (n_s, 2) and np.all(t["sigma"] >= 0)
    assert t["rhat"].shape == t["ess"].shape == (3, 2)


def test_same_seed_same_draws(setup):
    cfg, cfg_path, _, sur = setup
    quick = load_config(cfg_path, ["calibrate.samples=100", "calibrate.burn_in=40",
                                   "calibrate.chains=2", "calibrate.max_extensions=0"])
    flows = _observe(sur, _trend_unit()[:3], seed=3)
    a = calibrate_unit_joint(sur, quick, YEARS[:3], flows, NOISE, rng_seed=5)
    b = calibrate_unit_joint(sur, quick, YEARS[:3], flows, NOISE, rng_seed=5)
    assert np.array_equal(a.samples, b.samples)
    assert np.array_equal(a.trend["slope"], b.trend["slope"])
    c = calibrate_unit_joint(sur, quick, YEARS[:3], flows, NOISE, rng_seed=6)
    assert not np.array_equal(a.samples, c.samples)


def test_segment_starts_follow_the_events(setup):
    cfg, _, _, _ = setup
    years = np.array([1, 2, 3, 5, 6, 8])
    # pump_coef's component is "pump", motor_damping's "motor" (configs/pump.yaml).
    starts = segment_starts(cfg, years, [(4, "pump"), (6, "motor"), (9, "motor"),
                                         (2, "valve")])
    assert [s.tolist() for s in starts] == [[1, 6], [1, 5]]
    X, centres = design_matrix(years, starts[1])
    assert centres.tolist() == [2.0, 19 / 3]
    assert X[:, 0].tolist() == [1, 1, 1, 0, 0, 0] and X[:, 2].tolist() == [0, 0, 0, 1, 1, 1]
    assert np.allclose(X[:3, 1], [-1, 0, 1]) and np.allclose(X[:3, 3], 0)
    # Events as the observations file gives them (objects with year and component).
    from twinmon.observations import Event
    assert segment_starts(cfg, years, [Event(5, "pump")])[1].tolist() == [1, 5]


def test_a_replaced_part_restarts_its_trend(setup):
    """The pump is replaced in year 4: its coefficient jumps back up and declines again; the
    motor's damping keeps one line."""
    cfg, cfg_path, _, sur = setup
    quick = load_config(cfg_path, ["calibrate.samples=250", "calibrate.burn_in=100",
                                   "calibrate.max_extensions=0"])
    years = np.arange(1, 8)
    truth = np.column_stack([10.0 + 0.5 * (years - 1),
                             np.where(years < 4, 3.75 - 0.15 * (years - 1),
                                      3.8 - 0.05 * (years - 4))])
    flows = _observe(sur, truth, seed=4)
    p = calibrate_unit_joint(sur, quick, years, flows, NOISE, rng_seed=3,
                             events=[(4, "pump")])
    t = p.trend
    assert t["start"].tolist() == [[1, 1], [-1, 4]]
    assert np.all(np.isnan(t["slope"][:, 1, 0])) and not np.any(np.isnan(t["slope"][:, 1, 1]))
    # The new pump's line starts near 3.8 in year 4, well above where the old one ended
    # (the truth jumps by 0.35).
    new_level = np.median(t["intercept"][:, 1, 1])
    assert abs(new_level - 3.8) < 0.1
    assert p.mean[3, 1] - p.mean[2, 1] > 0.15
    assert np.all(np.abs(p.mean - truth) / truth < 0.05)
    # The predictive extrapolates each input's last segment.
    draws = trend_predictive(t, [10], np.random.default_rng(0))
    assert draws.shape == (len(t["sigma"]), 1, 2)
    expect = np.median(t["intercept"][:, 1, 1] + t["slope"][:, 1, 1] * 6)
    assert abs(np.median(draws[:, 0, 1]) - expect) < 0.05


def test_calibrate_stage_writes_the_trend_and_reads_it_back(setup, tmp_path):
    cfg, cfg_path, tmp, sur = setup
    flows = _observe(sur, _trend_unit()[:4], seed=6)
    obs = tmp_path / "obs.h5"
    # Two units, so that calibrate.workers=2 below runs them in two worker processes.
    write_observations(obs, Observations(sur.time, {
        "A": UnitObservations(YEARS[:4], {"m_flow": flows}, {"m_flow": NOISE}),
        "B": UnitObservations(YEARS[:4], {"m_flow": _observe(sur, _trend_unit(seed=7)[:4],
                                                              seed=8)}, {"m_flow": NOISE})},
        obs))
    quick_set = ["calibrate.samples=150", "calibrate.burn_in=50", "calibrate.chains=2",
                 "calibrate.keep_draws=100"]
    quick = load_config(cfg_path, quick_set)
    s = calibrate(quick, tmp / "sur.h5", obs, tmp_path / "post.h5")
    p = s.posterior["A"]              # its statistics; the draws are in the file
    q = read_posterior(tmp_path / "post.h5").units["A"]
    # The joint method's trend is the line alone: none of the shapes' fields.
    assert set(q.trend) == set(TREND_FIELDS) - set(TREND_OPTIONAL) | {"sigma_scale"}
    assert np.array_equal(q.trend["start"], p.trend["start"])
    for key in ("rhat", "ess", "acceptance"):
        assert np.array_equal(q.trend[key], p.trend[key]), key
    # Draws are thinned to keep_draws like the years'.
    assert q.trend["slope"].shape == (100, 1, 2) and q.samples.shape[1] == 100
    assert q.trend["slope"].dtype == np.float64
    assert np.array_equal(q.mean, p.mean)
    # The kept trend draws are evenly thinned from all of them, in single precision.
    rng = np.random.default_rng(3)
    many = {k: (rng.normal(size=(300,) + np.shape(v)[1:]) if k in ("intercept", "slope",
                                                                   "sigma") else v)
            for k, v in q.trend.items()}
    write_posterior(tmp_path / "thin.h5", {"A": replace(q, trend=many)},
                    quick.model.input_names, quick, [])
    back = read_posterior(tmp_path / "thin.h5").units["A"].trend["slope"]
    idx = thin_indices(300, 100)
    assert np.array_equal(back, many["slope"][idx].astype(np.float32).astype(float))
    prov = artifacts.read_provenance(tmp_path / "post.h5")
    assert "method: joint" in prov["config"]
    # The units' chains in two worker processes: the same arrays.
    calibrate(load_config(cfg_path, quick_set + ["calibrate.workers=2"]), tmp / "sur.h5",
              obs, tmp_path / "post2.h5")
    one, two = (read_posterior(tmp_path / n).units for n in ("post.h5", "post2.h5"))
    for u in "AB":
        assert np.array_equal(two[u].samples, one[u].samples)
        assert np.array_equal(two[u].trend["slope"], one[u].trend["slope"])
    # A sequential posterior has no trend.
    seq = load_config(cfg_path, ["calibrate.method=sequential", "calibrate.samples=100",
                                 "calibrate.burn_in=20", "calibrate.chains=2"])
    calibrate(seq, tmp / "sur.h5", obs, tmp_path / "seq.h5")
    assert read_posterior(tmp_path / "seq.h5").units["A"].trend == {}
    write_posterior(tmp_path / "again.h5", {"A": q}, quick.model.input_names, quick, [])
    assert np.array_equal(read_posterior(tmp_path / "again.h5").units["A"].trend["sigma"],
                          q.trend["sigma"])
    # The summary's posterior has no draws to write: refused, not written half.
    with pytest.raises(ValueError, match="no draws"):
        write_posterior(tmp_path / "slim.h5", {"A": p}, quick.model.input_names, quick, [])
    assert not (tmp_path / "slim.h5").exists()


@pytest.mark.parametrize("override, message", [
    ("calibrate.method=both", r"calibrate.method: expected one of auto, sequential, joint"),
    ("calibrate.joint_trend_moves=0", r"calibrate.joint_trend_moves: must be >= 1"),
])
def test_method_is_validated(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(CONFIGS / "pump.yaml", [override])
    cfg = load_config(CONFIGS / "pump.yaml")
    assert cfg.calibrate.method == "auto"


def test_auto_picks_the_joint_model_for_a_fleet_it_can_pool():
    """``calibrate.method: auto``: the joint model (drawn by the laplace method) from
    forecast.pool_min_units units on (pooled, it is the better calibrated one), sequential
    below or without pooling; a method named in the config is used as it is."""
    from twinmon.calibrate import resolve_method
    cfg = load_config(CONFIGS / "pump.yaml")
    assert resolve_method(cfg, 3) == ("sequential", "calibrate.method auto: sequential, 3 "
                                      "unit(s) < forecast.pool_min_units 5")
    method, why = resolve_method(cfg, 5)
    assert method == "laplace" and "5 units >= forecast.pool_min_units 5" in why
    off = load_config(CONFIGS / "pump.yaml", ["forecast.pool_sigma=false"])
    assert resolve_method(off, 500) == ("sequential", "calibrate.method auto: sequential, "
                                        "forecast.pool_sigma is false")
    named = load_config(CONFIGS / "pump.yaml", ["calibrate.method=sequential"])
    assert resolve_method(named, 500) == ("sequential", "")
    # The pooling settings decide auto's pick, so calibrate's recorded config holds them
    # (twinmon run re-runs calibrate when they change); a named method does not need them.
    three = ["forecast.pool_min_units=3"]
    assert load_config(CONFIGS / "pump.yaml", three).section_yaml("calibrate") != \
        cfg.section_yaml("calibrate")
    assert "forecast.pool_min_units: 3" in \
        load_config(CONFIGS / "pump.yaml", three).section_yaml("calibrate")
    assert load_config(CONFIGS / "pump.yaml", three + ["calibrate.method=sequential"]
                       ).section_yaml("calibrate") == named.section_yaml("calibrate")


def test_backtest_calibrates_each_cut_of_a_joint_history_again(setup, tmp_path):
    """A joint posterior's early years were estimated knowing the later ones: the back-test
    calibrates each cut's history again from the observations, and without them says its
    scores are optimistic."""
    from twinmon.backtest import backtest, calibrate_cut, read_backtest
    cfg, cfg_path, tmp, sur = setup
    years = YEARS[:5]
    obs = tmp_path / "obs.h5"
    write_observations(obs, Observations(sur.time, {
        u: UnitObservations(years, {"m_flow": _observe(sur, _trend_unit(seed=s)[:5], seed=s)},
                            {"m_flow": NOISE}) for u, s in (("A", 3), ("B", 4))}, obs))
    assert read_observations(obs, "m_flow").up_to(3, ["B"]).units["B"].years.tolist() == \
        [1, 2, 3]
    quick = load_config(cfg_path, ["calibrate.samples=150", "calibrate.burn_in=50",
                                   "calibrate.chains=2", "calibrate.max_extensions=0",
                                   "backtest.min_years=3", "forecast.samples=200",
                                   "forecast.horizon=3"])
    calibrate(quick, tmp / "sur.h5", obs, tmp_path / "post.h5")
    full = read_posterior(tmp_path / "post.h5").units["A"]
    cut = calibrate_cut(quick, tmp / "sur.h5", read_observations(obs, "m_flow"), ["A"], 3,
                        tmp_path)["A"]
    assert cut.years.tolist() == [1, 2, 3] and cut.trend["start"].tolist() == [[1, 1]]
    # The same unit's first three years alone: another posterior than the full history's.
    assert not np.allclose(cut.mean, full.mean[:3])

    s = backtest(quick, tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "bt.h5",
                 observations_path=obs)
    assert s.cut_posteriors == "recalibrated" and s.warnings == []
    assert s.units["A"].cuts.tolist() == [3, 4] and s.n_pairs == 6
    again = read_backtest(tmp_path / "bt.h5")
    assert again.cut_posteriors == "recalibrated" and again.coverage == s.coverage
    assert "calibrate:" in artifacts.read_provenance(tmp_path / "bt.h5")["config"]
    # Observations other than those the posterior was calibrated from: refused, one line.
    other = tmp_path / "other.h5"
    write_observations(other, Observations(sur.time, {"A": UnitObservations(
        years, {"m_flow": _observe(sur, _trend_unit(seed=9)[:5], seed=9)}, {"m_flow": NOISE})},
        other))
    from twinmon.errors import ArtifactError
    with pytest.raises(ArtifactError, match="not the observations .* was calibrated from"):
        backtest(quick, tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "bt_other.h5",
                 observations_path=other)
    assert not (tmp_path / "bt_other.h5").exists()
    t = backtest(quick, tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "bt_trunc.h5")
    assert t.cut_posteriors == "truncated" and "optimistic" in t.warnings[0]
    assert read_backtest(tmp_path / "bt_trunc.h5").warnings == t.warnings


def test_forecast_pools_the_year_to_year_sd_over_the_fleet(setup, tmp_path):
    """Five jointly calibrated units: forecast fits the fleet's prior of sigma from their
    draws (the calibration's scale is recorded with them), resamples each unit to it and
    records both scales and each unit's effective sample size; below
    forecast.pool_min_units, or with pool_sigma off, nothing is pooled."""
    from twinmon.forecast import fleet_sigma_prior, forecast, read_forecast
    cfg, cfg_path, tmp, sur = setup
    years = YEARS[:4]
    obs = tmp_path / "obs.h5"
    write_observations(obs, Observations(sur.time, {
        f"U{s}": UnitObservations(years, {"m_flow": _observe(sur, _trend_unit(seed=s)[:4],
                                                             seed=s)}, {"m_flow": NOISE})
        for s in range(5)}, obs))
    quick = ["calibrate.samples=150", "calibrate.burn_in=50", "calibrate.chains=2",
             "calibrate.max_extensions=0", "calibrate.keep_draws=200", "forecast.samples=200",
             "forecast.horizon=3", "forecast.observed_samples=50"]
    # calibrate.method auto: five units are a fleet to pool over, drawn by the laplace
    # method (the joint model; its sigma is pooled as the joint sampler's).
    q = load_config(cfg_path, quick + ["calibrate.method=auto"])
    cal = calibrate(q, tmp / "sur.h5", obs, tmp_path / "post.h5")
    assert cal.method == "laplace" and cal.as_dict()["method"] == "laplace"
    assert artifacts.read_provenance(tmp_path / "post.h5")["method"] == "laplace"
    # Four units next time: auto picks the sequential method, which cannot continue a
    # joint history. Refused, the posterior untouched.
    from twinmon.errors import ArtifactError
    four = tmp_path / "obs4.h5"
    whole = read_observations(obs, "m_flow")
    write_observations(four, Observations(sur.time, {f"U{s}": whole.units[f"U{s}"]
                                                     for s in range(4)}, four))
    before = (tmp_path / "post.h5").read_bytes()
    with pytest.raises(ArtifactError, match=r"post.h5: sampled with the laplace method, this run "
                       r"uses the sequential method \(calibrate.method auto, 4 units\); "
                       r"re-run calibrate without --update"):
        calibrate(q, tmp / "sur.h5", four, tmp_path / "post.h5", update=True)
    assert (tmp_path / "post.h5").read_bytes() == before
    post = read_posterior(tmp_path / "post.h5")
    span = np.diff(q.model.bounds, axis=1).ravel()
    assert np.allclose(post.units["U0"].trend["sigma_scale"], q.calibrate.prior_width * span)

    fleet = fleet_sigma_prior(q, post)
    assert fleet is not None and fleet.n_units == 5
    assert np.all(fleet.median < fleet.base)    # four years: the wide prior's sigma shrinks
    s = forecast(q, tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "fc.h5")
    pooling = s.as_dict()["sigma_pooling"]
    assert pooling["pooled"] and pooling["units"] == 5
    assert pooling["median"]["pump_coef"] == round(float(fleet.median[1]), 6)
    prov = artifacts.read_provenance(tmp_path / "fc.h5")
    assert '"pooled": true' in prov["sigma_pooling"]
    fc = read_forecast(tmp_path / "fc.h5")
    n_ess = np.array([u.pool_ess for u in fc.units.values()])
    assert np.all((n_ess > 1) & (n_ess <= 200))        # of the 200 kept draws

    # Four years a unit: too few for any shape but the line (acceleration needs five), so
    # there is no fleet prior of the shapes to fit, pool_shapes on or off.
    assert s.shape_pooling == {"pooled": False}
    off = forecast(load_config(cfg_path, quick + ["forecast.pool_sigma=false"]),
                   tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "off.h5")
    few = forecast(load_config(cfg_path, quick + ["forecast.pool_min_units=6"]),
                   tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "few.h5")
    assert off.pooling == few.pooling == {"pooled": False}
    assert off.shape_pooling == few.shape_pooling == {"pooled": False}
    a, b = read_forecast(tmp_path / "off.h5"), read_forecast(tmp_path / "few.h5")
    for u in a.units:
        # The slopes reported and tested per input are the posterior's, not an OLS fit to
        # the yearly means (which the trend smooths: its interval would be far too narrow).
        slopes = post.units[u].trend["slope"][:, 0, :]
        for i, name in enumerate(q.model.input_names):
            t = a.units[u].trends[name]
            assert np.allclose(t.slope_ci, np.quantile(slopes[:, i], [0.05, 0.95]))
            assert t.slope == pytest.approx(slopes[:, i].mean())
            assert t.test.startswith("one-sided test on the joint posterior's slope (normal)")
        assert np.isnan(a.units[u].pool_ess)
        assert np.array_equal(a.units[u].samples, b.units[u].samples)
        assert not np.array_equal(a.units[u].samples, fc.units[u].samples)

    # A damaged sigma (NaN) or calibrations under different priors: one line, nothing written.
    import shutil

    import h5py

    from twinmon.errors import CalibrationError
    shutil.copy(tmp_path / "post.h5", tmp_path / "nan.h5")
    with h5py.File(tmp_path / "nan.h5", "r+") as f:
        f["units/U2/trend/sigma"][3, 0] = np.nan
    with pytest.raises(ArtifactError, match=r"nan.h5: /units/U2/trend/sigma must hold finite "
                       r"values >= 0, got nan at draw 3, input 0"):
        forecast(q, tmp_path / "nan.h5", tmp / "sur.h5", tmp_path / "fc_nan.h5")
    shutil.copy(tmp_path / "post.h5", tmp_path / "mixed.h5")
    with h5py.File(tmp_path / "mixed.h5", "r+") as f:
        f["units/U4/trend/sigma_scale"][0] *= 2
    with pytest.raises(CalibrationError, match="different priors of their year-to-year sd"):
        forecast(q, tmp_path / "mixed.h5", tmp / "sur.h5", tmp_path / "fc_mixed.h5")
    assert not (tmp_path / "fc_nan.h5").exists() and not (tmp_path / "fc_mixed.h5").exists()
