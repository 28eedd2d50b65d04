"""Statistics of residuals: structure (Ljung-Box), excess from an onset on (pooled chi-square),
and the noise level when the observations do not record it.

All functions are pure numpy/scipy on arrays; nothing here runs the FMU.
"""
from __future__ import annotations

import math

import numpy as np

# chi2_sf is used from here by calibrate's goodness of fit and diagnose's tests.
from ..distributions import chi2_sf
from ..errors import InputDataError


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


def pooled_onset_pvalues(chi2: np.ndarray, dof: np.ndarray, counts: np.ndarray | None = None,
                         sf=None) -> np.ndarray:
    """p-value of the pooled chi-square of the years from each possible onset on, [n_y].

    ``chi2``, ``dof`` [n_y]; with ``sf`` (``sf(stat, counts, dof)``, e.g. a unit's test
    that counts estimated noise levels) the years' samples per channel ``counts``
    [n_y, n_ch] are pooled too and passed to it."""
    def from_onset(x):
        return np.cumsum(np.asarray(x)[::-1], axis=0)[::-1]
    c, d = from_onset(chi2), np.maximum(from_onset(dof), 1)
    return chi2_sf(c, d) if sf is None else sf(c, from_onset(counts), d)


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


def _logit_nodes(step: float) -> tuple[np.ndarray, np.ndarray]:
    """Nodes ``z`` of the integral over an estimated noise level, logits of its
    chi-square's cdf from 1e-13 to 1 - 1e-13, and their trapezoid weights times the cdf's
    density in ``z`` (the integrand is smooth in the logit; beyond weighs under 1e-13)."""
    z = np.arange(-30.0, 30.0 + step / 2, step)
    w = np.full(z.size, step)
    w[[0, -1]] *= 0.5
    e = 1.0 / (1.0 + np.exp(-z))
    return z, w * e * (1.0 - e)


def _scales(z: np.ndarray, nu: float) -> np.ndarray:
    """``w = nu / q`` with ``q`` the chi-square(``nu``) quantile at cdf ``expit(z)``, each
    tail from its own side for precision."""
    from scipy.special import expit, gammainccinv, gammaincinv
    a = 0.5 * min(nu, 1e12)
    q = np.where(z < 0, 2.0 * gammaincinv(a, expit(z)), 2.0 * gammainccinv(a, expit(-z)))
    return nu / q


#: Nodes per estimated channel on the product grid: one, 241; two, 121 x 121; three,
#: 31^3 (the integrand is smooth enough: at p = 0.0025, 0.00245 against 0.0025 simulated).
_NODES = {1: _logit_nodes(0.25), 2: _logit_nodes(0.5), 3: _logit_nodes(2.0)}


def noise_sf(stat, counts, dof_noise) -> np.ndarray:
    """p-value of a sum of squared whitened residuals when some channels' noise levels
    were estimated: the chi-square test with the estimates' own uncertainty counted.

    A channel whitened by an estimate ``s`` of its noise ``sigma`` contributes ``w X``
    with ``X ~ chi2(n)`` and ``w = sigma^2 / s^2 ~ nu / chi2(nu)``; its ``w`` is shared by
    every year. The test is integrated over each estimated channel's ``w`` on a product
    grid (the F test for one channel), ``X0 + sum_c w_c X_c`` given them being a scaled
    chi-square (Satterthwaite: exact for one channel, within a few % at p = 0.0025 for two
    or three; one shared scale for all, as a first version did, made p 3-4 times too small
    for two). Four or more estimated channels share the scale of the fewest degrees of
    freedom: their tails lie within it (safe, and cautious). With every noise level known
    this is the chi-square survival function itself.

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
    ce, nue = counts[:, est], nu[est]
    active = (ce > 0).any(axis=0)
    ce, nue = ce[:, active], nue[active]
    if not nue.size:
        return chi2_sf(stat, np.maximum(n0 + ce.sum(axis=1), 1.0))
    if nue.size > max(_NODES):
        ce, nue = ce.sum(axis=1, keepdims=True), nue.min(keepdims=True)
    z, wz1 = _NODES[nue.size]
    # Every combination of the channels' scales: [K, J^K], and the product of the weights.
    w = np.stack(np.meshgrid(*[_scales(z, float(v)) for v in nue], indexing="ij")
                 ).reshape(nue.size, -1)
    wz = wz1
    for _ in range(nue.size - 1):
        wz = np.multiply.outer(wz, wz1)
    wz = wz.ravel()
    mean = n0[:, None] + ce @ w                                     # [k, J]
    var2 = n0[:, None] + ce @ (w * w)                               # half the variance
    g, h = var2 / mean, mean ** 2 / var2
    sf = chi2_sf(stat[:, None] / g, np.maximum(h, 1e-9))
    return np.clip(sf @ wz, 0.0, 1.0)
