"""Covariance of the yearly estimates' errors and of the inputs' slopes.

The yearly estimates scatter about their trend by the true year-to-year variation *and* by
their own estimation error; the sequential method centres each year's prior on the previous
year's estimate, so an error carries into the next years (:func:`filter_error_covariance`,
from the config: :func:`estimate_error_covariance`). Along a direction the data barely
identify (two inputs trading off) those errors drift together and the regression residuals
do not show them: the slopes' covariance (:func:`slope_covariance`) is the residual scatter
raised, direction by direction, to the estimation errors (:func:`cover`). Detection and
attribution (:mod:`.judge`) test the slopes with it; the state predictive
(:mod:`.predictive`) combines its two terms with the same :func:`cover`.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..config import Config


def filter_error_covariance(post_cov: np.ndarray, prior_var: Optional[np.ndarray],
                            carry: bool = True) -> np.ndarray:
    """Covariance of the yearly estimates' errors across years, shape [n, n, d, d].

    The sequential method centres each year's prior on the previous year's estimate (a
    Kalman filter of a random walk, prior covariance ``Q_k = diag(prior_var [+ diag
    P_{k-1}])``), so an error carries into the next years: with the gain ``A_k = P_k
    Q_k^-1`` (``P_k`` year k's posterior covariance [d, d]), ``e_k = A_k e_{k-1} + ...`` and
    ``cov(e_k, e_l) = A_k ... A_{l+1} P_l`` for ``k > l``. Along a direction the data barely
    identify (two inputs trading off) ``A_k`` is near the identity and the errors drift
    together: the regression residuals do not show them, and the yearly variances alone
    (independent errors) undercount them. The first year (uniform prior) carries nothing in.

    Parameters
    ----------
    post_cov : ndarray, shape [n, d, d]
        Posterior covariance of each year, in the order calibrated.
    prior_var : ndarray, shape [d], or None
        The year-to-year prior variance (``(calibrate.prior_width * range)^2``); None: the
        estimates are independent across years (a method without a sequential prior).
    carry : bool
        ``calibrate.prior_carry_variance``: the previous posterior variance is added.
    """
    P = np.asarray(post_cov, float)
    n, d = P.shape[:2]
    E = np.zeros((n, n, d, d))
    for k in range(n):
        E[k, k] = P[k]
    if prior_var is None:
        return E
    gains = filter_gains(P, prior_var, carry)
    for m in range(n):
        M = P[m]
        for k in range(m + 1, n):
            M = gains[k] @ M
            E[k, m], E[m, k] = M, M.T
    return E


def filter_gains(post_cov: np.ndarray, prior_var: np.ndarray, carry: bool = True) -> list:
    """The sequential prior's gains ``A_k = P_k Q_k^-1`` per year [d, d] (year 1's, under
    the uniform prior, 0): ``Q_k = diag(prior_var [+ diag P_{k-1}])``
    (:func:`filter_error_covariance`)."""
    P = np.asarray(post_cov, float)
    gains = [np.zeros(P.shape[1:])]
    for k in range(1, len(P)):
        q = np.asarray(prior_var, float) + (np.diag(P[k - 1]) if carry else 0.0)
        gains.append(P[k] / q[None, :])
    return gains


def estimate_error_covariance(cfg: Config, post_cov: np.ndarray, sequential: bool) -> np.ndarray:
    """The yearly estimates' error covariance across years [n, n, d, d]
    (:func:`filter_error_covariance`) from the posterior covariances [n, d, d]: carried
    from year to year through the sequential prior (``calibrate.prior_width``,
    ``prior_carry_variance``), or independent across years for the joint method
    (``sequential`` False), whose years are tied by the trend instead."""
    prior_var = ((cfg.calibrate.prior_width * np.diff(cfg.model.bounds, axis=1).ravel()) ** 2
                 if sequential else None)
    return filter_error_covariance(post_cov, prior_var, cfg.calibrate.prior_carry_variance)


def slope_covariance(trends: list, residuals: np.ndarray, years: Optional[np.ndarray] = None,
                     post_cov: Optional[np.ndarray] = None) -> np.ndarray:
    """Covariance [d, d] of the inputs' OLS slopes.

    The larger, direction by direction (:func:`cover`), of ``S / Sxx`` -- ``S`` the
    covariance of the regression residuals [n, d] (``n - 2`` dof; all inputs share one
    design) -- and, with the estimates' error covariance ``post_cov`` of ``years`` [n],
    ``sum_kl w_k w_l cov(e_k, e_l)`` (``w_k = (k - kbar) / Sxx``, the slope's weights).
    ``post_cov`` is [n, n, d, d] (:func:`filter_error_covariance`: the errors the sequential
    prior carries from year to year, which the residual scatter does not show) or [n, d, d]
    (the yearly posterior covariances, errors taken independent). On
    ``benchmarks/prognosis.py`` (seed 11, flow only) the slopes' errors against the truth
    are then 1.04 / 1.06 of their standard errors (damping / pump); with independent errors
    and the sum of the two terms they were 1.10 / 1.28, with the residuals alone 2.1 / 2.7."""
    n = residuals.shape[0]
    se = np.array([t.slope_se for t in trends])
    post = None
    if post_cov is not None and years is not None and len(years) >= 3:
        x = np.asarray(years, float)
        w = (x - x.mean()) / np.sum((x - x.mean()) ** 2)
        pc = np.asarray(post_cov, float)
        post = (np.einsum("k,l,klij->ij", w, w, pc) if pc.ndim == 4
                else np.einsum("k,kij->ij", w ** 2, pc))
    if n < 3:       # too few common years (a recent repair) to estimate the correlation
        return np.diag(se ** 2) if post is None else cover(np.diag(se ** 2), post)
    S = residuals.T @ residuals / max(n - 2, 1)
    C = S / trends[0].sxx
    # Keep the per-input variances exactly those of the single-input fits.
    dg = np.sqrt(np.clip(np.diag(C), 1e-300, None))
    R = C / np.outer(dg, dg)
    w, V = np.linalg.eigh(R)
    R = (V * np.maximum(w, 1e-9)) @ V.T
    dg2 = np.sqrt(np.diag(R))
    R = R / np.outer(dg2, dg2)
    return R * np.outer(se, se) if post is None else cover(R * np.outer(se, se), post)


def cover(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A`` raised to ``B`` along the directions where ``B`` is larger: ``A + (B - A)_+``
    (the positive part of the difference, by eigenvalues)."""
    w, V = np.linalg.eigh(B - A)
    return A + (V * np.maximum(w, 0.0)) @ V.T


#: A sequential unit whose yearly estimates of an input show less than this share of a drift
#: (:func:`filter_attenuation`) gets an unreliable prognosis: its line and its test see
#: less than half of what happens.
MIN_ATTENUATION = 0.5


def filter_attenuation(cfg: Config, years: np.ndarray, post_cov: np.ndarray,
                       since: np.ndarray) -> np.ndarray:
    """How much of a steady drift of each input its sequential yearly estimates show.

    Each year's prior is centred on the year before (:func:`filter_error_covariance`'s
    gains ``A_k = P_k Q_k^-1``): in expectation the estimates follow ``m_k = A_k m_{k-1} +
    (I - A_k) theta_k``. Where the data give little a year (``A_k`` near ``I``), the
    estimates lag a drift: the slope of the line through them is a fraction of the truth's,
    and the slope's error, taken about that line, does not show it (a pump recorded at 10x
    the usual noise: a true -0.10/yr read as +0.006 +- 0.006). The fraction is computed from
    the gains alone, for a unit drift of each input in turn (the others steady) from year 1.

    Parameters
    ----------
    years : ndarray of int, shape [K]
    post_cov : ndarray, shape [K, d, d]
        The yearly posterior covariances, in the order calibrated.
    since : ndarray of int, shape [d]
        First year of each input's current trend (its line is fitted from there).

    Returns
    -------
    ndarray, shape [d]
        Per input, the slope of its expected estimates over its current trend's years for a
        drift of 1 a year (1: no lag); NaN where that trend has fewer than 3 years.
    """
    P = np.asarray(post_cov, float)
    K, d = P.shape[:2]
    t = np.asarray(years, float)
    q0 = (cfg.calibrate.prior_width * np.diff(cfg.model.bounds, axis=1).ravel()) ** 2
    gains = filter_gains(P, q0, cfg.calibrate.prior_carry_variance)
    out = np.full(d, np.nan)
    for j in range(d):
        seg = t >= since[j]
        if seg.sum() < 3:
            continue
        m = np.zeros(d)
        path = np.empty(K)
        for k in range(K):
            theta = np.zeros(d)
            theta[j] = t[k]
            m = gains[k] @ m + (theta - gains[k] @ theta)
            path[k] = m[j]
        x = t[seg] - t[seg].mean()
        out[j] = float(x @ path[seg] / (x @ x))
    return out
