"""calibrate: MCMC against quadrature, convergence diagnostics, noise source, artifact, CLI."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from twinmon.calibrate import (Prior, _noise_for, calibrate, calibrate_unit, ess,
                               estimate_noise, estimate_noise_checked, find_map,
                               make_log_density, read_posterior, sample_posterior, split_rhat,
                               write_posterior, year_prior)
from twinmon.calibrate.posterior import thin_indices
from twinmon.config import load_config
from twinmon.errors import ArtifactError, InputDataError
from twinmon.observations import Observations, UnitObservations, write_observations
from twinmon.reduce import read_surrogate, reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml

NOISE = 4.0  # kg/s, 1 % of the nominal flow as in the shipped fleet


@pytest.fixture(scope="module")
def setup(tmp_path_factory, fmu_path):
    """A real surrogate (FMU runs + reduce) and a config for fast sampling."""
    tmp = tmp_path_factory.mktemp("calibrate")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 64, "test_size": 8},
        # The OpenTURNS sampler, the reference (test_calibrate_vectorised.py: the other one).
        "calibrate": {"chains": 4, "samples": 1000, "burn_in": 200, "workers": 1,
                      "sampler": "openturns"}})
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    return cfg, cfg_path, tmp, read_surrogate(tmp / "sur.h5")


def _observe(surrogate, X, seed=0, noise=NOISE):
    """Synthetic flows [n, n_t]: surrogate transients plus Gaussian noise."""
    rng = np.random.default_rng(seed)
    clean = surrogate.predict(np.atleast_2d(X))
    return clean + noise * rng.standard_normal(clean.shape)


def _quadrature(ld, centre, cov, half_width=7.0, n=241):
    """Posterior mean and sd by the trapezoid-free midpoint rule on a fine 2-D grid covering
    +-7 Laplace standard deviations (clipped to the box)."""
    sd = np.sqrt(np.diag(cov))
    b = ld.prior.bounds
    axes = [np.linspace(max(b[j, 0], centre[j] - half_width * sd[j]),
                        min(b[j, 1], centre[j] + half_width * sd[j]), n) for j in range(2)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    lp = ld.batch(grid)
    w = np.exp(lp - lp.max())
    w2 = w.reshape(n, n)
    # The grid must hold the whole posterior: its rim carries no mass.
    rim = np.concatenate([w2[0], w2[-1], w2[:, 0], w2[:, -1]]).max()
    assert rim < 1e-6 or np.any(np.isclose([a[0] for a in axes] + [a[-1] for a in axes],
                                           list(b[:, 0]) + list(b[:, 1])))
    w /= w.sum()
    mean = w @ grid
    return mean, np.sqrt(w @ (grid - mean) ** 2)


@pytest.mark.parametrize("case", ["year1_uniform", "year2_gaussian"])
def test_mcmc_mean_matches_grid_quadrature(setup, case):
    cfg, _, _, sur = setup
    truth = np.array([12.0, 3.5])
    y = _observe(sur, truth, seed=3)[0]
    if case == "year1_uniform":
        prior = Prior.uniform(cfg.model.bounds)
    else:
        # A previous estimate off the truth: the prior pulls, and the test checks the
        # sampler gets the compromise right, not just the likelihood's peak.
        prior = year_prior(cfg, np.array([13.0, 3.45]))
    noise_var = NOISE ** 2 + sur.predict_var(prior.location[None])[0]
    ld = make_log_density(sur, y, noise_var, prior)
    draws, acc, x_map = sample_posterior(ld, chains=4, samples=2000, burn_in=300, seed=11)
    _, cov = find_map(ld)
    q_mean, q_sd = _quadrature(ld, x_map, cov)
    for j in range(2):
        chains = draws[:, :, j]
        mcse = q_sd[j] / np.sqrt(ess(chains))
        assert abs(chains.mean() - q_mean[j]) < 4 * mcse, (j, chains.mean(), q_mean[j], mcse)
        assert abs(chains.std() / q_sd[j] - 1) < 0.15
        assert split_rhat(chains) < 1.05
    assert np.all((acc > 0.1) & (acc < 0.7))


def test_mcmc_burn_in_is_discarded(setup):
    """Chains started far away must not carry their start into the kept draws: OpenTURNS
    returns the burn-in with the chain and sample_posterior cuts it."""
    cfg, _, _, sur = setup
    y = _observe(sur, [10.0, 3.6], seed=5)[0]
    ld = make_log_density(sur, y, NOISE ** 2, Prior.uniform(cfg.model.bounds))
    draws, _, x_map = sample_posterior(ld, chains=2, samples=300, burn_in=200, seed=1)
    assert draws.shape == (2, 300, 2)
    _, cov = find_map(ld)
    z = np.abs(draws[:, 0, :] - x_map) / np.sqrt(np.diag(cov))
    assert np.all(z < 5)


def test_rhat_and_ess_on_known_sequences():
    rng = np.random.default_rng(0)
    iid = rng.standard_normal((4, 2000))
    assert split_rhat(iid) < 1.01 and split_rhat(iid, rank_normalize=False) < 1.01
    assert 0.85 * 8000 < ess(iid) < 1.15 * 8000
    assert 0.85 * 8000 < ess(iid, rank_normalize=True) < 1.15 * 8000
    # AR(1) with phi: integrated autocorrelation time (1 + phi) / (1 - phi) = 19.
    phi = 0.9
    ar = np.empty((4, 20000))
    ar[:, 0] = rng.standard_normal(4) / np.sqrt(1 - phi ** 2)
    eps = rng.standard_normal(ar.shape)
    for t in range(1, ar.shape[1]):
        ar[:, t] = phi * ar[:, t - 1] + eps[:, t]
    expected = ar.size / ((1 + phi) / (1 - phi))
    assert 0.75 * expected < ess(ar) < 1.25 * expected
    assert split_rhat(ar) < 1.02
    # Chains that disagree (one shifted by a standard deviation) or drift within themselves.
    shifted = iid.copy()
    shifted[0] += 1.0
    assert split_rhat(shifted) > 1.05 and split_rhat(shifted, rank_normalize=False) > 1.05
    drift = iid + np.linspace(0, 3, 2000)
    assert split_rhat(drift) > 1.05
    # Same location, different spread: only the tail (folded) R-hat sees it.
    wide = iid.copy()
    wide[0] *= 3
    assert split_rhat(wide) > 1.05
    assert split_rhat(wide, rank_normalize=False) < 1.02


def test_average_ranks_are_scipys_with_ties():
    """The rank-normalisation's ranks: scipy's average ranks bit for bit, on draws that
    repeat (a rejected step, a resampled draw) and on draws that do not."""
    from scipy.stats import rankdata
    from twinmon.calibrate.diagnostics import _average_ranks
    rng = np.random.default_rng(1)
    for x in (rng.choice(rng.standard_normal(40), size=(4, 75)), rng.standard_normal((3, 50)),
              np.repeat([[2.0, 1.0, 2.0]], 2, axis=0)):
        assert np.array_equal(_average_ranks(x), rankdata(x, method="average").reshape(x.shape))


def _split_rhat_one(chains):
    """Vehtari et al.'s rank-normalised split R-hat of one quantity, term by term from the
    single-series pieces (scipy's average ranks, test_average_ranks_are_scipys_with_ties)."""
    from twinmon.calibrate.diagnostics import _rhat, _split, _z_scale
    if np.ptp(chains) == 0:
        return float("nan")
    bulk = _rhat(_z_scale(_split(chains)))
    folded = np.abs(chains - np.median(chains))
    tail = _rhat(_z_scale(_split(folded))) if np.ptp(folded) > 0 else bulk
    return max(bulk, tail)


def test_split_rhat_many_gives_split_rhats_values_bit_for_bit():
    # Resampled draws tie, a quantity may be constant, its folded values may be constant.
    from twinmon.calibrate.diagnostics import split_rhat_many
    rng = np.random.default_rng(4)
    for trial in range(60):
        m, n, B = int(rng.integers(1, 6)), int(rng.integers(4, 60)), int(rng.integers(1, 7))
        x = rng.standard_normal((B, m, n))
        if trial % 4 == 1:
            x = np.round(x, 1)
        elif trial % 4 == 2:
            x[0] = 3.0
        elif trial % 4 == 3:
            x = np.abs(np.round(x, 0))
        want = np.array([_split_rhat_one(c) for c in x])
        assert np.array_equal(split_rhat_many(x), want, equal_nan=True)
        assert np.array_equal([split_rhat(c) for c in x], want, equal_nan=True)
    x = rng.standard_normal((3, 2, 4, 50))
    assert split_rhat_many(x).shape == (3, 2)


def test_noise_source_file_then_config_then_estimated(setup):
    cfg, cfg_path, _, _ = setup
    with_file = UnitObservations(np.array([1]), {"m_flow": np.zeros((1, 25))}, {"m_flow": 3.0})
    without = UnitObservations(np.array([1]), {"m_flow": np.zeros((1, 25))})
    assert _noise_for(cfg, with_file) == (3.0, "file")
    assert _noise_for(cfg, without) == (None, "estimated")
    cfg2 = load_config(cfg_path, ["calibrate.noise_std=5.5"])
    assert _noise_for(cfg2, without) == (5.5, "config")
    assert _noise_for(cfg2, with_file) == (3.0, "file")


def test_estimated_noise_recovers_the_true_level(setup):
    cfg, _, _, sur = setup
    rng = np.random.default_rng(4)
    X = np.column_stack([rng.uniform(8, 20, 10), rng.uniform(3.0, 3.8, 10)])
    flows = _observe(sur, X, seed=9)
    flows[2, 5] = np.nan  # a missing sample is left out, not counted
    s = estimate_noise(sur, cfg, flows)
    # 250 samples, 20 fitted parameters: the std estimate has ~5 % relative sd.
    assert abs(s / NOISE - 1) < 0.15
    clean = estimate_noise_checked(sur, cfg, flows)
    assert not clean.structured and clean.source == "estimated"


def test_a_smooth_misfit_is_not_taken_for_noise(setup):
    # Half the years carry a smooth shift of the plateau the twin cannot follow (a fouled
    # pipe): the pooled residuals read it as noise, their second differences do not.
    cfg, _, _, sur = setup
    rng = np.random.default_rng(4)
    X = np.column_stack([rng.uniform(8, 20, 10), rng.uniform(3.0, 3.8, 10)])
    flows = _observe(sur, X, seed=9)
    t = np.asarray(sur.time, float)
    flows[5:] -= 6 * NOISE / (1 + np.exp(-(t - t[12]) / 3.0))
    est = estimate_noise_checked(sur, cfg, flows)
    assert est.residual_std > 1.4 * NOISE
    assert est.structured and est.p_structure < cfg.calibrate.fit_alpha
    assert est.std == est.difference_std and abs(est.std / NOISE - 1) < 0.2
    assert est.source == "differences"
    # A year with no sample (a further channel not recorded then) is no year of the fit.
    flows[0] = np.nan
    assert estimate_noise_checked(sur, cfg, flows).structured
    assert "hold more than noise" in est.warning("U", "m_flow", "kg/s")


def _posterior(cfg, sur, n_years=2, seed=0):
    X = np.column_stack([np.linspace(10, 11, n_years), np.linspace(3.6, 3.5, n_years)])
    flows = _observe(sur, X, seed=seed)
    return calibrate_unit(sur, cfg, np.arange(1, n_years + 1), flows, NOISE, rng_seed=5)


def test_calibrate_unit_is_deterministic_and_shaped(setup):
    cfg, _, _, sur = setup
    p1 = _posterior(cfg, sur)
    p2 = _posterior(cfg, sur)
    assert np.array_equal(p1.samples, p2.samples)
    n_s = cfg.calibrate.chains * cfg.calibrate.samples
    assert p1.samples.shape == (2, n_s, 2) and p1.mean.shape == (2, 2)
    assert p1.acceptance.shape == (2, cfg.calibrate.chains)
    assert np.all(p1.q05 < p1.median) and np.all(p1.median < p1.q95)
    assert np.all(p1.surrogate_var_ratio < 0.05)


def test_posterior_round_trip_and_schema(setup, tmp_path):
    cfg, _, _, sur = setup
    p = _posterior(cfg, sur)
    p.noise_source = "estimated"
    write_posterior(tmp_path / "post.h5", {"U1": p}, cfg.model.input_names, cfg, [])
    back = read_posterior(tmp_path / "post.h5")
    assert back.input_names == cfg.model.input_names
    q = back.units["U1"]
    for name in ("years", "mean", "median", "q05", "q95", "rhat", "ess",
                 "acceptance", "noise_std", "surrogate_var_ratio"):
        assert np.array_equal(getattr(q, name), getattr(p, name)), name
    # calibrate.keep_draws of the pooled draws are stored, evenly thinned, in single
    # precision (DRAW_DTYPE), and read back as float64.
    keep = cfg.calibrate.keep_draws
    kept = p.samples[:, thin_indices(p.samples.shape[1], keep)]
    assert q.samples.dtype == np.float64
    assert np.array_equal(q.samples, kept.astype(np.float32).astype(float))
    assert np.allclose(q.samples, kept, rtol=1e-7, atol=0)
    assert q.noise_source == "estimated"
    with h5py.File(tmp_path / "post.h5", "r") as f:
        # A unit is one compound record per year and its draws; the root documents every
        # field of the record (units, description) once.
        assert sorted(f["units/U1"]) == ["record", "samples"]
        doc = json.loads(f.attrs["record_fields"])
        for name in f["units/U1/record"].dtype.names:
            assert doc[name][0] and doc[name][1], name
        assert f.attrs["samples_description"]
    for key in ("rms", "p_chi2", "p_ljung_box", "window", "extensions", "status"):
        assert np.array_equal(q.fit[key], p.fit[key]), key
    with h5py.File(tmp_path / "wrong.h5", "w") as f:
        f.attrs["schema"] = "twinmon.forecast/1"
    with pytest.raises(ArtifactError, match="expected 'twinmon.posterior/2'"):
        read_posterior(tmp_path / "wrong.h5")


def _obs_file(path, time, flows, noise=None):
    units = {"A": UnitObservations(np.arange(1, len(flows) + 1), {"m_flow": flows},
                                   {"m_flow": noise} if noise else {})}
    write_observations(path, Observations(time, units, path))
    return path


def test_json_shape_through_the_cli(setup, tmp_path):
    cfg, cfg_path, tmp, sur = setup
    flows = _observe(sur, [[10.0, 3.6], [10.2, 3.58]], seed=2)
    obs = _obs_file(tmp_path / "obs.h5", sur.time, flows, noise=NOISE)
    from twinmon.cli import main
    res = CliRunner().invoke(main, [
        "calibrate", "-c", str(cfg_path), "--surrogate", str(tmp / "sur.h5"),
        "--observations", str(obs), "-o", str(tmp_path / "post.h5"), "--json",
        "--set", "calibrate.samples=300", "--set", "calibrate.burn_in=100"])
    assert res.exit_code == 0, res.stderr
    d = json.loads(res.stdout)
    assert set(d["units"]) == {"A"}
    assert d["units"]["A"]["years"] == [1, 2]
    assert set(d["units"]["A"]["params"]) == {"motor_damping", "pump_coef"}
    for stats in d["units"]["A"]["params"].values():
        assert set(stats) == {"mean", "median", "q05", "q95"}
        assert all(len(v) == 2 for v in stats.values())
    assert d["noise"]["A"] == {"std": NOISE, "source": "file"}
    assert np.shape(d["diagnostics"]["A"]["rhat"]) == (2, 2)
    assert isinstance(d["warnings"], list) and "truth_check" not in d
    # 4 chains x 300 draws, thinned to calibrate.keep_draws in the artifact.
    assert read_posterior(tmp_path / "post.h5").units["A"].samples.shape == (2, 1000, 2)


def test_time_grid_unlike_the_surrogates_names_both_files(setup, tmp_path):
    cfg, _, tmp, sur = setup
    time = sur.time[:-1]  # one sample short
    flows = _observe(sur, [10.0, 3.6])[:, :-1]
    obs = _obs_file(tmp_path / "short.h5", time, flows, noise=NOISE)
    out = tmp_path / "post.h5"
    with pytest.raises(InputDataError) as exc:
        calibrate(cfg, tmp / "sur.h5", obs, out)
    assert "short.h5" in str(exc.value) and "sur.h5" in str(exc.value)
    assert not out.exists()


def test_surrogate_of_other_inputs_is_rejected(setup, tmp_path):
    cfg, cfg_path, tmp, sur = setup
    obs = _obs_file(tmp_path / "obs.h5", sur.time, _observe(sur, [10.0, 3.6]), noise=NOISE)
    other = load_config(cfg_path, ["model.inputs.motor_damping.high=40"])
    with pytest.raises(ArtifactError, match="sur.h5: made for the design box"):
        calibrate(other, tmp / "sur.h5", obs, tmp_path / "post.h5")


def test_parallel_workers_give_the_serial_arrays(setup, tmp_path):
    cfg, cfg_path, tmp, sur = setup
    units = {name: UnitObservations(np.array([1, 2]), {"m_flow": _observe(sur, X, seed=i)})
             for i, (name, X) in enumerate({"A": [[10, 3.6], [10.5, 3.55]],
                                            "B": [[14, 3.3], [14.2, 3.2]]}.items())}
    obs = tmp_path / "obs.h5"
    write_observations(obs, Observations(sur.time, units, obs))
    # Chains not extended for a low ESS: what is compared is the workers' split, not the
    # mixing.
    quick = ["calibrate.samples=200", "calibrate.burn_in=100", "calibrate.noise_std=4.0",
             "calibrate.max_extensions=0"]
    posts = {}
    for w in (1, 2):
        c = load_config(cfg_path, quick + [f"calibrate.workers={w}"])
        s = calibrate(c, tmp / "sur.h5", obs, tmp_path / f"p{w}.h5")
        assert s.as_dict()["noise"]["A"] == {"std": 4.0, "source": "config"}
        posts[w] = read_posterior(tmp_path / f"p{w}.h5")
    for u in ("A", "B"):
        assert np.array_equal(posts[1].units[u].samples, posts[2].units[u].samples)


def test_noise_estimated_when_neither_file_nor_config_has_it(setup, tmp_path):
    cfg, cfg_path, tmp, sur = setup
    X = np.column_stack([np.linspace(9, 12, 6), np.linspace(3.7, 3.4, 6)])
    obs = _obs_file(tmp_path / "obs.h5", sur.time, _observe(sur, X, seed=8))
    c = load_config(cfg_path, ["calibrate.samples=150", "calibrate.burn_in=50",
                               "calibrate.max_extensions=0"])
    d = calibrate(c, tmp / "sur.h5", obs, tmp_path / "p.h5").as_dict()
    assert d["noise"]["A"]["source"] == "estimated"
    # 150 samples, 12 fitted parameters: ~6 % relative sd of the estimate.
    assert abs(d["noise"]["A"]["std"] / NOISE - 1) < 0.2
    assert read_posterior(tmp_path / "p.h5").units["A"].noise_source == "estimated"


def test_a_year_that_does_not_converge_is_sampled_longer_then_flagged(setup, tmp_path):
    cfg, cfg_path, tmp, sur = setup
    obs = _obs_file(tmp_path / "obs.h5", sur.time, _observe(sur, [[10.0, 3.6], [10.3, 3.58]]),
                    noise=NOISE)
    quick = ["calibrate.samples=150", "calibrate.burn_in=50", "calibrate.max_extensions=1"]
    # An ESS mark no chain of this length can reach: each year runs once more, twice as
    # long (same number of kept draws), and is then flagged.
    s = calibrate(load_config(cfg_path, quick + ["calibrate.ess_warn=1e6"]), tmp / "sur.h5",
                  obs, tmp_path / "slow.h5")
    p = read_posterior(tmp_path / "slow.h5").units["A"]
    assert list(p.fit["extensions"]) == [1, 1] and not p.fit["converged"].any()
    assert list(p.status) == ["unconverged"] * 2
    assert p.samples.shape == (2, 4 * 150, 2)
    assert sum("not converged after 1 longer run(s)" in w for w in s.warnings) == 2
    # A reachable mark: no extension, and the fit of a twin that explains the data is ok.
    calibrate(load_config(cfg_path, quick + ["calibrate.ess_warn=1"]), tmp / "sur.h5", obs,
              tmp_path / "fast.h5")
    p = read_posterior(tmp_path / "fast.h5").units["A"]
    assert list(p.fit["extensions"]) == [0, 0] and list(p.status) == ["ok", "ok"]
    assert np.all(p.fit["rms"] < 1.5) and np.all(p.fit["edge_share"] < 0.25)
