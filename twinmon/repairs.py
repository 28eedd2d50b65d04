"""Repairs nobody recorded: a unit's yearly estimates fall back towards nominal.

A replaced or repaired part starts again near its nominal value. When the work is in the
observations' events, the component's trend restarts there; when it is not, a straight line
through the whole history reads the fall as slower wear, or none, and the fault is missed.

The test (:func:`fall_test`), per input with a known degrading direction, over the years
every input's current part covers: every input gets a trend through its yearly estimates
(level, slope, curvature), the tested input also a step at year ``c``, fitted by
generalised least squares with each year's error covariance plus each input's year-to-year
variance (fitted with them by restricted maximum likelihood, :func:`_jitter`), for every
``c`` with at least :data:`MIN_BEFORE` years before it. The tested quantity is the step,
one-sided, against the degrading direction: a repair puts the estimates back towards
nominal at once, a jump the input's own trend does not make. It counts only where the
change from the year before ``c`` to ``c`` -- the trend's change plus the step -- is a fall
too: at the bend of accelerating wear a step can take up the misfit of the curve, but the
estimates do not fall there (the curvature keeps a bend from being read as a fall); and
only where the estimates themselves fall, the mean of the two years from ``c`` on the sound
side of the two before (:func:`_falls`): a quadratic with a step fitted to exponential wear
read a fall into estimates rising every year. The test on the benchmark's repaired fleets
found the same repairs with it (``benchmarks/repair_scan.py --family repair_hidden``, seeds
43 and 47: 26/32 each) and the same findings with no repair on ``--family rate_change``
(seeds 71 and 73: 2 and 3 of 44). The smallest p-value over the years tried, times their
number and the number of inputs tested (Bonferroni), is compared with
``forecast.repair_alpha``.

The step, not the change: a part that ages the good way within its normal band (a
bearing's friction easing by up to its tolerance a year) makes every year's change a small
fall, which the change's test read as a repair where the band is as wide as a year's
estimate error (the DC drive's fleets of ``benchmarks/prognosis.py --config
configs/dcdrive.yaml``, straight lines, seeds 61-73: 9 findings on 176 units, 5 with the
step); its step is nothing. The step's test also found more of the repairs there were
(``benchmarks/repair_scan.py``, the scan alone: pump seeds 11-12, 56 -> 57 of 64; pump
seeds 43, 47, 53, 76 -> 79 of 96; DC drive seeds 61-73, 121 -> 125 of 128) with fewer
findings and no repair (the pump's 15 fleets of seeds 11-53 with and without repairs:
6 -> 2 of 660 units; the DC drive's 12: 21 -> 14 of 528).

A finding names the component of the input whose own fall that year is the strongest, and
of every other input whose own step there is a fall of at least :data:`NAME_T` sds: inputs
that trade off in the likelihood cannot be told apart (on the flow alone a pump's repair
moves the damping's estimate as much as the pump coefficient's, and its step in sds is often
the larger), and naming the strongest alone named the wrong part for 3 of the 22 repaired
pumps found on ``benchmarks/repair_scan.py``'s seed 11. The user's work order tells which.

Who acts on a finding: ``calibrate``'s joint method scans the years' maximum-likelihood
points (with their Laplace covariances) before it samples, and starts a trend segment at
each repair found (``found_repairs`` of the posterior); ``forecast`` scans the yearly
estimates of a posterior calibrated year by year and restarts the trends it refits there.
Either way the forecast reports the finding with the command that records the event.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np

from .config import Config

#: Years of the current part before a candidate repair year: enough for its line.
MIN_BEFORE = 3
#: Years of the current part for a scan at all (one input: a trend's three coefficients, a
#: step and a degree of freedom).
MIN_YEARS = 5
#: A found repair names the input whose own fall that year is the strongest, and every
#: other whose own step there is a fall of at least this many sds.
NAME_T = 1.0
#: Coefficients of each input's trend in the scan's model: level, slope, curvature.
CURVE = 3
#: Years on each side of a candidate repair whose mean estimates must fall (:func:`_falls`).
FALL_YEARS = 2
#: The year-to-year variance's search grid (:func:`_jitter`): natural log of the variance
#: over the input's mean error variance, from none (e^-12) to the errors' variance, in steps
#: of a factor 4.5. A misfit beyond it scales the whole covariance (the overdispersion),
#: which keeps the errors' ridge: a variance free to grow far above the errors took up the
#: gradual fall of wear that swings back (``--family reversing``, seeds 11 and 43), which
#: the scan then missed: 27 units of 88 with a finding against 44 capped (45 with the
#: per-input variances before).
JITTER_GRID = np.arange(-12.0, 0.01, 1.5)
#: The grid of the variances when the parts are named (:func:`find_repairs`): up to 400
#: times the errors' variance. Each input's own step is fitted without the others' (an
#: input's fall absent from the fit must go to its own variance, not leak through the
#: correlated errors into the step tested: capped, a DC drive's replaced bearing had its
#: winding named too).
NAMING_GRID = np.arange(-12.0, 6.01, 1.5)
#: Passes over the inputs of the variance's coordinate search.
JITTER_SWEEPS = 2


@dataclass
class FoundRepair:
    """A fall back towards nominal that no event explains.

    Attributes
    ----------
    year : int
        First recorded year after the fall (the year an event would name).
    components : list of str
        The component(s) whose inputs fell that year (an input's own name when it has
        none). Several when the output cannot tell which part was repaired (their inputs
        trade off): the user knows which work was done.
    steps : dict input name -> float
        The fitted step of each input that fell (input units).
    p_value : float
        Bonferroni-adjusted p-value of the strongest fall (one-sided t test).
    """

    year: int
    components: list
    steps: dict = field(default_factory=dict)
    p_value: float = 1.0

    def headline(self) -> str:
        """What was found, in a few words (calibrate's lines, the report)."""
        return (f"the {' or the '.join(self.components)} fell back towards nominal in year "
                f"{self.year} (p = {self.p_value:.2g}), as after a repair nobody recorded")

    def describe(self, cfg: Config, unit: str) -> str:
        """One sentence for the user, with the command that records the event."""
        falls = " and ".join(f"{n} by {v:+.3g} {cfg.model.inputs[n].units}".rstrip()
                             for n, v in self.steps.items())
        parts = " or the ".join(self.components)
        which = (self.components[0] if len(self.components) == 1
                 else "<" + "|".join(self.components) + ">")
        told = ("" if len(self.components) == 1 else
                " (the data cannot tell which; the work order can)")
        return (f"{falls} fell back towards nominal in year {self.year} (p = "
                f"{self.p_value:.2g}), as after a repair of the {parts} nobody recorded{told}:"
                f" if the work was done, record it with `twinmon events add <observations> "
                f"-c <config> --unit {unit} --year {self.year} --component {which}`")

    def as_dict(self) -> dict:
        return {"year": self.year, "components": list(self.components),
                "steps": {n: float(f"{v:.4g}") for n, v in self.steps.items()},
                "p_value": float(f"{self.p_value:.3g}")}


def fall_test(years: np.ndarray, est: np.ndarray, cov: np.ndarray, i: int,
              direction: int) -> tuple[float, int, float, int]:
    """The strongest fall of input ``i``'s yearly estimates back towards nominal.

    Every input gets a trend (level, slope, curvature), input ``i`` also a step at year
    ``c``; the trends and the step are fitted by generalised least squares, each year's
    estimates weighted by the inverse of their error covariance plus each input's
    year-to-year variance (:func:`step_fits`). Weighting by the whole covariance matters
    when the inputs trade off in the likelihood (one output, two inputs that move it
    alike): the errors then run along a ridge, and the other inputs' trends tell a fall of
    ``i`` from a slide along it.

    Parameters
    ----------
    years : ndarray of int, shape [n]
    est : ndarray, shape [n, d]
        Yearly estimates of the inputs (input units).
    cov : ndarray, shape [n, d, d]
        Their error covariances (input units squared): a posterior's, or the likelihood's
        Laplace approximation.
    i : int
        The input tested.
    direction : int
        +1 when an increase of input ``i`` degrades the unit, -1 when a decrease does.

    Returns
    -------
    p : float
        The smallest one-sided p-value over the candidate years (not adjusted); 1 when none
        can be tested.
    year : int
        Its year (-1 when none).
    step : float
        Its fitted step of input ``i`` (input units).
    tried : int
        Number of candidate years (for the Bonferroni adjustment).
    """
    years = np.asarray(years)
    est = np.asarray(est, float)
    if est.shape[0] < MIN_YEARS or direction == 0:
        return 1.0, -1, 0.0, 0
    best = (1.0, -1, 0.0)
    cands = [int(c) for c in years[MIN_BEFORE:]]
    fitted = 0
    for k, (c, fit) in enumerate(zip(cands, step_fits(years, est, cov, i, cands)),
                                 start=MIN_BEFORE):
        if fit is None:
            continue
        fitted += 1
        p = fit.p_value(direction)
        if p < best[0] and _falls(est[:, i], k, direction):
            best = (p, c, fit.step)
    if not fitted:      # an input that does not vary at all: no test
        return 1.0, -1, 0.0, 0
    return (*best, len(cands))


def _falls(x: np.ndarray, k: int, direction: int) -> bool:
    """Whether the estimates ``x`` [n] themselves fall back at index ``k``: the mean of
    the (up to) :data:`FALL_YEARS` years from ``k`` lies on the sound side of the mean of
    as many before it. The model's step can take up the misfit of a curve its trend does
    not have (exponential wear: a spindle's drag estimates rising every year, 1.15 then
    1.43, read as a fall of 0.79 in the second year); after a repair the estimates are
    back towards nominal, in its year and the next."""
    before = x[max(0, k - FALL_YEARS):k]
    after = x[k:k + FALL_YEARS]
    return bool(-direction * (after.mean() - before.mean()) > 0)


@dataclass
class StepFit:
    """Trends for every input plus a step of one input at one year, fitted by generalised
    least squares (:func:`step_fits`).

    Attributes
    ----------
    step : float
        The fitted step (input units).
    change : float
        The fitted change from the year before the step to its year: the trend's change
        plus the step (what a repair makes fall back; accelerating wear never does).
    sd : float
        Standard deviation of ``change``, the overdispersion beyond the stated errors and
        year-to-year variances included.
    dof : int
    """

    step: float
    change: float
    sd: float
    dof: int
    #: Standard deviation of ``step``, the overdispersion included.
    step_sd: float = float("inf")

    def t(self, direction: int) -> float:
        """The change in sds, positive for a fall against the degrading ``direction``."""
        return -direction * self.change / self.sd

    def step_t(self, direction: int) -> float:
        """The step in sds, positive for a fall against the degrading ``direction``."""
        return -direction * self.step / self.step_sd

    def p_value(self, direction: int) -> float:
        """One-sided p-value of a step back against the degrading ``direction`` across
        which the estimates fall (1 when the change is no fall: a bend the step absorbs)."""
        from scipy import special
        if not self.t(direction) > 0:
            return 1.0
        # Student's t upper tail (scipy.stats.t.sf's value, without its per-call overhead).
        return float(special.stdtr(self.dof, -self.step_t(direction)))


def _design(years: np.ndarray, d: int, i: int, cands: Sequence[int]) -> np.ndarray:
    """:func:`step_fits`' designs, one per candidate year, stacked by year then input,
    shape [m, n, d, 3 d + 1]: columns ``3 j .. 3 j + 2`` input ``j``'s level, slope and
    curvature (time centred on the years' mean, its square centred too), the last input
    ``i``'s step at the candidate year."""
    n = len(years)
    t = years - years.mean()
    cols = (np.ones(n), t, t * t - np.mean(t * t))
    X = np.zeros((len(cands), n, d, CURVE * d + 1))
    for j in range(d):
        for k, col in enumerate(cols):
            X[:, :, j, CURVE * j + k] = col
    X[:, :, i, CURVE * d] = years[None, :] >= np.asarray(cands)[:, None]
    return X


def _gls(X: np.ndarray, V: np.ndarray, est: np.ndarray):
    """Generalised least squares of ``est`` [n, d] on designs ``X`` [m, n, d, p] with each
    year's covariance ``V`` [m, ..., n, d, d] (axes between: several covariances a design).

    Returns coefficients [m, ..., p], normal matrices [m, ..., p, p] and weighted residual
    sums of squares [m, ...]."""
    W = np.linalg.inv(V)
    Xe = X.reshape(X.shape[:1] + (1,) * (V.ndim - 4) + X.shape[1:])      # [m, 1.., n, d, p]
    WX = W @ Xe                                                          # [m, .., n, d, p]
    A = np.sum(np.swapaxes(Xe, -1, -2) @ WX, axis=-3)                    # [m, .., p, p]
    b = np.sum(np.swapaxes(WX, -1, -2) @ est[..., None], axis=-3)[..., 0]
    coef = np.linalg.solve(A, b[..., None])[..., 0]
    r = est - (Xe @ coef[..., None, :, None])[..., 0]                    # [m, .., n, d]
    return coef, A, np.sum(r * (W @ r[..., None])[..., 0], axis=(-2, -1))


def _jitter(X: np.ndarray, est: np.ndarray, cov: np.ndarray,
            grid: np.ndarray = JITTER_GRID) -> np.ndarray:
    """Each input's year-to-year variance beyond the errors, by restricted maximum likelihood
    under each design ``X`` [m, n, d, p], shape [m, d] (input units squared).

    Searched on ``grid`` (log-variance over each input's mean error variance,
    :data:`JITTER_GRID`), one input at a time, :data:`JITTER_SWEEPS` times. Restricted
    likelihood, under the whole covariance of the errors: when the inputs trade off, their
    errors run along a ridge and only the scatter across it tells a year-to-year variance
    from them. A variance taken per input, from its scatter about its own line less its
    mean error variance, is noise of the ridge's size: on the pump fleets it put the
    motor's at 0.3-0.7 against a true 0.15, and many a fall that a pump's replacement made
    was lost in it.
    """
    m, d = len(X), est.shape[1]
    base = np.maximum(np.einsum("kjj->j", cov) / len(cov), np.finfo(float).tiny)
    g = len(grid)
    z = np.full((m, d), grid[0])
    eye = np.eye(d)
    rows = np.arange(m)
    for _ in range(JITTER_SWEEPS):
        for j in range(d):
            Z = np.repeat(z[:, None, :], g, axis=1)                            # [m, g, d]
            Z[:, :, j] = grid
            V = cov[None, None] + (base * np.exp(Z))[:, :, None, :, None] * eye
            # V: [m, g, n, d, d]
            try:
                _, A, quad = _gls(X, V, est)
            except np.linalg.LinAlgError:
                return base * np.exp(z)
            nll = np.linalg.slogdet(V)[1].sum(axis=2) + np.linalg.slogdet(A)[1] + quad
            nll = np.where(np.isfinite(nll), nll, np.inf)
            z[rows, j] = grid[np.argmin(nll, axis=1)]
    return base * np.exp(z)


def step_fits(years: np.ndarray, est: np.ndarray, cov: np.ndarray, i: int,
              cands: Sequence[int], grid: np.ndarray = JITTER_GRID
              ) -> list[Optional[StepFit]]:
    """Every input's trend and input ``i``'s step at each candidate year (:func:`fall_test`'s
    model), all candidates at once; None for a candidate whose fit is not possible (an input
    that does not vary at all, a singular design, too few years for the coefficients).

    Each input's trend is a line with a curvature: wear that accelerates bends its
    estimates, and a line plus a step at the bend reads the bend as a fall (on the fleets of
    ``benchmarks/repair_scan.py`` most findings with no repair were faulty units whose wear
    sped up after year 3); a repair's fall back is a change no bend gives.

    Parameters
    ----------
    years, est, cov, i
        As :func:`fall_test`'s.
    cands : sequence of int
        The candidate years of the step.
    grid : ndarray
        The year-to-year variances' search grid: :data:`JITTER_GRID` for the test,
        :data:`NAMING_GRID` when the parts are named.

    Returns
    -------
    list of StepFit or None, one per candidate year
    """
    years = np.asarray(years)
    est = np.asarray(est, float)
    cov = np.asarray(cov, float)
    n, d = est.shape
    cands = [int(c) for c in cands]
    t = years - years.mean()
    ok = [bool(np.any(years < c) and np.any(years >= c)) for c in cands]
    if (not any(ok) or n * d - (CURVE * d + 1) < 1
            or np.any(np.all(est == est[0], axis=0))):
        return [None] * len(cands)
    use = [c for c, o in zip(cands, ok) if o]
    X = _design(years, d, i, use)
    dof = n * d - X.shape[3]
    # Errors with no variance (a year's estimates known exactly) make the weights infinite:
    # the fits then come out non-finite and are dropped below, without numpy's warnings.
    try:
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            V = cov[None] + _jitter(X, est, cov, grid)[:, None, :, None] * np.eye(d)
            coef, A, quad = _gls(X, V, est)                                # V: [m, n, d, d]
    except np.linalg.LinAlgError:
        return [None] * len(cands)
    # Overdispersion beyond the stated errors and jitter (never below 1).
    phi = np.maximum(1.0, quad / dof)
    # The change from the last year before the step to its first: the years between times
    # the slope, the curvature's part of it, and the step.
    contrast = np.zeros((len(use), X.shape[3]))
    for k, c in enumerate(use):
        t0, t1 = t[years < c][-1], t[years >= c][0]
        contrast[k, CURVE * i + 1] = t1 - t0
        contrast[k, CURVE * i + 2] = t1 * t1 - t0 * t0
    contrast[:, CURVE * d] = 1.0
    fits = {}
    unit = np.zeros(X.shape[3])
    unit[CURVE * d] = 1.0                                  # picks the step
    for k, c in enumerate(use):
        try:
            var = phi[k] * float(contrast[k] @ np.linalg.solve(A[k], contrast[k]))
            var_step = phi[k] * float(np.linalg.solve(A[k], unit)[CURVE * d])
        except np.linalg.LinAlgError:
            continue
        if var > 0 and var_step > 0 and np.all(np.isfinite(coef[k])):
            fits[c] = StepFit(float(coef[k, CURVE * d]), float(contrast[k] @ coef[k]),
                              float(np.sqrt(var)), dof, float(np.sqrt(var_step)))
    return [fits.get(c) for c in cands]


def step_fit(years: np.ndarray, est: np.ndarray, cov: np.ndarray, i: int,
             c: int, grid: np.ndarray = JITTER_GRID) -> Optional[StepFit]:
    """:func:`step_fits` at one year ``c``."""
    return step_fits(years, est, cov, i, [c], grid)[0]


def find_repairs(cfg: Config, years: np.ndarray, mean: np.ndarray, since: dict,
                 signs: dict, cov: np.ndarray) -> list[FoundRepair]:
    """Unrecorded repairs in a unit's yearly estimates, at ``forecast.repair_alpha``.

    Parameters
    ----------
    years : ndarray of int, shape [n_y]
    mean : ndarray, shape [n_y, d]
        Yearly estimates of the inputs (config order).
    since : dict input name -> int
        First year of each input's current part (:func:`~.trend.repair_years`).
    signs : dict input name -> int
        Degrading direction of each input (+1 up, -1 down); an input with 0 (unknown) is
        not scanned.
    cov : ndarray, shape [n_y, d, d]
        Error covariance of each year's estimates (input units squared).

    Only the years every input's current part covers are scanned (after the latest
    recorded repair of any component).

    Returns
    -------
    list of FoundRepair
        One per year some input fell in (each input's strongest year), by year.
    """
    alpha = cfg.forecast.repair_alpha
    if alpha <= 0:
        return []
    names = cfg.model.input_names
    seg = years >= max(since.values())
    y, x, c = years[seg], mean[seg], cov[seg]
    scans = {name: fall_test(y, x, c, i, signs[name]) for i, name in enumerate(names)}
    tested = sum(1 for s in scans.values() if s[3])
    found: dict[int, FoundRepair] = {}
    for name, (p, year, _, tried) in scans.items():
        if not tried or min(1.0, p * tried * tested) >= alpha:
            continue
        rep = found.setdefault(year, FoundRepair(year, [], {}, 1.0))
        rep.p_value = min(rep.p_value, min(1.0, p * tried * tested))
    for year, rep in found.items():
        # Which part: every input whose own step that year is a fall of at least NAME_T sds,
        # the strongest always. Inputs that trade off in the likelihood cannot be told apart
        # (on the flow alone a pump's repair reads as the motor's, its step the larger in
        # sds); the user's work order can.
        falls = {}
        for i, name in enumerate(names):
            f = step_fit(y, x, c, i, year, NAMING_GRID) if signs[name] != 0 else None
            if f is not None:
                falls[name] = f
        if not falls:
            continue
        top = max(falls, key=lambda n: falls[n].t(signs[n]))
        for n, f in falls.items():
            if n == top or f.t(signs[n]) >= NAME_T:
                comp = cfg.model.inputs[n].component or n
                if comp not in rep.components:
                    rep.components.append(comp)
                rep.steps[n] = f.step
    return [found[y] for y in sorted(found) if found[y].components]
