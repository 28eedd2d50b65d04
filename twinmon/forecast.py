"""Stage ``forecast``: trends of the calibrated inputs, failure probability, root cause, plan.

For every unit the yearly posterior means of each degradation input are regressed on the year
(OpenTURNS ``LinearModelAlgorithm``, ordinary least squares, as in the paper). The fitted lines
are extended over ``forecast.horizon`` years past the last observation with prediction
intervals for a *new observation* (Student t with ``n - 2`` degrees of freedom, not normal
quantiles)::

    yhat(x0) +- t_{n-2, (1+c)/2} * s * sqrt(1 + 1/n + (x0 - xbar)^2 / Sxx)

Monte Carlo samples of the inputs drawn from that predictive distribution (one multivariate
Student t per year, its correlation the correlation of the inputs' regression residuals) are
propagated through the twin: points inside the surrogate's training box through the Gaussian
process surrogate (vectorised), points outside it through the FMU itself, so a Gaussian
process is never extrapolated. A sample is unsafe when its health indicator passes
``safety.unsafe_if``, when the FMU reports the non-physical mode, or when the FMU run fails.
The failure year is the first future year whose probability of being unsafe exceeds
``safety.failure_probability``.

Detection and root cause (:mod:`twinmon.prognosis`, :func:`judge`): the trend of the unit's
health indicator (its posterior draws per observed year through the twin) is tested against
the drift normal ageing of every input produces, and the inputs' slopes jointly against the
normal-ageing box, each at ``forecast.alpha`` / 2. A drifting unit's components get
probabilities of ageing faster than normal; the verdict names those at or above
``forecast.attribution_confidence``, or says ``ambiguous`` with the probabilities and the
unrecorded channel that would tell them apart. Each input keeps its one-sided t test of the
slope against ``normal_rate`` +- ``normal_rate_tolerance`` in its degrading direction (the
paper's test, reported per trend).

Units stream through in chunks over ``simulate.executor``'s workers (:func:`iter_forecast`)
and are written as they come back, so memory does not grow with the fleet.

See ``docs/forecast.md`` for the choices (OLS on the estimates, correlated draws) and the
artifact layout.
"""
from __future__ import annotations

import json
import os
import time as _time
import zlib
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import artifacts
from .config import Config
from .errors import ArtifactError, CalibrationError
from .prognosis import (AMBIGUOUS, HEALTHY, POSTERIOR_DOF, Attribution, IndicatorDrift,
                        attribute, box_test_uniform, filter_error_covariance, gradient_from,
                        gradient_points, indicator_drift, mid_state, separating_channel,
                        slope_covariance)

#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "forecast", "safety", "seed")

#: Offset added to ``cfg.seed`` for this stage's random streams (other stages use others).
SEED_OFFSET = 5000
#: Below this effective number of posterior draws after pooling, forecast warns: the unit's
#: Monte Carlo rests on that many distinct trend states (the benchmark's seeds 11-16, 1000
#: kept draws: 31-72 at the fewest, 154-276 the median).
POOL_MIN_ESS = 30
#: Confidence of the slope interval reported as ``slope_ci90``.
SLOPE_CI = 0.90
#: Prognosis status of a unit.
STATUS_OK, STATUS_WITHHELD, STATUS_UNRELIABLE = "ok", "withheld", "unreliable"
#: Where a Monte Carlo point was evaluated.
SOURCE_SURROGATE, SOURCE_FMU, SOURCE_FAILED = 0, 1, 2


# ---------------------------------------------------------------------------------------
# Trends
# ---------------------------------------------------------------------------------------
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
        from scipy import stats
        x0 = np.asarray(x0, float)
        mean = self.intercept + self.slope * x0
        scale = self.residual_std * np.sqrt(1 + 1 / self.n + (x0 - self.x_mean) ** 2 / self.sxx)
        q = stats.t.ppf(0.5 + confidence / 2, self.dof)
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
    from scipy import stats
    x = np.asarray(years, float)
    y = np.asarray(values, float)
    n = x.size
    algo = ot.LinearModelAlgorithm(ot.Sample(x[:, None]), ot.Sample(y[:, None]))
    algo.run()
    res = algo.getResult()
    b0, b1 = map(float, res.getCoefficients())
    se = float(res.getCoefficientsStandardErrors()[1])
    s2 = float(res.getResidualsVariance())
    q = stats.t.ppf(0.5 + SLOPE_CI / 2, n - 2)
    resid = np.asarray(res.getSampleResiduals()).ravel()
    trend = Trend(intercept=b0, slope=b1, slope_se=se, slope_ci=(b1 - q * se, b1 + q * se),
                  residual_std=float(np.sqrt(max(s2, 0.0))), n=n, x_mean=float(x.mean()),
                  sxx=float(np.sum((x - x.mean()) ** 2)))
    return trend, resid


def repair_years(cfg: Config, up, years: np.ndarray) -> dict:
    """Per input, the first year of its current trend: the year its component was last
    repaired or replaced (``events`` of the posterior), else the first observed year."""
    since = {n: int(years[0]) for n in cfg.model.input_names}
    for year, component, _action in getattr(up, "events", None) or ():
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
    from scipy import stats
    dof = trend.dof if dof is None else dof
    df = f"df={dof}" if dof < POSTERIOR_DOF else "normal"

    def one_sided(d: int) -> float:
        excess = d * trend.slope - (d * normal_rate + tolerance)
        if trend.slope_se > 0:
            return float(stats.t.sf(excess / trend.slope_se, dof))
        return 0.0 if excess > 0 else 1.0     # a perfect fit: the slope is known exactly

    if direction:
        p = one_sided(direction)
        limit = direction * (direction * normal_rate + tolerance)
        op = "<=" if direction > 0 else ">="
        test = (f"one-sided {what} ({df}), H0: slope {op} "
                f"{limit:+.4g}/yr (normal ageing {normal_rate:+.4g} +- {tolerance:.4g}/yr)")
    else:
        p = min(1.0, 2 * min(one_sided(1), one_sided(-1)))
        test = (f"two-sided {what} ({df}; degrading direction "
                f"unknown), H0: |slope - {normal_rate:+.4g}| <= {tolerance:.4g}/yr")
    trend.normal_rate, trend.tolerance, trend.direction = normal_rate, tolerance, int(direction)
    trend.p_value, trend.test, trend.rejects = p, test, bool(p < alpha)
    return trend


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


def verdict(trends: dict[str, Trend]) -> str:
    """``healthy``, one component name, or ``both`` (several components) from the tests."""
    bad = sorted({t.component or name for name, t in trends.items() if t.rejects})
    if not bad:
        return "healthy"
    return bad[0] if len(bad) == 1 else "both"


@dataclass
class Direction:
    """Which way an input degrades the unit, and how that was decided.

    ``sign`` +1 (raising the input moves the indicator towards unsafe), -1, or 0 (unknown);
    ``source`` ``config`` or ``inferred``; ``effect`` the indicator change over the probe
    (indicator units) and ``noise`` the surrogate's own indicator error (same units)."""

    sign: int
    source: str
    effect: float = float("nan")
    noise: float = float("nan")
    note: str = ""


#: An inferred direction must exceed the surrogate's own indicator error this many times.
DIRECTION_MARGIN = 3.0
#: Half-width of the probe around the nominal point, as a fraction of each input's range.
DIRECTION_STEP = 0.25


def degrading_directions(cfg: Config, surrogate) -> dict[str, Direction]:
    """Degrading direction of every input: from the config, else inferred from the twin.

    Inference: the indicator at the nominal point +- 25 % of the input's range (clipped to
    the box), through the twin (:func:`evaluate_twin`: the surrogate, or the FMU for an
    indicator on another variable). The sign of the change that moves the indicator towards
    unsafe is kept only when the change exceeds ``DIRECTION_MARGIN`` times the surrogate's
    own indicator error on held-out FMU runs (:func:`indicator_noise`; 0 for the FMU).
    Otherwise the direction is 0 and the input is tested two-sided, with a note that says so.
    """
    from .safety import Indicator
    ind = Indicator.from_config(cfg)
    x0 = np.array([s.nominal for s in cfg.model.inputs.values()])
    rng = cfg.model.bounds[:, 1] - cfg.model.bounds[:, 0]
    out, probe = {}, {}
    for i, (name, spec) in enumerate(cfg.model.inputs.items()):
        if spec.degrading is not None:
            out[name] = Direction(1 if spec.degrading == "up" else -1, "config")
            continue
        step = np.zeros_like(x0)
        step[i] = DIRECTION_STEP * rng[i]
        probe[name] = (np.maximum(x0 - step, cfg.model.bounds[:, 0]),
                       np.minimum(x0 + step, cfg.model.bounds[:, 1]))
    if not probe:
        return out
    twin = evaluate_twin(cfg, surrogate, np.array([p for pair in probe.values() for p in pair]))
    noise = (indicator_noise(cfg, surrogate, surrogate.X_test, surrogate.Y_test)
             if np.any(twin.source == SOURCE_SURROGATE) else 0.0)
    for k, name in enumerate(probe):
        v_dn, v_up = twin.value[2 * k], twin.value[2 * k + 1]
        if not (np.isfinite(v_dn) and np.isfinite(v_up)):
            # A level never reached (inf) at one end: the direction is plain, the size not.
            same = (v_dn == v_up) or np.isnan(v_dn) or np.isnan(v_up)
            d = 0 if same else (1 if (v_up > v_dn) == (ind.sense > 0) else -1)
            out[name] = Direction(d, "inferred", float(v_up - v_dn) if not same else 0.0, noise,
                                  note="" if d else f"{name}: the twin gives no usable "
                                  f"{ind.name} at the probe; degrading direction unknown, "
                                  f"tested two-sided; set model.inputs.{name}.degrading")
            continue
        delta = float(v_up - v_dn)
        if delta != 0 and abs(delta) > DIRECTION_MARGIN * noise:
            out[name] = Direction(int(np.sign(delta)) * ind.sense, "inferred", delta, noise)
        else:
            out[name] = Direction(0, "inferred", delta, noise, note=(
                f"{name}: its effect on {ind.name} over the probe ({delta:+.3g} {ind.units}) "
                f"is not above {DIRECTION_MARGIN:g}x the surrogate's own error "
                f"({noise:.3g} {ind.units}): degrading direction unknown, tested two-sided; "
                f"set model.inputs.{name}.degrading to up or down"))
    return out


def indicator_noise(cfg: Config, surrogate, X_test: np.ndarray, Y_test: np.ndarray) -> float:
    """RMS error of the health indicator computed from the surrogate vs the FMU's test runs
    (indicator units); 0 when there is no usable test run."""
    from .safety import Indicator
    if len(X_test) == 0 or np.size(Y_test) == 0:
        return 0.0
    ind = Indicator.from_config(cfg)
    a = ind(surrogate.time, surrogate.predict(X_test))
    b = ind(surrogate.time, Y_test)
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.sqrt(np.mean((a[ok] - b[ok]) ** 2))) if ok.any() else 0.0


# ---------------------------------------------------------------------------------------
# Predictive sampling and the twin
# ---------------------------------------------------------------------------------------
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
        (:func:`~twinmon.prognosis.filter_error_covariance`), or the yearly posterior
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
    cov = np.array([_cover(c[j] * S, carried[j]) for j in range(fut.size)]) + jitter
    loc = np.column_stack([t.intercept + t.slope * fut for t in trends])
    return StatePredictive(loc, cov, max(n - 2, 1))


def _cover(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(B - A)
    return A + (V * np.maximum(w, 0.0)) @ V.T


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
    from scipy import stats
    q = stats.t.ppf(0.5 + confidence / 2, sp.dof)
    sd = np.sqrt(sp.cov[:, i, i])
    return sp.loc[:, i], sp.loc[:, i] - q * sd, sp.loc[:, i] + q * sd


@dataclass
class TwinResult:
    """The twin evaluated at Monte Carlo points.

    Attributes
    ----------
    value : ndarray, shape [m]
        The health indicator (its units); ``inf`` for a level never reached, NaN if the FMU
        failed.
    nonphysical : ndarray of bool, shape [m]
    source : ndarray of int8, shape [m]
        0 surrogate, 1 FMU, 2 FMU run failed.
    messages : list of str
        One message per failed FMU run.
    """

    value: np.ndarray
    nonphysical: np.ndarray
    source: np.ndarray
    messages: list = field(default_factory=list)

    def unsafe(self, safety) -> np.ndarray:
        """Unsafe per point [m]: the indicator passes its limit, non-physical, or a failed
        run."""
        from .safety import is_unsafe
        failed = self.source == SOURCE_FAILED
        return is_unsafe(self.value, safety, self.nonphysical) | failed


def evaluate_twin(cfg: Config, surrogate, X: np.ndarray, executor=None,
                  fmu_everywhere: bool = False,
                  progress: Optional[Callable[[int, int], None]] = None,
                  predict: Optional[Callable[[np.ndarray], np.ndarray]] = None,
                  spec=None) -> TwinResult:
    """Health indicator and non-physical flag of input points [m, d]: surrogate in its box,
    FMU outside.

    The surrogate has no non-physical output: inside its training box the flag is taken as 0
    (the box is checked to be physical, see :func:`box_is_physical`). ``fmu_everywhere`` sends
    every point to the FMU; so does an indicator computed from another variable than the
    output the surrogate learnt. ``predict`` replaces ``surrogate.predict`` (its numpy form,
    :func:`~twinmon.calibrate.vectorised.make_predictor`); ``spec`` the config's FMU spec (a
    worker's copy of the FMU).
    """
    from .safety import Indicator
    from .simulate import as_parameters, run_batch, spec_for
    ind = Indicator.from_config(cfg)
    X = np.asarray(X, float).reshape(-1, len(cfg.model.inputs))
    m = len(X)
    value = np.full(m, np.nan)
    nph = np.zeros(m, bool)
    source = np.full(m, SOURCE_SURROGATE, np.int8)
    on_surrogate = not fmu_everywhere and ind.variable == cfg.model.output.variable
    inside = surrogate.in_box(X) if on_surrogate else np.zeros(m, bool)
    if inside.any():
        # Chunks keep the [chunk, n_t] intermediate arrays small.
        idx = np.flatnonzero(inside)
        for lo in range(0, idx.size, 20000):
            j = idx[lo:lo + 20000]
            value[j] = ind(surrogate.time, (predict or surrogate.predict)(X[j]))
    messages = []
    out = np.flatnonzero(~inside)
    if out.size:
        spec = spec or spec_for(cfg)
        batch = run_batch(spec, as_parameters(cfg, X[out]), executor,
                          (lambda k: progress(k, out.size)) if progress else None)
        value[out] = np.where(batch.ok, ind(spec.times, batch.outputs[ind.variable]), np.nan)
        if cfg.model.nonphysical:
            nph[out] = batch.ok & (batch.outputs[cfg.model.nonphysical][:, -1] > 0.5)
        source[out] = np.where(batch.ok, SOURCE_FMU, SOURCE_FAILED)
        messages = [batch.messages[k] for k in np.flatnonzero(~batch.ok)]
    return TwinResult(value, nph, source, messages)


def box_is_physical(cfg: Config) -> bool:
    """True when the FMU is physical at every corner of the surrogate's box (2^d runs).

    The surrogate cannot say when the twin leaves its physical domain; if a corner of the
    box is non-physical, the forecast sends every point to the FMU instead."""
    if not cfg.model.nonphysical or len(cfg.model.inputs) > 10:
        return True
    from itertools import product
    from .simulate import as_parameters, run_batch, spec_for
    corners = np.array(list(product(*cfg.model.bounds)))
    batch = run_batch(spec_for(cfg), as_parameters(cfg, corners))
    flag = batch.outputs[cfg.model.nonphysical][:, -1]
    return bool(np.all(batch.ok) and np.all(flag[batch.ok] < 0.5))


# ---------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------
@dataclass
class UnitForecast:
    """The forecast of one unit.

    Attributes
    ----------
    years_observed : ndarray of int, shape [n_y]
    estimates : dict name -> ndarray [n_y]
        Posterior mean per observed year (the regression's data), input units.
    years_future : ndarray of int, shape [h]
    trends : dict name -> Trend
    pred_mean, pred_lo, pred_hi : dict name -> ndarray [h]
        Trend line and prediction interval for a new observation (``confidence``).
    samples : ndarray, shape [h, n_s, d]
        Monte Carlo input samples per future year.
    indicator : ndarray, shape [h, n_s]
        Health indicator per future year and sample (its units).
    nonphysical : ndarray of bool, shape [h, n_s]
    source : ndarray of int8, shape [h, n_s]
        0 surrogate, 1 FMU, 2 failed FMU run.
    p_unsafe : ndarray, shape [h]
    indicator_observed : ndarray, shape [n_y, n_o]
        Health indicator of the posterior samples of each observed year.
    p_unsafe_observed : ndarray, shape [n_y]
    failure_year : int or None
    root_cause : str
    plan : str
    fmu_failures : int
    true_failure_year : int or None
    true_indicator : ndarray [h] or None
        Health indicator of the true future inputs (with ``--truth``).
    true_inputs : dict name -> ndarray [h], or None
    true_unsafe : ndarray of bool [h] or None
    truth_source : str
        Where the true future inputs come from: ``"recorded future"`` (the truth file's)
        or ``"trend line"`` (each true trajectory's fitted line extended); ``""`` without
        a truth.
    """

    years_observed: np.ndarray
    estimates: dict
    years_future: np.ndarray
    trends: dict
    pred_mean: dict
    pred_lo: dict
    pred_hi: dict
    samples: np.ndarray
    indicator: np.ndarray
    nonphysical: np.ndarray
    source: np.ndarray
    p_unsafe: np.ndarray
    indicator_observed: np.ndarray
    p_unsafe_observed: np.ndarray
    failure_year: Optional[int]
    root_cause: str
    plan: str = ""
    fmu_failures: int = 0
    true_failure_year: Optional[int] = None
    true_indicator: Optional[np.ndarray] = None
    true_inputs: Optional[dict] = None
    true_unsafe: Optional[np.ndarray] = None
    has_truth: bool = False
    truth_source: str = ""
    #: ``ok``, ``withheld`` (the twin misses the plant: no failure year, no root cause) or
    #: ``unreliable`` (a calibrated year did not converge); see :func:`prognosis_status`.
    status: str = STATUS_OK
    status_reason: str = ""
    #: The prognosis of a withheld unit was given anyway (``forecast.force_prognosis``).
    forced: bool = False
    #: The indicator's trend and its test against normal ageing (detection).
    drift: Optional[IndicatorDrift] = None
    #: Which components the drift comes from, with probabilities.
    attribution: Optional[Attribution] = None
    #: Effective number of the unit's posterior draws once reweighted to the fleet's prior
    #: of the year-to-year sd (of ``calibrate.keep_draws``); NaN when not pooled.
    pool_ess: float = float("nan")

    #: Set by :meth:`slim`: the figures kept when the Monte Carlo arrays are dropped.
    _slim: Optional[dict] = field(default=None, repr=False)

    @property
    def fmu_fraction(self) -> float:
        """Share of the future Monte Carlo points that went through the FMU (outside the box)."""
        if self._slim is not None:
            return self._slim["fmu_fraction"]
        return float(np.mean(self.source != SOURCE_SURROGATE))

    @property
    def n_samples(self) -> int:
        """Monte Carlo draws per future year."""
        if self._slim is not None:
            return self._slim["n_samples"]
        return int(self.indicator.shape[1])

    @property
    def median_failure_year(self) -> Optional[int]:
        """Point forecast of the failure year: the first future year with P(unsafe) >= 0.5
        (:func:`twinmon.safety.median_failure_year`); ``failure_year`` is the year to act by.
        None for a withheld prognosis, as ``failure_year``."""
        from .safety import median_failure_year
        if self.status == STATUS_WITHHELD and not self.forced:
            return None
        return median_failure_year(self.years_future, self.p_unsafe)

    def indicator_quantiles(self, q) -> np.ndarray:
        """Quantiles of the indicator per future year, shape [len(q), h] (inf-aware; a failed
        run counts as an unreached level)."""
        if self._slim is not None and tuple(q) in self._slim["quantiles"]:
            return self._slim["quantiles"][tuple(q)]
        # The empirical (inverted-CDF) quantile never interpolates between two infinities.
        return np.quantile(np.where(np.isnan(self.indicator), np.inf, self.indicator), q, axis=1,
                           method="inverted_cdf")

    def slim(self) -> "UnitForecast":
        """A copy without the Monte Carlo arrays (samples, indicator, flags: ~0.4 MB a unit),
        keeping what :meth:`as_dict` and the command's lines read (a fleet's summary)."""
        from dataclasses import replace
        q = (0.05, 0.5, 0.95)
        keep = {"fmu_fraction": self.fmu_fraction, "n_samples": self.n_samples,
                "quantiles": {q: self.indicator_quantiles(list(q))}}
        return replace(self, samples=None, indicator=None, nonphysical=None, source=None,
                       indicator_observed=None, _slim=keep)

    def as_dict(self) -> dict:
        q05, med, q95 = self.indicator_quantiles((0.05, 0.5, 0.95))
        d = {
            "status": self.status,
            "status_reason": self.status_reason,
            "forced": self.forced,
            "root_cause": self.root_cause,
            "failure_year": self.failure_year,
            "median_failure_year": self.median_failure_year,
            "years": [int(y) for y in self.years_future],
            "p_unsafe": [round(float(p), 4) for p in self.p_unsafe],
            "trends": {name: {"slope": t.slope, "slope_ci90": [t.slope_ci[0], t.slope_ci[1]],
                              "intercept": t.intercept, "p_value": t.p_value, "test": t.test,
                              "normal_rate": t.normal_rate}
                       for name, t in self.trends.items()},
            "indicator": {"median": _finite(med), "q05": _finite(q05), "q95": _finite(q95)},
            "plan": self.plan,
            "detection": _drift_dict(self.drift),
            "attribution": ({"verdict": self.attribution.verdict,
                             "probabilities": {c: round(v, 3) for c, v in
                                               self.attribution.probabilities.items()},
                             "sets": {c: round(v, 3) for c, v in self.attribution.sets.items()},
                             "separating_channel": self.attribution.separating_channel or None}
                            if self.attribution is not None else None),
            "fmu_fraction": round(self.fmu_fraction, 4),
            "fmu_failures": self.fmu_failures,
        }
        if np.isfinite(self.pool_ess):
            d["pool_ess"] = round(self.pool_ess, 1)
        if self.has_truth:
            d["true_failure_year"] = self.true_failure_year
            d["truth_source"] = self.truth_source
        return d


def _drift_dict(dr: Optional[IndicatorDrift]) -> Optional[dict]:
    if dr is None:
        return None
    f = (lambda v: float(f"{v:.4g}") if np.isfinite(v) else None)
    return {"slope": f(dr.slope), "slope_se": f(dr.slope_se), "normal_slope": f(dr.normal_slope),
            "normal_tolerance": f(float(np.sum(dr.normal_halfwidth))),
            "p_value": f(dr.p_value), "p_inputs": f(dr.p_inputs),
            "abnormal": bool(dr.abnormal),
            "years": [int(y) for y in dr.years]}


def _drift_state(dr: IndicatorDrift) -> dict:
    """The detection as JSON-able values (for the artifact)."""
    return {"years": [int(y) for y in dr.years], "values": [float(v) for v in dr.values],
            "slope": dr.slope, "slope_se": dr.slope_se, "dof": dr.dof,
            "normal_slope": dr.normal_slope,
            "normal_halfwidth": [float(v) for v in dr.normal_halfwidth],
            "gradient": [float(v) for v in dr.gradient], "sense": dr.sense,
            "p_value": dr.p_value, "abnormal": bool(dr.abnormal), "p_inputs": dr.p_inputs}


def _drift_from(d: dict) -> IndicatorDrift:
    return IndicatorDrift(**{k: (np.asarray(v) if isinstance(v, list) else v)
                             for k, v in d.items()})


def _finite(a) -> list:
    """JSON-able list: non-finite values (a level never reached) become None."""
    return [round(float(v), 3) if np.isfinite(v) else None for v in a]


@dataclass
class ForecastSummary:
    """What :func:`forecast` did: per-unit results, the output path and the wall time (s)."""

    units: dict
    output: str
    wall_time: float
    box_physical: bool = True
    #: Plain-words warnings (an input whose degrading direction could not be told).
    warnings: list = field(default_factory=list)
    #: The fleet's prior of the joint method's year-to-year sd (:func:`_pooling_dict`).
    pooling: dict = field(default_factory=lambda: {"pooled": False})

    def as_dict(self) -> dict:
        return {"units": {u: f.as_dict() for u, f in self.units.items()},
                "output": self.output, "wall_time": round(self.wall_time, 3),
                "warnings": list(self.warnings), "sigma_pooling": self.pooling}


# ---------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------
def _unit_rng(cfg: Config, unit: str, stream: int) -> np.random.Generator:
    # Keyed by the unit's name, so a unit's forecast does not depend on the other units.
    return np.random.default_rng([cfg.seed + SEED_OFFSET, zlib.crc32(unit.encode()), stream])


def prognosis_status(up, cfg: Config, windows: list) -> tuple[str, str]:
    """Whether a unit's twin fits its data well enough for a prognosis.

    Withheld when at least ``forecast.withhold_years`` calibrated years (or the last one)
    miss the plant or sit on the design box's edge (calibrate's goodness of fit); else
    unreliable when a year did not converge; else ok.

    Returns
    -------
    status : str
        ``ok``, ``withheld`` or ``unreliable``.
    reason : str
        One sentence with the figures ("" when ok).
    """
    from .calibrate import STATUS_EDGE, STATUS_MISFIT, STATUS_UNCONVERGED
    st = np.asarray(up.status)
    bad = np.flatnonzero((st == STATUS_MISFIT) | (st == STATUS_EDGE))
    if bad.size and (bad.size >= cfg.forecast.withhold_years or bad[-1] == st.size - 1):
        f, k0 = up.fit, int(bad[0])
        first = int(up.years[k0])
        misfit = np.flatnonzero(st == STATUS_MISFIT)
        if misfit.size:
            k = int(misfit[np.argmax(f["window_rms"][misfit])])
            win = windows[int(f["window"][k])] if windows else "worst"
            return STATUS_WITHHELD, (
                f"prognosis withheld: the twin misses the plant by {f['window_rms'][k]:.1f} "
                f"noise sd in the {win} window (residual RMS {f['rms'][k]:.1f} sd in year "
                f"{int(up.years[k])}; {misfit.size} of {st.size} years miss) from year {first}; "
                "run 'twinmon diagnose'")
        k = int(bad[-1])
        j = int(np.argmax(f["edge_share"][k]))
        name = cfg.model.input_names[j]
        return STATUS_WITHHELD, (
            f"prognosis withheld: the estimates of {name} sit on the design box's edge "
            f"({100 * f['edge_share'][k][j]:.0f} % of the posterior in year {int(up.years[k])}) "
            f"from year {first}: the plant needs inputs outside the twin's box; widen "
            f"model.inputs.{name} or run 'twinmon diagnose'")
    unconv = np.flatnonzero(st == STATUS_UNCONVERGED)
    if unconv.size:
        yrs = ", ".join(str(int(up.years[k])) for k in unconv)
        return STATUS_UNRELIABLE, (f"prognosis unreliable: the posterior of year(s) {yrs} did "
                                   "not converge even with longer chains")
    return STATUS_OK, ""


def estimate_error_covariance(cfg: Config, post_cov: np.ndarray, sequential: bool) -> np.ndarray:
    """The yearly estimates' error covariance across years [n, n, d, d]
    (:func:`~twinmon.prognosis.filter_error_covariance`) from the posterior covariances
    [n, d, d]: carried from year to year through the sequential prior (``calibrate.
    prior_width``, ``prior_carry_variance``), or independent across years for the joint
    method (``sequential`` False), whose years are tied by the trend instead."""
    prior_var = ((cfg.calibrate.prior_width * np.diff(cfg.model.bounds, axis=1).ravel()) ** 2
                 if sequential else None)
    return filter_error_covariance(post_cov, prior_var, cfg.calibrate.prior_carry_variance)


def judge(cfg: Config, unit: str, plan: dict, ind_obs: np.ndarray, gradient: np.ndarray,
          directions: dict, observed: set) -> tuple[IndicatorDrift, Attribution]:
    """Detection on the health indicator, then attribution (see :mod:`twinmon.prognosis`).

    A unit is degrading when its indicator drifts beyond normal ageing or its inputs' slopes,
    jointly, leave the normal-ageing box; a unit whose indicator trend cannot be tested
    (fewer than 3 years with a finite indicator, e.g. a level no longer reached) is judged
    on its inputs alone."""
    from .safety import Indicator
    names = cfg.model.input_names
    specs = [cfg.model.inputs[n] for n in names]
    rate = np.array([s.normal_rate for s in specs])
    tol = np.array([s.normal_rate_tolerance for s in specs])
    ind = Indicator.from_config(cfg)
    alpha = cfg.forecast.alpha
    years = plan["years"]
    after = years >= plan["since"]     # a repair restarts the trends
    slope_draws = plan["slope_draws"]
    # A joint unit's indicator slope is its posterior trend's (the slopes of the last
    # segments, i.e. after any repair), through the gradient: the null is built on the same
    # linearisation.
    drift = indicator_drift(years[after], ind_obs[after], gradient, rate, tol,
                            ind.sense, alpha, _unit_rng(cfg, unit, 2),
                            slope_draws=None if slope_draws is None
                            else slope_draws @ np.asarray(gradient, float))
    trends = plan["trends"]
    tl = [trends[n] for n in names]
    dirs = [directions[n].sign for n in names]
    if slope_draws is not None:
        # The joint method sampled the slopes with the years: test its posterior's own
        # slopes (their spread includes the year-to-year variation and every year's
        # uncertainty, with the correlations the yearly means' regression cannot see).
        b, C, dof = slope_draws.mean(axis=0), np.cov(slope_draws, rowvar=False), POSTERIOR_DOF
    else:
        err = plan["err_cov"][after][:, after]
        b = np.array([t.slope for t in tl])
        C, dof = slope_covariance(tl, plan["resid"], years[after], err), max(tl[0].dof, 1)
    C = np.atleast_2d(C)
    drift.p_inputs = box_test_uniform(b, C, dof, rate, tol, dirs, _unit_rng(cfg, unit, 4))
    # Two views of one question, each at alpha / 2 (Bonferroni): the indicator's drift
    # (sees a fault the inputs trade off between) and the inputs' slopes jointly (sees a
    # fault another input's normal ageing hides from the indicator).
    if np.isfinite(drift.p_value):
        drift.abnormal = bool(min(drift.p_value, drift.p_inputs) < alpha / 2)
    else:
        drift.abnormal = bool(drift.p_inputs < alpha)
    if not drift.abnormal:
        return drift, Attribution(HEALTHY)
    att = attribute(tl, names, [s.component or n for s, n in zip(specs, names)], C, rate, tol,
                    dirs, cfg.forecast.attribution_confidence, _unit_rng(cfg, unit, 3),
                    draws=slope_draws)
    if att.verdict == AMBIGUOUS and att.leading_slopes is not None:
        years = plan["years"]
        first = np.array([trends[n].intercept + trends[n].slope * years[0] for n in names])
        observed = observed | {cfg.model.output.variable}
        att.separating_channel, att.channel_scores = separating_channel(
            cfg, observed, first, att.leading_slopes, float(years[-1] - years[0]))
    return drift, att


def maintenance_plan(trends: dict, years_future: np.ndarray,
                     p_unsafe: np.ndarray, failure_year: Optional[int], last_year: int,
                     p_unsafe_now: float, safety, drift: Optional[IndicatorDrift] = None,
                     attribution: Optional[Attribution] = None, cfg: Optional[Config] = None
                     ) -> str:
    """A concrete maintenance recommendation: component, deadline year, evidence.

    With a detection (``drift``, ``attribution``), the components come from the attribution
    and the evidence is the indicator's drift; otherwise from the inputs' slope tests."""
    comps = {}
    for name, t in trends.items():
        comps.setdefault(t.component or name, []).append((name, t))
    if attribution is not None and drift is not None:
        from .safety import Indicator
        ind = Indicator.from_config(cfg)
        probs = attribution.probabilities
        conf = cfg.forecast.attribution_confidence
        evidence = ""
        if drift.abnormal:
            evidence = drift.describe(ind.name, ind.units)
            evidence += f"; inputs' slopes vs normal ageing jointly p = {drift.p_inputs:.2g}"
        if attribution.verdict == AMBIGUOUS:
            faulty = sorted(probs, key=lambda c: -probs[c])
            evidence += ("; the data cannot tell which component: " +
                         ", ".join(f"{c} {probs[c]:.2f}" for c in faulty) +
                         (f"; recording {attribution.separating_channel} would separate them"
                          if attribution.separating_channel else ""))
            maybe = []
        else:
            faulty = sorted(c for c, pr in probs.items() if pr >= conf)
            maybe = sorted(c for c, pr in probs.items() if 0.05 < pr < conf)
            if maybe:
                evidence += "; " + ", ".join(f"{c} possibly too ({probs[c]:.2f})"
                                             for c in maybe)
        sound = sorted(c for c in comps if c not in faulty and c not in maybe)
    else:
        faulty = sorted(c for c, ts in comps.items() if any(t.rejects for _, t in ts))
        sound = sorted(c for c in comps if c not in faulty)
        evidence = "; ".join(
            f"{name} slope {t.slope:+.3g}/yr vs normal {t.normal_rate:+.3g} +- "
            f"{t.tolerance:.3g} (p = {t.p_value:.2g})"
            for c in faulty for name, t in comps[c] if t.rejects)
    # An ambiguous attribution lists the candidates, most probable first.
    join = " or the " if attribution is not None and attribution.verdict == AMBIGUOUS \
        else " and the "
    sound_txt = (f"; {' and '.join(sound)} within normal ageing" if sound else "")
    limit = safety.failure_probability
    if failure_year is not None:
        k = int(np.flatnonzero(years_future == failure_year)[0])
        when = ("now (already unsafe: P(unsafe) "
                f"{p_unsafe_now:.2f} in year {last_year})" if p_unsafe_now > limit
                else "now" if failure_year <= last_year + 1
                else f"before year {failure_year - 1} ends")
        what = (f"Inspect/replace the {join.join(faulty)}" if faulty
                else "Overhaul the unit (normal ageing alone reaches the limit)")
        return (f"{what} {when}: P(unsafe) {p_unsafe[k]:.2f} in year {failure_year} "
                f"(limit {limit:.2f})" + (f" [{evidence}]" if evidence else "") + sound_txt + ".")
    pmax = float(np.max(p_unsafe)) if p_unsafe.size else 0.0
    horizon_end = int(years_future[-1]) if years_future.size else last_year
    if faulty:
        return (f"Inspect the {join.join(faulty)} at the next planned stop: "
                f"degrading faster than normal ageing [{evidence}], though P(unsafe) stays "
                f"<= {limit:.2f} through year {horizon_end} (max {pmax:.2f}){sound_txt}.")
    return (f"No action: all components within normal ageing; P(unsafe) stays <= {limit:.2f} "
            f"through year {horizon_end} (max {pmax:.2f}). Re-check at next year's recording.")


def forecast(cfg: Config, posterior_path: str | os.PathLike, surrogate_path: str | os.PathLike,
             output: str | os.PathLike, truth_path: str | os.PathLike | None = None,
             executor=None, workers: Optional[int] = None,
             progress: Optional[Callable[[int, int], None]] = None) -> ForecastSummary:
    """Forecast every unit of a posterior and write ``forecast.h5``.

    Units stream through: read from the posterior one chunk at a time, forecast on the pool
    of :func:`iter_forecast`, written and dropped (the summary keeps each unit's figures, not
    its Monte Carlo arrays), so memory does not grow with the fleet.

    Parameters
    ----------
    cfg : Config
    posterior_path : path-like
        Posterior artifact of ``calibrate`` (per unit and year: samples and mean).
    surrogate_path : path-like
        Surrogate artifact of ``reduce``.
    output : path-like
        The forecast artifact to write.
    truth_path : path-like, optional
        Truth file of ``fabricate``: adds each unit's true failure year.
    executor : Executor, optional
        For the FMU runs when the units are forecast in this process (one unit, or one
        worker); defaults to ``cfg.simulate.executor`` with ``cfg.simulate.workers``.
    workers : int, optional
        Processes over units (default ``cfg.simulate.workers``; 0 = one per core).
    progress : callable, optional
        ``progress(done, total)`` over the units.

    Raises
    ------
    ArtifactError
        An input artifact is missing, of the wrong kind, or made for other inputs.
    CalibrationError
        A unit has fewer than 3 years (no prediction interval is possible).
    """
    from .calibrate import read_posterior
    from .reduce import check_made_for, read_surrogate

    from .executors import check_workers
    start = _time.perf_counter()
    check_workers(cfg.simulate.workers if workers is None else workers)
    posterior_path, surrogate_path = Path(posterior_path), Path(surrogate_path)
    names = cfg.model.input_names
    post = read_posterior(posterior_path)
    if list(post.input_names) != names:
        raise ArtifactError(f"{posterior_path}: posterior inputs {list(post.input_names)} "
                            f"differ from the config's inputs {names}")
    sur = read_surrogate(surrogate_path)
    check_made_for(cfg, surrogate_path, sur.input_names, sur.time, sur.bounds,
                   "simulate and reduce")
    if not post.units:
        raise ArtifactError(f"{posterior_path}: no units in the posterior")
    made_with = artifacts.read_provenance(posterior_path).get("surrogate_id", "")
    if made_with and made_with != sur.fingerprint():
        raise ArtifactError(f"{posterior_path}: calibrated through another surrogate than "
                            f"{surrogate_path} (their fingerprints differ); re-run calibrate, "
                            "or pass the surrogate it was made with")
    truth = None
    if truth_path is not None:
        from .fabricate import read_truth
        truth = read_truth(truth_path)
    directions = degrading_directions(cfg, sur)
    box_ok = box_is_physical(cfg)
    fleet = fleet_sigma_prior(cfg, post)
    units = {}
    with _open_forecast(output, cfg, names, directions, box_ok, seed=cfg.seed + SEED_OFFSET,
                        inputs=[posterior_path, surrogate_path] +
                        ([truth_path] if truth_path else [])) as f:
        f.attrs["sigma_pooling"] = artifacts.json_attr(_pooling_dict(fleet, names))
        for unit, uf in iter_forecast(cfg, post, sur, posterior_path=posterior_path,
                                      truth=truth, truth_path=truth_path, executor=executor,
                                      workers=workers, progress=progress,
                                      directions=directions, box_ok=box_ok, fleet=fleet):
            _write_unit(f, cfg, unit, uf, names)
            units[unit] = uf.slim()
    warnings = [d.note for d in directions.values() if d.note]
    few = {u: uf.pool_ess for u, uf in units.items() if uf.pool_ess < POOL_MIN_ESS}
    if few:
        worst = min(few, key=few.get)
        warnings.append(
            f"{len(few)} unit(s) keep fewer than {POOL_MIN_ESS} effective posterior draws "
            f"once their year-to-year sd is pooled over the fleet (fewest: {worst}, "
            f"{few[worst]:.0f}): their forecast rests on few trend draws; a larger "
            "calibrate.keep_draws keeps more")
    return ForecastSummary(units, str(output), _time.perf_counter() - start, box_ok,
                           warnings, _pooling_dict(fleet, names))


def fleet_sigma_prior(cfg: Config, post):
    """The fleet's prior of the joint method's year-to-year sd (:mod:`.calibrate.fleet`),
    fitted on the posterior's jointly calibrated units; None when ``forecast.pool_sigma`` is
    off or fewer than ``forecast.pool_min_units`` units were calibrated jointly.

    Returns
    -------
    FleetPrior or None

    The units' ``sigma`` draws ([keep_draws, d] each) are read before the units stream
    through the forecast. A posterior written before the prior's scale was
    recorded (``trend/sigma_scale``) is taken to have been calibrated with this config's
    ``calibrate.prior_width``.
    """
    from .calibrate.fleet import fit_fleet_prior
    from .calibrate.trend import sigma_prior_scale
    if not cfg.forecast.pool_sigma:
        return None
    default = sigma_prior_scale(cfg)
    sigmas, bases = [], []
    d = default.size
    for unit, trend in _sigma_draws(post):
        sigma = np.asarray(trend["sigma"], float)
        base = np.asarray(trend.get("sigma_scale", default), float)
        where = f"{post.path}: /units/{unit}/trend/sigma"
        if sigma.ndim != 2 or sigma.shape[1] != d or not sigma.size:
            raise ArtifactError(f"{where} must have shape (draws, {d}), got {sigma.shape}")
        bad = ~(np.isfinite(sigma) & (sigma >= 0))
        if bad.any():
            j, i = np.argwhere(bad)[0]
            raise ArtifactError(f"{where} must hold finite values >= 0, got {sigma[j, i]} "
                                f"at draw {j}, input {i}")
        if base.shape != (d,) or not np.all(np.isfinite(base) & (base > 0)):
            raise ArtifactError(f"{post.path}: /units/{unit}/trend/sigma_scale must hold "
                                f"{d} finite values > 0, got {base.tolist()}")
        sigmas.append(sigma)
        bases.append(base)
    if len(sigmas) < cfg.forecast.pool_min_units:
        return None
    if not np.allclose(bases, bases[0], rtol=1e-9):
        raise CalibrationError(
            f"{post.path}: the jointly calibrated units were calibrated with different "
            "priors of their year-to-year sd (calibrate.prior_width); pooling them needs one "
            "(re-run calibrate, or set forecast.pool_sigma: false)")
    return fit_fleet_prior(sigmas, bases[0])


def _sigma_draws(post):
    """``(unit, {"sigma": [n, d][, "sigma_scale": [d]]})`` per jointly calibrated unit. From
    a file only those datasets are read, in one opening of it: a sequential posterior, which
    has no trend, costs a look at each unit's group."""
    units = post.units
    if not isinstance(units, artifacts.LazyUnits):
        for u in units:
            trend = getattr(units[u], "trend", None) or {}
            if trend:
                yield u, trend
        return
    with artifacts.open_artifact(units.path, "posterior") as f:
        for u in units:
            g = f["units"][u]
            if "trend" in g:
                yield u, {key: artifacts.get(g["trend"], key, units.path)
                          for key in ("sigma", "sigma_scale")
                          if key == "sigma" or key in g["trend"]}


def _pooling_dict(fleet, names: list) -> dict:
    """What the forecast pooled: the fleet's log-normal prior of the year-to-year sd (median,
    log-sd) and the calibration's half-Cauchy scale, per input."""
    if fleet is None:
        return {"pooled": False}
    return {"pooled": True, "units": fleet.n_units,
            "median": dict(zip(names, np.round(fleet.median, 6).tolist())),
            "log_sd": dict(zip(names, np.round(fleet.tau, 4).tolist())),
            "calibration_scale": dict(zip(names, np.round(fleet.base, 6).tolist()))}


def forecast_units(cfg: Config, post, sur, *, posterior_path="<memory>", truth=None,
                   truth_path=None, executor=None, workers: Optional[int] = None,
                   progress=None, directions=None, box_ok=None) -> tuple[dict, dict, bool]:
    """The forecast of every unit of a loaded posterior, in memory (no file written).

    ``backtest`` (which calls it on truncated histories) and the benchmarks use it; the
    arguments are those of :func:`iter_forecast`.

    Returns
    -------
    units : dict unit -> UnitForecast
    directions : dict input -> Direction
    box_ok : bool
    """
    if directions is None:
        directions = degrading_directions(cfg, sur)
    if box_ok is None:
        box_ok = box_is_physical(cfg)
    units = dict(iter_forecast(cfg, post, sur, posterior_path=posterior_path, truth=truth,
                               truth_path=truth_path, executor=executor, workers=workers,
                               progress=progress, directions=directions, box_ok=box_ok,
                               fleet=fleet_sigma_prior(cfg, post)))
    return units, directions, box_ok


#: Units per pool task: big enough that a task's FMU and surrogate batches amortise their
#: set-up, small enough that a few tasks in flight per worker hold little memory.
CHUNK_UNITS = 8
#: Tasks in flight per worker (the results wait in order to be written).
TASKS_PER_WORKER = 2


def iter_forecast(cfg: Config, post, sur, *, directions: dict, box_ok: bool,
                  posterior_path="<memory>", truth=None, truth_path=None, executor=None,
                  workers: Optional[int] = None, progress=None, fleet=None):
    """Forecast the units of ``post`` one chunk at a time; yields ``(unit, UnitForecast)`` in
    the posterior's order.

    With several units and workers, chunks of units go to a pool of worker processes
    (``cfg.simulate.executor``: ``process`` or ``dask``), each with the surrogate in numpy
    form and its own FMU instance for the points outside the surrogate's box; a few chunks
    are in flight at a time, so memory stays flat however many units. Otherwise the units
    are forecast here, the FMU runs on ``executor``. Every unit's random streams are keyed
    by its name, and a point's prediction does not depend on the other points of its batch:
    the result is the same whatever the workers and chunks.

    Parameters
    ----------
    post : Posterior
        ``post.units`` may be lazy (read one unit at a time).
    sur : Surrogate
    directions : dict input -> Direction
        From :func:`degrading_directions`.
    box_ok : bool
        From :func:`box_is_physical`.
    truth : Truth, optional
    executor : Executor, optional
        FMU runs of in-process forecasts; defaults to ``cfg.simulate.executor``.
    workers : int, optional
        Processes over units (default ``cfg.simulate.workers``; 0 = one per core).
    progress : callable, optional
        ``progress(done, total)`` over the units.
    fleet : FleetPrior, optional
        From :func:`fleet_sigma_prior`: the jointly calibrated units' draws are resampled to
        the fleet's prior of their year-to-year sd. The one thing a unit's forecast takes
        from the rest of its fleet.

    Raises
    ------
    CalibrationError, ArtifactError
        A unit's posterior cannot be forecast (checked before any work is sent out).
    SimulationError
        A worker process died.
    """
    from .executors import check_workers, make_executor
    from .simulate import spec_for
    unit_names = list(post.units)
    n = len(unit_names)
    n_workers = cfg.simulate.workers if workers is None else workers
    check_workers(n_workers)
    n_workers = min(n_workers or len(os.sched_getaffinity(0)), n)
    if cfg.simulate.executor == "serial":
        n_workers = 1
    spec = spec_for(cfg)
    context = dict(directions=directions, box_ok=box_ok, fit_windows=post.fit_windows,
                   truth_path=truth_path, fleet=fleet)

    def chunk_of(names_):
        ups = []
        for u in names_:
            up = post.units[u]
            _check_unit(cfg, posterior_path, u, up)
            ups.append((u, up, _truth_of(truth, truth_path, u)))
        return ups

    size = _chunk_size(n, n_workers)
    chunks = [unit_names[i:i + size] for i in range(0, n, size)]
    done = 0
    if n_workers <= 1 and not (cfg.simulate.executor == "dask" and cfg.dask.address):
        own = executor is None
        if own:
            executor = make_executor(cfg.simulate.executor, cfg.simulate.workers, cfg.dask)
        try:
            # One unit, or one worker: the FMU runs fan out on the executor instead.
            state = _TwinState(cfg, sur, spec, executor)
            for names_ in chunks:
                for unit, uf in _forecast_chunk(state, chunk_of(names_), **context):
                    done += 1
                    if progress:
                        progress(done, n)
                    yield unit, uf
        finally:
            if own:
                executor.close()
        return
    yield from _pooled(cfg, sur, spec, chunks, chunk_of, context, n_workers, progress)


def _chunk_size(n_units: int, n_workers: int) -> int:
    """Units per chunk: up to ``CHUNK_UNITS``, at least four chunks per worker when the
    fleet is small (the workers finish together)."""
    return max(1, min(CHUNK_UNITS, -(-n_units // (4 * max(n_workers, 1)))))


def _pooled(cfg, sur, spec, chunks, chunk_of, context, n_workers, progress):
    """:func:`iter_forecast` on a pool: ``TASKS_PER_WORKER`` chunks in flight per worker,
    results yielded in the chunks' order."""
    from collections import deque

    from .errors import Interrupted, SimulationError
    from .executors import closing_pool, open_pool
    pool = open_pool(cfg, "simulate", n_workers, _init_worker, (cfg, sur, spec),
                     files=(spec.fmu,))
    n, done = sum(len(c) for c in chunks), 0
    with closing_pool(pool, SimulationError(
            f"{spec.fmu}: a worker process died while forecasting (a crash in the FMU's native "
            "code?); nothing was written; re-run with simulate.workers=1 to see which unit"),
            Interrupted("forecast: interrupted; nothing was written")):
        queue, todo = deque(), iter(chunks)
        for names_ in todo:
            queue.append(pool.submit(_chunk_task, chunk_of(names_), context))
            if len(queue) >= TASKS_PER_WORKER * n_workers:
                break
        while queue:
            results = queue.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                queue.append(pool.submit(_chunk_task, chunk_of(nxt), context))
            for unit, uf in results:
                done += 1
                if progress:
                    progress(done, n)
                yield unit, uf


class _TwinState:
    """What forecasting a chunk needs once per process: the config, the surrogate and its
    numpy form (:class:`~twinmon.calibrate.vectorised.GPBatch`, checked against OpenTURNS
    when built), the FMU spec and the executor of the FMU runs."""

    def __init__(self, cfg: Config, sur, spec, executor):
        from .calibrate.samplers.gpbatch import make_predictor
        self.cfg, self.sur, self.spec, self.executor = cfg, sur, spec, executor
        self.predict = make_predictor(sur)[0]


_worker_state: Optional[_TwinState] = None


def _init_worker(cfg: Config, sur, spec) -> None:
    """Pool initializer: the worker's twin, its FMU instance kept open from chunk to chunk."""
    global _worker_state
    from multiprocessing.util import Finalize

    from .executors import SerialExecutor
    ex = SerialExecutor(keep_open=True)
    _worker_state = _TwinState(cfg, sur, spec, ex)
    # Pool workers leave by os._exit: only multiprocessing's finalizers close the FMU.
    Finalize(ex, ex.close, exitpriority=10)


def _chunk_task(units: list, context: dict) -> list:
    return _forecast_chunk(_worker_state, units, **context)


def _check_unit(cfg: Config, posterior_path, unit: str, up) -> None:
    """A unit's posterior must allow a forecast (raised before any work is sent out)."""
    years = np.asarray(up.years, int)
    mean = np.asarray(up.mean, float)
    d = len(cfg.model.input_names)
    if years.size < 3:
        raise CalibrationError(f"{posterior_path}: unit {unit} has {years.size} year(s); a "
                               "trend with prediction intervals needs at least 3")
    if mean.shape != (years.size, d) or not np.all(np.isfinite(mean)):
        raise ArtifactError(f"{posterior_path}: /units/{unit}/mean must be finite with "
                            f"shape ({years.size}, {d}), got shape {mean.shape}")
    _check_plausible(posterior_path, unit, np.asarray(up.samples, float), cfg)


def _truth_of(truth, truth_path, unit: str):
    """The unit's (years, inputs, future years, future inputs) of the truth file (the last
    two None when it has no future), or None without one."""
    if truth is None:
        return None
    if unit not in truth.inputs:
        raise ArtifactError(f"{truth_path}: unit {unit} is missing from the truth file")
    return (np.asarray(truth.years[unit], float), truth.inputs[unit],
            truth.future_years.get(unit), truth.future_inputs.get(unit))


def _forecast_chunk(state: _TwinState, units: list, *, directions: dict, box_ok: bool,
                    fit_windows: list, truth_path, fleet=None) -> list:
    """Forecast a chunk of units: their Monte Carlo points go through the twin in one batch.

    Parameters
    ----------
    state : _TwinState
    units : list of (unit, UnitPosterior, truth or None)

    Returns
    -------
    list of (unit, UnitForecast)
    """
    cfg = state.cfg
    plans, points = [], []
    for unit, up, _ in units:
        p, pts = _plan_unit(cfg, unit, up, directions, fleet)
        plans.append(p)
        points += pts
    twin = evaluate_twin(cfg, state.sur, np.concatenate(points), state.executor,
                         fmu_everywhere=not box_ok, predict=state.predict, spec=state.spec)
    unsafe_all = twin.unsafe(cfg.safety)
    out, offset = [], 0
    for (unit, up, tr), p in zip(units, plans):
        uf, offset = _finish_unit(cfg, unit, up, p, twin, unsafe_all, offset, directions,
                                  fit_windows)
        if tr is not None:
            _add_truth(cfg, uf, unit, tr, truth_path, state.spec, state.executor)
        out.append((unit, uf))
    return out


def _plan_unit(cfg: Config, unit: str, up, directions: dict,
               fleet=None) -> tuple[dict, list]:
    """A unit's trends, tests and Monte Carlo points (future states, posterior draws of the
    observed years, the probes of the indicator's gradient) before the twin runs.

    With ``fleet`` (:func:`fleet_sigma_prior`), a jointly calibrated unit's draws -- the
    years' and the trend's, which are the same chain states -- are first resampled to its
    posterior under the fleet's prior of the year-to-year sd; its yearly estimates are then
    those draws' means."""
    fc = cfg.forecast
    names = cfg.model.input_names
    d = len(names)
    years = np.asarray(up.years, int)
    mean = np.asarray(up.mean, float)
    samples_post = np.asarray(up.samples, float)
    trend_post = getattr(up, "trend", None) or {}
    pool_ess = float("nan")
    if fleet is not None and trend_post:
        trend_post, pooled, pool_ess = _pool_unit(cfg, unit, trend_post, samples_post, fleet)
        if pooled is not samples_post:
            samples_post, mean = pooled, pooled.mean(axis=1)
    since = repair_years(cfg, up, years)
    trends = {}
    slope_draws = None
    if trend_post:
        from .calibrate.trend import last_segment
        slope_draws = last_segment(trend_post, "slope")         # [n, d]
    for i, name in enumerate(names):
        spec = cfg.model.inputs[name]
        t = segment_trend(years, mean[:, i], since[name], spec)
        t.component = spec.component
        args = (spec.normal_rate, spec.normal_rate_tolerance, directions[name].sign, fc.alpha)
        trends[name] = (t if t.test else
                        posterior_slope_test(t, slope_draws[:, i], *args) if trend_post
                        else slope_test(t, *args))
    # The inputs' residuals on the years every trend covers (after the latest repair).
    common = years >= max(since.values())
    resid = np.column_stack([mean[common, i] - (trends[n].intercept + trends[n].slope *
                                                years[common]) for i, n in enumerate(names)])
    corr = (residual_correlation(resid) if fc.correlate and common.sum() >= 3
            else np.eye(d))
    # Probe points of the indicator's gradient at the unit's mid-history state (the
    # detection's normal-ageing band), evaluated with every other point.
    probe, step = gradient_points(cfg, mid_state(trends, names))
    fut = years[-1] + np.arange(1, fc.horizon + 1)
    post_cov = np.array([np.cov(samples_post[k], rowvar=False).reshape(d, d)
                         for k in range(years.size)])
    state = None
    err_cov = estimate_error_covariance(cfg, post_cov, sequential=not trend_post)
    if trend_post:
        # The joint method sampled the trend itself: draw the future from its posterior
        # predictive (levels, slopes and year-to-year sd), not from lines refitted to
        # the yearly means.
        from .calibrate.trend import trend_predictive
        rng = _unit_rng(cfg, unit, 0)
        draws = trend_predictive(trend_post, fut, rng)          # [n, h, d]
        X = draws[rng.integers(0, draws.shape[0], fc.samples)].transpose(1, 0, 2)
        state = "trend"
    elif fc.predictive == "state":
        state = state_predictive([trends[n] for n in names], years[common], resid,
                                 post_cov[common], fut)
        X = sample_state(state, fc.samples, _unit_rng(cfg, unit, 0))
    else:
        X = sample_predictive([trends[n] for n in names], fut, corr, fc.samples,
                              _unit_rng(cfg, unit, 0))
    n_o = min(fc.observed_samples, samples_post.shape[1])
    pick = np.sort(_unit_rng(cfg, unit, 1).choice(samples_post.shape[1], n_o, replace=False))
    Xo = samples_post[:, pick, :]
    plan = dict(years=years, mean=mean, trends=trends, fut=fut, X=X, Xo=Xo, corr=corr,
                resid=resid, step=step, since=max(since.values()), post_cov=post_cov,
                err_cov=err_cov, state=state, slope_draws=slope_draws, pool_ess=pool_ess)
    return plan, [X.reshape(-1, d), Xo.reshape(-1, d), probe]


def _pool_unit(cfg: Config, unit: str, trend: dict, samples: np.ndarray,
               fleet) -> tuple[dict, np.ndarray, float]:
    """A jointly calibrated unit's trend draws and years' draws [n_y, n, d] resampled to the
    fleet's prior of the year-to-year sd; returns them and the weights' effective number of
    draws."""
    from .calibrate.trend import TREND_DRAWS
    idx, ess_frac = fleet.resample(np.asarray(trend["sigma"], float), _unit_rng(cfg, unit, 5))
    pooled = {k: (np.asarray(v)[idx] if k in TREND_DRAWS else v) for k, v in trend.items()}
    # The artifact thins the years' and the trend's draws alike, so draw j is one chain
    # state in both; a posterior whose counts differ keeps its years' draws as they are.
    if samples.shape[1] == idx.size:
        samples = samples[:, idx, :]
    return pooled, samples, ess_frac * idx.size


def _finish_unit(cfg: Config, unit: str, up, p: dict, twin: TwinResult,
                 unsafe_all: np.ndarray, offset: int, directions: dict,
                 fit_windows: list) -> tuple[UnitForecast, int]:
    """A unit's forecast from its plan and its slice of the chunk's twin results (starting at
    ``offset``): probabilities, failure year, verdict, plan, status. Returns it and the
    offset of the next unit."""
    from .safety import failure_year as first_failure
    fc = cfg.forecast
    names = cfg.model.input_names
    d = len(names)
    h, n_s = p["X"].shape[:2]
    n_y, n_o = p["Xo"].shape[:2]
    sl = slice(offset, offset + h * n_s)
    so = slice(sl.stop, sl.stop + n_y * n_o)
    sg = slice(so.stop, so.stop + 2 * d)
    value = twin.value[sl].reshape(h, n_s)
    p_unsafe = unsafe_all[sl].reshape(h, n_s).mean(axis=1)
    p_obs = unsafe_all[so].reshape(n_y, n_o).mean(axis=1)
    fyear = first_failure(p["fut"], p_unsafe, cfg.safety)
    trends = p["trends"]
    ind_obs = twin.value[so].reshape(n_y, n_o)
    drift, attribution = judge(cfg, unit, p, ind_obs, gradient_from(twin.value[sg], p["step"]),
                               directions, set(getattr(up, "channels", None) or ()))
    pm, plo, phi = {}, {}, {}
    for i, (name, t) in enumerate(trends.items()):
        if isinstance(p["state"], str):      # the joint method's trend draws
            q = np.quantile(p["X"][:, :, i], [0.5, (1 - fc.confidence) / 2,
                                              (1 + fc.confidence) / 2], axis=1)
            pm[name], plo[name], phi[name] = q
        elif p["state"] is not None:
            pm[name], plo[name], phi[name] = state_interval(p["state"], i, fc.confidence)
        else:
            pm[name], plo[name], phi[name], _ = t.predict(p["fut"], fc.confidence)
    uf = UnitForecast(
        years_observed=p["years"], estimates={n: p["mean"][:, i] for i, n in enumerate(names)},
        years_future=p["fut"], trends=trends, pred_mean=pm, pred_lo=plo, pred_hi=phi,
        samples=p["X"], indicator=value, nonphysical=twin.nonphysical[sl].reshape(h, n_s),
        source=twin.source[sl].reshape(h, n_s), p_unsafe=p_unsafe,
        indicator_observed=ind_obs, p_unsafe_observed=p_obs,
        failure_year=fyear, root_cause=attribution.verdict,
        fmu_failures=int(np.sum(twin.source[sl] == SOURCE_FAILED)),
        drift=drift, attribution=attribution, pool_ess=p["pool_ess"])
    uf.plan = maintenance_plan(trends, p["fut"], p_unsafe, fyear,
                               int(p["years"][-1]), float(p_obs[-1]), cfg.safety,
                               drift=drift, attribution=attribution, cfg=cfg)
    uf.status, uf.status_reason = prognosis_status(up, cfg, fit_windows)
    if uf.status == STATUS_WITHHELD:
        if fc.force_prognosis:
            uf.forced = True
            uf.plan = f"FORCED despite: {uf.status_reason}. {uf.plan}"
        else:
            # A twin that misses the data predicts nothing about the plant.
            uf.failure_year, uf.root_cause, uf.plan = None, STATUS_WITHHELD, \
                uf.status_reason[0].upper() + uf.status_reason[1:] + "."
    elif uf.status == STATUS_UNRELIABLE:
        uf.plan = f"{uf.plan} ({uf.status_reason}.)"
    return uf, sg.stop


def _check_plausible(path, unit: str, samples: np.ndarray, cfg: Config) -> None:
    """Posterior draws must be finite and inside the design box widened by the fit margin
    (calibration's prior never leaves the box): anything else is a damaged or foreign file,
    and a forecast from it would be garbage with exit 0."""
    box = cfg.model.bounds
    pad = cfg.diagnose.fit_margin * (box[:, 1] - box[:, 0])
    lo, hi = box[:, 0] - pad, box[:, 1] + pad
    bad = ~np.isfinite(samples) | (samples < lo) | (samples > hi)
    if bad.any():
        k, j, i = np.argwhere(bad)[0]
        name = cfg.model.input_names[i]
        raise ArtifactError(f"{path}: /units/{unit}/samples[{k}, {j}, {i}] ({name}) is "
                            f"{float(samples[k, j, i]):g}, outside the design box "
                            f"[{box[i, 0]:g}, {box[i, 1]:g}] widened by the fit margin: "
                            "a damaged or foreign posterior; re-run calibrate")


def _add_truth(cfg: Config, uf: UnitForecast, unit: str, truth_unit, truth_path, spec,
               executor) -> None:
    """True future inputs, indicator and failure year, run through the FMU.

    ``truth_unit``: the unit's years [n_y], inputs {name: [n_y]}, and the truth file's
    future years [h] and inputs {name: [h]} or None. The future is the truth file's where it
    covers the forecast's years (what the unit will really be, year-to-year jitter
    included); otherwise (truth files written before it was recorded, a longer horizon) each
    true trajectory's fitted line extended. ``uf.truth_source`` says which."""
    from .safety import Indicator, is_unsafe
    from .simulate import as_parameters, run_batch
    ty, inputs, fy, finputs = truth_unit
    names = cfg.model.input_names
    realised = False
    if fy is not None and all(n in finputs for n in names):
        fy = np.asarray(fy)
        pos = np.searchsorted(fy, uf.years_future)
        realised = bool(np.all(pos < fy.size)) and np.array_equal(fy[pos], uf.years_future)
    Xt = np.empty((uf.years_future.size, len(names)))
    for i, name in enumerate(names):
        if name not in inputs:
            raise ArtifactError(f"{truth_path}: /units/{unit}/inputs/{name} is missing")
        if realised:
            Xt[:, i] = np.asarray(finputs[name], float)[pos]
        else:
            slope, icpt = np.polyfit(ty, np.asarray(inputs[name], float), 1)
            Xt[:, i] = icpt + slope * uf.years_future
    uf.truth_source = "recorded future" if realised else "trend line"
    batch = run_batch(spec, as_parameters(cfg, Xt), executor)
    ind = Indicator.from_config(cfg)
    value = np.where(batch.ok, ind(spec.times, batch.outputs[ind.variable]), np.nan)
    nph = (batch.outputs[cfg.model.nonphysical][:, -1] > 0.5) if cfg.model.nonphysical else None
    bad = is_unsafe(value, cfg.safety, nph) | ~batch.ok
    uf.has_truth = True
    uf.true_indicator = value
    uf.true_unsafe = bad
    uf.true_inputs = {n: Xt[:, i] for i, n in enumerate(cfg.model.input_names)}
    uf.true_failure_year = int(uf.years_future[np.argmax(bad)]) if bad.any() else None


# ---------------------------------------------------------------------------------------
# The artifact
# ---------------------------------------------------------------------------------------
@contextmanager
def _open_forecast(path, cfg: Config, names: list, directions: dict, box_ok: bool, *,
                   seed: int, inputs: list):
    """The forecast artifact being written, its fleet-wide attributes set; yields the open
    (temporary) file for :func:`_write_unit`, renamed into place when the block ends well."""
    from .safety import Indicator
    ind = Indicator.from_config(cfg)
    section = cfg.section_yaml(*SECTIONS)
    with artifacts.write_artifact(path, "forecast", config=section, inputs=inputs,
                                  seed=seed, compact=True) as f:
        f.attrs["input_names"] = artifacts.json_attr(names)
        f.attrs["input_units"] = artifacts.json_attr([cfg.model.inputs[n].units for n in names])
        f.attrs["directions"] = artifacts.json_attr({n: d.sign for n, d in directions.items()})
        f.attrs["direction_sources"] = artifacts.json_attr(
            {n: {"source": d.source, "effect": d.effect, "noise": d.noise, "note": d.note}
             for n, d in directions.items()})
        f.attrs["confidence"] = cfg.forecast.confidence
        f.attrs["alpha"] = cfg.forecast.alpha
        f.attrs["indicator"] = artifacts.json_attr(
            {"name": ind.name, "label": ind.label, "units": ind.units, "limit": ind.limit,
             "sense": ind.sense, "variable": ind.variable, "kind": ind.spec.kind})
        f.attrs["failure_probability"] = cfg.safety.failure_probability
        f.attrs["box_physical"] = box_ok
        yield f


def _write_unit(f, cfg: Config, unit: str, u: UnitForecast, names: list) -> None:
    """One unit's group of the forecast artifact."""
    from .safety import Indicator
    put = artifacts.put
    ind = Indicator.from_config(cfg)
    g = f.create_group(f"units/{unit}")
    g.attrs["status"], g.attrs["status_reason"] = u.status, u.status_reason
    g.attrs["forced"] = u.forced
    g.attrs["root_cause"] = u.root_cause
    if u.drift is not None:
        g.attrs["detection"] = artifacts.json_attr(_drift_state(u.drift))
    if u.attribution is not None:
        a = u.attribution
        g.attrs["attribution"] = artifacts.json_attr(
            {"verdict": a.verdict, "probabilities": a.probabilities, "sets": a.sets,
             "separating_channel": a.separating_channel,
             "channel_scores": a.channel_scores})
    g.attrs["failure_year"] = -1 if u.failure_year is None else u.failure_year
    g.attrs["plan"] = u.plan
    g.attrs["fmu_fraction"] = u.fmu_fraction
    g.attrs["fmu_failures"] = u.fmu_failures
    put(g, "years_observed", u.years_observed.astype(np.int64), "year",
        "observed years (1 = first year of service)")
    put(g, "years_future", u.years_future.astype(np.int64), "year", "forecast years")
    for i, name in enumerate(names):
        t, un = u.trends[name], cfg.model.inputs[name].units
        tg = g.create_group(f"trends/{name}")
        for key in ("intercept", "slope", "slope_se", "residual_std", "x_mean", "sxx",
                    "normal_rate", "tolerance", "p_value"):
            tg.attrs[key] = float(getattr(t, key))
        tg.attrs["n"], tg.attrs["direction"] = t.n, t.direction
        tg.attrs["slope_ci90"] = np.array(t.slope_ci, float)
        tg.attrs["test"], tg.attrs["rejects"] = t.test, t.rejects
        tg.attrs["component"] = t.component
        put(tg, "estimate", u.estimates[name], un,
            f"posterior mean of {name} per observed year (regression data)")
        put(tg, "pred_mean", u.pred_mean[name], un, f"trend line of {name}, future years")
        c = f"{100 * cfg.forecast.confidence:g} %"
        put(tg, "pred_lo", u.pred_lo[name], un,
            f"lower {c} prediction bound (Student t, new observation)")
        put(tg, "pred_hi", u.pred_hi[name], un,
            f"upper {c} prediction bound (Student t, new observation)")
    # The Monte Carlo arrays: one compressed chunk per year (see _put_per_year).
    _put_per_year(g, "samples", u.samples, "input units",
                  "Monte Carlo input samples [future year, sample, input]")
    _put_per_year(g, "indicator", u.indicator, ind.units, f"{ind.name} per future "
                  "year and sample; inf = level never reached, NaN = FMU run failed")
    _put_per_year(g, "nonphysical", u.nonphysical.astype(np.int8), "1",
                  "1 where the FMU reported the non-physical mode")
    _put_per_year(g, "source", u.source, "1", "0 surrogate, 1 FMU (outside the box), "
                  "2 FMU run failed (counted unsafe)")
    put(g, "p_unsafe", u.p_unsafe, "1", "probability of being unsafe per future year")
    _put_per_year(g, "indicator_observed", u.indicator_observed, ind.units,
                  f"{ind.name} of posterior samples per observed year [year, sample]")
    put(g, "p_unsafe_observed", u.p_unsafe_observed, "1",
        "probability of being unsafe per observed year (posterior samples)")
    if np.isfinite(u.pool_ess):
        g.attrs["pool_ess"] = u.pool_ess
    if u.has_truth:
        g.attrs["true_failure_year"] = (-1 if u.true_failure_year is None
                                        else u.true_failure_year)
        g.attrs["truth_source"] = u.truth_source
        put(g, "truth/indicator", u.true_indicator, ind.units,
            f"{ind.name} of the true future inputs ({u.truth_source}), future years (FMU)")
        put(g, "truth/unsafe", u.true_unsafe.astype(np.int8), "1",
            "1 where the true unit is unsafe, future years")
        for name in names:
            put(g, f"truth/inputs/{name}", u.true_inputs[name],
                cfg.model.inputs[name].units,
                f"true {name} over the future years ({u.truth_source})")


def _put_per_year(g, name: str, data: np.ndarray, units: str, description: str) -> None:
    """A [year, sample, ...] array as one chunk per year, shuffled and gzip-compressed
    (flags and failed-run codes are mostly zeros; draws lose about a fifth), so that a
    fleet's forecast stays small and a unit-year is read alone."""
    data = np.asarray(data)
    opts = ({"chunks": (1,) + data.shape[1:], "compression": "gzip", "compression_opts": 4,
             "shuffle": True} if data.ndim >= 2 and data.size else {})
    artifacts.put(g, name, data, units, description, **opts)


@dataclass
class Forecast:
    """A loaded ``forecast.h5``: ``units`` maps unit -> :class:`UnitForecast`.

    Read from a file, ``units`` is an :class:`~twinmon.artifacts.LazyUnits` mapping: a unit
    is read when it is looked up, so a fleet's forecast never sits in memory whole."""

    path: Path
    input_names: list
    confidence: float
    units: Mapping
    directions: dict = field(default_factory=dict)
    #: The health indicator the forecast was made with (name, label, units, limit, sense,
    #: variable, kind); empty for files written before it was recorded.
    indicator: dict = field(default_factory=dict)
    #: The fleet's prior of the joint method's year-to-year sd (:func:`_pooling_dict`).
    sigma_pooling: dict = field(default_factory=lambda: {"pooled": False})


def read_forecast(path: str | os.PathLike, arrays: bool = True) -> Forecast:
    """Open a forecast artifact (schema checked); its units are read when looked up.

    ``arrays=False`` leaves each unit's Monte Carlo arrays (samples, indicator and flags,
    ~0.4 MB a unit) on disk: the unit is then as :meth:`UnitForecast.slim` makes it, for a
    fleet's summaries.

    Raises
    ------
    ArtifactError
        Missing file, wrong schema, no ``/units``; on access: a unit's missing datasets or
        damaged bytes (naming the file and the dataset).
    """
    path = Path(path)
    with artifacts.open_artifact(path, "forecast") as f:
        names = json.loads(f.attrs["input_names"])
        if "units" not in f:
            raise ArtifactError(f"{path}: group /units is missing")
        unit_names = list(f["units"])
        out = Forecast(path, names, float(f.attrs["confidence"]), {},
                       json.loads(f.attrs["directions"]),
                       json.loads(f.attrs["indicator"]) if "indicator" in f.attrs else {},
                       json.loads(f.attrs.get("sigma_pooling", '{"pooled": false}')))
    out.units = artifacts.LazyUnits(path, "forecast", unit_names,
                                    lambda f, unit, p: _read_unit(f, unit, p, names, arrays))
    return out


#: The per-sample datasets of a unit (what ``read_forecast(arrays=False)`` leaves on disk).
_MC_ARRAYS = ("samples", "indicator", "nonphysical", "source", "indicator_observed")


def _n_samples(g, path: Path) -> int:
    if "indicator" not in g:
        raise ArtifactError(f"{path}: dataset {g.name}/indicator is missing")
    return int(g["indicator"].shape[1])


def _read_unit(f, unit: str, path: Path, names: list, arrays: bool = True) -> UnitForecast:
    """Read one unit of an open forecast artifact (without its Monte Carlo arrays unless
    ``arrays``)."""
    def get(g, n):
        if not arrays and n in _MC_ARRAYS:
            return None
        return artifacts.get(g, n, path)
    if f"units/{unit}" not in f:
        raise ArtifactError(f"{path}: group /units/{unit} is missing")
    g = f["units"][unit]
    trends, est, pm, plo, phi = {}, {}, {}, {}, {}
    for name in names:
        if f"trends/{name}" not in g:
            raise ArtifactError(f"{path}: group /units/{unit}/trends/{name} is missing")
        tg = g[f"trends/{name}"]
        a = tg.attrs
        trends[name] = Trend(
            intercept=float(a["intercept"]), slope=float(a["slope"]),
            slope_se=float(a["slope_se"]), slope_ci=tuple(map(float, a["slope_ci90"])),
            residual_std=float(a["residual_std"]), n=int(a["n"]),
            x_mean=float(a["x_mean"]), sxx=float(a["sxx"]),
            normal_rate=float(a["normal_rate"]), tolerance=float(a["tolerance"]),
            direction=int(a["direction"]), p_value=float(a["p_value"]),
            test=str(a["test"]), rejects=bool(a["rejects"]),
            component=str(a["component"]))
        est[name], pm[name] = get(tg, "estimate"), get(tg, "pred_mean")
        plo[name], phi[name] = get(tg, "pred_lo"), get(tg, "pred_hi")
    fy = int(g.attrs["failure_year"])
    has_truth = "true_failure_year" in g.attrs
    tfy = int(g.attrs["true_failure_year"]) if has_truth else -1
    return UnitForecast(
        years_observed=get(g, "years_observed"), estimates=est,
        years_future=get(g, "years_future"), trends=trends, pred_mean=pm,
        pred_lo=plo, pred_hi=phi, samples=get(g, "samples"), indicator=get(g, "indicator"),
        nonphysical=get(g, "nonphysical").astype(bool) if arrays else None,
        source=get(g, "source"),
        p_unsafe=get(g, "p_unsafe"), indicator_observed=get(g, "indicator_observed"),
        p_unsafe_observed=get(g, "p_unsafe_observed"),
        failure_year=None if fy < 0 else fy, root_cause=str(g.attrs["root_cause"]),
        plan=str(g.attrs["plan"]), fmu_failures=int(g.attrs["fmu_failures"]),
        status=str(g.attrs.get("status", STATUS_OK)),
        status_reason=str(g.attrs.get("status_reason", "")),
        forced=bool(g.attrs.get("forced", False)),
        pool_ess=float(g.attrs.get("pool_ess", np.nan)),
        drift=_drift_from(json.loads(g.attrs["detection"])) if "detection" in g.attrs else None,
        attribution=(Attribution(**json.loads(g.attrs["attribution"]))
                     if "attribution" in g.attrs else None),
        has_truth=has_truth, true_failure_year=None if tfy < 0 else tfy,
        truth_source=str(g.attrs.get("truth_source", "trend line" if has_truth else "")),
        true_indicator=get(g, "truth/indicator") if has_truth else None,
        true_unsafe=get(g, "truth/unsafe").astype(bool) if has_truth else None,
        true_inputs={n: get(g, f"truth/inputs/{n}") for n in names} if has_truth
        else None,
        _slim=None if arrays else {"fmu_fraction": float(g.attrs["fmu_fraction"]),
                                   "quantiles": {}, "n_samples": _n_samples(g, path)})
