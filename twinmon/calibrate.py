"""Stage ``calibrate``: posterior of the degradation inputs per unit and year.

For each unit, each year's start-up transient is inverted through the surrogate by Bayesian
inference, as in the paper (section V):

* prior: year 1 uniform on the design box; year k > 1 Gaussian (independent per input,
  truncated to the box) centred on year k-1's posterior mean, standard deviation
  ``sqrt((prior_width * (high - low))^2 + previous posterior variance)`` per input (the
  second term with ``prior_carry_variance``, the default; see docs/calibration.md);
* likelihood: Gaussian, independent per time step, variance = measurement noise variance +
  surrogate predictive variance; missing (NaN) samples are left out;
* sampling: OpenTURNS' random-walk Metropolis-Hastings, several chains started around the
  maximum a posteriori (MAP) point with a proposal shaped on the Laplace (Gauss-Newton)
  covariance there; OpenTURNS returns the burn-in with the chain, so it is cut here; the
  chains of all units' same year run in parallel processes;
* diagnostics: rank-normalised split R-hat and bulk effective sample size (Vehtari et al.
  2021) and the acceptance rate per chain, with warnings when they are poor.

The result is ``posterior.h5`` (``twinmon.posterior/1``)::

    attrs input_names (JSON list), input_units (JSON list)
    /units/<U>/years        int64   [n_y]             year of service
    /units/<U>/samples      float64 [n_y, n_s, d]     pooled post-burn-in draws (input units)
    /units/<U>/mean, median, q05, q95  float64 [n_y, d]
    /units/<U>/rhat, ess    float64 [n_y, d]
    /units/<U>/acceptance   float64 [n_y, chains]
    /units/<U>/noise_std    float64 [n_y]             output units (noise used in the likelihood)
    /units/<U>/surrogate_var_ratio float64 [n_y]      mean surrogate variance / noise variance
    /units/<U>/fit/<field>  [n_y] or [n_y, d]         goodness of fit per year (FIT_FIELDS):
                            rms, p_chi2, p_ljung_box, window, window_rms, edge_share,
                            extensions, converged, status (ok|misfit|edge|unconverged)
    /units/<U>.attrs noise_source  "file" | "config" | "estimated"
    attrs fit_windows (JSON list: the window names fit/window indexes)

Goodness of fit: each year's residual at the posterior mean, standardised by the likelihood's
variance, is tested for size and structure; a year whose residual is well above the noise
(``calibrate.fit_min_rms``) and significant (``fit_alpha``) is "misfit" -- the twin misses the
plant -- and one whose draws pile against a bound of the design box is "edge". A year whose
R-hat or ESS is poor is sampled again with longer chains (``max_extensions`` times); still
poor, it is "unconverged". ``forecast`` withholds or flags a prognosis on these verdicts.
"""
from __future__ import annotations

import json
import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import h5py
import numpy as np

from . import artifacts
from .config import Config
from .errors import ArtifactError, CalibrationError, InputDataError, Interrupted
from .observations import read_observations

#: Per-year verdicts of the fit, in order of precedence.
STATUS_OK, STATUS_MISFIT, STATUS_EDGE, STATUS_UNCONVERGED = "ok", "misfit", "edge", "unconverged"

#: Config sections recorded as the posterior's provenance (and compared by ``twinmon run``).
SECTIONS = ("model", "calibrate", "seed")
#: Added to ``cfg.seed`` so that calibrate's random streams differ from other stages'.
SEED_OFFSET = 3000
#: Acceptance rates outside this range make a warning (random-walk MH is efficient near
#: 0.2-0.4 in low dimension; far outside, the proposal scale was badly adapted).
ACCEPTANCE_RANGE = (0.1, 0.7)


# ---------------------------------------------------------------------------------------
# Prior and log-density
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Prior:
    """Prior of one unit-year: uniform on the box, or an independent Gaussian truncated to it.

    Attributes
    ----------
    bounds : ndarray, shape [d, 2]
        Design box (low, high), input units.
    centre : ndarray, shape [d], optional
        Mean of the Gaussian before truncation; ``None`` for the uniform prior.
    std : ndarray, shape [d], optional
        Standard deviation of the Gaussian before truncation, input units.
    """

    bounds: np.ndarray
    centre: Optional[np.ndarray] = None
    std: Optional[np.ndarray] = None

    @classmethod
    def uniform(cls, bounds) -> "Prior":
        return cls(np.asarray(bounds, float))

    @classmethod
    def gaussian(cls, bounds, centre, std) -> "Prior":
        return cls(np.asarray(bounds, float), np.asarray(centre, float), np.asarray(std, float))

    @property
    def is_uniform(self) -> bool:
        return self.centre is None

    @property
    def location(self) -> np.ndarray:
        """The prior's centre, shape [d]: box centre (uniform) or Gaussian centre."""
        return self.bounds.mean(axis=1) if self.is_uniform else self.centre

    def inside(self, X: np.ndarray) -> np.ndarray:
        X = np.atleast_2d(X)
        return np.all((X >= self.bounds[:, 0]) & (X <= self.bounds[:, 1]), axis=1)

    def logpdf(self, X: np.ndarray) -> np.ndarray:
        """Unnormalised log-density, shape [n]; ``-inf`` outside the box.

        The truncation constant of the Gaussian does not depend on ``X`` and is dropped."""
        X = np.atleast_2d(X)
        out = np.where(self.inside(X), 0.0, -np.inf)
        if not self.is_uniform:
            out = out - 0.5 * np.sum(((X - self.centre) / self.std) ** 2, axis=1)
        return out

    def precision(self) -> np.ndarray:
        """Prior precision matrix [d, d] (zero for the uniform prior), for the Laplace fit."""
        d = len(self.bounds)
        return np.zeros((d, d)) if self.is_uniform else np.diag(1.0 / self.std ** 2)


class LogDensity:
    """Unnormalised log-posterior of one unit-year's inputs.

    ``log p(x | y) = log prior(x) - 1/2 sum_t (y_t - f_t(x))^2 / v_t`` over the observed
    (non-NaN) time steps, with ``f`` the surrogate and ``v = noise_std^2 + surrogate variance``.

    Parameters
    ----------
    surrogate : Surrogate
        Maps inputs [n, d] to transients [n, n_t].
    obs_row : ndarray, shape [n_t]
        Measured output (its units); NaN = missing sample, left out of the likelihood.
    noise_var : ndarray, shape [n_t] or float
        Total variance per time step (output units)^2.
    prior : Prior
    """

    def __init__(self, surrogate, obs_row: np.ndarray, noise_var, prior: Prior):
        obs_row = np.asarray(obs_row, float)
        self.surrogate = surrogate
        self.prior = prior
        self.mask = ~np.isnan(obs_row)
        self.y = obs_row[self.mask]
        self.var = np.broadcast_to(np.asarray(noise_var, float), obs_row.shape)[self.mask]
        self.dim = len(prior.bounds)
        self._inv_var = 1.0 / self.var
        self._lo, self._hi = prior.bounds[:, 0], prior.bounds[:, 1]

    def loglik(self, X: np.ndarray) -> np.ndarray:
        """Gaussian log-likelihood up to a constant, shape [n], for inputs [n, d]."""
        pred = self.surrogate.predict(np.atleast_2d(X))[:, self.mask]
        return -0.5 * np.sum((self.y - pred) ** 2 / self.var, axis=1)

    def batch(self, X: np.ndarray) -> np.ndarray:
        """Log-posterior, shape [n], for inputs [n, d]; ``-inf`` outside the box."""
        X = np.atleast_2d(np.asarray(X, float))
        out = self.prior.logpdf(X)
        ok = np.isfinite(out)
        if ok.any():
            out[ok] += self.loglik(X[ok])
        return out

    def __call__(self, x) -> float:
        # The per-step path of the sampler: one point, no masks over batches.
        x = np.asarray(x, float)
        if np.any(x < self._lo) or np.any(x > self._hi):
            return -np.inf
        r = self.y - self.surrogate.predict(x[None, :])[0, self.mask]
        lp = -0.5 * float(np.dot(r * r, self._inv_var))
        if not self.prior.is_uniform:
            lp -= 0.5 * float(np.sum(((x - self.prior.centre) / self.prior.std) ** 2))
        return lp

    def residuals(self, x: np.ndarray, with_prior: bool = False) -> np.ndarray:
        """Standardised residuals at one point, shape [n_obs] (+ [d] prior terms).

        With ``with_prior``, a Gaussian prior adds ``(x - centre) / std``, so that
        ``-log posterior = 0.5 * sum(residuals^2)`` + const inside the box."""
        pred = self.surrogate.predict(np.atleast_2d(x))[0, self.mask]
        r = (self.y - pred) / np.sqrt(self.var)
        if with_prior and not self.prior.is_uniform:
            r = np.concatenate([r, (np.asarray(x) - self.prior.centre) / self.prior.std])
        return r

    def as_openturns(self):
        """The log-density as an OpenTURNS function R^d -> R (point-wise callback)."""
        import openturns as ot
        return ot.PythonFunction(self.dim, 1, lambda x: [self(x)],
                                 func_sample=lambda X: self.batch(np.asarray(X))[:, None])


def make_log_density(surrogate, obs_row: np.ndarray, noise_var, prior: Prior) -> LogDensity:
    """The unnormalised log-posterior of one unit-year (see :class:`LogDensity`)."""
    return LogDensity(surrogate, obs_row, noise_var, prior)


# ---------------------------------------------------------------------------------------
# Convergence diagnostics (Vehtari, Gelman, Simpson, Carpenter, Buerkner 2021)
# ---------------------------------------------------------------------------------------
def _split(chains: np.ndarray) -> np.ndarray:
    """[m, n] -> [2m, n//2]: each chain cut in halves, so drifts within a chain show."""
    chains = np.atleast_2d(np.asarray(chains, float))
    half = chains.shape[1] // 2
    return np.vstack([chains[:, :half], chains[:, -half:]])


def _z_scale(x: np.ndarray) -> np.ndarray:
    """Rank-normalisation: ranks over all draws mapped to normal scores."""
    from scipy.special import ndtri
    from scipy.stats import rankdata
    r = rankdata(x, method="average").reshape(x.shape)
    return ndtri((r - 0.375) / (x.size + 0.25))


def _rhat(chains: np.ndarray) -> float:
    m, n = chains.shape
    within = np.mean(np.var(chains, axis=1, ddof=1))
    between = n * np.var(np.mean(chains, axis=1), ddof=1)
    if within <= 0:
        return float("nan")
    return float(np.sqrt((between / within + n - 1) / n))


def split_rhat(chains: np.ndarray, rank_normalize: bool = True) -> float:
    """Split R-hat of one scalar quantity.

    Parameters
    ----------
    chains : ndarray, shape [m, n]
        ``m`` chains of ``n`` post-burn-in draws.
    rank_normalize : bool
        True: the rank-normalised R-hat of Vehtari et al. (2021), the larger of the bulk
        (ranks) and tail (ranks of ``|x - median|``) values; False: the classic split R-hat.

    Returns
    -------
    float
        Near 1 when the chains agree; > 1.01-1.05 signals poor mixing.
    """
    chains = np.atleast_2d(np.asarray(chains, float))
    if np.ptp(chains) == 0:
        return float("nan")
    if not rank_normalize:
        return _rhat(_split(chains))
    bulk = _rhat(_z_scale(_split(chains)))
    folded = np.abs(chains - np.median(chains))
    tail = _rhat(_z_scale(_split(folded))) if np.ptp(folded) > 0 else bulk
    return max(bulk, tail)


def _autocov(x: np.ndarray) -> np.ndarray:
    """Biased autocovariance of each row, shape [m, n], by FFT."""
    m, n = x.shape
    xc = x - x.mean(axis=1, keepdims=True)
    size = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(xc, size, axis=1)
    return np.fft.irfft(f * np.conj(f), size, axis=1)[:, :n] / n


def ess(chains: np.ndarray, rank_normalize: bool = False) -> float:
    """Effective sample size of one scalar quantity over all chains.

    Autocorrelations combine the chains as in Stan/ArviZ and are summed with Geyer's initial
    monotone sequence. ``rank_normalize=True`` gives the bulk ESS of Vehtari et al. (2021)
    (split chains, ranks); False the plain ESS of the values (use it for the Monte Carlo
    standard error of the mean: ``sd / sqrt(ess)``).

    Parameters
    ----------
    chains : ndarray, shape [m, n]

    Returns
    -------
    float
        Between ~0 and ``m * n`` (more for antithetic chains).
    """
    x = np.atleast_2d(np.asarray(chains, float))
    if rank_normalize:
        x = _z_scale(_split(x))
    m, n = x.shape
    if np.ptp(x) == 0 or n < 4:
        return float("nan")
    acov = _autocov(x)
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n
    if m > 1:
        var_plus += np.var(x.mean(axis=1), ddof=1)
    rho = np.zeros(n)
    rho_even = 1.0
    rho[0] = rho_even
    rho_odd = 1.0 - (mean_var - np.mean(acov[:, 1])) / var_plus
    rho[1] = rho_odd
    # Geyer's initial positive sequence: sum pairs while their sum stays positive.
    t = 1
    while t < n - 3 and rho_even + rho_odd > 0.0:
        rho_even = 1.0 - (mean_var - np.mean(acov[:, t + 1])) / var_plus
        rho_odd = 1.0 - (mean_var - np.mean(acov[:, t + 2])) / var_plus
        if rho_even + rho_odd >= 0:
            rho[t + 1] = rho_even
            rho[t + 2] = rho_odd
        t += 2
    max_t = t - 2
    if rho_even > 0:
        rho[max_t + 1] = rho_even
    # Geyer's initial monotone sequence: pair sums may not increase.
    t = 1
    while t <= max_t - 2:
        if rho[t + 1] + rho[t + 2] > rho[t - 1] + rho[t]:
            rho[t + 1] = (rho[t - 1] + rho[t]) / 2.0
            rho[t + 2] = rho[t + 1]
        t += 2
    total = m * n
    tau = -1.0 + 2.0 * np.sum(rho[:max_t + 1]) + np.sum(rho[max_t + 1:max_t + 2])
    tau = max(tau, 1.0 / np.log10(total))
    return float(total / tau)


# ---------------------------------------------------------------------------------------
# MAP, Laplace covariance, sampling
# ---------------------------------------------------------------------------------------
def _jacobian(ld: LogDensity, x: np.ndarray) -> np.ndarray:
    """Jacobian of the standardised residuals at ``x``, shape [n_obs, d] (central
    differences, one vectorised surrogate call)."""
    d = len(x)
    h = 1e-4 * np.diff(ld.prior.bounds, axis=1).ravel()
    pts = np.vstack([x + np.diag(h), x - np.diag(h)])
    pred = ld.surrogate.predict(pts)[:, ld.mask] / np.sqrt(ld.var)
    return -((pred[:d] - pred[d:]) / (2 * h[:, None])).T


def find_map(ld: LogDensity) -> tuple[np.ndarray, np.ndarray]:
    """Maximum a posteriori point and Laplace covariance of one unit-year.

    With the uniform prior a coarse grid over the box (one vectorised surrogate call) picks
    the start, so a flat or multi-modal year-1 posterior does not trap the local optimiser;
    with a Gaussian prior the start is its centre. The optimiser is a bounded nonlinear least
    squares (the negative log-posterior is half a sum of squared standardised residuals).
    The covariance is the inverse Gauss-Newton Hessian, always positive definite.

    Returns
    -------
    x_map : ndarray, shape [d]
    cov : ndarray, shape [d, d]
    """
    from scipy.optimize import least_squares
    b = ld.prior.bounds
    span = np.diff(b, axis=1).ravel()
    if ld.prior.is_uniform:
        axes = [np.linspace(lo, hi, 21) for lo, hi in b]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(b))
        lp = ld.batch(grid)
        if not np.isfinite(lp).any():
            raise CalibrationError("log-posterior is -inf on the whole design box")
        x0 = grid[int(np.argmax(lp))]
    else:
        x0 = np.clip(ld.prior.centre, b[:, 0], b[:, 1])
    # least_squares wants a strictly interior start.
    x0 = np.clip(x0, b[:, 0] + 1e-9 * span, b[:, 1] - 1e-9 * span)
    fit = least_squares(lambda x: ld.residuals(x, with_prior=True), x0,
                        bounds=(b[:, 0], b[:, 1]), x_scale=span, method="trf")
    x = fit.x
    J = _jacobian(ld, x)
    H = J.T @ J + ld.prior.precision()
    # A floor on the curvature: a flat direction gets at most a box-wide proposal.
    H = H + np.diag(1.0 / span ** 2)
    return x, np.linalg.inv(H)


def _initial_states(rng: np.random.Generator, x_map: np.ndarray, cov: np.ndarray,
                    prior: Prior, chains: int) -> np.ndarray:
    """Dispersed starting points: N(MAP, (2 sd)^2) draws kept inside the box."""
    L = np.linalg.cholesky(cov)
    out = []
    while len(out) < chains:
        x = x_map + 2.0 * L @ rng.standard_normal(len(x_map))
        if prior.inside(x)[0]:
            out.append(x)
        elif rng.random() < 0.05:  # stuck against a wall: fall back to the MAP itself
            out.append(x_map.copy())
    return np.array(out)


def plan_chains(ld: LogDensity, chains: int, seed: int) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
    """Starting points and proposal covariance of one unit-year's chains.

    The proposal is Gaussian with covariance ``2.38^2/d`` times the Laplace covariance at the
    MAP (the optimal random-walk scale for a Gaussian target); the starting points are
    dispersed around the MAP (see :func:`_initial_states`).

    Returns
    -------
    starts : ndarray, shape [chains, d]
    proposal_cov : ndarray, shape [d, d]
    x_map : ndarray, shape [d]
    """
    x_map, cov = find_map(ld)
    starts = _initial_states(np.random.default_rng(seed), x_map, cov, ld.prior, chains)
    return starts, 2.38 ** 2 / len(x_map) * cov, x_map


def run_chain(ld: LogDensity, start: np.ndarray, proposal_cov: np.ndarray, samples: int,
              burn_in: int, seed: int, thin: int = 1) -> tuple[np.ndarray, float]:
    """One OpenTURNS random-walk Metropolis-Hastings chain, burn-in removed.

    OpenTURNS adapts the proposal scale during the burn-in only, and ``getSample(n)``
    returns the burn-in with the chain (OpenTURNS 1.27), so the first ``burn_in`` draws are
    dropped here.

    Parameters
    ----------
    ld : LogDensity
    start : ndarray, shape [d]
    proposal_cov : ndarray, shape [d, d]
    samples, burn_in : int
        Kept and discarded draws.
    seed : int
        Seed of OpenTURNS' generator for this chain.
    thin : int
        Run ``samples * thin`` steps after the burn-in and keep every ``thin``-th.

    Returns
    -------
    draws : ndarray, shape [samples, d]
    acceptance : float
        Fraction of accepted moves after the burn-in.
    """
    import openturns as ot
    d = len(start)
    proposal = ot.Normal([0.0] * d, ot.CovarianceMatrix(np.asarray(proposal_cov).tolist()))
    support = ot.Interval(ld.prior.bounds[:, 0].tolist(), ld.prior.bounds[:, 1].tolist())
    ot.RandomGenerator.SetSeed(int(seed) % (2 ** 31))
    mh = ot.RandomWalkMetropolisHastings(ld.as_openturns(), support, list(map(float, start)),
                                         proposal)
    mh.setBurnIn(burn_in)
    x = np.asarray(mh.getSample(burn_in + samples * thin))[burn_in:]
    # A continuous proposal never repeats a point: a repeated row is a rejection.
    acceptance = float(np.mean(np.any(np.diff(x, axis=0) != 0, axis=1)))
    return x[thin - 1::thin], acceptance


def sample_posterior(ld: LogDensity, chains: int, samples: int, burn_in: int,
                     seed: int, thin: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw ``chains`` random-walk Metropolis-Hastings chains from one unit-year's posterior
    (:func:`plan_chains` then :func:`run_chain` for each chain).

    Parameters
    ----------
    ld : LogDensity
    chains, samples, burn_in : int
        Number of chains, kept draws per chain, discarded draws per chain.
    seed : int
        Seeds numpy (starting points) and OpenTURNS (chain ``c`` uses ``seed + 1 + c``).
    thin : int
        Run ``samples * thin`` steps after the burn-in and keep every ``thin``-th.

    Returns
    -------
    draws : ndarray, shape [chains, samples, d]
        Post-burn-in draws, input units.
    acceptance : ndarray, shape [chains]
        Fraction of accepted moves after burn-in.
    x_map : ndarray, shape [d]
    """
    starts, cov, x_map = plan_chains(ld, chains, seed)
    out = [run_chain(ld, starts[c], cov, samples, burn_in, seed + 1 + c, thin)
           for c in range(chains)]
    return np.array([o[0] for o in out]), np.array([o[1] for o in out]), x_map


# ---------------------------------------------------------------------------------------
# One unit
# ---------------------------------------------------------------------------------------
@dataclass
class UnitPosterior:
    """Posterior of one unit's inputs, year by year.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    samples : ndarray, shape [n_y, n_s, d]
        Pooled post-burn-in draws of all chains (chain-major), input units.
    mean, median, q05, q95 : ndarray, shape [n_y, d]
    rhat, ess : ndarray, shape [n_y, d]
        Rank-normalised split R-hat and bulk effective sample size per input.
    acceptance : ndarray, shape [n_y, chains]
    noise_std : ndarray, shape [n_y]
        Output noise standard deviation used in the likelihood (output units).
    noise_source : str
        ``"file"``, ``"config"`` or ``"estimated"``.
    surrogate_var_ratio : ndarray, shape [n_y]
        Mean over time steps of surrogate predictive variance / noise variance.
    """

    years: np.ndarray
    samples: np.ndarray
    mean: np.ndarray
    median: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    rhat: np.ndarray
    ess: np.ndarray
    acceptance: np.ndarray
    noise_std: np.ndarray
    noise_source: str
    surrogate_var_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: Goodness of fit per year (see :func:`year_fit`); empty for posteriors written before.
    fit: dict = field(default_factory=dict)

    @property
    def chains(self) -> int:
        return self.acceptance.shape[1]

    @property
    def status(self) -> np.ndarray:
        """Per year: ``ok``, ``misfit`` (the twin misses the plant), ``edge`` (the posterior
        sits on the design box's edge) or ``unconverged``; all ``ok`` when not recorded."""
        st = self.fit.get("status")
        return np.asarray(st) if st is not None else np.full(len(self.years), STATUS_OK)


def year_prior(cfg: Config, previous: Optional[np.ndarray],
               previous_var: Optional[np.ndarray] = None) -> Prior:
    """Prior of a year: uniform on the box without a previous estimate, else Gaussian
    around it with ``prior_width * range`` (plus the previous posterior variance when
    ``calibrate.prior_carry_variance`` is set)."""
    bounds = cfg.model.bounds
    if previous is None:
        return Prior.uniform(bounds)
    var = (cfg.calibrate.prior_width * np.diff(bounds, axis=1).ravel()) ** 2
    if cfg.calibrate.prior_carry_variance and previous_var is not None:
        var = var + previous_var
    return Prior.gaussian(bounds, previous, np.sqrt(var))


@dataclass
class _ChainTask:
    """Everything a worker needs to run one chain of one unit-year (picklable)."""

    prior: Prior
    obs_row: np.ndarray
    noise_var: np.ndarray
    start: np.ndarray
    proposal_cov: np.ndarray
    samples: int
    burn_in: int
    seed: int
    thin: int


def _run_task(surrogate, task: _ChainTask) -> tuple[np.ndarray, float]:
    ld = make_log_density(surrogate, task.obs_row, task.noise_var, task.prior)
    return run_chain(ld, task.start, task.proposal_cov, task.samples, task.burn_in, task.seed,
                     task.thin)


class _UnitRun:
    """One unit's calibration, advanced a year at a time.

    :meth:`plan` sets up the next year (prior, noise, MAP, starting points) and returns its
    chain tasks; :meth:`finish` takes their results. The serial path runs the tasks in turn,
    the parallel path spreads the tasks of every unit's year over worker processes; both give
    identical arrays.
    """

    def __init__(self, surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                 noise_source: str):
        cc = cfg.calibrate
        self.surrogate, self.cfg, self.seed, self.source = surrogate, cfg, rng_seed, noise_source
        self.years = np.asarray(years, dtype=np.int64)
        self.flows = np.atleast_2d(np.asarray(flows, float))
        n_y, d = len(self.years), len(cfg.model.input_names)
        self.noise = np.broadcast_to(np.asarray(noise_std, float), (n_y,)).copy()
        self.stats = {k: np.empty((n_y, d))
                      for k in ("mean", "median", "q05", "q95", "rhat", "ess")}
        self.samples = np.empty((n_y, cc.chains * cc.samples, d))
        self.acc = np.empty((n_y, cc.chains))
        self.ratio = np.empty(n_y)
        self.fits: list[dict] = []
        self.k = 0
        self.ext = 0             # how many times year k's chains were lengthened
        self.prev = self.prev_var = None

    @property
    def done(self) -> bool:
        return self.k >= len(self.years)

    def plan(self) -> list[_ChainTask]:
        cc, k = self.cfg.calibrate, self.k
        prior = year_prior(self.cfg, self.prev, self.prev_var)
        # The surrogate's variance is held at its value at the prior's centre: computing it
        # costs ~4 likelihood evaluations and it is 3 orders of magnitude below the noise.
        s_var = self.surrogate.predict_with_var(prior.location[None, :])[1][0]
        total = self.noise[k] ** 2 + s_var
        self.ratio[k] = float(np.mean(s_var) / self.noise[k] ** 2)
        ld = make_log_density(self.surrogate, self.flows[k], total, prior)
        self._total, self._prior = total, prior
        seed = self.seed + 97 * k
        starts, cov, _ = plan_chains(ld, cc.chains, seed)
        # The year-1 posterior (uniform prior) is wider and more curved than the Laplace
        # shape of the proposal: its chains mix about half as well, so they run twice as long.
        # A year sampled again (poor R-hat or ESS) runs 2^ext times longer, thinned to the
        # same number of kept draws, from fresh seeds.
        thin = (2 if prior.is_uniform else 1) * 2 ** self.ext
        burn = cc.burn_in * 2 ** self.ext
        seed = seed + 7919 * self.ext
        return [_ChainTask(prior, self.flows[k], total, starts[c], cov, cc.samples, burn,
                           seed + 1 + c, thin) for c in range(cc.chains)]

    def finish(self, results: list[tuple[np.ndarray, float]]) -> None:
        cc, k = self.cfg.calibrate, self.k
        draws = np.array([r[0] for r in results])          # [chains, samples, d]
        d = draws.shape[2]
        rhat = np.array([split_rhat(draws[:, :, j]) for j in range(d)])
        n_eff = np.array([ess(draws[:, :, j], rank_normalize=True) for j in range(d)])
        converged = bool(np.all(rhat <= cc.rhat_warn) and np.all(n_eff >= cc.ess_warn))
        if not converged and self.ext < cc.max_extensions:
            self.ext += 1          # sample this year again, longer (plan() sees ext)
            return
        self.acc[k] = [r[1] for r in results]
        pooled = draws.reshape(-1, d)
        self.samples[k] = pooled
        st = self.stats
        st["mean"][k] = pooled.mean(axis=0)
        st["median"][k] = np.median(pooled, axis=0)
        st["q05"][k], st["q95"][k] = np.quantile(pooled, [0.05, 0.95], axis=0)
        st["rhat"][k], st["ess"][k] = rhat, n_eff
        fit = year_fit(self.surrogate, self.cfg, self.flows[k], self._total, pooled,
                       self._prior.bounds)
        fit.update(extensions=self.ext, converged=converged)
        if fit["status"] == STATUS_OK and not converged:
            fit["status"] = STATUS_UNCONVERGED
        self.fits.append(fit)
        self.prev, self.prev_var = st["mean"][k], pooled.var(axis=0)
        self.k += 1
        self.ext = 0

    def result(self) -> UnitPosterior:
        fit = {key: np.array([f[key] for f in self.fits]) for key in FIT_FIELDS}
        return UnitPosterior(years=self.years, samples=self.samples, acceptance=self.acc,
                             noise_std=self.noise, noise_source=self.source,
                             surrogate_var_ratio=self.ratio, fit=fit, **self.stats)


#: Per-year goodness-of-fit fields: (units, description). ``window`` indexes the
#: config's diagnose windows (recorded as the posterior's ``fit_windows`` attribute).
FIT_FIELDS = {
    "rms": ("1", "RMS of the standardised residual at the posterior mean, in noise sd [year]"),
    "p_chi2": ("1", "p-value of the residual's chi-square (n - d dof) [year]"),
    "p_ljung_box": ("1", "Ljung-Box p-value of the residual (structure) [year]"),
    "window": ("1", "index of the window where the residual RMS is largest [year]"),
    "window_rms": ("1", "residual RMS in that window, in noise sd [year]"),
    "edge_share": ("1", "share of draws within edge_margin of a box bound [year, input]"),
    "extensions": ("1", "times the year's chains were lengthened for convergence [year]"),
    "converged": ("1", "1 when R-hat and ESS met calibrate.rhat_warn/ess_warn [year]"),
    "status": ("1", "ok | misfit | edge | unconverged [year]"),
}


def year_fit(surrogate, cfg: Config, y: np.ndarray, total_var: np.ndarray,
             draws: np.ndarray, bounds: np.ndarray) -> dict:
    """Goodness of fit of one calibrated year.

    The residual of the observation against the twin at the posterior mean, standardised
    by the likelihood's own variance (noise + surrogate), is tested for size (chi-square,
    n - d degrees of freedom) and for structure (Ljung-Box, ``diagnose.ljung_box_lags``);
    its RMS per diagnose window says where the twin misses. The draws' share near a box
    bound says whether the plant needs inputs outside the twin's box.

    Parameters
    ----------
    y : ndarray, shape [n_t]
        The observation (output units); NaN = missing.
    total_var : ndarray, shape [n_t]
        Likelihood variance per time step (output units squared).
    draws : ndarray, shape [n_s, d]
        Posterior draws (input units).
    bounds : ndarray, shape [d, 2]
        The design box.

    Returns
    -------
    dict
        The fields of :data:`FIT_FIELDS` but ``extensions``/``converged``; ``status`` is
        ``misfit``, ``edge`` or ``ok``.
    """
    from scipy import stats

    from .diagnose.stats import ljung_box
    cc = cfg.calibrate
    d = draws.shape[1]
    pred = surrogate.predict(draws.mean(axis=0)[None, :])[0]
    z = (np.asarray(y, float) - pred) / np.sqrt(total_var)
    ok = np.isfinite(z)
    n = int(ok.sum())
    chi2 = float(np.sum(z[ok] ** 2))
    rms = float(np.sqrt(chi2 / max(n, 1)))
    p_chi2 = float(stats.chi2.sf(chi2, max(n - d, 1)))
    p_lb = ljung_box(z, cfg.diagnose.ljung_box_lags)
    t = surrogate.time
    wins = list(cfg.diagnose_windows().values())
    w_rms = np.array([np.sqrt(np.mean(z[(t >= w.start) & (t < w.stop) & ok] ** 2))
                      if np.any((t >= w.start) & (t < w.stop) & ok) else 0.0 for w in wins])
    width = bounds[:, 1] - bounds[:, 0]
    near = (draws <= bounds[:, 0] + cc.edge_margin * width) | \
           (draws >= bounds[:, 1] - cc.edge_margin * width)
    edge = near.mean(axis=0)
    misfit = rms > cc.fit_min_rms and min(p_chi2, p_lb) < cc.fit_alpha
    status = STATUS_MISFIT if misfit else STATUS_EDGE if edge.max() > cc.edge_share \
        else STATUS_OK
    return {"rms": rms, "p_chi2": p_chi2, "p_ljung_box": p_lb,
            "window": int(np.argmax(w_rms)), "window_rms": float(w_rms.max()),
            "edge_share": edge, "status": status}


def calibrate_unit(surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                   noise_source: str = "file") -> UnitPosterior:
    """Posterior of one unit's inputs for each of its years, in year order (in-process).

    Parameters
    ----------
    surrogate : Surrogate
    cfg : Config
        Uses ``model`` (box) and ``calibrate`` (chains, samples, burn-in, prior width).
    years : array of int, shape [n_y]
    flows : ndarray, shape [n_y, n_t]
        Measured output (its units) on the surrogate's time grid; NaN = missing.
    noise_std : float or ndarray, shape [n_y]
        Output noise standard deviation (output units).
    rng_seed : int
        Seed of this unit's draws (year ``k`` uses ``rng_seed + 97 * k``, as
        :func:`sample_posterior` would).
    noise_source : str
        Recorded with the result.
    """
    run = _UnitRun(surrogate, cfg, years, flows, noise_std, rng_seed, noise_source)
    while not run.done:
        run.finish([_run_task(surrogate, t) for t in run.plan()])
    return run.result()


def estimate_noise(surrogate, cfg: Config, flows: np.ndarray) -> float:
    """Output noise standard deviation (output units) of one unit from its own data.

    Each year is fitted by least squares (no prior) over the box; the residuals of all the
    unit's years are pooled, with ``d`` degrees of freedom taken per year:
    ``s^2 = sum RSS / (n_obs - d * n_y)``.
    """
    flows = np.atleast_2d(flows)
    bounds = cfg.model.bounds
    d = len(bounds)
    rss, dof = 0.0, 0
    for row in flows:
        # Unit variance: find_map is then the plain (bounded) least-squares fit.
        ld = make_log_density(surrogate, row, 1.0, Prior.uniform(bounds))
        x, _ = find_map(ld)
        rss += float(np.sum(ld.residuals(x) ** 2))
        dof += int(ld.mask.sum()) - d
    if dof <= 0:
        raise CalibrationError(f"too few samples ({dof + d * len(flows)}) to estimate the noise "
                               "level; set calibrate.noise_std")
    return float(np.sqrt(rss / dof))


# ---------------------------------------------------------------------------------------
# Stage entry point
# ---------------------------------------------------------------------------------------
@dataclass
class CalibrateSummary:
    """What :func:`calibrate` did; ``as_dict`` is the ``--json`` output."""

    input_names: list[str]
    posterior: dict[str, UnitPosterior]
    warnings: list[str]
    output: str
    truth_check: Optional[dict] = None
    #: Names of the windows the fit's ``window`` indexes.
    windows: list = field(default_factory=list)

    def as_dict(self) -> dict:
        units = {}
        for u, p in self.posterior.items():
            params = {name: {stat: getattr(p, stat)[:, j].tolist()
                             for stat in ("mean", "median", "q05", "q95")}
                      for j, name in enumerate(self.input_names)}
            f = p.fit
            fit = {"status": [str(v) for v in p.status],
                   "rms": np.round(f["rms"], 3).tolist(),
                   "p_chi2": [float(f"{v:.3g}") for v in f["p_chi2"]],
                   "p_ljung_box": [float(f"{v:.3g}") for v in f["p_ljung_box"]],
                   "worst_window": [self.windows[i] for i in f["window"]],
                   "worst_window_rms": np.round(f["window_rms"], 3).tolist(),
                   "edge_share": np.round(f["edge_share"], 3).tolist(),
                   "extensions": f["extensions"].tolist()} if f else {}
            units[u] = {"years": p.years.tolist(), "params": params, "fit": fit}
        out = {
            "units": units,
            "noise": {u: {"std": float(p.noise_std[0]), "source": p.noise_source}
                      for u, p in self.posterior.items()},
            "diagnostics": {u: {"rhat": p.rhat.tolist(), "ess": p.ess.tolist(),
                                "acceptance": p.acceptance.tolist()}
                            for u, p in self.posterior.items()},
            "warnings": list(self.warnings),
            "output": self.output,
        }
        if self.truth_check is not None:
            out["truth_check"] = self.truth_check
        return out


def _unit_seed(cfg: Config, unit: str) -> int:
    # From the unit's name, not its position: adding a unit does not change the others.
    return (cfg.seed + SEED_OFFSET + zlib.crc32(unit.encode())) % (2 ** 31 - 10 ** 6)


def _noise_for(cfg: Config, u) -> tuple[Optional[float], str]:
    if cfg.model.output.name in u.noise_std:
        return float(u.noise_std[cfg.model.output.name]), "file"
    if cfg.calibrate.noise_std is not None:
        return float(cfg.calibrate.noise_std), "config"
    return None, "estimated"


_worker = {}


def _init_worker(surrogate, surrogate_path) -> None:
    if surrogate is None:  # spawned, not forked: rebuild from the file
        from .reduce import read_surrogate
        surrogate = read_surrogate(surrogate_path)
    _worker["surrogate"] = surrogate


def _work(task: _ChainTask):
    return _run_task(_worker["surrogate"], task)


def _check_inputs(cfg: Config, surrogate, surrogate_path, obs) -> None:
    from .reduce import check_made_for
    check_made_for(cfg, surrogate_path, surrogate.input_names, surrogate.time,
                   surrogate.bounds, "simulate and reduce")
    t_s, t_o = np.asarray(surrogate.time), np.asarray(obs.time)
    if t_s.shape != t_o.shape or not np.allclose(t_s, t_o, rtol=0, atol=1e-6):
        raise InputDataError(
            f"{obs.path}: time grid ({t_o.size} samples, {t_o[0]:g}..{t_o[-1]:g} s) differs "
            f"from the surrogate's in {surrogate_path} ({t_s.size} samples, "
            f"{t_s[0]:g}..{t_s[-1]:g} s)")
    check_observed_range(cfg, surrogate, obs)


#: Observed values beyond the simulated range by more than this many times its width are
#: taken for a unit or scale mistake (or a broken sensor), not for a degraded machine.
RANGE_FACTOR = 1.0


def check_observed_range(cfg: Config, surrogate, obs) -> None:
    """Observed output values must lie near what the design's simulations produced.

    Raises
    ------
    InputDataError
        A value further than ``RANGE_FACTOR`` times the simulated range from it, naming the
        unit, year, time and value."""
    train = surrogate.training_outputs()
    lo, hi = float(np.min(train)), float(np.max(train))
    width = max(hi - lo, abs(hi), 1e-300)
    low, high = lo - RANGE_FACTOR * width, hi + RANGE_FACTOR * width
    name, units = cfg.model.output.name, cfg.model.output.units
    for unit in obs.units:
        y = obs.output_of(unit)
        with np.errstate(invalid="ignore"):
            bad = (y < low) | (y > high)
        if bad.any():
            k, j = np.argwhere(bad)[0]
            raise InputDataError(
                f"{obs.path}: /units/{unit}/{name} year {obs.units[unit].years[k]} at "
                f"t = {obs.time[j]:g} s is {y[k, j]:g} {units}, far outside anything the "
                f"design's simulations produced ({lo:.4g} to {hi:.4g} {units}); check the "
                "units and the channel")


def calibrate(cfg: Config, surrogate_path: str | os.PathLike,
              observations_path: str | os.PathLike, output: str | os.PathLike,
              truth_path: str | os.PathLike | None = None,
              progress: Optional[Callable[[int, int], None]] = None) -> CalibrateSummary:
    """Calibrate every unit of an observations file and write ``posterior.h5``.

    Years within a unit run in order (each year's prior is centred on the previous estimate);
    the chains of every unit's same year run in parallel worker processes
    (``calibrate.workers``; 0 = one per core, 1 = in this process). Results do not depend on
    the number of workers.

    Parameters
    ----------
    cfg : Config
    surrogate_path, observations_path : path-like
        ``twinmon.surrogate/1`` and ``twinmon.observations/1`` artifacts.
    output : path-like
        ``posterior.h5`` to write.
    truth_path : path-like, optional
        A ``twinmon.truth/1`` file: adds the relative errors and 90 % interval coverage.
    progress : callable(done, total), optional
        Called as unit-years complete.

    Raises
    ------
    ArtifactError
        Surrogate inputs or box unlike the config's.
    InputDataError
        Observations on another time grid than the surrogate.
    """
    from .reduce import read_surrogate
    surrogate = read_surrogate(surrogate_path)
    obs = read_observations(observations_path, cfg.model.output.name)
    _check_inputs(cfg, surrogate, surrogate_path, obs)
    truth = None
    if truth_path is not None:
        from .fabricate import read_truth
        truth = read_truth(truth_path)
        missing = [u for u in obs.units if u not in truth.inputs]
        if missing:
            raise ArtifactError(f"{truth_path}: no truth for unit {missing[0]!r}")

    runs = {}
    for unit, u in obs.units.items():
        noise, source = _noise_for(cfg, u)
        y = obs.output_of(unit)
        if noise is None:
            noise = estimate_noise(surrogate, cfg, y)
        runs[unit] = _UnitRun(surrogate, cfg, u.years, y, noise, _unit_seed(cfg, unit), source)
    total = sum(len(r.years) for r in runs.values())
    n_tasks = len(runs) * cfg.calibrate.chains
    workers = min(cfg.calibrate.workers or len(os.sched_getaffinity(0)), n_tasks)
    if workers <= 1:
        for run in runs.values():
            while not run.done:
                run.finish([_run_task(surrogate, t) for t in run.plan()])
                if progress:
                    progress(sum(r.k for r in runs.values()), total)
    else:
        # Years of one unit are sequential (each prior is centred on the previous estimate),
        # so the parallel grain is the chain: every unit's chains of the same year at once.
        from concurrent.futures.process import BrokenProcessPool

        from .executors import InterruptGuard, start_pool, stop_pool
        fork = hasattr(os, "fork")
        pool = start_pool(workers, _init_worker, (surrogate if fork else None,
                                                  str(surrogate_path)))
        ok = False
        try:
            with InterruptGuard() as guard:
                _run_parallel(pool, runs, total, progress, guard)
            ok = True
        except KeyboardInterrupt:
            raise Interrupted(f"{output}: interrupted; nothing was written") from None
        except BrokenProcessPool:
            raise CalibrationError(f"{output}: a worker process died while sampling; nothing "
                                   "was written; re-run with calibrate.workers=1 to see "
                                   "why") from None
        finally:
            if ok:
                pool.shutdown(wait=True)
            else:
                stop_pool(pool)
    posterior = {unit: run.result() for unit, run in runs.items()}

    names = cfg.model.input_names
    windows = list(cfg.diagnose_windows())
    warnings = fit_warnings(posterior, names, windows, cfg) + \
        diagnostics_warnings(posterior, names, cfg)
    # The truth only feeds the summary, but it is recorded so that `twinmon run` re-runs
    # the stage (and its truth check) when it changes.
    inputs = [surrogate_path, observations_path] + ([truth_path] if truth_path else [])
    write_posterior(output, posterior, names, cfg, inputs, surrogate_id=surrogate.fingerprint())
    check = truth_check(posterior, truth, names) if truth is not None else None
    return CalibrateSummary(names, posterior, warnings, str(output), check, windows)


def _run_parallel(pool, runs: dict[str, "_UnitRun"], total: int, progress, guard) -> None:
    from concurrent.futures import wait
    while True:
        active = [r for r in runs.values() if not r.done]
        if not active:
            return
        plans = [r.plan() for r in active]
        futures = [pool.submit(_work, t) for p in plans for t in p]
        # Poll, so that a Ctrl-C stops long chains within a fraction of a second.
        while wait(futures, timeout=0.2).not_done:
            guard.check()
        guard.check()
        results = [f.result() for f in futures]
        i = 0
        for run, plan in zip(active, plans):
            run.finish(results[i:i + len(plan)])
            i += len(plan)
        if progress:
            progress(sum(r.k for r in runs.values()), total)


def fit_warnings(posterior: dict[str, UnitPosterior], names: list[str], windows: list,
                 cfg: Config) -> list[str]:
    """One line per unit-year whose twin misses the plant, sits on the box edge, or did not
    converge even with longer chains."""
    out = []
    for unit, p in posterior.items():
        f = p.fit
        for k, year in enumerate(p.years):
            st = p.status[k]
            if st == STATUS_MISFIT:
                out.append(f"{unit} year {int(year)}: the twin misses the plant: residual RMS "
                           f"{f['rms'][k]:.1f} x noise (worst in the {windows[f['window'][k]]} "
                           f"window, {f['window_rms'][k]:.1f} x), chi-square p = "
                           f"{f['p_chi2'][k]:.2g}, Ljung-Box p = {f['p_ljung_box'][k]:.2g}")
            elif st == STATUS_EDGE:
                j = int(np.argmax(f["edge_share"][k]))
                out.append(f"{unit} year {int(year)}: {100 * f['edge_share'][k][j]:.0f} % of "
                           f"the posterior of {names[j]} sits on the design box's edge")
            if not f["converged"][k]:
                out.append(f"{unit} year {int(year)}: not converged after "
                           f"{f['extensions'][k]} longer run(s): unreliable")
    return out


def diagnostics_warnings(posterior: dict[str, UnitPosterior], names: list[str],
                         cfg: Config) -> list[str]:
    """One line per unit-year whose R-hat, ESS or acceptance rate is poor."""
    cc = cfg.calibrate
    out = []
    for unit, p in posterior.items():
        for k, year in enumerate(p.years):
            bad = []
            for j, name in enumerate(names):
                if not p.rhat[k, j] <= cc.rhat_warn:
                    bad.append(f"R-hat {p.rhat[k, j]:.3f} > {cc.rhat_warn:g} for {name}")
                if not p.ess[k, j] >= cc.ess_warn:
                    bad.append(f"ESS {p.ess[k, j]:.0f} < {cc.ess_warn:g} for {name}")
            lo, hi = ACCEPTANCE_RANGE
            a = p.acceptance[k]
            if np.any((a < lo) | (a > hi)):
                bad.append(f"acceptance {a.min():.2f}..{a.max():.2f} outside [{lo:g}, {hi:g}]")
            if bad:
                out.append(f"{unit} year {int(year)}: " + "; ".join(bad))
    return out


def truth_check(posterior: dict[str, UnitPosterior], truth, names: list[str]) -> dict:
    """Relative error of the posterior mean and 90 % interval coverage against a truth file.

    Returns
    -------
    dict name -> {"max_rel_error", "mean_rel_error", "coverage_90"}
        Ratios (not percent), over all units and years.
    """
    out = {}
    for j, name in enumerate(names):
        rel, cover = [], []
        for unit, p in posterior.items():
            ty = np.asarray(truth.years[unit])
            tv = np.asarray(truth.inputs[unit][name])
            idx = np.searchsorted(ty, p.years)
            if np.any(idx >= len(ty)) or np.any(ty[np.minimum(idx, len(ty) - 1)] != p.years):
                raise ArtifactError(f"truth file: unit {unit!r} lacks some observed years")
            t = tv[idx]
            rel.append(np.abs(p.mean[:, j] - t) / np.abs(t))
            cover.append((p.q05[:, j] <= t) & (t <= p.q95[:, j]))
        rel, cover = np.concatenate(rel), np.concatenate(cover)
        out[name] = {"max_rel_error": float(rel.max()), "mean_rel_error": float(rel.mean()),
                     "coverage_90": float(cover.mean())}
    return out


# ---------------------------------------------------------------------------------------
# Artifact
# ---------------------------------------------------------------------------------------
@dataclass
class Posterior:
    """A loaded ``posterior.h5``: ``input_names`` and per unit a :class:`UnitPosterior`."""

    input_names: list[str]
    units: dict[str, UnitPosterior]
    path: Path = Path("<memory>")
    #: Names of the windows ``fit/window`` indexes.
    fit_windows: list = field(default_factory=list)


_DATASETS = {
    # name: (units, description); "in" = input units (listed per input in the attrs)
    "years": ("year", "year of service of each calibration"),
    "samples": ("input units", "pooled post-burn-in MCMC draws [year, draw, input]"),
    "mean": ("input units", "posterior mean [year, input]"),
    "median": ("input units", "posterior median [year, input]"),
    "q05": ("input units", "posterior 5 % quantile [year, input]"),
    "q95": ("input units", "posterior 95 % quantile [year, input]"),
    "rhat": ("1", "rank-normalised split R-hat [year, input]"),
    "ess": ("1", "bulk effective sample size [year, input]"),
    "acceptance": ("1", "Metropolis-Hastings acceptance rate after burn-in [year, chain]"),
    "noise_std": ("output units", "output noise standard deviation used in the likelihood "
                  "[year]"),
    "surrogate_var_ratio": ("1", "mean surrogate predictive variance / noise variance [year]"),
}


def write_posterior(path, posterior: dict[str, UnitPosterior], input_names: list[str],
                    cfg: Config, inputs, surrogate_id: str = "") -> None:
    """Write ``posterior.h5`` atomically (layout in the module docstring).

    ``surrogate_id`` is the :meth:`~twinmon.reduce.Surrogate.fingerprint` of the surrogate
    the posterior was sampled through."""
    with artifacts.write_artifact(path, "posterior", config=cfg.section_yaml(*SECTIONS),
                                  inputs=inputs, seed=cfg.seed + SEED_OFFSET) as f:
        if surrogate_id:
            f.attrs["surrogate_id"] = surrogate_id
        f.attrs["input_names"] = json.dumps(list(input_names))
        f.attrs["input_units"] = json.dumps([cfg.model.inputs[n].units for n in input_names])
        for unit, p in posterior.items():
            g = f.create_group(f"units/{unit}")
            for name, (units, desc) in _DATASETS.items():
                units = cfg.model.output.units if units == "output units" else units
                artifacts.put(g, name, np.asarray(getattr(p, name)), units, desc)
            g.attrs["noise_source"] = p.noise_source
            for key, (units, desc) in (FIT_FIELDS.items() if p.fit else ()):
                data = np.asarray(p.fit[key])
                if key == "status":
                    data = np.array([str(v) for v in data], dtype=h5py.string_dtype())
                elif data.dtype == bool:
                    data = data.astype(np.int8)
                artifacts.put(g, f"fit/{key}", data, units, desc)
        f.attrs["fit_windows"] = json.dumps(list(cfg.diagnose_windows()))


def read_posterior(path: str | os.PathLike) -> Posterior:
    """Load ``posterior.h5`` (schema checked).

    Raises
    ------
    ArtifactError
        Missing file, wrong schema, missing datasets or inconsistent shapes.
    """
    path = Path(path)
    with artifacts.open_artifact(path, "posterior") as f:
        if "input_names" not in f.attrs:
            raise ArtifactError(f"{path}: root attribute input_names is missing")
        names = json.loads(f.attrs["input_names"])
        if "units" not in f or len(f["units"]) == 0:
            raise ArtifactError(f"{path}: group /units is missing or empty")
        units = {}
        for unit, g in f["units"].items():
            arrs = {n: artifacts.get(g, n, path) for n in _DATASETS
                    if n != "surrogate_var_ratio" or n in g}
            n_y, d = len(arrs["years"]), len(names)
            for n in ("mean", "median", "q05", "q95", "rhat", "ess"):
                if arrs[n].shape != (n_y, d):
                    raise ArtifactError(f"{path}: /units/{unit}/{n} has shape {arrs[n].shape}, "
                                        f"expected ({n_y}, {d})")
            if arrs["samples"].ndim != 3 or arrs["samples"].shape[::2] != (n_y, d):
                raise ArtifactError(f"{path}: /units/{unit}/samples has shape "
                                    f"{arrs['samples'].shape}, expected ({n_y}, n_s, {d})")
            src = g.attrs.get("noise_source", "")
            fit = {}
            if "fit" in g:
                fit = {key: artifacts.get(g["fit"], key, path) for key in FIT_FIELDS}
                fit["converged"] = fit["converged"].astype(bool)
                if len(fit["status"]) != n_y:
                    raise ArtifactError(f"{path}: /units/{unit}/fit/status has "
                                        f"{len(fit['status'])} years, expected {n_y}")
            units[unit] = UnitPosterior(noise_source=src.decode() if isinstance(src, bytes)
                                        else str(src), fit=fit, **arrs)
        windows = json.loads(f.attrs["fit_windows"]) if "fit_windows" in f.attrs else []
        return Posterior(names, units, path, windows)
