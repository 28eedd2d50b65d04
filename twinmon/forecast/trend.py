"""Trends of the calibrated inputs over the years, and their tests against normal ageing.

For every unit, each input's yearly posterior means are regressed on the year
(:func:`fit_trend`: OpenTURNS ``LinearModelAlgorithm``, ordinary least squares, as in the
paper). A repair or replacement of the input's component restarts its trend
(:func:`repair_years`, :func:`segment_trend`). The fitted line is extended with a prediction
interval for a *new observation* (:meth:`Trend.predict`, Student t with ``n - 2`` degrees of
freedom, not normal quantiles)::

    yhat(x0) +- t_{n-2, (1+c)/2} * s * sqrt(1 + 1/n + (x0 - xbar)^2 / Sxx)

Each slope is tested against ``normal_rate`` +- ``normal_rate_tolerance`` in the input's
degrading direction (:func:`slope_test`, the paper's test, reported per trend); a jointly
calibrated unit's slope, its standard error and interval are its posterior's
(:func:`posterior_slope_test`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..config import Config

#: Confidence of the slope interval reported as ``slope_ci90``.
SLOPE_CI = 0.90
#: Degrees of freedom that stand for "normal": a slope's error taken from posterior draws
#: (their count is no small-sample correction).
POSTERIOR_DOF = 10 ** 6


@dataclass
class Trend:
    """OLS trend of one input over the years, with its root-cause test.

    Attributes
    ----------
    intercept, slope : float
        ``value = intercept + slope * year`` (input units, input units per year).
    slope_se : float
        Standard error of the slope.
    slope_ci : (float, float)
        90 % confidence interval of the slope (Student t, n - 2 dof); for a joint posterior
        its posterior interval (:func:`posterior_slope_test`).
    residual_std : float
        ``s``, square root of the residual variance SSR / (n - 2).
    n : int
        Number of years fitted.
    x_mean, sxx : float
        Mean year and sum of squared deviations of the years (for prediction intervals).
    normal_rate, tolerance : float
        Yearly drift normal ageing allows, and its tolerance (from the input's spec).
    direction : int
        +1 when an increase of the input degrades the unit (moves the health indicator
        towards unsafe), -1 when a decrease does, 0 when unknown (two-sided test).
    p_value : float
        p-value of the one-sided test H0: the slope stays within normal ageing.
    test : str
        Name and hypothesis of the test.
    rejects : bool
        ``p_value < alpha``: the input drifts faster than normal ageing.
    component : str
        Component the input belongs to (``motor``, ``pump``, ...).
    """

    intercept: float
    slope: float
    slope_se: float
    slope_ci: tuple
    residual_std: float
    n: int
    x_mean: float
    sxx: float
    normal_rate: float = 0.0
    tolerance: float = 0.0
    direction: int = 1
    p_value: float = float("nan")
    test: str = ""
    rejects: bool = False
    component: str = ""

    @property
    def dof(self) -> int:
        return self.n - 2

    def predict(self, x0, confidence: float = 0.90):
        """Prediction and interval for a new observation at years ``x0``.

        Returns
        -------
        mean, lo, hi, scale : ndarray, each shape of ``x0``
            ``scale = s * sqrt(1 + 1/n + (x0 - xbar)^2 / Sxx)``, the scale of the Student t
            predictive distribution; ``lo, hi = mean -+ t_{n-2,(1+c)/2} * scale``.
        """
        from ..distributions import t_ppf
        x0 = np.asarray(x0, float)
        mean = self.intercept + self.slope * x0
        scale = self.residual_std * np.sqrt(1 + 1 / self.n + (x0 - self.x_mean) ** 2 / self.sxx)
        q = t_ppf(0.5 + confidence / 2, self.dof)
        return mean, mean - q * scale, mean + q * scale, scale


def fit_trend(years: np.ndarray, values: np.ndarray) -> tuple[Trend, np.ndarray]:
    """Ordinary least squares line through yearly values (OpenTURNS LinearModelAlgorithm).

    Parameters
    ----------
    years : ndarray, shape [n]
        Observation years (n >= 3).
    values : ndarray, shape [n]
        Yearly estimates (input units).

    Returns
    -------
    trend : Trend
        Without the root-cause test filled in (see :func:`slope_test`).
    residuals : ndarray, shape [n]
    """
    import openturns as ot

    from ..distributions import t_ppf
    x = np.asarray(years, float)
    y = np.asarray(values, float)
    n = x.size
    algo = ot.LinearModelAlgorithm(ot.Sample(x[:, None]), ot.Sample(y[:, None]))
    algo.run()
    res = algo.getResult()
    b0, b1 = map(float, res.getCoefficients())
    se = float(res.getCoefficientsStandardErrors()[1])
    s2 = float(res.getResidualsVariance())
    q = t_ppf(0.5 + SLOPE_CI / 2, n - 2)
    resid = np.asarray(res.getSampleResiduals()).ravel()
    trend = Trend(intercept=b0, slope=b1, slope_se=se, slope_ci=(b1 - q * se, b1 + q * se),
                  residual_std=float(np.sqrt(max(s2, 0.0))), n=n, x_mean=float(x.mean()),
                  sxx=float(np.sum((x - x.mean()) ** 2)))
    return trend, resid


def repair_years(cfg: Config, up, years: np.ndarray, found=()) -> dict:
    """Per input, the first year of its current trend: the year its component was last
    repaired or replaced (``events`` of the posterior, the repairs calibration found
    unrecorded, ``found_repairs``, and ``found``: :class:`~twinmon.repairs.FoundRepair`
    found here), else the first observed year."""
    since = {n: int(years[0]) for n in cfg.model.input_names}
    work = [(e[0], e[1]) for e in getattr(up, "events", None) or ()]
    work += [(r["year"], c) for r in getattr(up, "found_repairs", None) or ()
             for c in r["components"]]
    work += [(r.year, c) for r in found for c in r.components]
    for year, component in work:
        for name in cfg.model.components.get(component, ()):
            if year <= years[-1]:
                since[name] = max(since[name], int(year))
    return since


def segment_trend(years: np.ndarray, values: np.ndarray, since: int, spec) -> Trend:
    """The trend of one input from year ``since`` on (its component's last repair).

    With 3 or more years since, an OLS fit of those years. With fewer, no slope can be
    estimated: the repaired part is taken to age normally (``normal_rate``) from the level of
    its post-repair estimates, with the scatter (residual sd, dof) of the whole history's fit
    -- the year-to-year scatter belongs to the unit's recording, not to the part -- and the
    test says so (it never rejects)."""
    seg = years >= since
    if seg.sum() >= 3:
        return fit_trend(years[seg], values[seg])[0]
    full, _ = fit_trend(years, values)
    x = years[seg].astype(float)
    level = float(values[seg].mean())
    x_mean = float(x.mean())
    return Trend(intercept=level - spec.normal_rate * x_mean, slope=spec.normal_rate,
                 slope_se=spec.normal_rate_tolerance,
                 slope_ci=(spec.normal_rate - spec.normal_rate_tolerance,
                           spec.normal_rate + spec.normal_rate_tolerance),
                 residual_std=full.residual_std, n=full.n, x_mean=x_mean, sxx=full.sxx,
                 normal_rate=spec.normal_rate, tolerance=spec.normal_rate_tolerance,
                 p_value=1.0, rejects=False,
                 test=f"repaired in year {since}: fewer than 3 years since, normal ageing "
                      "assumed")


def slope_p_value(slope: float, se: float, dof: float, normal_rate: float, tolerance: float,
                  direction: int) -> float:
    """:func:`slope_test`'s p-value of a slope ``slope`` with standard error ``se`` (Student t
    with ``dof``): one-sided towards ``direction`` (+-1), two-sided for 0."""
    from ..distributions import t_sf

    def one_sided(d: int) -> float:
        excess = d * slope - (d * normal_rate + tolerance)
        if se > 0:
            # Not scipy.stats.t.sf (the same value): its per-call overhead counts here, as
            # the fleet's prior tests every unit's inputs up front.
            return float(t_sf(excess / se, dof))
        return 0.0 if excess > 0 else 1.0     # a perfect fit: the slope is known exactly

    if direction:
        return one_sided(direction)
    return min(1.0, 2 * min(one_sided(1), one_sided(-1)))


def slope_test(trend: Trend, normal_rate: float, tolerance: float, direction: int,
               alpha: float, dof: Optional[int] = None,
               what: str = "t test on the OLS slope") -> Trend:
    """t test of the slope against normal ageing, in the degrading direction.

    With ``direction`` +-1, one-sided: H0 ``direction * slope <= direction * normal_rate +
    tolerance`` (the input degrades no faster than normal ageing allows); the statistic
    ``(direction * slope - bound) / se`` is Student t with n - 2 dof at the boundary of H0.
    With ``direction`` 0 (which way degrades is not known), two-sided: H0 ``|slope -
    normal_rate| <= tolerance``, p = twice the smaller one-sided p-value.

    ``dof`` (default ``trend.dof``) and ``what`` name another test of the same form:
    :func:`posterior_slope_test`'s.

    Returns
    -------
    Trend
        ``trend`` with ``p_value``, ``test``, ``rejects``, ``normal_rate``, ``tolerance`` and
        ``direction`` filled in.
    """
    dof = trend.dof if dof is None else dof
    df = f"df={dof}" if dof < POSTERIOR_DOF else "normal"
    p = slope_p_value(trend.slope, trend.slope_se, dof, normal_rate, tolerance, direction)
    if direction:
        limit = direction * (direction * normal_rate + tolerance)
        op = "<=" if direction > 0 else ">="
        test = (f"one-sided {what} ({df}), H0: slope {op} "
                f"{limit:+.4g}/yr (normal ageing {normal_rate:+.4g} +- {tolerance:.4g}/yr)")
    else:
        test = (f"two-sided {what} ({df}; degrading direction "
                f"unknown), H0: |slope - {normal_rate:+.4g}| <= {tolerance:.4g}/yr")
    trend.normal_rate, trend.tolerance, trend.direction = normal_rate, tolerance, int(direction)
    trend.p_value, trend.test, trend.rejects = p, test, bool(p < alpha)
    return trend


def safe_way(trends: dict, alpha: float) -> dict:
    """The inputs whose slope lies beyond normal ageing on the side *away* from their
    degrading direction: ``{name: p}``, one-sided at ``alpha`` divided by the number of
    inputs with a known direction (Student t, the trend's own dof).

    Detection tests wear towards the limit only, so such a part is no risk by the health
    indicator; but it is not ageing normally either (a fan's belt slip rising 0.5 %/yr
    against a band of 0.05 +- 0.1 lowered the power drawn, the indicator, and read "within
    normal ageing"). The plan and the report name it instead of calling it normal."""
    known = [n for n, t in trends.items() if t.direction]
    out = {}
    for n in known:
        t = trends[n]
        p = slope_p_value(t.slope, t.slope_se, t.dof, t.normal_rate, t.tolerance,
                          -t.direction)
        if p < alpha / len(known):
            out[n] = p
    return out


def posterior_slope_test(trend: Trend, draws: np.ndarray, normal_rate: float,
                         tolerance: float, direction: int, alpha: float) -> Trend:
    """:func:`slope_test` for a jointly calibrated unit: from its posterior's slope draws.

    The yearly means of a joint posterior lie close to its trend (each year is estimated
    with the trend's help), so an OLS fit to them gives a slope interval far narrower than
    the posterior's (the DC drive's worn bearing, 90 %: 6·10⁻⁶ N.m.s/rad per year wide
    against the posterior's 3.5·10⁻⁵). The slope, its standard error and 90 % interval
    are the draws' (mean, sd, quantiles); the test is ``judge``'s, per input (normal, as
    its joint test); the line keeps the yearly means' centroid.

    Parameters
    ----------
    trend : Trend
        The OLS trend of the yearly means (:func:`segment_trend`).
    draws : ndarray, shape [n]
        Posterior draws of the input's slope in its last segment (input units per year).
    """
    b = float(np.mean(draws))
    lo, hi = np.quantile(draws, [(1 - SLOPE_CI) / 2, (1 + SLOPE_CI) / 2])
    trend.intercept += (trend.slope - b) * trend.x_mean
    trend.slope, trend.slope_se = b, float(np.std(draws, ddof=1))
    trend.slope_ci = (float(lo), float(hi))
    return slope_test(trend, normal_rate, tolerance, direction, alpha, dof=POSTERIOR_DOF,
                      what="test on the joint posterior's slope")


#: Fewest years of a part's history on which acceleration is tested (a quadratic fit has
#: three coefficients; five years leave two degrees of freedom).
SHAPE_MIN_YEARS = 5


def acceleration_test(years: np.ndarray, values: np.ndarray, direction: int) -> float:
    """p-value of a one-sided test that the yearly values accelerate in ``direction``.

    The least-squares fit ``a + b x + c x^2`` (x the centred year); H0: ``direction * c <=
    0``; Student t with n - 3 dof.

    Parameters
    ----------
    years : ndarray, shape [n]
    values : ndarray, shape [n]
        Yearly estimates of one input (input units), n >= :data:`SHAPE_MIN_YEARS`.
    direction : int
        +1 when an increase degrades the unit, -1 when a decrease does (0: two-sided).

    Returns
    -------
    float
        The p-value (1 for fewer than :data:`SHAPE_MIN_YEARS` years or an exact fit).
    """
    from ..distributions import t_sf
    x = np.asarray(years, float)
    y = np.asarray(values, float)
    if x.size < SHAPE_MIN_YEARS:
        return 1.0
    x = x - x.mean()
    X = np.column_stack([np.ones_like(x), x, x * x])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    dof = x.size - 3
    resid = y - X @ coef
    se = float(np.sqrt(resid @ resid / dof * np.linalg.inv(X.T @ X)[2, 2]))
    if se == 0:
        return 1.0
    t = coef[2] / se
    if direction:
        return float(t_sf(direction * t, dof))
    return float(min(1.0, 2 * t_sf(abs(t), dof)))


def shape_gate(cfg: Config, since: dict, years: np.ndarray, mean: np.ndarray,
               trends: dict, every: bool = True) -> tuple[str, Optional[str]]:
    """Why a unit's straight-line trends cannot be trusted, or ``""``, and the input that
    accelerates the most surely (None when none does).

    When an input's slope test found abnormal drift, only those inputs are tested (a sound
    input's estimates may bend beside a fast fault, the inputs trading off in the
    likelihood, without moving the failure year); when none did, every input is (wear that
    starts late keeps the slope over the whole record within normal ageing while it runs
    to the limit: a pump coefficient ageing normally for 6 years, then falling 0.2 a year,
    was "healthy, no action" and failed in year 14). Each for acceleration in its degrading
    direction over its current part's years (:func:`acceleration_test`), at
    ``forecast.shape_alpha`` divided by the number tested. ``every`` False: the drifting
    inputs only, always (a unit already judged unsafe at a part's level: a sound input's
    bend beside it moves nothing).

    Parameters
    ----------
    since : dict input name -> int
        First year of each input's current part (:func:`repair_years`, and repairs found
        in the estimates).
    years : ndarray of int, shape [n_y]
    mean : ndarray, shape [n_y, d]
        The yearly estimates the trends were fitted to.
    trends : dict name -> Trend
        With their tests filled in.
    """
    alpha = cfg.forecast.shape_alpha
    if alpha <= 0:
        return "", None
    names = list(trends)
    drifting = any(trends[n].rejects for n in names) or not every
    tested = [i for i, n in enumerate(names)
              if (trends[n].rejects or not drifting)
              and (years >= since[n]).sum() >= SHAPE_MIN_YEARS]
    found = []
    for i in tested:
        n = names[i]
        seg = years >= since[n]
        p = acceleration_test(years[seg], mean[seg, i], trends[n].direction)
        if p < alpha / len(tested):
            found.append((p, n, int(years[seg][0]), int(years[seg][-1])))
    if not found:
        return "", None
    p, n, a, b = min(found)
    return (f"{n}'s yearly estimates accelerate over years {a}-{b} (one-sided test of a "
            f"quadratic term, p = {p:.2g}): the straight-line trend understates its wear and "
            "the failure may come earlier than forecast"), n
