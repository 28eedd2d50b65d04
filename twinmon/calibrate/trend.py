"""The joint method's trend model: piecewise-linear segments per input (a maintenance event
starts a new one), the Gibbs state's layout, the slopes' prior, and what ``forecast`` reads
from a trend posterior (:data:`TREND_FIELDS`)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..config import Config
from ..repairs import find_repairs

#: The trend posterior of a jointly calibrated unit (``UnitPosterior.trend``; the posterior
#: artifact's ``/units/<U>/trend/<field>``): (units, description). ``S`` is the largest
#: number of segments of any input; an input with fewer has NaN (``start``: -1) in the rest.
#: Segment ``s`` of input ``i`` is the line ``intercept + slope * (year - start)``.
TREND_FIELDS = {
    "start": ("year", "first year of each segment of the trend [segment, input]; -1 = none"),
    "intercept": ("input units", "trend value at the segment's start year "
                  "[draw, segment, input]"),
    "slope": ("input units per year", "trend slope [draw, segment, input]"),
    "sigma": ("input units", "standard deviation of the year-to-year variation around the "
              "trend [draw, input]"),
    "sigma_scale": ("input units", "scale of sigma's half-Cauchy prior, calibrate.prior_width "
                    "x the input's range [input] (forecast pools sigma over the fleet from it)"),
    "rhat": ("1", "split R-hat of the last segment's intercept, slope, and of sigma "
             "[3, input]"),
    "ess": ("1", "bulk effective sample size of the last segment's intercept, slope, and of "
            "sigma [3, input]"),
    "acceptance": ("1", "acceptance rate of the trend's moves after burn-in [chain]"),
    "now": ("input units, per year, per year squared, input units",
            "the trend at the last recorded year, which the forecast extends: level, rate, "
            "curvature and growth amplitude, the trend u = t - now_year years later being "
            "level + rate u + curvature u^2 + amplitude (exp(growth u) - 1 - growth u) "
            "[draw, 4, input] (laplace method)"),
    "growth": ("per year", "growth rate of the draw's exponential form; minus the exponent "
               "of its power-law form; 0 for the other forms [draw] (laplace method)"),
    "now_year": ("year", "the last recorded year (laplace method)"),
    "shape": ("1", "the draw's trend shape on the current segment: 0 line, 1 accelerating, "
              "2 change (calibrate.shapes) [draw] (laplace method)"),
    "change_year": ("year", "the first year of a change shape's jumps, -1 for the other "
                    "shapes [draw] (laplace method)"),
    "change_years": ("year", "a change shape's year per input, -1 for an input that does not "
                     "change and for the other shapes [draw, input] (laplace method)"),
    "shape_prob": ("1", "posterior probability of the line, accelerating and change shapes "
                   "[3] (laplace method)"),
}

#: Fields of :data:`TREND_FIELDS` a trend posterior may lack: the prior's scale (written
#: since it was recorded) and the shapes' (the laplace method; the joint method's trend is
#: the line alone).
TREND_OPTIONAL = ("sigma_scale", "now", "now_year", "shape", "change_year", "shape_prob",
                  "growth", "change_years")

#: The fields of :data:`TREND_FIELDS` that hold draws (first axis): the artifact thins them
#: like the years' draws (``calibrate.keep_draws``).
TREND_DRAWS = ("intercept", "slope", "sigma", "now", "shape", "change_year", "growth",
               "change_years")


# ---------------------------------------------------------------------------------------
# The trend's design
# ---------------------------------------------------------------------------------------
def segment_starts(cfg: Config, years: np.ndarray, events: Sequence) -> list[np.ndarray]:
    """First year of each trend segment, per input.

    Parameters
    ----------
    years : array of int, shape [K]
        The unit's recorded years, increasing.
    events : sequence of ``(year, component, ...)`` tuples or objects with ``year`` and
        ``component`` (``observations.Event``)
        Maintenance events. An event concerns the inputs whose ``component`` (or, without
        one, whose own name) it names; their new segment starts at the first recorded year
        on or after it. Events no input's component matches, or after the last recorded
        year, change no segment.

    Returns
    -------
    list of ndarray of int, one per input (config order)
        Segment start years, increasing; the first is ``years[0]``.
    """
    years = np.asarray(years, dtype=np.int64)
    out = []
    for name, spec in cfg.model.inputs.items():
        comp = spec.component or name
        starts = {int(years[0])}
        for e in events:
            year, component = (e.year, e.component) if hasattr(e, "year") else tuple(e)[:2]
            later = years[years >= int(year)]
            if component == comp and later.size:
                starts.add(int(later[0]))
        out.append(np.array(sorted(starts), dtype=np.int64))
    return out


def with_found_repairs(cfg: Config, years: np.ndarray, events: Sequence,
                       starts: list[np.ndarray], est: np.ndarray, cov: np.ndarray
                       ) -> tuple[list[np.ndarray], list]:
    """Segment starts with the repairs no event records added: where the years' estimates
    fall back towards nominal (:func:`~twinmon.repairs.find_repairs`, each year's covariance
    as its error). A straight line across a repair would describe neither part, and the
    unit's fault would be missed.

    Parameters
    ----------
    years : array of int, shape [K]
    events : sequence
        The recorded events (as :func:`segment_starts` takes them).
    starts : list of ndarray
        :func:`segment_starts` of the recorded events.
    est : ndarray, shape [K, d]
        The years' estimates (input units).
    cov : ndarray, shape [K, d, d]
        Their error covariances.

    Returns
    -------
    starts : list of ndarray
        ``starts`` with a segment from each found repair on (the same list when none).
    found : list of FoundRepair
    """
    names = cfg.model.input_names
    since = {n: int(starts[i][-1]) for i, n in enumerate(names)}
    signs = {n: {"up": 1, "down": -1}.get(cfg.model.inputs[n].degrading, 0) for n in names}
    found = find_repairs(cfg, years, est, since, signs, cov)
    if found:
        starts = segment_starts(cfg, years, list(events) + [
            (r.year, c) for r in found for c in r.components])
    return starts, found


def design_matrix(years: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-linear design of one input.

    Each segment's time is centred on the mean of its recorded years: its level and slope
    are then nearly uncorrelated, which the trend's random-walk block likes.

    Returns
    -------
    X : ndarray, shape [K, 2 S]
        Columns ``(1, t - centre)`` of each segment, zero outside it (columns ``2s`` levels,
        ``2s + 1`` slopes).
    centres : ndarray, shape [S]
        Mean recorded year of each segment.
    """
    years = np.asarray(years, float)
    seg = np.searchsorted(starts, years, side="right") - 1
    centres = np.array([years[seg == s].mean() for s in range(len(starts))])
    X = np.zeros((len(years), 2 * len(starts)))
    rows = np.arange(len(years))
    X[rows, 2 * seg] = 1.0
    X[rows, 2 * seg + 1] = years - centres[seg]
    return X, centres


def lines_at_start(coef: np.ndarray, starts: np.ndarray, centres: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The lines of one input's segments as :data:`TREND_FIELDS` stores them (value at the
    segment's start year, slope) from their coefficients as the design has them (level at
    the segment's centre, slope): ``coef`` [..., 2 S] -> intercepts, slopes [..., S]."""
    slope = coef[..., 1::2]
    return coef[..., 0::2] - slope * (centres - starts), slope


@dataclass
class Layout:
    """Where each block sits in the Gibbs state vector
    ``[eps (K*d, year-major) | beta_1 | ... | beta_d | s (d)]``; ``beta_i`` holds
    ``(level, slope)`` of each of input ``i``'s segments."""

    K: int
    d: int
    n_coef: list

    @property
    def n_eps(self) -> int:
        return self.K * self.d

    def eps(self, k: int) -> list[int]:
        return list(range(k * self.d, (k + 1) * self.d))

    def beta(self, i: int) -> list[int]:
        first = self.n_eps + sum(self.n_coef[:i])
        return list(range(first, first + self.n_coef[i]))

    @property
    def trend(self) -> list[int]:
        """Every trend component: the betas, then ``s``."""
        return list(range(self.n_eps, self.size))

    @property
    def s(self) -> list[int]:
        return list(range(self.size - self.d, self.size))

    @property
    def size(self) -> int:
        return self.n_eps + sum(self.n_coef) + self.d

    def mean_map(self, X: list) -> np.ndarray:
        """``M`` [K*d, n_beta] with ``m = M @ beta`` the trend of every (year, input)."""
        M = np.zeros((self.K, self.d, sum(self.n_coef)))
        col = 0
        for i, Xi in enumerate(X):
            M[:, i, col:col + Xi.shape[1]] = Xi
            col += Xi.shape[1]
        return M.reshape(self.K * self.d, -1)


def theta(z: np.ndarray, lay: Layout, M: np.ndarray) -> np.ndarray:
    """The years' inputs ``theta`` [..., K, d] from states ``z`` [..., D]."""
    z = np.asarray(z, float)
    beta = z[..., lay.n_eps:lay.size - lay.d]
    m = (beta @ M.T).reshape(z.shape[:-1] + (lay.K, lay.d))
    eps = z[..., :lay.n_eps].reshape(z.shape[:-1] + (lay.K, lay.d))
    return m + z[..., None, lay.size - lay.d:] * eps


def slope_prior(task, lay: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which trend coefficients are slopes (mask [n_beta]; every segment's columns are
    (level, slope)), and their prior means and precisions, one per slope."""
    slope = np.zeros(sum(lay.n_coef), bool)
    slope[1::2] = True
    mean = np.concatenate([np.full(p, task.slope_mean[i]) for i, p in enumerate(lay.n_coef)])
    prec = np.concatenate([np.full(p, task.slope_sd[i] ** -2.0)
                           for i, p in enumerate(lay.n_coef)])
    return slope, mean[slope], prec[slope]


def sigma_prior_scale(cfg: Config) -> np.ndarray:
    """Scale ``A`` [d] of sigma's half-Cauchy prior, input units: ``calibrate.prior_width``
    times each input's design range (recorded with the trend as ``sigma_scale``)."""
    return cfg.calibrate.prior_width * np.diff(cfg.model.bounds, axis=1).ravel()


def last_segment(trend: dict, field: str) -> np.ndarray:
    """Draws [n, d] of ``field`` (``intercept`` or ``slope``) of each input's last segment
    (the one in force now) from ``UnitPosterior.trend`` (:data:`TREND_FIELDS`)."""
    start = np.asarray(trend["start"])
    last = (start >= 0).sum(axis=0) - 1                                 # [d]
    return np.asarray(trend[field])[:, last, np.arange(start.shape[1])]


def trend_predictive(trend: dict, years, rng: np.random.Generator) -> np.ndarray:
    """Draws of the inputs in (future) ``years`` from the trend's posterior predictive: the
    trend in force at the last recorded year extended (``now`` and ``growth``, the laplace
    method's shapes, :func:`~twinmon.calibrate.shapes.extend`), or the last segment's line ``intercept + slope * (year -
    start)`` (the joint method), plus ``sigma * N(0, 1)``.

    Parameters
    ----------
    trend : dict
        ``UnitPosterior.trend`` (:data:`TREND_FIELDS`).
    years : array of int, shape [n_h]
    rng : numpy Generator

    Returns
    -------
    ndarray, shape [n_draws, n_h, d]
        Input units; not clipped to the design box.
    """
    years = np.asarray(years, float)
    s = np.asarray(trend["sigma"])
    if "now" in trend:
        from .shapes import extend
        now = np.asarray(trend["now"], float)                            # [n, 4, d]
        growth = np.asarray(trend.get("growth", np.zeros(len(now))), float)
        mean = extend(now, growth, years - float(trend["now_year"]))
        return mean + s[:, None, :] * rng.standard_normal(mean.shape)
    start = np.asarray(trend["start"])
    last = (start >= 0).sum(axis=0) - 1                                 # [d]
    a, b = last_segment(trend, "intercept"), last_segment(trend, "slope")   # [n, d]
    t0 = start[last, np.arange(start.shape[1])].astype(float)
    mean = a[:, None, :] + b[:, None, :] * (years[None, :, None] - t0)
    return mean + s[:, None, :] * rng.standard_normal(mean.shape)
