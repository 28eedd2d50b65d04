"""calibrate, laplace method: the joint model on each year's Laplace approximation, drawn
exactly. Its Gaussian posterior against a dense quadrature and on data drawn from the model;
through a real surrogate: the known trend, the artifact, determinism, workers, agreement
with the joint method's sampler, and a forecast on it."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
from scipy import stats

from twinmon import artifacts
from twinmon.calibrate import calibrate, read_posterior
from twinmon.calibrate.methods.joint import calibrate_unit_joint
from twinmon.calibrate.gaussian_trend import GaussianTrend
from twinmon.calibrate.trend import TREND_FIELDS
from twinmon.config import load_config
from twinmon.observations import Observations, UnitObservations, write_observations
from twinmon.reduce import read_surrogate, reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml
# The joint method's test unit, so that the two methods are held to the same one.
from .test_calibrate_joint import NOISE, SLOPES, YEARS, _observe, _trend_unit

WIDE = np.array([[-1e9, 1e9]])


def _line_model(years, c, A, slope_sd, d=1):
    """A one-segment GaussianTrend per input over ``years`` with covariances ``c``
    [K, d, d] and slope priors N(0, slope_sd^2) (levels flat); the design is centred as
    the methods centre it."""
    K = len(years)
    t = years - years.mean()
    Mk = np.zeros((K, d, 2 * d))
    for i in range(d):
        Mk[:, i, 2 * i], Mk[:, i, 2 * i + 1] = 1.0, t
    prec = np.ravel([[0.0, sd ** -2.0] for sd in np.broadcast_to(slope_sd, d)])
    return lambda x: GaussianTrend(np.asarray(x, float), c, Mk, prec, np.zeros(2 * d),
                                   np.asarray(A, float))


def test_pareto_smoothing_finds_the_tail_and_keeps_one_draw_from_deciding():
    """PSIS on log-weights of known tails: the fitted shape is the tail's (a lognormal's
    grows with its sigma, a Cauchy's is near 1), the order is kept, no smoothed weight
    exceeds the largest raw one, and a single huge draw no longer takes the mass."""
    from twinmon.calibrate.gaussian_trend import pareto_smooth
    rng = np.random.default_rng(0)
    z = rng.standard_normal(8000)
    _, k1 = pareto_smooth(1.0 * z)
    _, k2 = pareto_smooth(2.0 * z)
    _, kc = pareto_smooth(np.log(np.abs(rng.standard_cauchy(8000))))
    assert 0.05 < k1 < 0.3 < k2 < 0.7 < kc < 1.1
    lw = 2.0 * z
    lw[-5] = lw.max() + 8.0                     # one draw 3000 times the next
    sm, _ = pareto_smooth(lw)
    assert sm.max() <= lw.max() and int(np.argmax(sm)) == 7995

    def ess(v):
        w = np.exp(v - v.max())
        return w.sum() ** 2 / (w ** 2).sum()
    assert ess(lw) < 2 < 100 < ess(sm)
    # -inf (outside the box) stays out.
    lw[:10] = -np.inf
    assert np.all(np.isneginf(pareto_smooth(lw)[0][:10]))
    # A tail hundreds of nats below the top, ties at the cutoff, all equal: the raw
    # weights, no division by zero.
    for bad in (np.r_[0.0, -800 - rng.random(299) * 100], np.r_[[0.0] * 3, -720 - rng.random(297)],
                np.r_[np.full(270, -5.0), rng.random(30)], np.zeros(300)):
        sm, k = pareto_smooth(bad)
        assert sm.shape == bad.shape and not np.isnan(sm).any()


def test_a_site_off_its_likelihood_is_widened_until_the_weights_reach_the_mass():
    """One year's site sits 7 of its sds off a Gaussian likelihood (and narrower): the
    plain weights collapse onto a few draws and put that year 5 posterior sds off; the
    widened site gives enough effective draws, and the exact posterior's mean and spread
    (the model with the true likelihoods as its sites, drawn densely). The sites are
    left as they were."""
    years = np.arange(1.0, 9.0)
    K, s = len(years), 0.1
    y = 1.0 + 0.05 * years + s * np.random.default_rng(5).standard_normal(K)
    c = np.full((K, 1, 1), s ** 2)

    def loglik(theta):
        return -0.5 * ((theta[..., 0] - y) / s) ** 2

    ref = _line_model(years, c, [0.05], 1.0)(y[:, None]).draw(
        200000, np.random.default_rng(1), WIDE)[2][:, 2, 0]
    c_off, x_off = c.copy(), y[:, None].copy()
    c_off[2], x_off[2] = 0.03 ** 2, x_off[2] + 0.35
    m = _line_model(years, c_off, [0.05], 1.0)(x_off)
    for seed in range(3):
        rng = np.random.default_rng(seed)
        first = m.importance(loglik, 4000, rng, WIDE)
        assert first[3] < 100 and np.argmin(m.year_ess) == 2
        assert abs(first[2][:, 2, 0].mean() - ref.mean()) > 3 * ref.std()
        got = m.importance_widened(loglik, 4000, rng, WIDE, first, 400)
        assert got[3] >= 400
        assert abs(got[2][:, 2, 0].mean() - ref.mean()) < 0.25 * ref.std()
        assert 0.8 < got[2][:, 2, 0].std() / ref.std() < 1.2
        assert np.array_equal(m.cov, c_off) and np.array_equal(m.x, x_off)


def test_closed_form_inverse_and_factor_are_numpys():
    # The years' conditional covariances of 2 inputs are inverted and factored in closed
    # form; 1 and 3 inputs go through LAPACK.
    from twinmon.calibrate.stacked import inv_chol
    rng = np.random.default_rng(2)
    for d in (1, 2, 3):
        A = rng.standard_normal((50, 4, d, d))
        A = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(d)
        G, L = inv_chol(A)
        np.testing.assert_allclose(G, np.linalg.inv(A), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(L, np.linalg.cholesky(np.linalg.inv(A)), rtol=1e-9,
                                   atol=1e-12)


def test_evidence_alone_from_the_factor_is_the_solves():
    # The log marginal likelihood without beta's mean (forward substitution on Pb's
    # factor) is the one computed with it.
    from twinmon.calibrate.gaussian_trend import linear_gaussian, year_weights
    rng = np.random.default_rng(3)
    K, d, nb, G = 6, 2, 5, 3
    cov = rng.standard_normal((K, d, d))
    cov = cov @ np.swapaxes(cov, 1, 2) + 0.1 * np.eye(d)
    Wf, logdet_v = year_weights(cov, np.abs(rng.standard_normal((40, d))))
    args = (Wf, logdet_v, rng.standard_normal((G, K, d, nb)), rng.standard_normal((K, d)),
            np.tile(np.eye(nb), (G, 1, 1)), rng.standard_normal((G, nb)), np.zeros(G))
    full, alone = linear_gaussian(*args), linear_gaussian(*args, want_mean=False)
    assert alone[2] is None
    np.testing.assert_allclose(alone[3], full[3], rtol=1e-12)
    # Many systems go through the substitution, few through LAPACK's solve: the same mean.
    for P in (8, 400):
        Wf, logdet_v = year_weights(cov, np.abs(rng.standard_normal((P, d))))
        Pb, _, mean, _ = linear_gaussian(Wf, logdet_v, *args[2:])
        Mk, x, prior_P, prior_mean = args[2], args[3], args[4], args[5]
        W = Wf.reshape(P, K, d, d)
        b = np.einsum("gkia,pkij,kj->gpa", Mk, W, x) + \
            np.einsum("gab,gb->ga", prior_P, prior_mean)[:, None]
        np.testing.assert_allclose(np.einsum("gpab,gpb->gpa", Pb, mean), b, rtol=1e-9,
                                   atol=1e-9 * np.abs(b).max())


def test_year_weights_closed_form_is_the_general_inverse():
    from twinmon.calibrate.gaussian_trend import year_weights
    from twinmon.calibrate.stacked import inv_logdet
    rng = np.random.default_rng(5)
    cov = rng.standard_normal((7, 2, 2))
    cov = cov @ np.swapaxes(cov, 1, 2) + 0.1 * np.eye(2)
    sigma = np.abs(rng.standard_normal((30, 2)))
    W, logdet = year_weights(cov, sigma)
    W0, l0 = inv_logdet(cov[None] + (sigma ** 2)[:, None, :, None] * np.eye(2))
    assert np.array_equal(W, W0.reshape(30, -1)) and np.array_equal(logdet, l0.sum(axis=1))


@pytest.mark.slow
def test_posterior_matches_a_dense_quadrature_over_sigma():
    """One input, eight years with unequal errors: the draws' slope and sigma moments equal
    those of a brute-force posterior (the years' joint Gaussian written out whole, a nearly
    flat level prior, sigma on a fine grid under its half-Cauchy prior)."""
    rng = np.random.default_rng(4)
    years = np.arange(1.0, 9.0)
    err = rng.uniform(0.05, 0.2, len(years))
    x = 1.0 + 0.3 * (years - years.mean()) + rng.normal(0, 0.15, len(years)) + \
        err * rng.standard_normal(len(years))
    A = 0.2
    model = _line_model(years, (err ** 2)[:, None, None], [A], 10.0)(x[:, None])
    beta, sigma, _, n_eff = model.draw(40000, np.random.default_rng(1), WIDE)
    assert n_eff >= 100

    # Brute force: x ~ N(X mu0, V + X P0^-1 X') for each sigma on a fine grid.
    X = np.column_stack([np.ones_like(years), years - years.mean()])
    P0inv = np.diag([1e6, 10.0 ** 2])
    grid = np.linspace(1e-5, 3.0, 30001)
    lw, m_slope, v_slope = [], [], []
    for s in grid:
        V = np.diag(err ** 2 + s * s)
        lw.append(stats.multivariate_normal(np.zeros(8), V + X @ P0inv @ X.T).logpdf(x)
                  + np.log(2 / (np.pi * A * (1 + (s / A) ** 2))))
        Vi = np.linalg.inv(V)
        C = np.linalg.inv(X.T @ Vi @ X + np.linalg.inv(P0inv))
        mb = C @ (X.T @ Vi @ x)
        m_slope.append(mb[1])
        v_slope.append(C[1, 1])
    w = np.exp(np.array(lw) - max(lw))
    w /= w.sum()
    m_slope, v_slope = np.array(m_slope), np.array(v_slope)
    mean = float(w @ m_slope)
    sd = float(np.sqrt(w @ (v_slope + m_slope ** 2) - mean ** 2))
    s_mean = float(w @ grid)
    assert abs(beta[:, 1].mean() - mean) < 0.02 * sd + 4 * sd / np.sqrt(40000), (
        beta[:, 1].mean(), mean)
    assert abs(beta[:, 1].std() - sd) < 0.03 * sd
    assert abs(sigma[:, 0].mean() - s_mean) < 0.05 * s_mean, (sigma[:, 0].mean(), s_mean)


def test_intervals_cover_on_data_drawn_from_the_model():
    """Two inputs with correlated yearly errors, 300 units whose trends and sigma are drawn
    from the priors: the 90 % intervals of the last level and of the slopes cover the truth
    about 90 % of the time (a Bayesian posterior is calibrated on its own prior)."""
    rng = np.random.default_rng(7)
    years = np.arange(1.0, 11.0)
    K, d = len(years), 2
    A = np.array([0.3, 0.05])
    hits, n = np.zeros(3), 300
    for _ in range(n):
        sigma = A * np.abs(np.tan(0.5 * np.pi * rng.uniform(0, 0.8, d)))
        slope = rng.normal(0.0, [0.5, 0.05])
        level = rng.normal(0.0, [1.0, 0.1])
        t = years - years.mean()
        theta = level + np.outer(t, slope) + sigma * rng.standard_normal((K, d))
        sd = np.array([0.2, 0.03]) * rng.uniform(0.5, 1.5, (K, 1))
        r = rng.uniform(-0.8, 0.8, K)
        c = np.einsum("ki,kj->kij", sd, sd) * np.where(np.eye(d, dtype=bool), 1.0,
                                                       r[:, None, None])
        x = theta + np.einsum("kij,kj->ki", np.linalg.cholesky(c), rng.standard_normal((K, d)))
        model = _line_model(years, c, A, [0.5, 0.05], d=2)(x)
        beta, _, th, _ = model.draw(2000, rng, np.array([[-1e9, 1e9]] * 2))
        truths = [slope[0], slope[1], theta[-1, 0]]
        for j, (v, truth) in enumerate(zip([beta[:, 1], beta[:, 3], th[:, -1, 0]], truths)):
            lo, hi = np.quantile(v, [0.05, 0.95])
            hits[j] += lo <= truth <= hi
    cover = hits / n
    # 90 % +- 3 binomial sd (0.052 for 300 units).
    assert np.all(np.abs(cover - 0.90) < 0.052), cover


@pytest.fixture(scope="module")
def setup(tmp_path_factory, fmu_path):
    """A real surrogate (FMU runs + reduce) and a config for the laplace method."""
    tmp = tmp_path_factory.mktemp("laplace")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 64, "test_size": 8},
        "calibrate": {"method": "laplace", "chains": 3, "samples": 400, "burn_in": 150,
                      "workers": 1, "ess_warn": 100, "max_extensions": 1}})
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    return cfg, cfg_path, tmp, read_surrogate(tmp / "sur.h5")


def _fleet(path, sur, seeds):
    write_observations(path, Observations(sur.time, {
        f"U{s}": UnitObservations(YEARS, {"m_flow": _observe(sur, _trend_unit(seed=s),
                                                              seed=s + 50)}, {"m_flow": NOISE})
        for s in seeds}, path))


def test_the_stage_recovers_the_trend_and_agrees_with_the_joint_sampler(setup, tmp_path):
    """Through the real surrogate: the known slopes inside the posterior, the years and
    trend shaped as the joint method's (the artifact round trip), the same arrays with the
    same seed and with two worker processes; and on the same unit the joint method's Gibbs
    sampler gives the same slopes and years within their posterior sd."""
    cfg, cfg_path, tmp, sur = setup
    obs = tmp_path / "obs.h5"
    _fleet(obs, sur, [2, 3])
    s = calibrate(cfg, tmp / "sur.h5", obs, tmp_path / "post.h5")
    assert s.method == "laplace"
    # The summary keeps the statistics; the draws went to the file as the unit finished.
    assert s.posterior["U2"].samples.size == 0 and "slope" not in s.posterior["U2"].trend
    p = read_posterior(tmp_path / "post.h5").units["U2"]
    assert np.array_equal(p.mean, s.posterior["U2"].mean)
    K = len(YEARS)
    n_s = p.samples.shape[1]
    with h5py.File(tmp_path / "post.h5") as f:
        total = int(f["units/U2/samples"].attrs["draws_total"])
    assert p.samples.shape == (K, cfg.calibrate.keep_draws, 2)
    assert total >= 2 * cfg.calibrate.keep_draws
    assert list(p.status) == ["ok"] * K and np.all(p.fit["converged"])
    # The weighted draws' effective number, not their count, is the ESS.
    assert np.all(p.ess >= cfg.calibrate.ess_warn) and np.all(p.ess < total)
    assert np.all(np.isnan(p.acceptance))
    t = p.trend
    assert set(t) == set(TREND_FIELDS) and t["start"].tolist() == [[1, 1]]
    assert t["slope"].shape == (n_s, 1, 2) and np.all(t["sigma"] >= 0)
    assert np.all(t["rhat"] < 1.01) and np.all(p.rhat < 1.01)
    slope = t["slope"][:, 0, :]
    lo, hi = np.quantile(slope, [0.01, 0.99], axis=0)
    assert np.all((lo < SLOPES) & (SLOPES < hi)), (lo, hi)
    assert lo[0] > 0
    # The years stay inside the box.
    b = cfg.model.bounds
    assert np.all((p.samples >= b[:, 0]) & (p.samples <= b[:, 1]))
    assert "method: laplace" in artifacts.read_provenance(tmp_path / "post.h5")["config"]

    calibrate(cfg, tmp / "sur.h5", obs, tmp_path / "again.h5")
    calibrate(load_config(cfg_path, ["calibrate.workers=2"]), tmp / "sur.h5", obs,
              tmp_path / "two.h5")
    first = read_posterior(tmp_path / "post.h5").units
    for name in ("again.h5", "two.h5"):
        other = read_posterior(tmp_path / name).units
        for u in ("U2", "U3"):
            assert np.array_equal(other[u].samples, first[u].samples)
            assert np.array_equal(other[u].trend["slope"], first[u].trend["slope"])

    joint_cfg = load_config(cfg_path, ["calibrate.method=joint"])
    flows = _observe(sur, _trend_unit(seed=2), seed=52)
    j = calibrate_unit_joint(sur, joint_cfg, YEARS, flows, NOISE, rng_seed=11)
    js = j.trend["slope"][:, 0, :]
    assert np.all(np.abs(np.median(slope, 0) - np.median(js, 0)) < 0.5 * js.std(0)), (
        np.median(slope, 0), np.median(js, 0), js.std(0))
    assert np.all(np.abs(slope.std(0) / js.std(0) - 1) < 0.3), (slope.std(0), js.std(0))
    assert np.all(np.abs(p.mean - j.mean) < 0.5 * np.sqrt(j.var)), (p.mean, j.mean)


def test_forecast_runs_on_a_laplace_fleet_and_pools_its_sigma(setup, tmp_path):
    """Five units: forecast pools sigma over them as for the joint method, gives each unit a
    verdict and the shapes' probabilities of its trend, which forecast.h5 keeps."""
    from twinmon.forecast import forecast
    cfg, cfg_path, tmp, sur = setup
    obs = tmp_path / "obs.h5"
    _fleet(obs, sur, range(5))
    quick = load_config(cfg_path, ["calibrate.keep_draws=200", "forecast.samples=200",
                                   "forecast.horizon=3", "forecast.observed_samples=50"])
    calibrate(quick, tmp / "sur.h5", obs, tmp_path / "post.h5")
    s = forecast(quick, tmp_path / "post.h5", tmp / "sur.h5", tmp_path / "fc.h5")
    d = s.as_dict()
    assert d["sigma_pooling"]["pooled"] and d["sigma_pooling"]["units"] == 5
    assert set(d["units"]) == {f"U{i}" for i in range(5)}
    # The trend's shapes reach the verdict, and the artifact keeps them.
    from twinmon.forecast import read_forecast
    back = read_forecast(tmp_path / "fc.h5")
    for u, ud in d["units"].items():
        shape = ud["trend_shape"]
        assert abs(shape["line"] + shape["accelerating"] + shape["change"] - 1) < 1e-6
        assert back.units[u].shape == shape


def test_a_trend_beyond_the_box_gets_no_weight_and_stays_in_the_box():
    """Every draw of the Gaussian model outside the design box (a unit whose inputs lie
    beyond it): no error, the draws held in the box, an effective number of 0 (which the
    method reports as unconverged years)."""
    years = np.arange(1.0, 7.0)
    model = _line_model(years, np.full((6, 1, 1), 0.01), [0.1], 1.0)(
        (5.0 + 0.2 * years)[:, None])
    box = np.array([[0.0, 1.0]])
    beta, sigma, theta, n_eff = model.importance(lambda t: np.zeros(t.shape[:2]), 400,
                                                 np.random.default_rng(0), box)
    assert n_eff == 0.0 and theta.shape == (400, 6, 1)
    assert np.all((theta >= 0.0) & (theta <= 1.0))


def _assert_same_unit(a, b, where=""):
    """Every field of two unit posteriors equal, bit for bit (NaN equal to NaN)."""
    import dataclasses
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        pairs = [(np.asarray(x[k]), np.asarray(y[k])) for k in x] if isinstance(x, dict) \
            else [(x, y)]
        if isinstance(x, dict):
            assert x.keys() == y.keys(), (where, f.name)
        for p, q in pairs:
            if isinstance(p, np.ndarray):
                assert np.array_equal(p, q, equal_nan=p.dtype.kind == "f"), (where, f.name)
            else:
                assert p == q, (where, f.name)


def test_update_summarises_only_the_new_years_and_equals_a_full_run(setup, tmp_path):
    """Years 1..4 of two units, then ``--update`` with years 1..6 and a third unit (two
    workers): only the new unit-years are summarised, the stored years' sites are kept, and
    every array equals a full run on years 1..6, bit for bit; an update with nothing new
    keeps everything; a posterior without sites (written before they were recorded) is
    summarised again whole, to the same arrays."""
    import dataclasses

    from twinmon.calibrate import write_posterior
    from twinmon.observations import read_observations
    cfg, cfg_path, tmp, sur = setup
    full_obs, short_obs = tmp_path / "o6.h5", tmp_path / "o4.h5"
    _fleet(full_obs, sur, [2, 3, 4])
    whole = read_observations(full_obs)
    write_observations(short_obs, dataclasses.replace(whole, units={
        u: dataclasses.replace(o, years=o.years[:4],
                               channels={c: v[:4] for c, v in o.channels.items()})
        for u, o in whole.units.items() if u != "U4"}))
    s = calibrate(cfg, tmp / "sur.h5", full_obs, tmp_path / "full.h5")
    assert s.method == "laplace" and s.posterior["U2"].site["x"].shape == (len(YEARS), 2)
    calibrate(cfg, tmp / "sur.h5", short_obs, tmp_path / "upd.h5")
    two = load_config(cfg_path, ["calibrate.workers=2"])
    u = calibrate(two, tmp / "sur.h5", full_obs, tmp_path / "upd.h5", update=True).update
    assert (u["kept_years"], u["new_years"]) == (8, 2 * 2 + len(YEARS))
    assert u["new_units"] == ["U4"] and not u["redone_units"]
    full, upd = read_posterior(tmp_path / "full.h5"), read_posterior(tmp_path / "upd.h5")
    assert list(upd.units) == list(full.units)
    for unit in full.units:
        _assert_same_unit(full.units[unit], upd.units[unit], unit)

    # Nothing new: every unit kept as it is; the command says what it kept.
    from click.testing import CliRunner

    from twinmon.cli import main
    r = CliRunner().invoke(main, ["calibrate", "-c", str(cfg_path), "--surrogate",
                                  str(tmp / "sur.h5"), "--observations", str(full_obs),
                                  "-o", str(tmp_path / "upd.h5"), "--update"])
    assert r.exit_code == 0, r.output
    assert f"sites of {3 * len(YEARS)} unit-year(s) kept from" in r.output
    assert "0 summarised, each unit with a new year drawn again" in r.output
    for unit in full.units:
        _assert_same_unit(full.units[unit], read_posterior(tmp_path / "upd.h5").units[unit],
                          unit)

    # Sites missing (an older posterior): the units with new years are summarised whole.
    calibrate(cfg, tmp / "sur.h5", short_obs, tmp_path / "old.h5")
    stored = read_posterior(tmp_path / "old.h5")
    units = {}
    for unit, p in stored.units.each():
        p.site = {}
        units[unit] = p
    write_posterior(tmp_path / "old.h5", units, stored.input_names, cfg,
                    [tmp / "sur.h5", short_obs], surrogate_id=sur.fingerprint(),
                    method="laplace")
    assert not read_posterior(tmp_path / "old.h5").units["U2"].site
    u = calibrate(cfg, tmp / "sur.h5", full_obs, tmp_path / "old.h5", update=True).update
    assert (u["kept_years"], u["new_years"]) == (0, 3 * len(YEARS))
    for unit in full.units:
        _assert_same_unit(full.units[unit], read_posterior(tmp_path / "old.h5").units[unit],
                          unit)


def test_units_are_written_as_they_finish_and_a_failure_keeps_the_old_file(setup, tmp_path,
                                                                            monkeypatch):
    """One unit a task: each unit reaches the file before the next task is sampled, and
    leaves the main process's memory (the summary keeps no draws); a failure in a later
    task leaves the posterior already at the output as it was, with no temporary file."""
    from twinmon.calibrate import posterior_writer as posterior_module
    from twinmon.calibrate.methods import laplace
    cfg, _, tmp, sur = setup
    obs = tmp_path / "obs.h5"
    _fleet(obs, sur, [2, 3, 4])
    out = tmp_path / "post.h5"
    calibrate(cfg, tmp / "sur.h5", obs, out)
    before = out.read_bytes()

    events = []
    group, add = laplace._group, posterior_module.PosteriorWriter.add

    def recording_group(surrogate, predict, runs):
        events.append(("sample", runs[0].seed))
        return group(surrogate, predict, runs)

    def recording_add(self, unit, p):
        events.append(("write", unit))
        assert p.samples.shape[1] > 0       # the draws reach the file
        return add(self, unit, p)

    monkeypatch.setattr(laplace, "UNITS_PER_TASK", 1)
    monkeypatch.setattr(laplace, "_group", recording_group)
    monkeypatch.setattr(posterior_module.PosteriorWriter, "add", recording_add)
    s = calibrate(cfg, tmp / "sur.h5", obs, tmp_path / "again.h5")
    assert [e[0] for e in events] == ["sample", "write"] * 3
    assert [e[1] for e in events if e[0] == "write"] == ["U2", "U3", "U4"]
    assert all(p.samples.size == 0 for p in s.posterior.values())
    # One unit a task gives the same file as the groups of the first run.
    a, b = read_posterior(out).units, read_posterior(tmp_path / "again.h5").units
    for unit in ("U2", "U3", "U4"):
        _assert_same_unit(a[unit], b[unit], unit)

    def failing_group(surrogate, predict, runs):
        if len(events) > 2:
            raise RuntimeError("a task failed")
        return recording_group(surrogate, predict, runs)

    events.clear()
    monkeypatch.setattr(laplace, "_group", failing_group)
    with pytest.raises(RuntimeError, match="a task failed"):
        calibrate(cfg, tmp / "sur.h5", obs, out)
    assert ("write", "U2") in events            # a unit was written before the failure
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.h5", "obs.h5", "post.h5"]


def test_update_redraws_a_unit_whose_events_changed_without_a_new_year(setup, tmp_path):
    """An event added to a unit with no new year moves its trend's segments: the update
    draws it again (as a full run would), not keeps the stored trend under the new event."""
    import shutil

    from twinmon.observations import Event, add_events
    cfg, _, tmp, sur = setup
    obs = tmp_path / "o.h5"
    _fleet(obs, sur, [2, 3])
    calibrate(cfg, tmp / "sur.h5", obs, tmp_path / "upd.h5")
    ev = tmp_path / "ev.h5"
    shutil.copy(obs, ev)
    add_events(ev, {"U3": [Event(int(YEARS[4]), "pump")]})
    u = calibrate(cfg, tmp / "sur.h5", ev, tmp_path / "upd.h5", update=True).update
    assert u["redone_units"] == ["U3"] and u["kept_years"] == len(YEARS)
    calibrate(cfg, tmp / "sur.h5", ev, tmp_path / "full.h5")
    full, upd = read_posterior(tmp_path / "full.h5"), read_posterior(tmp_path / "upd.h5")
    for unit in full.units:
        _assert_same_unit(full.units[unit], upd.units[unit], unit)
    assert upd.units["U3"].trend["start"].shape[0] == 2        # the event starts a segment
