"""Resample-move on the laplace method's model (twinmon.calibrate.rejuvenate): where the
weighted draws collapse, the moved draws are the exact posterior's."""
from __future__ import annotations

import copy

import numpy as np

from twinmon.calibrate.rejuvenate import moved_by_chain, rejuvenate, resampled_ess

from .test_calibrate_laplace import setup  # noqa: F401 (the real surrogate, a fixture)
from .test_calibrate_shapes import WIDE, YEARS, _mixture


def _off_sites(seed: int):
    """Ten years of two inputs, one bending, with Gaussian likelihoods; the model's sites
    each a little off their likelihood and too narrow. Returns the model on the off sites,
    the exact posterior (the same model, its priors kept, with the likelihoods as its
    sites) and the likelihood."""
    rng = np.random.default_rng(seed)
    t = YEARS.astype(float)
    K, d = len(t), 2
    s = np.array([0.08, 0.05])
    truth = np.column_stack([1.0 + 0.05 * t + 0.004 * (t - 1) ** 2, 2.0 - 0.03 * t])
    y = truth + s * rng.standard_normal((K, d))

    def loglik(theta):
        return -0.5 * (((theta - y) / s) ** 2).sum(axis=-1)

    model = _mixture(y + 0.7 * s * rng.standard_normal((K, d)), np.tile(0.6 * s, (K, 1)),
                     {"line": 0.5, "accelerating": 0.5})
    exact = copy.deepcopy(model)
    exact.x, exact.cov = y, np.tile(np.diag(s ** 2), (K, 1, 1))
    return model, exact, loglik


def test_draws_whose_weights_collapse_are_moved_to_the_exact_posterior():
    """Each year's site a little off and too narrow: every year's own weights stay fair,
    their product over ten years and two inputs collapses (under 100 effective draws of
    4000). Moved, the draws reach the mark, and every year's inputs, the trend's rate at
    the last year and the accelerating shape's share are the exact posterior's (its
    mean within 0.2 sd, its sd within 20 %, the share within 0.1)."""
    model, exact, loglik = _off_sites(7)
    ref_coef, ref_sigma, ref, _ = exact.draw(100000, np.random.default_rng(1), WIDE)
    ref_code, _, ref_now = exact.decode(ref_coef)
    model.sigma_points(np.random.default_rng(2))
    rng = np.random.default_rng(3)
    first = model.importance(loglik, 4000, rng, WIDE)
    assert first[3] < 100
    moved = rejuvenate(model, loglik, first, 1000, rng, WIDE, 400.0)
    assert moved.ess >= 400 and moved.sweeps <= 80
    assert all(0.05 < a < 1.0 for a in moved.acceptance.values()), moved.acceptance
    th, sd = ref.mean(axis=0), ref.std(axis=0)
    assert np.all(np.abs(moved.theta.mean(axis=0) - th) < 0.2 * sd)
    assert np.all(np.abs(moved.theta.std(axis=0) / sd - 1.0) < 0.2)
    code, _, now = model.decode(moved.coef)
    rate, ref_rate = now[:, 1], ref_now[:, 1]
    assert np.all(np.abs(rate.mean(axis=0) - ref_rate.mean(axis=0)) < 0.2 * ref_rate.std(axis=0))
    assert np.all(np.abs(rate.std(axis=0) / ref_rate.std(axis=0) - 1.0) < 0.2)
    assert abs(np.mean(code > 0) - np.mean(ref_code > 0)) < 0.1
    np.testing.assert_allclose(np.median(moved.sigma, axis=0), np.median(ref_sigma, axis=0),
                               rtol=0.25)
    # The plain weighted draws are not: some year's mean more than half an sd off.
    assert np.max(np.abs(first[2].mean(axis=0) - th) / sd) > 0.5


def test_the_moves_keep_the_exact_posterior():
    """Started from the exact posterior itself (its draws, no weights), the chains stay on
    it: after 40 sweeps every year's mean and sd, and the sds' medians, are as before."""
    model, exact, loglik = _off_sites(11)
    coef, sigma, theta, _ = exact.draw(2000, np.random.default_rng(4), WIDE)
    model.sigma_points(np.random.default_rng(5))
    moved = rejuvenate(model, loglik, (coef, sigma, theta, 2000.0), 2000,
                       np.random.default_rng(6), WIDE, np.inf, max_sweeps=40)
    assert moved.sweeps == 40
    sd = theta.std(axis=0)
    assert np.all(np.abs(moved.theta.mean(axis=0) - theta.mean(axis=0)) < 0.15 * sd)
    assert np.all(np.abs(moved.theta.std(axis=0) / sd - 1.0) < 0.15)
    np.testing.assert_allclose(np.median(moved.sigma, axis=0), np.median(sigma, axis=0),
                               rtol=0.2)


def test_copies_that_never_moved_count_as_their_groups():
    """Chains still where they started (every copy of a draw alike) count as many draws as
    the copies' design effect allows (1000 copies of 100 draws: 100); chains that forgot
    their start count whole."""
    rng = np.random.default_rng(0)
    groups = np.repeat(np.arange(100), 10)
    start = rng.standard_normal((100, 3))[groups]
    assert abs(resampled_ess(groups, start, start, 10, 10) - 100.0) < 1e-9
    fresh = rng.standard_normal((1000, 3))
    assert resampled_ess(groups, start, fresh, 10, 10) > 990


def test_moved_draws_are_named_so_in_the_summary_and_the_reason():
    """A unit whose weighted draws were moved: the calibrate summary and the report say so
    instead of 'weighted independent draws', and an unreliable status names the moves."""
    from types import SimpleNamespace

    from twinmon.cli.calibrate_cmd import _drawn
    from twinmon.config import load_config
    from twinmon.forecast.judge import _unconverged
    from twinmon.report.html import _acceptance

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    K = 4
    p = SimpleNamespace(years=np.arange(1, K + 1), ess=np.full((K, 2), 150.0),
                        acceptance=np.full((K, 4), np.nan), rhat=np.ones((K, 2)),
                        fit={"extensions": np.full(K, 2)},
                        trend={"acceptance": np.full(4, 0.17)})
    assert _drawn(p) == "weighted draws moved by a Markov chain (trend moves accepted 0.17)"
    why = _unconverged(p, cfg, np.arange(K))
    assert "150 effective draws" in why and "doubled 2 time(s) and moved by a Markov chain" in why
    assert _acceptance([float("nan")] * 2, True) == "- (weighted draws, moved by a Markov chain)"
    p.trend = {"acceptance": np.full(4, np.nan)}
    assert _drawn(p) == "weighted independent draws"
    assert "moved" not in _unconverged(p, cfg, np.arange(K))


def test_a_unit_whose_years_share_a_warning_gets_one_line():
    """The laplace method's effective number is the unit's: ten years with the same ESS
    make one warning naming the years, not ten; years that differ keep their own."""
    from types import SimpleNamespace

    from twinmon.calibrate import diagnostics_warnings
    from twinmon.config import load_config

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    K = 10
    ess = np.full((K, 2), 197.0)
    ess[7:] = [[900.0, 900.0]] * 3
    rhat = np.ones((K, 2))
    rhat[8, 1] = 1.2
    p = SimpleNamespace(years=np.arange(1, K + 1), ess=ess, rhat=rhat,
                        acceptance=np.full((K, 4), np.nan))
    got = diagnostics_warnings({"U7": p}, ["a", "b"], cfg)
    assert got == ["U7 years 1-7: ESS 197 < 400 for a; ESS 197 < 400 for b",
                   "U7 year 9: R-hat 1.200 > 1.05 for b"]
    # The report keeps a drawn unit's warnings and counts the units warned, either form.
    from twinmon.report.stage import _only
    diag = {"units": {"U7": {"max_rhat": 1.2, "min_ess": 197.0},
                      "V": {"max_rhat": 1.0, "min_ess": 900.0}},
            "warnings": got + ["V year 2: ESS 300 < 400 for a"]}
    kept = _only(diag, ["U7"])
    assert kept["warnings"] == got and kept["fleet"]["warned_units"] == 2


def test_a_unit_whose_weights_stay_short_is_moved_end_to_end(setup, tmp_path, monkeypatch):
    """Through the real surrogate: a unit whose weighted draws count as too few (their
    effective number cut to 50 here, the draws themselves kept) goes through the chain:
    converged, its trend moves' acceptance recorded, and calibrate's summary and the
    report's table name the moves."""
    from twinmon.calibrate import calibrate, gaussian_trend, read_posterior
    from twinmon.cli.calibrate_cmd import _drawn
    from twinmon.report.summary import _trend_acceptance

    from .test_calibrate_laplace import _fleet
    cfg, _, tmp, sur = setup
    obs = tmp_path / "obs.h5"
    _fleet(obs, sur, [2])
    weigh = gaussian_trend.SiteModel.importance
    monkeypatch.setattr(gaussian_trend.SiteModel, "importance",
                        lambda self, *args: weigh(self, *args)[:3] + (50.0,))
    calibrate(cfg, tmp / "sur.h5", obs, tmp_path / "post.h5")
    p = read_posterior(tmp_path / "post.h5").units["U2"]
    assert np.all(p.fit["converged"]) and np.all(p.ess >= cfg.calibrate.ess_warn)
    assert np.isfinite(p.trend["acceptance"]).all() and np.all(np.isnan(p.acceptance))
    assert _drawn(p).startswith("weighted draws moved by a Markov chain")
    assert moved_by_chain(p.acceptance, _trend_acceptance(tmp_path / "post.h5")["U2"])
