"""What the forecast gives: one unit's result (:class:`UnitForecast`) and the stage's summary
(:class:`ForecastSummary`), each with its ``as_dict`` for ``--json``."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .attribution import Attribution
from .detection import IndicatorDrift
from .judge import STATUS_OK, STATUS_WITHHELD
from .twin import SOURCE_FAILED, SOURCE_FMU, SOURCE_MODEL


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
    #: ``unreliable`` (a calibrated year did not converge, the trend's shape or its fit to the
    #: unit's history cannot be trusted: :mod:`.trendfit`); see :func:`~.judge.prognosis_status`.
    status: str = STATUS_OK
    status_reason: str = ""
    #: The prognosis of a withheld unit was given anyway (``forecast.force_prognosis``).
    forced: bool = False
    #: The indicator's trend and its test against normal ageing (detection).
    drift: Optional[IndicatorDrift] = None
    #: Which components the drift comes from, with probabilities.
    attribution: Optional[Attribution] = None
    #: Effective number of the unit's posterior draws once reweighted to the fleet's prior
    #: of the year-to-year sd (of ``calibrate.keep_draws``), or to its priors of the sd and
    #: of the trend forms (the draws the future extends), the smaller; NaN when not pooled.
    pool_ess: float = float("nan")
    #: Jumps back towards nominal no event explains (:meth:`~twinmon.repairs.FoundRepair.as_dict`).
    repairs: list = field(default_factory=list)
    #: The trend's shape on the current segment, from a posterior that weighed several
    #: (``calibrate.shapes``; :func:`~twinmon.calibrate.shapes.shape_summary`): the
    #: probability of each, and the most probable change year; empty otherwise.
    shape: dict = field(default_factory=dict)

    #: The one-year-ahead check of the unit's trend model (:mod:`.trendfit`,
    #: ``forecast.trend_fit_alpha``): ``p_value``, the ``years`` predicted, their
    #: ``year_p_values``, the ``missed_years`` named when it fails and the ``shapes``
    #: weighed; empty when it was off or no year could be predicted.
    trend_fit: dict = field(default_factory=dict)
    #: A unit unsafe now with no drift to blame: the inputs whose level puts it past its
    #: limit (:func:`~.plan.level_cause`: ``{input: {"value", "nominal", "restored",
    #: "safe"}}``; its components are the root cause); empty otherwise.
    level_cause: dict = field(default_factory=dict)
    #: A unit past its limit that a new unit is past too: the twin's health indicator at
    #: every input's nominal value (the limit, not a part, is to check); None otherwise.
    unsafe_at_nominal: Optional[float] = None
    #: The first of the last recorded years in a row whose P(unsafe) is past the limit
    #: (``safety.failure_probability``): the unit is unsafe now, since then; None when its
    #: last year is not (``failure_year`` is a future year's, so says nothing of it).
    unsafe_since: Optional[int] = None
    #: Components to watch though no fault was found, each with why: a part whose wear
    #: accelerates with its slope over the record within normal ageing
    #: (:func:`~.trend.shape_gate`), or whose own slope test rejects where the unit's tests
    #: together do not (:func:`~.plan.unconfirmed`).
    watch: dict = field(default_factory=dict)

    #: Set by :meth:`slim`: the figures kept when the Monte Carlo arrays are dropped.
    _slim: Optional[dict] = field(default=None, repr=False)
    #: Set by :func:`~.artifact.pack_unit` in a worker: the Monte Carlo arrays as the
    #: artifact stores them (compressed), for the writer alone.
    _packed: Optional[dict] = field(default=None, repr=False)

    @property
    def fmu_fraction(self) -> float:
        """Share of the future Monte Carlo points that went through the FMU (outside the box)."""
        if self._slim is not None:
            return self._slim["fmu_fraction"]
        return float(np.mean((self.source == SOURCE_FMU) | (self.source == SOURCE_FAILED)))

    @property
    def model_fraction(self) -> float:
        """Share of the future Monte Carlo points the limit-state model answered (outside the
        box, surely unsafe)."""
        if self._slim is not None:
            return self._slim.get("model_fraction", 0.0)
        return float(np.mean(self.source == SOURCE_MODEL))

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
        from ..safety import median_failure_year
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
        if self._slim is not None:      # slim already (a worker's): drop the packed arrays
            return replace(self, _packed=None)
        q = (0.05, 0.5, 0.95)
        keep = {"fmu_fraction": self.fmu_fraction, "model_fraction": self.model_fraction,
                "n_samples": self.n_samples,
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
            "unsafe_since": self.unsafe_since,
            "years_observed": [int(y) for y in self.years_observed],
            "p_unsafe_observed": [round(float(p), 4) for p in self.p_unsafe_observed],
            "years": [int(y) for y in self.years_future],
            "p_unsafe": [round(float(p), 4) for p in self.p_unsafe],
            "trends": {name: {"slope": t.slope, "slope_ci90": [t.slope_ci[0], t.slope_ci[1]],
                              "intercept": t.intercept, "p_value": t.p_value, "test": t.test,
                              "normal_rate": t.normal_rate}
                       for name, t in self.trends.items()},
            "indicator": {"median": _finite(med), "q05": _finite(q05), "q95": _finite(q95)},
            "plan": self.plan,
            "detection": _drift_dict(self.drift, list(self.trends)),
            "attribution": ({"verdict": self.attribution.verdict,
                             "probabilities": {c: round(v, 3) for c, v in
                                               self.attribution.probabilities.items()},
                             "sets": {c: round(v, 3) for c, v in self.attribution.sets.items()},
                             "separating_channel": self.attribution.separating_channel or None,
                             "named": list(self.attribution.named)}
                            if self.attribution is not None else None),
            "fmu_fraction": round(self.fmu_fraction, 4),
            "model_fraction": round(self.model_fraction, 4),
            "fmu_failures": self.fmu_failures,
        }
        if np.isfinite(self.pool_ess):
            d["pool_ess"] = round(self.pool_ess, 1)
        d["unrecorded_repairs"] = list(self.repairs)
        if self.shape:
            d["trend_shape"] = dict(self.shape)
        if self.trend_fit:
            d["trend_fit"] = dict(self.trend_fit)
        if self.level_cause:
            d["level_cause"] = {n: dict(v) for n, v in self.level_cause.items()}
        if self.unsafe_at_nominal is not None:
            d["unsafe_at_nominal"] = float(self.unsafe_at_nominal)
        if self.watch:
            d["watch"] = dict(self.watch)
        if self.has_truth:
            d["true_failure_year"] = self.true_failure_year
            d["truth_source"] = self.truth_source
        return d


def _drift_dict(dr: Optional[IndicatorDrift], names: list) -> Optional[dict]:
    """The detection for ``--json``; ``detectable`` per input name (multiples of its
    normal-ageing tolerance), when recorded."""
    if dr is None:
        return None
    f = (lambda v: float(f"{v:.4g}") if np.isfinite(v) else None)
    out = {"slope": f(dr.slope), "slope_se": f(dr.slope_se), "normal_slope": f(dr.normal_slope),
           "normal_tolerance": f(float(np.sum(dr.normal_halfwidth))),
           "p_value": f(dr.p_value), "p_inputs": f(dr.p_inputs),
           "p_history": f(dr.p_history), "p_inputs_rate": f(dr.p_inputs_rate),
           "abnormal": bool(dr.abnormal),
           "years": [int(y) for y in dr.years]}
    if np.size(dr.detectable) == len(names):
        out["detectable"] = {n: f(float(v)) for n, v in zip(names, dr.detectable)}
    return out


def _finite(a) -> list:
    """JSON-able list: non-finite values (a level never reached) become None."""
    return [round(float(v), 3) if np.isfinite(v) else None for v in a]


@dataclass
class ForecastSummary:
    """What :func:`~twinmon.forecast.forecast` did: per-unit results, the output path and
    the wall time (s)."""

    units: dict
    output: str
    wall_time: float
    box_physical: bool = True
    #: Plain-words warnings (an input whose degrading direction could not be told).
    warnings: list = field(default_factory=list)
    #: The fleet's prior of the joint method's year-to-year sd (:func:`~.pooling._pooling_dict`).
    pooling: dict = field(default_factory=lambda: {"pooled": False})
    #: The fleet's prior of the trend forms (:func:`~.pooling._shapes_dict`).
    shape_pooling: dict = field(default_factory=lambda: {"pooled": False})
    #: The limit-state model of the points outside the box (its runs, rounds, region), or
    #: ``used`` false with the reason.
    limit_state: dict = field(default_factory=lambda: {"used": False, "reason": ""})
    #: Units left out for too few calibrated years: unit -> its number of years.
    too_few_years: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"units": {u: f.as_dict() for u, f in self.units.items()},
                "output": self.output, "wall_time": round(self.wall_time, 3),
                "warnings": list(self.warnings), "sigma_pooling": self.pooling,
                "shape_pooling": self.shape_pooling, "limit_state": self.limit_state,
                "too_few_years": dict(self.too_few_years)}
