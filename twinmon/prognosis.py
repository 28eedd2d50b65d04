"""Detection on the health indicator and attribution of a drift to components.

Why not per-input slope tests alone: from one output channel, two inputs can move the
output in nearly the same way (for the pump, a damping rise and an efficiency decline give
almost the same start-up curve; their single-year estimates correlate at 0.9). Each input's
slope can then sit inside its normal-ageing band while the health indicator -- which the
data do identify -- drifts abnormally. So a unit is judged in two steps:

1. **Detection** (:func:`indicator_drift`): the OLS trend of the unit's yearly indicator
   (the posterior median of the indicator of each calibrated year; for a jointly calibrated
   unit, its posterior trend slopes through the twin's gradient) is tested against the
   indicator drift that normal ageing of every input produces. Under normal ageing each
   input's yearly rate is taken as uniform on ``normal_rate +- normal_rate_tolerance``,
   independently across inputs; through the twin's gradient at the unit's mid-history state
   this gives the distribution of the indicator's normal slope (a sum of uniforms). Its
   convolution with the Student-t error of the fitted slope is the null distribution; the
   p-value is its tail beyond the observed slope, on the unsafe side. The inputs' slopes
   are tested jointly against the same null (:func:`box_test_uniform`), and a unit is
   degrading when either p-value is below ``forecast.alpha / 2`` (``forecast.judge``).
2. **Attribution** (:func:`attribute`): the joint sampling distribution of the inputs'
   slopes (OLS slopes, covariance :func:`slope_covariance` -- the residual part ``S / Sxx``
   raised to the estimation errors the sequential prior carries from year to year,
   :func:`filter_error_covariance`; both carry the inputs' trade-off -- Student t, ``n - 2``
   dof) is split into the regions "these components beyond their normal band, the others
   within": the probability of each set of components, given that at least one is abnormal.
   The verdict names the components whose probability reaches
   ``forecast.attribution_confidence``; when none does, or another component sits between
   0.5 and that, it is ``ambiguous``, with the probabilities and the unobserved channel
   that would tell the leading explanations apart.

A repaired component's inputs are fitted from the repair on (see ``forecast``): their pre-repair
history does not make the unit degrading.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product
from typing import Optional

import numpy as np

#: Monte Carlo draws for the null distribution of the indicator slope and for attribution:
#: a probability's Monte Carlo sd is at most 0.0022 (0.5 / sqrt(50 000)), a tenth of the
#: distance at which a verdict threshold (0.5, 0.8) would matter; 200 000 cost 0.13 s a unit.
DRAWS = 50_000
#: Null draws of :func:`box_test_uniform` (each one a projection on the box): the Monte
#: Carlo sd of a p-value near alpha / 2 = 0.005 is 0.0005.
BOX_DRAWS = 20_000
#: Degrees of freedom that stand for "normal": a slope's error taken from posterior draws
#: (their count is no small-sample correction). ``twinmon.forecast`` uses the same value.
POSTERIOR_DOF = 10 ** 6
#: Verdict when no component can be named with enough confidence.
AMBIGUOUS = "ambiguous"
HEALTHY = "healthy"
#: Verdict for several components at once.
SEVERAL = "both"


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
    #: p-value of the inputs' slopes against the normal-ageing box (:func:`box_test`).
    p_inputs: float = float("nan")

    @property
    def excess(self) -> float:
        """Slope beyond the normal one, towards unsafe (indicator units per year)."""
        return float(self.sense * (self.slope - self.normal_slope))

    def describe(self, name: str, units: str) -> str:
        if not np.isfinite(self.slope):
            return f"{name} trend not testable ({self.years.size} finite year(s))"
        return (f"{name} slope {self.slope:+.3g} {units}/yr vs normal ageing "
                f"{self.normal_slope:+.3g} +- {float(np.sum(self.normal_halfwidth)):.3g} "
                f"(p = {self.p_value:.2g})")


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
                    alpha: float, rng: np.random.Generator,
                    slope_draws: Optional[np.ndarray] = None) -> IndicatorDrift:
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
    rng : numpy Generator
        For the Monte Carlo convolution (seeded per unit by the caller).
    slope_draws : ndarray, shape [n], optional
        Posterior draws of the indicator's slope (indicator units per year): a joint
        posterior's trend slopes through ``gradient``. The slope and its standard error are
        then theirs (normal error), not the OLS fit's to the yearly values. Those values
        are smoothed towards the joint trend, so their scatter about a line understates the
        slope's uncertainty: 4.4 times, median over the 96 healthy units of
        ``benchmarks/prognosis.py --healthy-only 96``, seed 31.
    """
    from scipy import stats
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
    # Null: excess = sum_i half_i * U(-1, 1) + se * t_dof. The uniform sum is drawn, the t
    # tail is exact given it.
    u = rng.uniform(-1.0, 1.0, (DRAWS, half.size)) @ half
    if se > 0:
        p = float(np.mean(stats.t.sf((excess - u) / se, dof)))
    else:
        p = float(np.mean(u >= excess))
    return IndicatorDrift(yrs, vals, slope, se, dof, normal, half, g, sense, p, p < alpha)


@dataclass
class Attribution:
    """Which components a unit's abnormal drift comes from.

    Attributes
    ----------
    verdict : str
        ``healthy``, a component name, ``both`` (several components) or ``ambiguous``.
    probabilities : dict component -> float
        P(component beyond its normal ageing | data, at least one is); empty when healthy.
    sets : dict str -> float
        Probability of each non-empty set of abnormal components ("pump", "motor+pump").
    separating_channel : str
        The unobserved channel that would tell the two leading explanations apart ("" when not
        ambiguous or none is configured).
    channel_scores : dict channel -> float
        Difference between the leading explanations on each candidate channel, in that
        channel's noise sd.
    """

    verdict: str
    probabilities: dict = field(default_factory=dict)
    sets: dict = field(default_factory=dict)
    separating_channel: str = ""
    channel_scores: dict = field(default_factory=dict)
    #: Mean slope vector [d] of the draws of the two leading sets (for the separating channel).
    leading_slopes: Optional[np.ndarray] = None

    def describe(self) -> str:
        if not self.probabilities:
            return self.verdict
        probs = ", ".join(f"{c} {p:.2f}" for c, p in
                          sorted(self.probabilities.items(), key=lambda kv: -kv[1]))
        return f"{self.verdict} ({probs})"


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
    gains = [np.zeros((d, d))]
    for k in range(1, n):
        q = np.asarray(prior_var, float) + (np.diag(P[k - 1]) if carry else 0.0)
        gains.append(P[k] / q[None, :])
    for m in range(n):
        M = P[m]
        for k in range(m + 1, n):
            M = gains[k] @ M
            E[k, m], E[m, k] = M, M.T
    return E


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
    from scipy import stats
    from scipy.optimize import lsq_linear
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
    p = 0.5 * stats.f.sf(T, 1, dof) + 0.5 * stats.f.sf(T / k, k, dof)
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


def attribute(trends: list, names: list, components: list, C: np.ndarray,
              normal_rate, tolerance, directions, confidence: float,
              rng: np.random.Generator, draws: Optional[np.ndarray] = None) -> Attribution:
    """Probabilities of each set of abnormal components, given that the unit drifts.

    Parameters
    ----------
    trends : list of Trend, length d
        OLS trends of the inputs (slopes and standard errors).
    names, components : list of str, length d
        Input names and the component of each.
    C : ndarray, shape [d, d]
        Covariance of the slopes (:func:`slope_covariance`; it ties the inputs).
    normal_rate, tolerance : ndarray, shape [d]
    directions : ndarray of int, shape [d]
        Degrading direction of each input (+1, -1, or 0 = either way).
    confidence : float
        Probability the leading set needs for a verdict naming it.
    rng : numpy Generator
    draws : ndarray, shape [n, d], optional
        Posterior draws of the slopes (the joint method's trend), used as they are instead
        of the Student-t distribution of ``trends``' slopes with covariance ``C``.
    """
    if draws is None:
        b = np.array([t.slope for t in trends])
        dof = max(trends[0].dof, 1)
        L = np.linalg.cholesky(C + 1e-300 * np.eye(len(b)))
        z = rng.standard_normal((DRAWS, len(b))) @ L.T
        draws = b + z / np.sqrt(rng.chisquare(dof, (DRAWS, 1)) / dof)
    normal_rate, tolerance = np.asarray(normal_rate, float), np.asarray(tolerance, float)
    dirs = np.asarray(directions, int)
    dev = draws - normal_rate
    beyond = np.where(dirs[None, :] == 0, np.abs(dev), dev * dirs[None, :]) > tolerance
    comps = sorted(set(components))
    comp_bad = np.column_stack([beyond[:, [c == comp for c in components]].any(axis=1)
                                for comp in comps])
    some = comp_bad.any(axis=1)
    if not some.any():
        # No draw leaves the normal band: the drift is not in any input's slope (e.g. a
        # fault on a path the inputs do not model); name nothing.
        return Attribution(AMBIGUOUS, {c: 1.0 / len(comps) for c in comps}, {})
    sets, means = {}, {}
    for pattern in product((False, True), repeat=len(comps)):
        if not any(pattern):
            continue
        sel = some & np.all(comp_bad == np.array(pattern), axis=1)
        label = "+".join(c for c, on in zip(comps, pattern) if on)
        sets[label] = float(sel.sum() / some.sum())
        if sel.any():
            means[label] = draws[sel].mean(axis=0)
    probs = {c: float(comp_bad[some, k].mean()) for k, c in enumerate(comps)}
    # The components abnormal with probability >= confidence are named (a motor fault whose
    # pump is only possibly degrading too is a motor fault, the pump's probability shown);
    # with none, the data cannot say which: ambiguous.
    sure = [c for c in comps if probs[c] >= confidence]
    # ... unless another is more likely than not abnormal too, without being sure: then
    # the data cannot say whether it is one component or several.
    doubt = [c for c in comps if 0.5 <= probs[c] < confidence]
    if sure and not doubt:
        return Attribution(sure[0] if len(sure) == 1 else SEVERAL, probs, sets)
    ranked = sorted((s for s in sets if s in means), key=sets.get, reverse=True)
    lead = np.array([means[s] for s in ranked[:2]]) if len(ranked) >= 2 else None
    return Attribution(AMBIGUOUS, probs, sets, leading_slopes=lead)


def separating_channel(cfg, observed: set, x_first: np.ndarray, lead_slopes: np.ndarray,
                       span: float, executor=None) -> tuple[str, dict]:
    """The unobserved channel whose recording would best tell two explanations apart.

    The two explanations (mean slope vectors of the two leading sets, [2, d]) both reproduce
    the observed output; started from the unit's first-year state ``x_first`` [d], after
    ``span`` years they reach different states that look alike on the output. Each candidate channel (``model.channels`` not observed) is simulated at both and
    scored by the RMS difference in its noise sd (``diagnose.channel_noise_fraction`` of the
    healthy unit's range on that channel).

    Returns
    -------
    channel : str
        "" when no channel is configured or none differs.
    scores : dict channel -> float
    """
    from .simulate import as_parameters, run_batch, spec_for
    chans = [c for c in cfg.model.channels if c not in observed]
    if not chans or lead_slopes is None:
        return "", {}
    lo, hi = cfg.model.bounds[:, 0], cfg.model.bounds[:, 1]
    ends = [np.clip(x_first + s * span, lo, hi) for s in lead_slopes]
    nominal = np.array([s.nominal for s in cfg.model.inputs.values()])
    spec = spec_for(cfg, outputs=list(dict.fromkeys([cfg.model.output.variable, *chans])))
    batch = run_batch(spec, as_parameters(cfg, np.array([*ends, nominal])), executor)
    if not batch.ok.all():
        return "", {}
    frac = cfg.diagnose.channel_noise_fraction
    scores = {}
    for c in chans:
        y = batch.outputs[c]
        healthy = y[2]
        scale = float(healthy.max() - healthy.min()) or float(abs(healthy).max()) or 1.0
        scores[c] = float(np.sqrt(np.mean((y[0] - y[1]) ** 2)) / (frac * scale))
    best = max(scores, key=scores.get)
    return (best if scores[best] > 0 else ""), scores
