"""Detection: does a unit drift beyond normal ageing?

Per-input slope tests alone miss faults: from one output channel, two inputs can move the
output in nearly the same way (for the pump, a damping rise and an efficiency decline give
almost the same start-up curve; their single-year estimates correlate at 0.9), so each
input's slope can sit inside its normal-ageing band while the health indicator -- which the
data do identify -- drifts abnormally. Two views of the question, which :func:`~.judge.judge`
pools by Simes' test at ``forecast.alpha`` (:func:`simes`):

* **the indicator's drift** (:func:`indicator_drift`): the OLS trend of the unit's yearly
  indicator (the posterior median of the indicator of each calibrated year,
  :func:`yearly_indicator`; for a jointly calibrated unit, its posterior trend slopes
  through the twin's gradient) is tested against the indicator drift that normal ageing of
  every input produces. Under normal ageing each input's yearly rate is taken as uniform on
  ``normal_rate +- normal_rate_tolerance``, independently across inputs; through the twin's
  gradient at the unit's mid-history state (:func:`mid_state`, :func:`gradient_points`,
  :func:`gradient_from`) this gives the distribution of the indicator's normal slope (a sum
  of uniforms). Its convolution with the Student-t error of the fitted slope is the null
  distribution; the p-value is its tail beyond the observed slope, on the unsafe side.
* **the inputs' slopes jointly** (:func:`box_test_uniform`): their Mahalanobis distance to
  the box of rates no worse than normal, against the same null. :func:`box_test` is the
  same statistic against the least favourable rates instead, which costs power (figures in
  :func:`box_test_uniform`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .trend import POSTERIOR_DOF

#: Monte Carlo draws of attribution: a probability's Monte Carlo sd is at most 0.0022
#: (0.5 / sqrt(50 000)), a tenth of the distance at which a verdict threshold (0.5, 0.8)
#: would matter; 200 000 cost 0.13 s a unit.
DRAWS = 50_000
#: Null draws of :func:`box_test_uniform` (each one a projection on the box): the Monte
#: Carlo sd of a p-value near alpha / 2 = 0.005 is 0.0005.
BOX_DRAWS = 20_000


@dataclass
class IndicatorDrift:
    """The trend of a unit's health indicator and its test against normal ageing.

    Attributes
    ----------
    years : ndarray of int, shape [n]
        Years whose indicator is finite (used in the fit).
    values : ndarray, shape [n]
        Posterior median of the indicator per year (indicator units).
    slope, slope_se : float
        OLS slope (indicator units per year) and its standard error, or a joint posterior's
        (:func:`indicator_drift`'s ``slope_draws``); NaN with < 3 years.
    dof : int
        ``n - 2``, or :data:`POSTERIOR_DOF` for a joint posterior's slope.
    normal_slope : float
        Indicator slope when every input ages at its normal rate (indicator units/yr).
    normal_halfwidth : ndarray, shape [d]
        Per input, ``|dI/dx_i| * tolerance_i``: how far normal ageing of that input can move
        the indicator's slope either way.
    gradient : ndarray, shape [d]
        ``dI/dx`` at the unit's mid-history state (indicator units per input unit).
    sense : int
        +1 when the indicator is unsafe above its limit, -1 below.
    p_value : float
        Probability, under normal ageing, of a slope at least this far towards unsafe.
    abnormal : bool
        ``p_value < alpha``.
    """

    years: np.ndarray
    values: np.ndarray
    slope: float
    slope_se: float
    dof: int
    normal_slope: float
    normal_halfwidth: np.ndarray
    gradient: np.ndarray
    sense: int
    p_value: float
    abnormal: bool
    #: p-value of the inputs' slopes against the normal-ageing box (:func:`box_test_uniform`).
    p_inputs: float = float("nan")
    #: The same test on each input's wear rate pooled over its trend's segments, when a
    #: repair restarted one (:func:`~.judge.history_slope_draws`); NaN otherwise.
    p_history: float = float("nan")
    #: The inputs' test on the trend's rate at the last recorded year instead of its chord
    #: over the segment, for a unit whose posterior puts most of its weight on wear that
    #: changed or accelerated (:func:`~.judge.judge`); NaN otherwise.
    p_inputs_rate: float = float("nan")
    #: Per input, the fault this record shows half the time: its excess rate, in tolerances
    #: beyond normal ageing, at which a test would reject with probability 0.5
    #: (:func:`detectable_multiples`); NaN for an input with no tolerance. Empty in
    #: forecasts written before it was recorded.
    detectable: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def excess(self) -> float:
        """Slope beyond the normal one, towards unsafe (indicator units per year)."""
        return float(self.sense * (self.slope - self.normal_slope))

    def describe(self, name: str, units: str) -> str:
        if not np.isfinite(self.slope):
            return f"{name} trend not testable ({self.years.size} finite year(s))"
        # The null is each input's rate anywhere in its band (uniform): their sum reaches
        # the band's edge only when every input does at once. Its 90 % range is what a
        # normal unit shows; "+- the edge" alone read as if a slope inside it were normal.
        half = np.abs(np.asarray(self.normal_halfwidth, float))
        u, w = uniform_sum(half)
        order = np.argsort(np.abs(u))
        q90 = float(np.abs(u)[order][np.searchsorted(np.cumsum(w[order]), 0.9)])
        return (f"{name} slope {self.slope:+.3g} {units}/yr vs normal ageing "
                f"{self.normal_slope:+.3g} (90 % of normal units within +-{q90:.3g}, all "
                f"within +-{float(np.sum(half)):.3g}; p = {self.p_value:.2g})")


def mid_state(trends: dict, names: list) -> np.ndarray:
    """The unit's state at its mean observed year, from its input trends, shape [d]."""
    return np.array([trends[n].intercept + trends[n].slope * trends[n].x_mean for n in names])


def gradient_points(cfg, x_mid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference probe points around ``x_mid`` [d] (clipped to the box).

    Returns
    -------
    X : ndarray, shape [2d, d]
        ``x - h_i e_i`` and ``x + h_i e_i`` for each input in turn.
    step : ndarray, shape [d]
        The actual distance between each pair (input units).
    """
    bounds = cfg.model.bounds
    width = bounds[:, 1] - bounds[:, 0]
    d = len(x_mid)
    x = np.clip(x_mid, bounds[:, 0], bounds[:, 1])
    X = np.repeat(x[None, :], 2 * d, axis=0)
    for i in range(d):
        h = 0.03 * width[i]
        X[2 * i, i] = max(x[i] - h, bounds[i, 0])
        X[2 * i + 1, i] = min(x[i] + h, bounds[i, 1])
    step = np.array([X[2 * i + 1, i] - X[2 * i, i] for i in range(d)])
    return X, step


def gradient_from(values: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``dI/dx`` [d] from the indicator at the probe points [2d] of :func:`gradient_points`;
    0 where a value is not finite (a level never reached: no usable slope)."""
    v = np.asarray(values, float).reshape(-1, 2)
    g = (v[:, 1] - v[:, 0]) / np.where(step > 0, step, 1.0)
    return np.where(np.isfinite(g), g, 0.0)


def yearly_indicator(years: np.ndarray, ind_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posterior median of the indicator per year, keeping years where it is finite.

    Parameters
    ----------
    years : ndarray of int, shape [n_y]
    ind_obs : ndarray, shape [n_y, n_o]
        Indicator of posterior draws of each year (inf = level not reached, NaN = failed).
    """
    v = np.where(np.isnan(ind_obs), np.inf, ind_obs)
    med = np.quantile(v, 0.5, axis=1, method="inverted_cdf")
    ok = np.isfinite(med)
    return np.asarray(years)[ok], med[ok]


def indicator_drift(years, ind_obs, gradient, normal_rate, tolerance, sense: int,
                    alpha: float, slope_draws: Optional[np.ndarray] = None) -> IndicatorDrift:
    """Test a unit's indicator trend against what normal ageing of every input produces.

    Parameters
    ----------
    years : ndarray of int, shape [n_y]
    ind_obs : ndarray, shape [n_y, n_o]
        Indicator of each year's posterior draws (indicator units).
    gradient : ndarray, shape [d]
        ``dI/dx`` at the unit's mid-history state.
    normal_rate, tolerance : ndarray, shape [d]
        Normal ageing per input (input units per year).
    sense : int
        +1 unsafe above the limit, -1 below.
    alpha : float
    slope_draws : ndarray, shape [n], optional
        Posterior draws of the indicator's slope (indicator units per year): a joint
        posterior's trend slopes through ``gradient``. The slope and its standard error are
        then theirs (normal error), not the OLS fit's to the yearly values. Those values
        are smoothed towards the joint trend, so their scatter about a line understates the
        slope's uncertainty: 4.4 times, median over the 96 healthy units of
        ``benchmarks/prognosis.py --healthy-only 96``, seed 31.
    """
    yrs, vals = yearly_indicator(years, ind_obs)
    g = np.asarray(gradient, float)
    normal = float(g @ np.asarray(normal_rate, float))
    half = np.abs(g) * np.asarray(tolerance, float)
    if yrs.size < 3:
        return IndicatorDrift(yrs, vals, np.nan, np.nan, max(yrs.size - 2, 0), normal, half, g,
                              sense, np.nan, False)
    if slope_draws is not None:
        draws = np.asarray(slope_draws, float)
        slope, se, dof = float(draws.mean()), float(draws.std(ddof=1)), POSTERIOR_DOF
    else:
        x = yrs.astype(float)
        xc = x - x.mean()
        sxx = float(xc @ xc)
        slope = float(xc @ (vals - vals.mean()) / sxx)
        resid = vals - vals.mean() - slope * xc
        dof = yrs.size - 2
        se = float(np.sqrt(resid @ resid / dof / sxx))
    excess = sense * (slope - normal)
    # Null: excess = sum_i half_i * U(-1, 1) + se * t_dof. The uniform sum by quadrature
    # (:func:`uniform_sum`), the t tail exact given it.
    u, w = uniform_sum(half)
    if se > 0:
        p = float(w @ t_sf((excess - u) / se, dof))
    else:
        p = float(w @ (u >= excess))
    return IndicatorDrift(yrs, vals, slope, se, dof, normal, half, g, sense, p, p < alpha)


#: Midpoints per uniform term of :func:`uniform_sum`, and the most points its sum keeps
#: (beyond, the sum is binned onto a grid; its mean is kept).
UNIFORM_NODES = 64
UNIFORM_MAX_POINTS = 4096


#: Degrees of freedom from which Student's t is taken as the normal: its tail then differs
#: by less than 1e-5 (the posterior's slopes, :data:`~.trend.POSTERIOR_DOF`), and the normal's
#: is 25 times cheaper to evaluate on the thousands of points of :func:`uniform_sum`.
NORMAL_DOF = 10 ** 5


def t_sf(x: np.ndarray, dof: float) -> np.ndarray:
    """Student's t upper tail at ``x`` (the normal's from :data:`NORMAL_DOF` on)."""
    from scipy.special import ndtr

    from ..distributions import t_sf as exact
    x = np.asarray(x, float)
    return ndtr(-x) if dof >= NORMAL_DOF else exact(x, dof)


def t_isf(p: float, dof: float) -> float:
    """The quantile :func:`t_sf` puts ``p`` above."""
    from scipy.special import ndtri, stdtrit
    return float(-ndtri(p) if dof >= NORMAL_DOF else stdtrit(dof, 1.0 - p))


def uniform_sum(half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and weights of ``sum_i half_i U_i``, each ``U_i`` uniform on [-1, 1]: the
    product of each term's ``UNIFORM_NODES`` midpoints (exact for an integrand linear in
    each term, error of order ``(half_i / UNIFORM_NODES)^2`` times its curvature), binned
    onto a grid once the product passes ``UNIFORM_MAX_POINTS`` points (three terms or more).

    Deterministic. The 50 000 Monte Carlo draws it replaces moved the p-values by 5 % of
    their size (median over ``benchmarks/fleet_scale.py``'s first 60 units; 0.0036 at most)
    and cost 10 ms a unit; this, under 1 ms."""
    mid = (np.arange(UNIFORM_NODES) + 0.5) * (2.0 / UNIFORM_NODES) - 1.0
    pts, w = np.zeros(1), np.ones(1)
    for h in np.abs(np.asarray(half, float)):
        if not h > 0:
            continue
        pts = (pts[:, None] + h * mid[None, :]).ravel()
        w = np.repeat(w / UNIFORM_NODES, UNIFORM_NODES)
        if pts.size > UNIFORM_MAX_POINTS:
            pts, w = _binned(pts, w, UNIFORM_MAX_POINTS // UNIFORM_NODES)
    return pts, w


def _binned(pts: np.ndarray, w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Weights ``w`` at ``pts`` moved to ``n`` evenly spaced points, each split between its
    two neighbours in proportion (the mean is kept)."""
    grid = np.linspace(pts.min(), pts.max(), n)
    step = grid[1] - grid[0]
    pos = np.clip((pts - grid[0]) / step, 0.0, n - 1.0)
    lo = np.minimum(np.floor(pos).astype(int), n - 2)
    frac = pos - lo
    out = np.bincount(lo, w * (1 - frac), n) + np.bincount(lo + 1, w * frac, n)
    return grid, out


def simes(p_values, alpha: float) -> bool:
    """Simes' test of the intersection of the hypotheses whose p-values are given: rejects
    when the j-th smallest of the k finite ones is below ``j alpha / k`` for some j. Its
    level is ``alpha`` when the p-values are independent or positively dependent (Sarkar
    1998), as one unit's views of its wear are (each grows with the same rates); it rejects
    whenever Bonferroni's ``min p < alpha / k`` does, and also when several views are
    small together. False when none is finite."""
    p = np.sort([float(v) for v in p_values if np.isfinite(v)])
    k = p.size
    return bool(k) and bool(np.any(p < alpha * np.arange(1, k + 1) / k))


def box_test(b: np.ndarray, C: np.ndarray, dof: int, normal_rate, tolerance,
             directions) -> tuple[float, np.ndarray]:
    """Test of the inputs' slopes [d] against the normal-ageing box, jointly.

    H0: every input ages within its band on the degrading side (``dir_i (b_i - r_i) <=
    tol_i``; both sides for an unknown direction). Statistic: the squared Mahalanobis
    distance (metric ``C``) from the estimate to the box, a bounded least-squares problem.
    Its null law is a chi-bar-square mixture; the p-value uses conservative equal weights
    on 1 and ``k`` (active bounds at the projection) degrees of freedom, with F laws for the
    Student-t error (``dof``).

    Returns
    -------
    p : float
    b0 : ndarray, shape [d]
        The closest slopes inside the box.
    """
    from scipy.optimize import lsq_linear

    from ..distributions import f_sf
    r, tol, dirs = (np.asarray(a, float) for a in (normal_rate, tolerance, directions))
    lo = np.where(dirs > 0, -np.inf, r - tol)
    hi = np.where(dirs < 0, np.inf, r + tol)
    Li = np.linalg.inv(np.linalg.cholesky(C))
    res = lsq_linear(Li, Li @ b, bounds=(lo, hi))
    b0 = res.x
    z = Li @ (b - b0)
    T = float(z @ z)
    if T <= 1e-12:
        return 1.0, b0
    k = max(1, int(np.sum(np.isclose(b0, lo) | np.isclose(b0, hi))))
    p = 0.5 * f_sf(T, 1, dof) + 0.5 * f_sf(T / k, k, dof)
    return float(min(1.0, p)), b0


def box_distance(B: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 sweeps: int = 200) -> np.ndarray:
    """Squared Mahalanobis distance (metric ``C``) from each row of ``B`` [m, d] to the box
    ``lo <= x <= hi`` [d] (bounds may be infinite), shape [m].

    Cyclic coordinate descent on the box-constrained quadratic, vectorised over the rows; it
    converges for any positive definite ``C`` (``sweeps`` passes: ample for d of a few
    inputs even at a correlation of 0.95)."""
    B = np.atleast_2d(np.asarray(B, float))
    Q = np.linalg.inv(C)
    X = np.clip(B, lo, hi)
    tol = 1e-10 * np.sqrt(np.diag(C))
    for _ in range(sweeps):
        X0 = X.copy()
        for i in range(B.shape[1]):
            g = (X - B) @ Q[:, i]
            X[:, i] = np.clip(X[:, i] - g / Q[i, i], lo[i], hi[i])
        if np.all(np.abs(X - X0) <= tol):
            break
    D = X - B
    return np.einsum("mi,ij,mj->m", D, Q, D)


def box_test_uniform(b: np.ndarray, C: np.ndarray, dof: int, normal_rate, tolerance,
                     directions, rng: np.random.Generator) -> float:
    """Test of the inputs' slopes [d] against normal ageing, with :func:`indicator_drift`'s
    null: each input's true rate uniform on ``normal_rate +- tolerance``, independently.

    Statistic: :func:`box_test`'s -- the squared Mahalanobis distance (metric ``C``) from the
    estimate to the box of rates no worse than normal (degrading side only). Its null law is
    drawn: a uniform rate in the band plus the slopes' Student-t error (covariance ``C``,
    ``dof``), ``BOX_DRAWS`` times. :func:`box_test` instead takes the least favourable
    rates -- every input at its band's degrading edge at once -- which a healthy unit almost
    never has; along the ridge of two inputs whose estimates trade off, that costs most of
    the power: on ``benchmarks/prognosis.py`` (seed 11, flow only, the slopes' covariance
    then the sum of the residual and the yearly posterior parts) detection of the faults at
    least twice the tolerance went 0.870 -> 0.957 with this null, false alarms 0 of 12
    either way.

    Returns
    -------
    p : float
        Share of null draws at least as far from the box as the estimate (1 inside it).
    """
    r, tol, dirs = (np.asarray(a, float) for a in (normal_rate, tolerance, directions))
    lo = np.where(dirs > 0, -np.inf, r - tol)
    hi = np.where(dirs < 0, np.inf, r + tol)
    T = float(box_distance(np.asarray(b, float)[None, :], C, lo, hi)[0])
    if T <= 1e-12:
        return 1.0
    n, d = BOX_DRAWS, len(r)
    L = np.linalg.cholesky(C)
    e = (rng.standard_normal((n, d)) @ L.T) / np.sqrt(rng.chisquare(max(dof, 1), (n, 1))
                                                     / max(dof, 1))
    null = r + tol * rng.uniform(-1.0, 1.0, (n, d)) + e
    return float(np.mean(box_distance(null, C, lo, hi) >= T))


def detectable_multiples(drift: IndicatorDrift, C: np.ndarray, dof: int, tolerance,
                         directions, level: float) -> np.ndarray:
    """How large a fault of each input this unit's record would show half the time.

    A fault of input ``i`` ages it ``m`` tolerances beyond its normal rate, the other inputs
    at theirs. The inputs' test sees it half the time once the slope's excess beyond the
    band's edge reaches the test's critical value, ``(m - 1) tol_i = q sd_i`` (``q`` the
    one-sided Student-t quantile at ``level``, ``sd_i`` the slope's posterior sd); the
    indicator's drift test once the indicator's excess ``m |dI/dx_i| tol_i`` reaches its
    critical value under its null (:func:`indicator_drift`); an input moving the indicator
    towards safe is not seen by that test. The smaller of the two, per input: the fault
    the record could still miss. A few years of data, or gaps, make it large: a healthy
    verdict then says little.

    Parameters
    ----------
    drift : IndicatorDrift
        The unit's indicator test (its slope error, gradient, null).
    C : ndarray, shape [d, d]
        Covariance of the inputs' slopes ((input units per year)^2).
    dof : int
        Degrees of freedom of the slopes' error.
    tolerance : ndarray, shape [d]
        Normal-ageing tolerance per input (input units per year).
    directions : ndarray, shape [d]
        Degrading direction per input (+1, -1, or 0 for unknown).
    level : float
        Each test's level (``forecast.alpha`` over the number of tests).

    Returns
    -------
    ndarray, shape [d]
        Multiples of each input's tolerance; inf when neither test can bound it (no slope
        error: too few years); NaN where the tolerance is 0.
    """
    from scipy.optimize import brentq

    from .. import distributions
    tol = np.asarray(tolerance, float)
    sd = np.sqrt(np.maximum(np.diag(np.atleast_2d(C)), 0.0))
    q = float(distributions.t_isf(level, dof))
    with np.errstate(divide="ignore", invalid="ignore"):
        by_inputs = np.where(tol > 0, 1.0 + q * sd / tol, np.nan)
    by_indicator = np.full(tol.size, np.inf)
    half, se = np.asarray(drift.normal_halfwidth, float), drift.slope_se
    if np.isfinite(se) and se > 0 and half.size == tol.size:
        u, w = uniform_sum(half)

        def tail(e):
            return float(w @ t_sf((e - u) / se, drift.dof)) - level

        # The root lies within q se of the uniform sum's range (q the tail's own
        # quantile at ``level``): below it every term's tail is at least ``level``, above
        # it at most. A bracket end that rounding puts on the wrong side is the root.
        q_dr = t_isf(level, drift.dof)
        lo, hi = float(u.min() + q_dr * se), float(u.max() + q_dr * se)
        if hi <= lo or tail(lo) <= 0:
            crit = lo
        elif tail(hi) >= 0:
            crit = hi
        else:
            crit = brentq(tail, lo, hi, xtol=1e-9 * se)
        g = np.asarray(drift.gradient, float)
        towards = drift.sense * g * np.where(np.asarray(directions) == 0, np.sign(
            drift.sense * g), np.asarray(directions, float)) > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            by_indicator = np.where(towards & (half > 0), crit / half, np.inf)
    # A slope with no error estimate (too few years) bounds nothing: inf, unless the
    # indicator's test still can.
    by_inputs = np.where(np.isfinite(by_inputs), by_inputs, np.inf)
    return np.where(tol > 0, np.minimum(by_inputs, by_indicator), np.nan)
