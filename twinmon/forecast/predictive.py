"""The future inputs' distribution, and its Monte Carlo draws.

Two forms for a sequentially calibrated unit (``forecast.predictive``):

* ``state`` (the default) -- where the unit's inputs will truly be: the trend line's
  uncertainty, including estimation errors carried from year to year, plus the true
  year-to-year variation beyond the estimation error (:func:`state_predictive`,
  :func:`sample_state`, :func:`state_interval`);
* ``estimate`` -- the paper's: each input's Student-t predictive of a *new yearly
  estimate* of its trend, the inputs tied by the correlation of their regression residuals
  (:func:`residual_correlation`, :func:`sample_predictive`).

A jointly calibrated unit draws its future from its own posterior trend instead
(:func:`twinmon.calibrate.trend.trend_predictive`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .covariance import cover
from .trend import Trend


def residual_correlation(residuals: np.ndarray) -> np.ndarray:
    """Correlation matrix [d, d] of the inputs' regression residuals [n, d] (identity for a
    constant column), made positive definite."""
    d = residuals.shape[1]
    sd = residuals.std(axis=0)
    R = np.eye(d)
    ok = sd > 0
    if ok.sum() > 1:
        R[np.ix_(ok, ok)] = np.corrcoef(residuals[:, ok], rowvar=False)
    w, V = np.linalg.eigh(R)
    R = (V * np.maximum(w, 1e-9)) @ V.T
    dg = np.sqrt(np.diag(R))
    return R / np.outer(dg, dg)


def sample_predictive(trends: list[Trend], years: np.ndarray, corr: np.ndarray, size: int,
                      rng: np.random.Generator) -> np.ndarray:
    """Joint input samples for new observations in the given years.

    Each input's marginal is the Student t predictive of its trend (n - 2 dof, location the
    line, scale ``s * sqrt(1 + 1/n + (x0 - xbar)^2 / Sxx)``); the inputs are tied by a
    multivariate t with correlation ``corr`` (one shared chi-square draw per sample).

    Parameters
    ----------
    trends : list of Trend, length d
    years : ndarray, shape [h]
    corr : ndarray, shape [d, d]
    size : int
        Samples per year, n_s.
    rng : numpy Generator

    Returns
    -------
    ndarray, shape [h, n_s, d]
        Input values (input units).
    """
    h, d = len(years), len(trends)
    dof = trends[0].dof
    L = np.linalg.cholesky(corr)
    z = rng.standard_normal((h, size, d)) @ L.T
    w = np.sqrt(rng.chisquare(dof, (h, size, 1)) / dof)
    loc = np.empty((h, d))
    scale = np.empty((h, d))
    for i, t in enumerate(trends):
        loc[:, i], _, _, scale[:, i] = t.predict(years)
    return loc[:, None, :] + scale[:, None, :] * z / w


@dataclass
class StatePredictive:
    """Predictive distribution of a unit's true inputs in future years.

    ``loc`` [h, d] on the trend lines; ``cov`` [h, d, d]; multivariate Student t with
    ``dof`` degrees of freedom (the trends' ``n - 2``)."""

    loc: np.ndarray
    cov: np.ndarray
    dof: int


def state_predictive(trends: list, years: np.ndarray, residuals: np.ndarray,
                     post_cov: np.ndarray, future: np.ndarray) -> StatePredictive:
    """Where the unit's inputs will truly be, not where next year's estimate will fall.

    The yearly estimates scatter around the trend by the true year-to-year variation *and*
    by their own estimation error; the paper's interval for a new observation counts both,
    so it is too wide for the state (and the failure year comes early). Here, with
    ``c(x0) = 1/n + (x0 - xbar)^2 / Sxx`` and the slope weights ``a_k(x0) = 1/n + (x0 -
    xbar)(k - xbar) / Sxx``::

        cov(x0) = cover(c(x0) S, sum_kl a_k(x0) a_l(x0) cov(e_k, e_l))  +  (S - mean_k P_k)_+

    ``S`` the residual covariance (``n - 2`` dof), ``cov(e_k, e_l)`` the covariance of
    years k and l's estimation errors (``P_k`` on the diagonal, year k's posterior
    covariance): the line's uncertainty, from the scatter or -- where larger -- from the
    estimation errors the sequential prior carries from year to year (the residuals do not
    show those: along a direction two inputs trade off, the estimates drift together), plus
    the true year-to-year variation (the scatter beyond the estimation error, made positive
    semi-definite). ``cover(A, B) = A + (B - A)_+`` takes the larger of two covariances
    direction by direction. ``forecast`` passes the yearly covariances alone (errors taken
    independent): on ``benchmarks/prognosis.py`` (seed 11) the 90 % intervals then cover
    0.77 (flow only) / 0.94 (flow + speed) of the true future inputs. With the errors'
    cross-year covariance they cover 0.92 / 0.97, but the failure year by P(unsafe) > 5 %
    comes earlier (the paper case's pump unit: year 13 instead of 14, true 15); with the
    sum of the two terms instead of ``cover``, 0.86 / 0.97 and the pump unit two years
    early.

    Parameters
    ----------
    trends : list of Trend, length d
    years : ndarray, shape [n]
        Years the residuals and posterior covariances belong to.
    residuals : ndarray, shape [n, d]
    post_cov : ndarray, shape [n, n, d, d] or [n, d, d]
        Covariance of the yearly estimates' errors across years
        (:func:`~.covariance.filter_error_covariance`), or the yearly posterior
        covariances alone (errors taken independent across years).
    future : ndarray, shape [h]
    """
    x = np.asarray(years, float)
    n = x.size
    xbar, sxx = x.mean(), float(np.sum((x - x.mean()) ** 2))
    S = residuals.T @ residuals / max(n - 2, 1)
    post_cov = np.asarray(post_cov, float)
    full = post_cov.ndim == 4
    Pbar = (np.einsum("kkij->ij", post_cov) / n) if full else post_cov.mean(axis=0)
    w, V = np.linalg.eigh(S - Pbar)
    jitter = (V * np.maximum(w, 0.0)) @ V.T
    fut = np.asarray(future, float)
    c = 1 / n + (fut - xbar) ** 2 / sxx                                    # [h]
    a = 1 / n + np.outer(fut - xbar, x - xbar) / sxx                       # [h, n]
    carried = (np.einsum("hk,hl,klij->hij", a, a, post_cov) if full
               else np.einsum("hk,kij->hij", a ** 2, post_cov))
    cov = np.array([cover(c[j] * S, carried[j]) for j in range(fut.size)]) + jitter
    loc = np.column_stack([t.intercept + t.slope * fut for t in trends])
    return StatePredictive(loc, cov, max(n - 2, 1))


def sample_state(sp: StatePredictive, size: int, rng: np.random.Generator) -> np.ndarray:
    """Input samples [h, size, d] from a :class:`StatePredictive` (one chi-square draw per
    sample shared by the inputs, as :func:`sample_predictive`)."""
    h, d = sp.loc.shape
    out = np.empty((h, size, d))
    w = np.sqrt(rng.chisquare(sp.dof, (h, size, 1)) / sp.dof)
    z = rng.standard_normal((h, size, d))
    for j in range(h):
        ev, V = np.linalg.eigh(sp.cov[j])
        L = V * np.sqrt(np.maximum(ev, 0.0))
        out[j] = sp.loc[j] + (z[j] @ L.T) / w[j]
    return out


def state_interval(sp: StatePredictive, i: int, confidence: float):
    """Centre, lower and upper bound [h] of input ``i``'s predictive interval."""
    from ..distributions import t_ppf
    q = t_ppf(0.5 + confidence / 2, sp.dof)
    sd = np.sqrt(sp.cov[:, i, i])
    return sp.loc[:, i], sp.loc[:, i] - q * sd, sp.loc[:, i] + q * sd
