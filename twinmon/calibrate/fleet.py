"""The fleet's year-to-year variation: partial pooling of the joint method's ``sigma``.

Each unit's joint calibration (:mod:`.methods.joint`) estimates its own ``sigma_i``, the standard
deviation of input ``i``'s year-to-year variation around its trend, under a weak
half-Cauchy prior of scale ``A_i = calibrate.prior_width * range_i``. Ten years cannot tell a
small ``sigma`` from the years' estimation errors, least of all along the ridge of inputs
that move the output alike, and a flat prior leaves it there: on benchmarks/prognosis.py the
pump coefficient's ``sigma`` came out 0.028-0.030 per unit against 0.01 fabricated, and the
larger ``sigma`` widens the slopes' and the future's intervals (indicator coverage 0.966
against 0.90 wanted). The units of a fleet share this scale far better than ten years of one
unit can estimate it.

The fleet's prior (empirical Bayes): ``log sigma_i ~ N(mu_i, tau_i^2)``, ``mu`` and ``tau``
chosen to maximise the fleet's marginal likelihood ``prod_u p(y_u | mu, tau)``. Each unit's is
known up to a constant from its own posterior draws under the half-Cauchy (importance
sampling)::

    p(y_u | mu, tau) / p(y_u | A) = E_{posterior_u, A} [ prod_i LN(sigma_i; mu_i, tau_i)
                                                               / hc(sigma_i; A_i) ]

so no unit is calibrated again: its draws are reweighted by that ratio, and resampled, to
follow its posterior under the fleet's prior. Each unit's effective sample size is reported.

Why a log-normal and not the half-Cauchy with a fitted scale: one unit's ten years cannot
tell ``sigma`` from 0 (its likelihood is flat from 0 to about the years' estimation error),
and a family that reaches 0 follows that flat stretch down. On benchmarks/prognosis.py
(fabricated sigma 0.15 and 0.01) a fitted half-Cauchy scale came out a third of the truth
(0.046 and 0.0036 on seed 11); the log-normal, whose density vanishes at 0, put the fleet's
median at 0.078-0.132 and 0.0088-0.0257 over seeds 11-16 (docs/forecast.md). ``tau`` is
kept at or above :data:`MIN_TAU`: the units' ``sigma`` may differ, and a prior narrower than
that leaves a unit only a few percent of its draws.

With fewer than ``forecast.pool_min_units`` units the fleet's ``sigma`` is no better known
than one unit's, and nothing is pooled.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.special import logsumexp

#: Smallest spread (log units) of the units' sigma about the fleet's median: below it the
#: importance weights of a unit's draws concentrate on a few (on the benchmark's seeds 11-12,
#: tau 0.3 left a median of 6-8 % of the draws effective and 1 % for the worst unit; 0.5 left
#: 15-18 % and 4 %), and the units of a real fleet differ at least that much.
MIN_TAU = 0.5
#: Largest spread: beyond it the prior is flat over every draw.
MAX_TAU = 3.0


def _log_ratio(sigma: np.ndarray, mu: np.ndarray, tau: np.ndarray,
               base: np.ndarray) -> np.ndarray:
    """``log prod_i LN(sigma_i; mu_i, tau_i) / hc(sigma_i; base_i)`` per draw.

    Parameters
    ----------
    sigma : ndarray, shape [n, d]
        Draws of the year-to-year sd, input units (>= 0).
    mu, tau : ndarray, shape [d]
        The log-normal's log-median and log-sd.
    base : ndarray, shape [d]
        The calibration's half-Cauchy scales, input units.

    Returns
    -------
    ndarray, shape [n]
    """
    # A draw at exactly 0 (s crossed 0 in the sampler) has log-normal density 0.
    sigma = np.maximum(sigma, np.finfo(float).tiny)
    ls = np.log(sigma)
    log_ln = -ls - np.log(tau) - 0.5 * np.log(2 * np.pi) - 0.5 * ((ls - mu) / tau) ** 2
    # hc(s; A) = 2 / (pi A (1 + (s / A)^2))
    log_hc = np.log(2 / np.pi) - np.log(base) - np.log1p((sigma / base) ** 2)
    return (log_ln - log_hc).sum(axis=1)


@dataclass(frozen=True)
class FleetPrior:
    """The fleet's log-normal prior of the year-to-year sd (see the module's docstring).

    Attributes
    ----------
    median : ndarray, shape [d]
        The fleet's median ``exp(mu)`` per input, input units.
    tau : ndarray, shape [d]
        Spread of the units' ``log sigma`` about it.
    base : ndarray, shape [d]
        The calibration's half-Cauchy scale ``A`` per input, input units.
    n_units : int
        Units it was fitted on.
    """

    median: np.ndarray
    tau: np.ndarray
    base: np.ndarray
    n_units: int

    def weights(self, sigma: np.ndarray) -> np.ndarray:
        """Normalised importance weights [n] of a unit's draws ``sigma`` [n, d]."""
        lr = _log_ratio(np.asarray(sigma, float), np.log(self.median), self.tau, self.base)
        return np.exp(lr - logsumexp(lr))

    def resample(self, sigma: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        """Indices [n] of a unit's draws resampled to its posterior under this prior
        (systematic resampling: each draw kept about ``n * weight`` times), and the
        weights' effective sample size as a fraction of ``n``.

        Parameters
        ----------
        sigma : ndarray, shape [n, d]
        rng : numpy Generator
            One uniform is drawn (the systematic comb's offset).
        """
        return systematic_resample(self.weights(sigma), rng)


def systematic_resample(w: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """Indices [n] of draws resampled by their normalised weights ``w`` [n] (systematic
    resampling: each draw kept about ``n * weight`` times; one uniform drawn from ``rng``),
    and the weights' effective sample size as a fraction of ``n``."""
    n = w.size
    comb = (rng.uniform() + np.arange(n)) / n
    idx = np.minimum(np.searchsorted(np.cumsum(w), comb), n - 1)
    return idx, float(1.0 / np.sum(w ** 2) / n)


#: Units per block of the marginal likelihood's arrays ([block, draws, d] each): a few tens
#: of MB whatever the fleet's size.
BLOCK_UNITS = 500


def _blocks(sig: list, base: np.ndarray) -> list:
    """The units' draws as blocks of ``BLOCK_UNITS`` for :func:`fit_fleet_prior`: per block
    ``(log sigma [b, n, d], the part of the log ratio that does not depend on the prior's
    parameters [b, n])``, units with fewer draws than the block's most padded with draws of
    log ratio -inf (weight 0)."""
    tiny = np.finfo(float).tiny
    out = []
    for lo in range(0, len(sig), BLOCK_UNITS):
        part = sig[lo:lo + BLOCK_UNITS]
        n = max(len(s) for s in part)
        S = np.ones((len(part), n, base.size))
        pad = np.zeros((len(part), n), bool)
        for j, s in enumerate(part):
            S[j, :len(s)] = s
            pad[j, len(s):] = True
        S = np.maximum(S, tiny)
        ls = np.log(S)
        # _log_ratio's terms free of mu and tau: -log s - log(2 pi)/2 less the half-Cauchy's.
        fixed = (-ls - 0.5 * np.log(2 * np.pi) - np.log(2 / np.pi) + np.log(base)
                 + np.log1p((S / base) ** 2)).sum(axis=2)
        fixed[pad] = -np.inf
        out.append((ls, fixed))
    return out


def _neg_log_marginal(x: np.ndarray, blocks: list, d: int) -> tuple[float, np.ndarray]:
    """Minus the fleet's log marginal likelihood (up to a constant) at ``x = (mu, log tau)``
    [2d], and its gradient [2d]; ``blocks`` from :func:`_blocks`.

    Per unit u and draw n: ``lr = fixed - sum_i log tau_i - sum_i z_i^2 / 2`` with
    ``z_i = (log s_i - mu_i) / tau_i`` (:func:`_log_ratio`); the unit's term is
    ``logsumexp_n lr``, whose derivatives are those of ``lr`` averaged with the weights
    ``softmax_n lr``: ``d lr / d mu_i = z_i / tau_i``, ``d lr / d log tau_i = z_i^2 - 1``."""
    mu, tau = x[:d], np.exp(x[d:])
    value, grad = 0.0, np.zeros(2 * d)
    for ls, fixed in blocks:
        z = (ls - mu) / tau                                               # [b, n, d]
        lr = fixed - np.log(tau).sum() - 0.5 * np.einsum("bni,bni->bn", z, z)
        top = lr.max(axis=1, keepdims=True)
        w = np.exp(lr - top)
        total = w.sum(axis=1, keepdims=True)
        value += float(np.sum(top[:, 0] + np.log(total[:, 0])))
        w /= total
        grad[:d] += np.einsum("bn,bni->i", w, z) / tau
        grad[d:] += np.einsum("bn,bni->i", w, z * z) - len(ls)
    return -value, -grad


def fit_fleet_prior(sigmas: Sequence[np.ndarray], base: np.ndarray) -> FleetPrior:
    """The fleet's log-normal prior by maximum marginal likelihood over its units.

    The marginal likelihood and its gradient in ``(mu, log tau)`` are array operations over
    blocks of units (:func:`_blocks`); with the gradient in closed form, L-BFGS-B takes a
    fifth of the evaluations finite differences needed (1000 units: 27 s -> under 1 s).

    Parameters
    ----------
    sigmas : sequence of ndarray, shape [n_u, d]
        Each unit's posterior draws of ``sigma`` under the half-Cauchy prior of scale ``base``.
    base : ndarray, shape [d]
        The calibration's scale ``A`` (``trend["sigma_scale"]``), input units.

    Returns
    -------
    FleetPrior
    """
    # Imported here: scipy.optimize takes 0.7 s to import, and the forecast's workers read
    # this module's constants and resampler without ever fitting.
    from scipy.optimize import minimize
    base = np.asarray(base, float)
    d = base.size
    sig = [np.asarray(s, float) for s in sigmas]
    blocks = _blocks(sig, base)

    # Start at the units' pooled posterior median of log sigma; mu ranges over the
    # calibration prior's reach (1e-4 A .. 10 A).
    start = np.median(np.log(np.maximum(np.concatenate(sig), np.finfo(float).tiny)), axis=0)
    bounds = ([(float(np.log(b * 1e-4)), float(np.log(b * 10))) for b in base]
              + [(float(np.log(MIN_TAU)), float(np.log(MAX_TAU)))] * d)
    r = minimize(_neg_log_marginal, np.r_[np.clip(start, *np.array(bounds[:d]).T),
                                          np.full(d, np.log(MIN_TAU))],
                 args=(blocks, d), method="L-BFGS-B", jac=True, bounds=bounds)
    return FleetPrior(median=np.exp(r.x[:d]), tau=np.exp(r.x[d:]), base=base,
                      n_units=len(sig))
