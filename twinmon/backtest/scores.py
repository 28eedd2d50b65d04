"""The back-test's scores: each unit's cut forecasts against its later years (coverage pairs,
time-to-failure scores: :class:`UnitBacktest`, :func:`ttf_scores`), the fleet's summary
(:class:`BacktestSummary`) and the verdict on its coverage (:func:`coverage_verdict`,
:func:`coverage_by_record`); the package docstring defines them."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass
class UnitBacktest:
    """One unit's back-test.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    observed : ndarray, shape [n_y]
        Observed indicator per year (posterior median; inf = level not reached).
    observed_unsafe : ndarray of bool, shape [n_y]
    cuts : ndarray of int, shape [n_c]
    pred_lo, pred_med, pred_hi : ndarray, shape [n_c, h]
        Forecast interval and median of the indicator for cut + 1 .. cut + h.
    failure_pred : ndarray of int, shape [n_c]
        Predicted failure year per cut (-1: none within the horizon).
    end_of_life : int or None
        First observed unsafe year.
    """

    years: np.ndarray
    observed: np.ndarray
    observed_unsafe: np.ndarray
    cuts: np.ndarray
    pred_lo: np.ndarray
    pred_med: np.ndarray
    pred_hi: np.ndarray
    failure_pred: np.ndarray
    end_of_life: Optional[int]
    horizon: int
    #: Years of the unit's recorded maintenance events (a part replaced or repaired).
    repairs: tuple = ()

    def pairs(self):
        """(cut index, future index, year) of every forecast year that was later observed
        (and not past the end of life, after which the unit would have been repaired), and
        not across a recorded repair: a forecast made before a part was replaced is not
        scored against the new part (a DC drive's worn bearing, replaced in year 8, made 15
        of the fleet's 16 misses from the cuts before it)."""
        last = self.end_of_life if self.end_of_life is not None else int(self.years[-1])
        for c, k, j, y in self._candidates(last):
            if not any(int(k) < e <= y for e in self.repairs):
                yield c, j, y

    def across_repairs(self) -> int:
        """How many pairs :meth:`pairs` leaves out for a recorded repair between the cut
        and the year."""
        last = self.end_of_life if self.end_of_life is not None else int(self.years[-1])
        return sum(any(int(k) < e <= y for e in self.repairs)
                   for _, k, _, y in self._candidates(last))

    def _candidates(self, last: int):
        for c, k in enumerate(self.cuts):
            for j in range(self.horizon):
                y = int(k) + 1 + j
                if y <= last and y in self.years:
                    yield c, k, j, y

    def scored(self):
        """(years recorded up to the cut, observation inside the interval) of every pair of
        :meth:`pairs`."""
        for c, j, y in self.pairs():
            o = self.observed[np.flatnonzero(self.years == y)[0]]
            yield (int(np.sum(self.years <= self.cuts[c])),
                   bool(self.pred_lo[c, j] <= o <= self.pred_hi[c, j]))


@dataclass
class TTFScore:
    """Time-to-failure scores of one unit that reached unsafe (see module docstring)."""

    end_of_life: int
    rul_true: np.ndarray
    rul_pred: np.ndarray
    cut_lambda: int
    alpha_lambda: bool
    relative_accuracy: float
    prognostic_horizon: float


def ttf_scores(cuts: np.ndarray, failure_pred: np.ndarray, end_of_life: int, horizon: int,
               alpha: float = 0.2, lam: float = 0.5) -> Optional[TTFScore]:
    """alpha-lambda accuracy, relative accuracy and prognostic horizon of one unit.

    Parameters
    ----------
    cuts : ndarray of int, shape [n_c]
    failure_pred : ndarray of int, shape [n_c]
        Predicted failure year per cut; -1 = none within ``horizon`` (censored at
        ``cut + horizon + 1``).
    end_of_life : int
        True (or observed) failure year.

    Returns
    -------
    TTFScore or None
        None when no cut precedes the end of life.
    """
    cuts = np.asarray(cuts, int)
    before = cuts < end_of_life
    if not before.any():
        return None
    k = cuts[before]
    fp = np.asarray(failure_pred, int)[before]
    fp = np.where(fp < 0, k + horizon + 1, fp)
    rul, pred = end_of_life - k, fp - k
    ok = np.abs(pred - rul) <= alpha * rul
    k_lam = k[0] + lam * (end_of_life - k[0])
    i = int(np.argmin(np.abs(k - k_lam)))
    ra = float(1 - abs(rul[i] - pred[i]) / rul[i])
    # Prognostic horizon: from the first cut after which every prediction stays in the cone.
    ph = 0.0
    for j in range(len(k)):
        if ok[j:].all():
            ph = float(end_of_life - k[j])
            break
    return TTFScore(end_of_life, rul, pred, int(k[i]), bool(ok[i]), ra, ph)


@dataclass
class BacktestSummary:
    units: dict
    coverage: float
    n_pairs: int
    indicator_mae: float
    ttf: dict = field(default_factory=dict)
    output: str = ""
    confidence: float = 0.9
    #: Caveats of the scores (a joint posterior truncated instead of calibrated again).
    warnings: list = field(default_factory=list)
    #: ``truncated`` (the stored posterior cut at each cut year) or ``recalibrated``.
    cut_posteriors: str = "truncated"
    #: False when the coverage is outside ``coverage_band`` beyond its sampling error
    #: (:func:`coverage_verdict`; the warning is among ``warnings``).
    coverage_in_band: bool = True
    coverage_band: tuple = (float("nan"), float("nan"))
    #: The coverage of the forecasts made from each number of recorded years (at the cut):
    #: ``{n: {"coverage", "pairs", "in_band"}}`` (:func:`coverage_by_record`). Wear whose shape
    #: a short record cannot show misses there while the pooled coverage may still hold.
    by_record: dict = field(default_factory=dict)

    @property
    def unsafe_before_cuts(self) -> dict:
        """Units unsafe already at or before their first cut: ``{unit: first unsafe year}``.
        No forecast was made from before their end of life, so they have no time-to-failure
        score and their years past it no coverage pair (the unit would have been repaired)."""
        return {u: int(b.end_of_life) for u, b in self.units.items()
                if b.end_of_life is not None and u not in self.ttf}

    @property
    def across_repairs(self) -> int:
        """Pairs left out for a recorded repair between the cut and the year."""
        return sum(b.across_repairs() for b in self.units.values())

    @property
    def all_in_band(self) -> bool:
        """The pooled coverage and that of every record length in their band."""
        return self.coverage_in_band and all(v["in_band"] for v in self.by_record.values())

    @property
    def alpha_lambda(self) -> float:
        return float(np.mean([s.alpha_lambda for s in self.ttf.values()])) if self.ttf \
            else float("nan")

    def as_dict(self) -> dict:
        f = (lambda v: None if v is None or not np.isfinite(v) else round(float(v), 4))
        return {
            "coverage": f(self.coverage), "confidence": self.confidence,
            "coverage_in_band": self.coverage_in_band,
            "coverage_band": [f(b) for b in self.coverage_band],
            "pairs": self.n_pairs, "indicator_mae": f(self.indicator_mae),
            "pairs_across_repairs": self.across_repairs,
            "coverage_by_record": {str(n): {"coverage": f(v["coverage"]), "pairs": v["pairs"],
                                            "in_band": v["in_band"]}
                                   for n, v in self.by_record.items()},
            "alpha_lambda_accuracy": f(self.alpha_lambda),
            "units_reaching_unsafe": len(self.ttf),
            "units_unsafe_before_cuts": self.unsafe_before_cuts,
            "ttf": {u: {"end_of_life": s.end_of_life, "cut_lambda": s.cut_lambda,
                        "alpha_lambda": s.alpha_lambda,
                        "relative_accuracy": f(s.relative_accuracy),
                        "prognostic_horizon": f(s.prognostic_horizon)}
                    for u, s in self.ttf.items()},
            "units": {u: {"cuts": b.cuts.tolist(), "failure_pred": b.failure_pred.tolist(),
                          "end_of_life": b.end_of_life} for u, b in self.units.items()},
            "cut_posteriors": self.cut_posteriors, "warnings": list(self.warnings),
            "output": self.output,
        }


def wilson_interval(share: float, n: int, z: float = 1.645) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``share`` of ``n`` trials (90 % for the
    default ``z``); NaNs when ``n`` is 0."""
    if n == 0:
        return float("nan"), float("nan")
    centre = (share + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(share * (1 - share) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(centre - half), float(centre + half)


def coverage_verdict(coverage: float, n_pairs: int, confidence: float,
                     band: float) -> tuple[bool, str]:
    """Whether a back-test's coverage is consistent with its intervals' confidence.

    Parameters
    ----------
    coverage : float
        Share of the ``n_pairs`` later observations inside the forecast intervals.
    confidence : float
        The intervals' nominal confidence (``forecast.confidence``).
    band : float
        Tolerated departure (``backtest.coverage_band``): coverage in
        ``[confidence - band, confidence + band]`` is in the band.

    Returns
    -------
    in_band : bool
        False when the coverage's 90 % Wilson interval lies wholly outside the band: with
        few pairs a coverage outside the band may be chance, and is not flagged.
    message : str
        The warning, naming the coverage, the pairs and what it means; ``""`` when in band.
    """
    lo_band, hi_band = confidence - band, confidence + band
    if n_pairs == 0 or not np.isfinite(coverage):
        return True, ""
    lo, hi = wilson_interval(coverage, n_pairs)
    if hi < lo_band:
        return False, (f"back-test coverage {coverage:.2f} of {n_pairs} later observations "
                       f"(90 % interval {lo:.2f}-{hi:.2f}) is below {lo_band:.2f}-{hi_band:.2f}: "
                       f"the {100 * confidence:.0f} % forecast intervals were too narrow on "
                       "this history (wear that is not a straight line, an unrecorded repair, "
                       "a record too short); do not rely on the forecast's failure years")
    if lo > hi_band:
        return False, (f"back-test coverage {coverage:.2f} of {n_pairs} later observations "
                       f"(90 % interval {lo:.2f}-{hi:.2f}) is above {lo_band:.2f}-{hi_band:.2f}: "
                       f"the {100 * confidence:.0f} % forecast intervals were wider than this "
                       "history needed; failure years come early")
    return True, ""


def coverage_by_record(units: dict, confidence: float, band: float) -> tuple[dict, list]:
    """The coverage of the forecasts made from each number of recorded years.

    Forecasts from five or six years of accelerating wear cover far less than those from
    ten (the record cannot show the shape yet), and a pooled coverage can hide it: each
    record length is judged against the band on its own (:func:`coverage_verdict`).

    Parameters
    ----------
    units : dict unit -> UnitBacktest
    confidence, band : float
        As :func:`coverage_verdict`'s.

    Returns
    -------
    by_record : dict int -> dict
        ``{"coverage", "pairs", "in_band"}`` per number of years recorded up to the cut.
    warnings : list of str
        One per record length outside the band.
    """
    groups: dict = {}
    for b in units.values():
        for n, inside in b.scored():
            groups.setdefault(n, []).append(inside)
    out, warnings = {}, []
    for n in sorted(groups):
        cov, m = float(np.mean(groups[n])), len(groups[n])
        in_band = coverage_verdict(cov, m, confidence, band)[0]
        out[n] = {"coverage": cov, "pairs": m, "in_band": in_band}
        if not in_band:
            lo, hi = wilson_interval(cov, m)
            low = cov < confidence
            warnings.append(
                f"back-test: the forecasts made from {n} recorded year(s) covered {cov:.2f} of "
                f"{m} later observations (90 % interval {lo:.2f}-{hi:.2f}), "
                f"{'below' if low else 'above'} {confidence - band:.2f}-{confidence + band:.2f}: "
                + ("from so few years the intervals were too narrow on this history (a shape "
                   "of wear the record could not show yet); trust a forecast from a record "
                   "that short less" if low else
                   "from so few years the intervals were wider than this history needed"))
    return out, warnings
