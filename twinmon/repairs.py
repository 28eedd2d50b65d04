"""Repairs nobody recorded: a unit's yearly estimates fall back towards nominal.

A replaced or repaired part starts again near its nominal value. When the work is in the
observations' events, the component's trend restarts there; when it is not, a straight line
through the whole history reads the fall as slower wear, or none, and the fault is missed.

The test (:func:`fall_test`), per input with a known degrading direction, over the years
every input's current part covers: every input gets a line through its yearly estimates,
the tested input also a step at year ``c``, fitted by generalised least squares with each
year's error covariance (plus each input's year-to-year variance), for every ``c`` with at
least :data:`MIN_BEFORE` years before it. The tested quantity is the change from the year
before ``c`` to ``c`` -- one year's wear plus the step -- one-sided, against the degrading
direction: a repair makes the estimates *fall back*, which accelerating wear or a step of
wear never does. The smallest p-value over the years tried, times their number and the
number of inputs tested (Bonferroni), is compared with ``forecast.repair_alpha``.

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
from typing import Optional

import numpy as np

from .config import Config

#: Years of the current part before a candidate repair year: enough for its line.
MIN_BEFORE = 3
#: Years of the current part for a scan at all (a line, a step and two degrees of freedom).
MIN_YEARS = 5
#: A found repair names the input whose own fall that year is the strongest, and every
#: other whose own step there is a fall of at least this many sds.
NAME_T = 1.0


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

    Every input gets a line, input ``i`` also a step at year ``c``; the lines and the step
    are fitted by generalised least squares, each year's estimates weighted by the inverse
    of their error covariance plus each input's year-to-year variance (the scatter about
    its fit beyond the errors). Weighting by the whole covariance matters when the inputs
    trade off in the likelihood (one output, two inputs that move it alike): the errors
    then run along a ridge, and the other inputs' lines tell a fall of ``i`` from a slide
    along it.

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
    for c in cands:
        fit = step_fit(years, est, cov, i, c)
        if fit is None:
            continue
        fitted += 1
        p = fit.p_value(direction)
        if p < best[0]:
            best = (p, c, fit.step)
    if not fitted:      # an input that does not vary at all: no test
        return 1.0, -1, 0.0, 0
    return (*best, len(cands))


@dataclass
class StepFit:
    """Lines for every input plus a step of one input at one year, fitted by generalised
    least squares (:func:`step_fit`).

    Attributes
    ----------
    step : float
        The fitted step (input units).
    change : float
        The fitted change from the year before the step to its year: one year's wear plus
        the step (what a repair makes fall back; accelerating wear never does, though a
        line plus a step would fit its bend).
    sd : float
        Standard deviation of ``change``, the overdispersion beyond the stated errors and
        year-to-year variances included.
    dof : int
    """

    step: float
    change: float
    sd: float
    dof: int

    def t(self, direction: int) -> float:
        """The change in sds, positive for a fall against the degrading ``direction``."""
        return -direction * self.change / self.sd

    def p_value(self, direction: int) -> float:
        """One-sided p-value of a fall against the degrading ``direction``."""
        from scipy import stats
        return float(stats.t.sf(self.t(direction), self.dof))


def step_fit(years: np.ndarray, est: np.ndarray, cov: np.ndarray, i: int,
             c: int) -> Optional[StepFit]:
    """Every input's line and input ``i``'s step at year ``c`` (:func:`fall_test`'s model);
    None when the fit is not possible (an input that does not vary at all, a singular
    design)."""
    est = np.asarray(est, float)
    cov = np.asarray(cov, float)
    n, d = est.shape
    t = years - years.mean()
    lines = [np.column_stack([np.ones(n), t]) for _ in range(d)]
    jump = (years >= c).astype(float)
    design = [np.column_stack([x, jump]) if j == i else x for j, x in enumerate(lines)]
    # Each input's year-to-year variance: its scatter about its own fit beyond the errors'
    # variance (0 when the errors explain it).
    jitter = np.empty(d)
    for j, x in enumerate(design):
        r = est[:, j] - x @ np.linalg.lstsq(x, est[:, j], rcond=None)[0]
        jitter[j] = max(float(r @ r) / (n - x.shape[1]) - float(np.mean(cov[:, j, j])), 0)
    try:
        W = np.linalg.inv(cov + np.diag(jitter))                     # [n, d, d]
    except np.linalg.LinAlgError:
        return None
    # Stacked by year, then input: column blocks per input's design.
    X = np.zeros((n, d, 2 * d + 1))
    for j in range(d):
        X[:, j, 2 * j:2 * j + 2] = lines[j]
    X[:, i, 2 * d] = jump
    A = np.einsum("kap,kab,kbq->pq", X, W, X)
    b = np.einsum("kap,kab,kb->p", X, W, est)
    try:
        coef = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return None
    resid = est - np.einsum("kap,p->ka", X, coef)
    dof = n * d - (2 * d + 1)
    # Overdispersion beyond the stated errors and jitter (never below 1).
    phi = max(1.0, float(np.einsum("ka,kab,kb->", resid, W, resid)) / dof)
    contrast = np.zeros(2 * d + 1)
    contrast[2 * i + 1] = contrast[2 * d] = 1.0
    var = phi * float(contrast @ np.linalg.solve(A, contrast))
    if not var > 0:
        return None
    return StepFit(float(coef[2 * d]), float(contrast @ coef), float(np.sqrt(var)), dof)


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
            f = step_fit(y, x, c, i, year) if signs[name] != 0 else None
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
