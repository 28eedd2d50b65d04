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


def estimate_noise(y: np.ndarray, time: np.ndarray, start: float) -> float:
    """Noise standard deviation from second differences of samples after ``start`` (s),
    where the transient is nearly flat: std(d2 y) = sqrt(6) sigma; median absolute
    deviation for robustness. ``y`` [n_y, n_t]."""
    sel = np.asarray(time) >= start
    if sel.sum() < 4:
        sel = np.ones(len(time), bool)
    d2 = np.diff(y[:, sel], n=2, axis=1).ravel()
    d2 = d2[np.isfinite(d2)]
    if d2.size < 3:
        raise InputDataError("too few samples to estimate the noise; record noise_std")
    s = 1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0)
    if not s > 0:
        raise InputDataError("cannot estimate the noise (flat record); record noise_std")
    return float(s)
