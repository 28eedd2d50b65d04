"""The fleet's prior of the joint method's year-to-year sd (twinmon.calibrate.fleet): the
importance weights move a unit's draws to the fleet's prior, and the empirical-Bayes fit
recovers a fleet's sigma from posteriors drawn under a much wider prior."""
from __future__ import annotations

import numpy as np
from scipy.stats import halfcauchy, lognorm

from twinmon.calibrate.fleet import MIN_TAU, FleetPrior, fit_fleet_prior


def _posterior_draws(y: np.ndarray, err: float, base: float, n: int, rng) -> np.ndarray:
    """Draws [n] of sigma given the years' estimated deviations ``y`` [K] ~ N(0, sigma^2 +
    err^2) (year-to-year variation plus estimation error) under a half-Cauchy(base) prior,
    by inverse CDF on a fine grid (exact up to the grid)."""
    grid = np.linspace(1e-5, 10 * base, 20000)
    v = grid ** 2 + err ** 2
    logp = (-0.5 * y.size * np.log(v) - 0.5 * np.sum(y ** 2) / v
            + halfcauchy.logpdf(grid, scale=base))
    cdf = np.cumsum(np.exp(logp - logp.max()))
    return np.interp(rng.uniform(size=n) * cdf[-1], cdf, grid)


def test_weights_move_prior_draws_to_the_fleet_prior():
    """With no data the posterior is the prior: draws of half-Cauchy(A) reweighted to the
    fleet's log-normal follow it (median and quartiles)."""
    rng = np.random.default_rng(1)
    base = np.array([0.09, 0.5])
    draws = np.column_stack([halfcauchy.rvs(scale=b, size=200000, random_state=rng)
                             for b in base])
    fleet = FleetPrior(median=np.array([0.02, 0.4]), tau=np.array([0.5, 1.0]), base=base,
                       n_units=1)
    idx, ess = fleet.resample(draws, rng)
    assert idx.shape == (200000,)
    for i in range(2):
        want = lognorm.ppf([0.25, 0.5, 0.75], fleet.tau[i], scale=fleet.median[i])
        got = np.quantile(draws[idx, i], [0.25, 0.5, 0.75])
        assert np.allclose(got, want, rtol=0.05), (i, got, want)
    assert 0.01 < ess < 0.5


def test_the_fleet_sigma_is_recovered_from_wide_posteriors():
    """60 units whose sigma is log-normal about B0 (log-sd 0.5), ten years each, estimated with
    an error as large as B0 (the joint method's ridge), calibrated under a half-Cauchy prior
    10x wider: the fitted median lands near B0 per input, and the units' intervals of sigma
    still cover their truth while narrower than under the wide prior."""
    rng = np.random.default_rng(7)
    B0, base, K = np.array([0.01, 0.15]), np.array([0.1, 1.5]), 10
    sigmas, truths = [], []
    for _ in range(60):
        s_true = B0 * np.exp(MIN_TAU * rng.standard_normal(2))
        truths.append(s_true)
        y = rng.normal(0.0, np.sqrt(s_true ** 2 + B0 ** 2), (K, 2))
        sigmas.append(np.column_stack([_posterior_draws(y[:, i], B0[i], base[i], 1000, rng)
                                       for i in range(2)]))
    fp = fit_fleet_prior(sigmas, base)
    assert fp.n_units == 60
    ratio = fp.median / B0
    assert np.all((ratio > 0.75) & (ratio < 1.33)), fp.median
    assert np.all((fp.tau >= MIN_TAU) & (fp.tau < 1.0)), fp.tau
    truth = np.array(truths)

    def cover_and_width(draws):
        lo = np.array([np.quantile(s, 0.05, axis=0) for s in draws])
        hi = np.array([np.quantile(s, 0.95, axis=0) for s in draws])
        return ((truth >= lo) & (truth <= hi)).mean(axis=0), np.median(hi - lo, axis=0)

    cover_own, width_own = cover_and_width(sigmas)
    cover, width = cover_and_width([s[fp.resample(s, rng)[0]] for s in sigmas])
    assert np.all(cover >= 0.85), cover
    assert np.all(width < 0.7 * width_own), (width, width_own)



def test_marginal_likelihood_in_blocks_equals_the_per_unit_sum_and_its_gradient():
    """The fleet's marginal likelihood computed over blocks of units (ragged numbers of
    draws padded) equals the sum of each unit's logsumexp of :func:`_log_ratio`, and its
    closed-form gradient matches central differences; three inputs, blocks of two units."""
    from scipy.special import logsumexp
    import twinmon.calibrate.fleet as fleet
    rng = np.random.default_rng(3)
    base = np.array([0.1, 1.5, 0.02])
    sig = [np.abs(rng.standard_cauchy((n, 3))) * base for n in (40, 55, 40, 31, 60)]
    sig[1][3, 0] = 0.0                        # a draw at exactly 0 (log-normal density 0)
    old = fleet.BLOCK_UNITS
    fleet.BLOCK_UNITS = 2
    try:
        blocks = fleet._blocks(sig, base)
    finally:
        fleet.BLOCK_UNITS = old
    assert len(blocks) == 3
    for x in (np.r_[np.log(base * 0.3), np.log([0.5, 0.7, 1.2])],
              np.r_[np.log(base * 2.0), np.log([2.0, 0.5, 0.9])]):
        value, grad = fleet._neg_log_marginal(x, blocks, 3)
        want = -sum(logsumexp(fleet._log_ratio(s, x[:3], np.exp(x[3:]), base)) for s in sig)
        assert np.isclose(value, want, rtol=1e-12), (value, want)
        h = 1e-6
        fd = [(fleet._neg_log_marginal(x + h * e, blocks, 3)[0]
               - fleet._neg_log_marginal(x - h * e, blocks, 3)[0]) / (2 * h)
              for e in np.eye(6)]
        assert np.allclose(grad, fd, rtol=1e-5, atol=1e-6), (grad, fd)
