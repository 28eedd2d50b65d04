"""The ``forecast`` and ``backtest`` sections: the prognosis (horizon, confidence, trend
tests, what the future inputs are drawn from) and its scoring on truncated histories."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class ForecastConfig:
    horizon: int = 7
    confidence: float = 0.90
    samples: int = 2000
    #: Significance level of the detection and root-cause trend tests. 0.03 keeps false
    #: alarms on healthy units within 5 %: on benchmarks/prognosis.py (10 seeds, 120
    #: healthy units, flow only) 3 false alarms, and 0.959 of the faults at least twice the
    #: tolerance detected (0.01: none and 0.929).
    alpha: float = 0.03
    #: Draw the inputs of a future year jointly, correlated as their regression residuals
    #: (a multivariate Student t); false: independent Student t marginals.
    correlate: bool = True
    #: Posterior samples per observed year run through the twin (P(unsafe) and the
    #: indicator's history).
    observed_samples: int = 500
    #: A unit's prognosis is withheld when at least this many of its years miss the plant or
    #: sit on the box edge (or its last year does): a twin that misses the data gives none.
    withhold_years: int = 2
    #: Give the prognosis of such units anyway (experts; labelled "forced" everywhere).
    force_prognosis: bool = False
    #: A degrading unit's verdict names the components abnormal with at least this
    #: probability; when none is, it is "ambiguous" (with the probabilities).
    attribution_confidence: float = 0.8
    #: What the future inputs are drawn from: ``state`` (the unit's true inputs: the trend
    #: line's uncertainty, including estimation errors carried from year to year, plus the
    #: year-to-year variation beyond estimation error) or ``estimate`` (the paper's Student t
    #: interval for a new yearly estimate).
    predictive: Literal["state", "estimate"] = "state"
    #: The joint method's year-to-year sd: pool it over the fleet (a log-normal prior fitted
    #: on the fleet's posteriors, each unit's draws reweighted to it;
    #: twinmon/calibrate/fleet.py) when at least ``pool_min_units`` units were calibrated
    #: jointly. false: each unit's own prior (``calibrate.prior_width``).
    pool_sigma: bool = True
    pool_min_units: int = 5
    #: A laplace posterior's trend shapes: fit the fleet's prior probabilities of the
    #: trend forms (line, quadratic, each exponential growth rate and power, change) on its
    #: units' draws, and reweight each unit's draws to it (twinmon/calibrate/fleet_shapes.py),
    #: when at least ``pool_min_units`` units weighed shapes. false: ``calibrate.shapes`` as is.
    pool_shapes: bool = True
    #: The fleet's prior of the trend forms is learnt from the units whose current segment
    #: spans at least this many recorded years: over fewer, each unit's evidence favours the
    #: line whatever the wear (a slight curvature costs a shape more than it explains), and
    #: a fleet of such records learnt "lines" and extended accelerating wear as lines
    #: (docs/forecast.md, *A fleet-level prior of the trend shapes*).
    pool_shapes_min_years: int = 8
    #: Trend-shape gate: an input that drifts abnormally and whose yearly estimates
    #: accelerate in its degrading direction (one-sided test of a quadratic term over the
    #: current part's years, at this level, Bonferroni over the inputs tested) makes the
    #: unit's prognosis ``unreliable``: its straight-line trend understates the wear. 0: off.
    shape_alpha: float = 0.01
    #: Trend-fit gate: the unit's trend model (the posterior's shapes, or the line alone)
    #: fitted to the years before each year predicts it; when the standardised one-year-ahead
    #: errors, over the years predicted, reject the model at this level
    #: (twinmon/forecast/trendfit.py), the unit's prognosis is ``unreliable``: its history
    #: does not follow the trend its forecast extends. 0: off.
    trend_fit_alpha: float = 0.01
    #: A healthy verdict is ``unreliable`` when the record could miss a fault of this many
    #: normal-ageing tolerances, for some input, half the time (a few years of history,
    #: gaps; twinmon/forecast/detection.py, detectable_multiples): "no fault seen" then
    #: says little. Flow-only records of the pump (benchmarks/prognosis.py, seed 13): ten
    #: years show a fault from at most 1.4 (motor) and 2.6 (pump) tolerances, eight years
    #: from 2.9, four from 3.7-5.0, three from 4.4-5.3. 0: off.
    detectable_multiple: float = 4.0
    #: Unrecorded repairs: yearly estimates that fall back towards nominal (twinmon/repairs.py,
    #: at this level, Bonferroni over the years tried and the inputs) are reported with the
    #: command that records the event, and the component's trend restarts there: in
    #: calibrate for the joint method (which therefore records this level), in forecast for
    #: yearly estimates calibrated one year at a time. 0: off. 0.05: on
    #: benchmarks/repair_scan.py's seeds 11 and 12, 53 of 64 hidden repairs found (0.01: 46)
    #: with at most one finding on 44 units of each family without repairs.
    repair_alpha: float = 0.05
    #: Monte Carlo points outside the surrogate's box: ``learn`` (a model of the margin to
    #: the safety limit, learnt from FMU runs once per forecast, answers the points it is
    #: sure are unsafe; the others run through the FMU; twinmon/forecast/limitstate.py) or
    #: ``fmu`` (every one through the FMU). P(unsafe) is the same within Monte Carlo error.
    outside_box: Literal["learn", "fmu"] = "learn"

    def _check(self):
        if self.pool_min_units < 2:
            yield "pool_min_units", "must be >= 2 (one unit cannot inform a fleet's prior)", \
                self.pool_min_units
        if self.pool_shapes_min_years < 1:
            yield "pool_shapes_min_years", "must be >= 1", self.pool_shapes_min_years
        if not 0.5 <= self.attribution_confidence < 1:
            yield "attribution_confidence", "must lie in [0.5, 1)", self.attribution_confidence
        if self.horizon < 1:
            yield "horizon", "must be >= 1", self.horizon
        if not 0 < self.confidence < 1:
            yield "confidence", "must lie in (0, 1)", self.confidence
        if self.samples < 10:
            yield "samples", "must be >= 10", self.samples
        if not 0 < self.alpha < 1:
            yield "alpha", "must lie in (0, 1)", self.alpha
        if not 0 <= self.shape_alpha < 1:
            yield "shape_alpha", "must lie in [0, 1)", self.shape_alpha
        if not 0 <= self.trend_fit_alpha < 1:
            yield "trend_fit_alpha", "must lie in [0, 1)", self.trend_fit_alpha
        if self.detectable_multiple != 0 and not self.detectable_multiple > 1:
            yield "detectable_multiple", "must be 0 (off) or > 1", self.detectable_multiple
        if not 0 <= self.repair_alpha < 1:
            yield "repair_alpha", "must lie in [0, 1)", self.repair_alpha
        if self.observed_samples < 1:
            yield "observed_samples", "must be >= 1", self.observed_samples
        if self.withhold_years < 1:
            yield "withhold_years", "must be >= 1", self.withhold_years


@dataclass(frozen=True)
class BacktestConfig:
    """``twinmon backtest``: forecasts from truncated histories scored on the later years."""

    #: The first cut sees this many years (the trends need at least 3).
    min_years: int = 5
    #: alpha-lambda accuracy: the predicted RUL must lie within +- alpha * true RUL ...
    alpha: float = 0.2
    #: ... at the cut this fraction of the way from the first cut to the end of life.
    lambda_value: float = 0.5
    #: The back-test warns when its coverage leaves ``forecast.confidence`` +- this band
    #: (0.85-0.95 for 90 % intervals) by more than its own sampling error allows.
    coverage_band: float = 0.05

    def _check(self):
        if self.min_years < 3:
            yield "min_years", "must be >= 3 (a trend with intervals needs 3 years)", \
                self.min_years
        if not 0 < self.alpha < 1:
            yield "alpha", "must lie in (0, 1)", self.alpha
        if not 0 <= self.lambda_value <= 1:
            yield "lambda_value", "must lie in [0, 1]", self.lambda_value
        if not 0 < self.coverage_band < 0.5:
            yield "coverage_band", "must lie in (0, 0.5)", self.coverage_band
