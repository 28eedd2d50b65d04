"""The unnormalised posterior of one unit-year, its maximum and Laplace covariance, and the
output noise level estimated from a unit's own data."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..config import Config
from ..errors import CalibrationError


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


#: How far the residuals' excess over their second differences' level must lie beyond the
#: surrogate's own error (its predictive sd at the fits, a multiple of it) to be called
#: structure: a smooth surrogate error is in the residuals too, and on data all but
#: noise-free it is all they hold.
STRUCTURE_SURROGATE_SD = 3.0


@dataclass(frozen=True)
class NoiseEstimate:
    """The noise level of one unit's output (or channel) estimated from its own records.

    Attributes
    ----------
    std : float
        The level calibrate uses (output units): ``residual_std``, or ``difference_std``
        where the residuals hold structure (``structured``).
    residual_std : float
        From the pooled residuals of each year's least-squares fit.
    difference_std, difference_dof : float
        From the second differences of those residuals (NaN when too few).
    p_structure : float
        p-value of ``log(residual_std^2 / difference_std^2)`` (normal, variance
        ``2/difference_dof - 2/n``; NaN when not made).
    structured : bool
    """

    std: float
    residual_std: float
    difference_std: float = float("nan")
    difference_dof: float = float("nan")
    p_structure: float = float("nan")
    structured: bool = False

    @property
    def source(self) -> str:
        """``"estimated"``, or ``"differences"`` where the level is the second
        differences' (the ``noise_source`` calibrate records)."""
        return "differences" if self.structured else "estimated"

    def warning(self, unit: str, channel: str, units: str = "") -> str:
        """The line that says a unit's residuals hold structure ("" when they do not)."""
        if not self.structured:
            return ""
        u = f" {units}" if units and units != "1" else ""
        return (f"{unit}: the residuals of {channel} hold more than noise (RMS "
                f"{self.residual_std:.4g}{u} against {self.difference_std:.4g}{u} from their "
                f"second differences, p = {self.p_structure:.2g}): the twin misses the plant "
                f"somewhere; the noise level is taken as {self.difference_std:.4g}{u}, so the "
                f"years it misses fail the fit check (record the noise level, or run "
                f"diagnose)")


def estimate_noise_checked(surrogate, cfg: Config, flows: np.ndarray) -> NoiseEstimate:
    """Output noise standard deviation (output units) of one unit from its own data.

    Each year is fitted by least squares (no prior) over the box; the residuals of all the
    unit's years are pooled, with ``d`` degrees of freedom taken per year:
    ``s^2 = sum RSS / (n_obs - d * n_y)``.

    A twin that misses the plant leaves a smooth, structured residual
    that this ``s`` takes in as noise: the fit check, in units of ``s``, then passes every
    year (an unmodelled effect from year 6 of 10 read as noise twice the true level). The
    second differences of the residuals (:func:`~twinmon.diagnose.stats.plateau_noise` over
    every sample) cancel what is smooth: where ``s`` exceeds their level by a test at the
    fit check's own level (``calibrate.fit_alpha``; on log(s^2 / s_d^2), whose variance
    under white noise is 2/nu - 2/dof, the two being drawn from the same residuals), and
    by more than
    :data:`STRUCTURE_SURROGATE_SD` of the surrogate's predictive sd, the noise level is
    theirs.
    """
    from scipy.special import ndtr

    from ..diagnose.stats import plateau_noise
    from ..errors import InputDataError
    flows = np.atleast_2d(flows)
    bounds = cfg.model.bounds
    d = len(bounds)
    rss, dof, sur_var = 0.0, 0, []
    resid = np.full(flows.shape, np.nan)
    for k, row in enumerate(flows):
        if not np.isfinite(row).any():
            continue                # a further channel not recorded that year
        # Unit variance: find_map is then the plain (bounded) least-squares fit.
        ld = make_log_density(surrogate, row, 1.0, Prior.uniform(bounds))
        x, _ = find_map(ld)
        r = ld.residuals(x)
        resid[k, ld.mask] = r
        rss += float(np.sum(r ** 2))
        dof += int(ld.mask.sum()) - d
        sur_var.append(float(np.mean(surrogate.predict_var(x[None, :])[0, ld.mask])))
    if dof <= 0:
        raise CalibrationError(f"too few samples ({dof + d * len(flows)}) to estimate the noise "
                               "level; set calibrate.noise_std")
    s_r = float(np.sqrt(rss / dof))
    try:
        s_d, nu = plateau_noise(resid, np.arange(flows.shape[1], dtype=float), -np.inf)
    except InputDataError:
        return NoiseEstimate(s_r, s_r)
    # The two levels come from the same residuals: the pooled one is efficient under white
    # noise, so its covariance with the other is its own variance, and log(s_r^2 / s_d^2)
    # has variance 2/nu - 2/dof (an F test, which takes them as independent, needed a ratio
    # of 1.40 where 1.22 is significant).
    var = 2.0 / nu - 2.0 / dof
    z = math.log(s_r ** 2 / s_d ** 2) / math.sqrt(var) if var > 0 else 0.0
    p = float(ndtr(-z))
    excess = s_r ** 2 - s_d ** 2
    structured = bool(p < cfg.calibrate.fit_alpha
                      and excess > STRUCTURE_SURROGATE_SD ** 2 * float(np.mean(sur_var)))
    return NoiseEstimate(s_d if structured else s_r, s_r, s_d, nu, p, structured)


def estimate_noise(surrogate, cfg: Config, flows: np.ndarray) -> float:
    """The noise level of :func:`estimate_noise_checked` (output units)."""
    return estimate_noise_checked(surrogate, cfg, flows).std
