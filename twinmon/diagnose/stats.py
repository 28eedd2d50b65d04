"""Statistics of residuals: structure (Ljung-Box), excess from an onset on (pooled chi-square),
and the noise level when the observations do not record it.

All functions are pure numpy/scipy on arrays; nothing here runs the FMU.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.special import chdtrc

from ..errors import InputDataError


def chi2_sf(x, dof):
    """Chi-square survival function, ``scipy.stats.chi2.sf(x, dof)`` (the same values: it
    calls ``chdtrc``) without importing scipy.stats, 0.55-0.60 s at every start of
    calibrate, whose goodness-of-fit checks use it. Note ``chdtrc`` takes ``dof`` first."""
    return chdtrc(dof, x)


def ljung_box(z: np.ndarray, lags: int) -> float:
    """Ljung-Box p-value of a residual sequence (NaN dropped) for ``lags`` lags."""
    z = np.asarray(z, float)
    z = z[np.isfinite(z)]
    n = z.size
    lags = min(lags, n - 2)
    if lags < 1:
        return 1.0
    z = z - z.mean()
    c0 = float(z @ z)
    if c0 <= 0:
        return 1.0
    rho = np.array([float(z[k:] @ z[:-k]) / c0 for k in range(1, lags + 1)])
    q = n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, lags + 1)))
    return float(chi2_sf(q, lags))


def pooled_onset_pvalues(chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """p-value of the pooled chi-square of the years from each possible onset on, [n_y]."""
    c = np.cumsum(chi2[::-1])[::-1]
    d = np.cumsum(dof[::-1])[::-1]
    return chi2_sf(c, np.maximum(d, 1))


#: Second differences :func:`plateau_noise` needs before it drops outliers.
TRIM_MIN = 20


def plateau_noise(y: np.ndarray, time: np.ndarray, start: float) -> tuple[float, float]:
    """Noise standard deviation from the second differences of the samples after ``start``
    (s), where the transient is nearly flat, and the degrees of freedom the estimate carries.

    std(d2 y) = sqrt(6) sigma for white noise. Of :data:`TRIM_MIN` or more second
    differences, those further than 5 robust (MAD) deviations from their median are dropped
    as outliers (a spike, a glitch), and
    sigma is the RMS of the others about that median: the MAD alone is 2.7 times as noisy
    (on 10 years of 11 samples, sigma/true 0.14 apart against 0.10), and too low an
    estimate reads as a gap in every year.

    The estimate is a quadratic form of the noise, so its spread is that of a scaled
    chi-square whose degrees of freedom are ``(tr C)^2 / tr(C^2)``, ``C`` the covariance of
    the second differences kept (6 on the diagonal, -4 and 1 on the first two off-diagonals
    within a year): about half their number (adjacent differences share samples). The tests
    of :func:`noise_sf` count them.

    Parameters
    ----------
    y : ndarray, shape [n_y, n_t]
        One channel, NaN = missing.
    time : ndarray, shape [n_t]
        Sample times (s).
    start : float
        Start of the calm window (s); all samples if fewer than 4 lie after it.

    Returns
    -------
    (sigma, dof) : (float, float)
        In ``y``'s units; dof > 0.
    """
    sel = np.asarray(time) >= start
    if sel.sum() < 4:
        sel = np.ones(len(time), bool)
    d2 = np.diff(np.asarray(y, float)[:, sel], n=2, axis=1)          # [n_y, n_sel - 2]
    ok = np.isfinite(d2)
    if ok.sum() < 3:
        raise InputDataError("too few samples to estimate the noise; record noise_std")
    med = float(np.median(d2[ok]))
    mad = 1.4826 * float(np.median(np.abs(d2[ok] - med)))
    if ok.sum() >= TRIM_MIN and mad > 0:
        # Few differences give a MAD that may itself be tiny (two close values of five),
        # and quantised data one of zero:
        # cutting at it would keep those alone.
        with np.errstate(invalid="ignore"):
            ok &= np.abs(d2 - med) <= 5.0 * mad
    dev = (d2 - med)[ok]
    if not float(dev @ dev) > 0:
        raise InputDataError("cannot estimate the noise (flat record); record noise_std")
    s = math.sqrt(float(dev @ dev) / (6.0 * dev.size))
    n = int(ok.sum())
    lag1 = int((ok[:, 1:] & ok[:, :-1]).sum())
    lag2 = int((ok[:, 2:] & ok[:, :-2]).sum())
    dof = (6.0 * n) ** 2 / (36.0 * n + 32.0 * lag1 + 2.0 * lag2)
    return float(s), float(dof)


def estimate_noise(y: np.ndarray, time: np.ndarray, start: float) -> float:
    """Noise standard deviation of :func:`plateau_noise` alone (``y`` [n_y, n_t])."""
    return plateau_noise(y, time, start)[0]


#: Nodes of the integral over an estimated noise level in :func:`noise_sf`: logits of the
#: estimate's chi-square cdf, from 1e-13 to 1 - 1e-13 (trapezoid; the integrand is smooth
#: in the logit, and what lies beyond weighs under 1e-13).
_Z = np.linspace(-30.0, 30.0, 241)
_WZ = np.full(_Z.size, _Z[1] - _Z[0])
_WZ[[0, -1]] *= 0.5


def noise_sf(stat, counts, dof_noise) -> np.ndarray:
    """p-value of a sum of squared whitened residuals when some channels' noise levels
    were estimated: the chi-square test with the estimates' own uncertainty counted.

    A channel whitened by an estimate ``s`` of its noise ``sigma`` contributes
    ``w X`` with ``X ~ chi2(n)`` and ``w = sigma^2 / s^2 ~ nu / chi2(nu)``; its ``w`` is
    shared by every year (an F test for one channel). The estimated channels' ``w`` are
    pooled into one with the dof matching their spread (``N^2 / sum(n_c^2 / nu_c)``),
    the test is integrated over it, and ``X0 + w X`` given ``w`` is a scaled chi-square
    (Satterthwaite; exact for one channel). With every noise level known this is the
    chi-square survival function itself.

    Parameters
    ----------
    stat : array_like, shape [k]
        The statistics.
    counts : array_like, shape [k, n_ch]
        Residual degrees of freedom of each statistic per channel (samples less the
        parameters fitted, shared out in proportion).
    dof_noise : array_like, shape [n_ch]
        Degrees of freedom of each channel's noise level; ``inf`` where it is known.

    Returns
    -------
    ndarray, shape [k]
    """
    stat = np.atleast_1d(np.asarray(stat, float))
    counts = np.atleast_2d(np.asarray(counts, float))
    nu = np.asarray(dof_noise, float)
    est = np.isfinite(nu)
    n0 = counts[:, ~est].sum(axis=1)
    ne = counts[:, est].sum(axis=1)
    if not est.any() or not (ne > 0).any():
        return chi2_sf(stat, np.maximum(n0 + ne, 1.0))
    from scipy.special import expit, gammainccinv, gammaincinv
    with np.errstate(divide="ignore", invalid="ignore"):
        nu_p = ne ** 2 / (counts[:, est] ** 2 / nu[est]).sum(axis=1)
    nu_p = np.where(ne > 0, nu_p, np.inf)[:, None]                 # [k, 1]
    a = 0.5 * np.minimum(nu_p, 1e12)
    z = _Z[None, :]
    # q = chi2(nu) at cdf expit(z), each tail from its own side for precision.
    q = np.where(z < 0, 2.0 * gammaincinv(a, expit(z)), 2.0 * gammainccinv(a, expit(-z)))
    w = np.where(np.isfinite(nu_p), nu_p / q, 1.0)                  # [k, n_z]
    m0, me = n0[:, None], ne[:, None]
    mean = m0 + w * me
    var2 = m0 + w * w * me                                          # half the variance
    g, h = var2 / mean, mean ** 2 / var2
    sf = chi2_sf(stat[:, None] / g, np.maximum(h, 1e-9))
    dens = expit(z) * expit(-z)                                     # d cdf / d z
    return np.clip((sf * dens * _WZ).sum(axis=1), 0.0, 1.0)
