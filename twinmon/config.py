"""Typed, frozen, validated configuration.

A config is one YAML file (optionally ``extends:`` another, merged key by key) holding the
sections below. It is loaded once, ``--set a.b=v`` overrides are applied to the raw mapping,
and only then is it validated: every unknown key is rejected and every error names the file,
the YAML path and the value received, so a typo never silently falls back to a default.

The sections are plain frozen dataclasses; :func:`_build` turns a mapping into one by reading
the dataclass's type hints, so adding a field is a one-line change and needs no parser code.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping, Optional

import numpy as np
import yaml

from .errors import ConfigError, ReadError


# ---------------------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InputSpec:
    """One calibrated (degradation) input of the model.

    ``low``/``high`` bound the design box that the surrogate is trained on and that the
    year-1 uniform prior covers; ``normal_rate`` is the yearly drift normal ageing allows
    (signed: a pump coefficient normally falls a little), used for root-cause tests.
    """

    variable: str
    low: float
    high: float
    nominal: float
    units: str = "1"
    description: str = ""
    component: str = ""
    normal_rate: float = 0.0
    normal_rate_tolerance: float = 0.0
    #: Which way the input moves as the unit degrades (raises the risk of the health
    #: indicator): ``up`` or ``down``; None: inferred from the twin by ``forecast``.
    degrading: Optional[Literal["up", "down"]] = None

    def _check(self):
        if not self.low < self.high:
            yield "high", f"must be greater than low ({self.low})", self.high
        if not self.low <= self.nominal <= self.high:
            yield "nominal", f"must lie in [{self.low}, {self.high}]", self.nominal
        if self.normal_rate_tolerance < 0:
            yield "normal_rate_tolerance", "must be >= 0", self.normal_rate_tolerance


@dataclass(frozen=True)
class TimeGrid:
    """Sample times ``start, start+step, ..., stop`` in seconds."""

    start: float = 2.0
    stop: float = 50.0
    step: float = 2.0

    def _check(self):
        if self.step <= 0:
            yield "step", "must be > 0", self.step
        if self.start <= 0:
            yield "start", "must be > 0 (the model starts from rest at t = 0)", self.start
        if self.stop < self.start + self.step:
            yield "stop", f"must be at least start + step ({self.start + self.step:g}): a " \
                "transient needs two samples or more", self.stop

    @property
    def times(self) -> np.ndarray:
        """Sample times, shape [n_t], seconds."""
        n = int(round((self.stop - self.start) / self.step)) + 1
        return self.start + self.step * np.arange(n)


@dataclass(frozen=True)
class OutputSpec:
    """The observed model output and its sample grid.

    ``variable`` is the FMU variable; ``name`` is the channel's name in observation files
    (default: the variable itself, so a file written for one FMU names what it measured);
    ``label`` is the words the report uses (default: the name)."""

    variable: str
    name: str = ""
    label: str = ""
    units: str = "1"
    times: TimeGrid = TimeGrid()

    def __post_init__(self):
        # Derived defaults, resolved once so every reader sees the same words.
        if not self.name:
            object.__setattr__(self, "name", self.variable)
        if not self.label:
            object.__setattr__(self, "label", self.name)

    def _check(self):
        if not self.variable:
            yield "variable", "must name an FMU variable", self.variable


@dataclass(frozen=True)
class ChannelSpec:
    """A further FMU variable recorded as an observation channel (speed, pressure, ...)."""

    units: str = ""
    label: str = ""


@dataclass(frozen=True)
class EffectSpec:
    """A candidate unmodelled effect, keyed by its FMU parameter; its ``baseline`` value
    switches it off (gives exactly the base model). (Not ``off``: YAML reads that as false.)"""

    baseline: float
    low: float
    high: float
    units: str = "1"
    description: str = ""
    #: The effect alters only what the sensors read, not the machine (a sensor lag or gain):
    #: it is left out when the twin judges the unit's safety.
    measurement_only: bool = False

    def _check(self):
        if not self.low < self.high:
            yield "high", f"must be greater than low ({self.low})", self.high
        if not self.low <= self.baseline <= self.high:
            yield "baseline", f"must lie in [{self.low}, {self.high}]", self.baseline


@dataclass(frozen=True)
class ModelConfig:
    """Which FMU, which inputs are calibrated, what is observed."""

    fmu: Path
    inputs: dict[str, InputSpec]
    output: OutputSpec
    fmi_type: Literal["CoSimulation", "ModelExchange"] = "CoSimulation"
    #: Further FMU variables recorded as extra channels, keyed by FMU variable name (a plain
    #: YAML list of names is accepted too).
    channels: dict[str, ChannelSpec] = field(default_factory=dict)
    #: FMU output that is 1 when the twin left its physical domain; "" if the FMU has none.
    nonphysical: str = ""
    #: FMU parameters held at a value other than the FMU's default.
    fixed: dict[str, float] = field(default_factory=dict)
    #: Candidate unmodelled effects, screened by ``diagnose``.
    effects: dict[str, EffectSpec] = field(default_factory=dict)

    def _check(self):
        if len(self.inputs) == 0:
            yield "inputs", "at least one input is needed", {}
        if self.output.name in self.channels:
            yield "channels", f"{self.output.name!r} is the output's own channel name", \
                self.output.name

    @property
    def channel_units(self) -> dict[str, str]:
        """Units per observation channel name: the output's, then each further channel's."""
        return {self.output.name: self.output.units,
                **{k: c.units for k, c in self.channels.items()}}

    def variable_words(self, variable: str) -> tuple[str, str]:
        """``(label, units)`` of an FMU variable: the output's, a channel's, or the bare
        name with no units for a variable the config does not describe."""
        if variable == self.output.variable:
            return self.output.label, self.output.units
        ch = self.channels.get(variable)
        return (ch.label if ch is not None and ch.label else variable,
                ch.units if ch is not None else "")

    @property
    def input_names(self) -> list[str]:
        return list(self.inputs)

    @property
    def components(self) -> dict[str, tuple[str, ...]]:
        """Input names per component word (an input's ``component``, or its own name when
        it has none), in config order: what a maintenance event may name."""
        out: dict[str, tuple[str, ...]] = {}
        for name, spec in self.inputs.items():
            key = spec.component or name
            out[key] = out.get(key, ()) + (name,)
        return out

    @property
    def bounds(self) -> np.ndarray:
        """Design box, shape [n_inputs, 2] (low, high), in each input's units."""
        return np.array([[s.low, s.high] for s in self.inputs.values()])


INDICATOR_KINDS = ("time_to_reach", "value_at", "max", "min", "mean", "final")


@dataclass(frozen=True)
class IndicatorSpec:
    """The health indicator: one number computed from one recorded transient.

    Kinds (``variable`` is an FMU variable recorded at the output times):

    - ``time_to_reach``: time (s) at which the variable first crosses ``level``, upwards
      (``direction: up``) or downwards; ``inf`` when it never does within the record.
      ``initial`` is the variable's value at t = 0 (a start from rest), so a crossing
      before the first sample is interpolated too; without it that crossing is reported at
      the first sample time.
    - ``value_at``: the variable at time ``at`` (linear interpolation).
    - ``max`` / ``min`` / ``mean``: over ``window`` [start, stop] s (default: the record).
    - ``final``: the last sample.
    """

    kind: Literal["time_to_reach", "value_at", "max", "min", "mean", "final"]
    #: FMU variable; "" means the model's output variable.
    variable: str = ""
    level: Optional[float] = None
    direction: Literal["up", "down"] = "up"
    initial: Optional[float] = None
    at: Optional[float] = None
    window: Optional[tuple[float, ...]] = None
    #: Short name (table headers, JSON); "" gives one from the kind.
    name: str = ""
    #: Words for the report; "" gives one from the kind and variable.
    label: str = ""
    #: Units of the indicator; "" gives "s" for time_to_reach, else the variable's units.
    units: str = ""

    def _check(self):
        if self.kind == "time_to_reach" and self.level is None:
            yield "level", "is required for kind time_to_reach", self.level
        if self.kind == "value_at" and self.at is None:
            yield "at", "is required for kind value_at", self.at
        if self.window is not None:
            if len(self.window) != 2 or not self.window[0] < self.window[1]:
                yield "window", "must be [start, stop] with start < stop", list(self.window)


@dataclass(frozen=True)
class UnsafeIf:
    """The indicator's limit: unsafe ``above`` or ``below`` a value (exactly one)."""

    above: Optional[float] = None
    below: Optional[float] = None

    def _check(self):
        if (self.above is None) == (self.below is None):
            yield "above", "give exactly one of above or below", \
                {"above": self.above, "below": self.below}

    @property
    def limit(self) -> float:
        return self.above if self.above is not None else self.below

    @property
    def sense(self) -> int:
        """+1 when high values are unsafe (``above``), -1 when low values are."""
        return 1 if self.above is not None else -1


@dataclass(frozen=True)
class SafetyConfig:
    """A unit is unsafe when its health indicator passes ``unsafe_if``, or its twin is
    non-physical; it fails in the first year with P(unsafe) > ``failure_probability``."""

    indicator: IndicatorSpec
    unsafe_if: UnsafeIf
    failure_probability: float = 0.05

    def _check(self):
        if not 0 < self.failure_probability < 1:
            yield "failure_probability", "must lie in (0, 1)", self.failure_probability


@dataclass(frozen=True)
class SimulateConfig:
    train_size: int = 128
    test_size: int = 64
    design: Literal["lhs", "sobol", "halton"] = "lhs"
    #: Worker processes; 0 means one per core.
    workers: int = 0
    #: ``dask``: on a Dask cluster (the ``dask`` section; docs/cluster.md). Also used by
    #: ``forecast``'s FMU runs.
    executor: Literal["process", "serial", "dask"] = "process"
    #: Runs flushed to the partial artifact at a time (what a crash can lose).
    chunk_size: int = 64

    def _check(self):
        if self.train_size < 2:
            yield "train_size", "must be >= 2", self.train_size
        if self.test_size < 0:
            yield "test_size", "must be >= 0", self.test_size
        if self.workers < 0:
            yield "workers", "must be >= 0", self.workers
        if self.chunk_size < 1:
            yield "chunk_size", "must be >= 1", self.chunk_size


@dataclass(frozen=True)
class TrajectorySpec:
    """True yearly trajectory of one input: ``start + slope * (year - 1)`` plus jitter."""

    start: float
    slope: float = 0.0
    #: Standard deviation of the year-to-year jitter, in the input's units.
    jitter: float = 0.0
    #: Quadratic term, for trajectories that are not quite linear.
    curvature: float = 0.0


@dataclass(frozen=True)
class InjectedEffect:
    """An effect switched on in a fabricated unit from ``onset`` (year) on."""

    value: float
    onset: int = 1


@dataclass(frozen=True)
class Disturbance:
    """An additive disturbance outside the candidate list (e.g. a pulsation), in the
    output's units."""

    amplitude: float
    period: float = 7.0
    onset: int = 1
    #: "sine": A*sin(2*pi*t/period); "bump": A*exp(-((t-period)/4)^2).
    shape: Literal["sine", "bump"] = "sine"


@dataclass(frozen=True)
class FabricateEvent:
    """A maintenance event of a fabricated unit: from ``year`` on, the inputs of
    ``component`` (``model.inputs[*].component``) follow their trajectory again from its
    ``start``, as a new part would. Written into the observations as a plant records it."""

    year: int
    component: str
    #: Only a replacement can be fabricated (the part is as new).
    action: Literal["replaced"] = "replaced"
    note: str = ""


@dataclass(frozen=True)
class UnitSpec:
    trajectories: dict[str, TrajectorySpec]
    effects: dict[str, InjectedEffect] = field(default_factory=dict)
    disturbance: Optional[Disturbance] = None
    #: Maintenance events, ``[{year, component[, action, note]}]``.
    events: tuple[FabricateEvent, ...] = ()


@dataclass(frozen=True)
class FabricateConfig:
    """Synthetic plant data: simulations of known trajectories plus noise."""

    units: dict[str, UnitSpec]
    years: int = 10
    #: Output noise standard deviation, in the output's units; None: ``noise_fraction``.
    noise_std: Optional[float] = None
    #: Output noise standard deviation as a fraction of the range of the healthy unit's
    #: output over the record (used when ``noise_std`` is not given).
    noise_fraction: float = 0.01
    #: Noise of the extra channels, as a fraction of each channel's range over the healthy
    #: unit's record.
    channel_noise_fraction: float = 0.01
    #: Also simulate and record (noise-free) in the truth file these FMU variables.
    truth_variables: tuple[str, ...] = ()
    #: Record the extra channels (``model.channels``) in the observations.
    record_channels: bool = False
    #: Write ``noise_std`` into the observations (False: the user must estimate it).
    record_noise: bool = True
    seed: int = 2024

    def _check(self):
        if not 0 <= self.seed < 2 ** 32:
            yield "seed", "must lie in [0, 2**32 - 1]", self.seed
        if self.years < 1:
            yield "years", "must be >= 1", self.years
        if self.noise_fraction < 0:
            yield "noise_fraction", "must be >= 0", self.noise_fraction
        if self.noise_std is not None and self.noise_std < 0:
            yield "noise_std", "must be >= 0", self.noise_std
        for unit, spec in self.units.items():
            seen = set()
            for i, ev in enumerate(spec.events):
                # Year 1 is the first recording: an event then has no "before" to end.
                if not 2 <= ev.year <= self.years:
                    yield f"units.{unit}.events.{i}.year", \
                        f"must lie in [2, {self.years}] (after the first year, within years)", \
                        ev.year
                if (ev.year, ev.component) in seen:
                    yield f"units.{unit}.events.{i}", \
                        f"a second event for {ev.component!r} in year {ev.year}", to_plain(ev)
                seen.add((ev.year, ev.component))


@dataclass(frozen=True)
class ReduceConfig:
    #: Keep the fewest Karhunen-Loeve modes whose variance ratio reaches this.
    variance_threshold: float = 0.99999
    #: "log": reduce log(output), so the error is relative at every time step (the early,
    #: small samples of a start-up are otherwise learnt to absolute, not relative, accuracy);
    #: only for an output that stays > 0. "auto": log when every training value is > 0.
    transform: Literal["auto", "log", "none"] = "auto"
    max_modes: int = 8
    kernel: Literal["squared_exponential", "matern52", "matern32", "exponential"] = "matern52"
    trend: Literal["constant", "linear", "quadratic"] = "linear"
    #: Further channels (keys of ``model.channels``) that get a surrogate of their own, built
    #: like the output's but with transform ``auto``; None: every channel the design
    #: recorded; []: the output only (each channel costs about one more reduce).
    channels: Optional[tuple[str, ...]] = None

    def _check(self):
        if not 0 < self.variance_threshold <= 1:
            yield "variance_threshold", "must lie in (0, 1]", self.variance_threshold
        if self.max_modes < 1:
            yield "max_modes", "must be >= 1", self.max_modes


@dataclass(frozen=True)
class CalibrateConfig:
    """Bayesian calibration per unit and year (see docs/calibration.md).

    ``samples`` and ``burn_in`` count draws per chain; year-1 chains (uniform prior, a
    longer and more curved posterior) run twice as long and keep every second draw."""

    chains: int = 4
    samples: int = 1500
    burn_in: int = 250
    #: Width (std) of the Gaussian prior of year n+1 around year n's estimate, as a
    #: fraction of each input's design range. See docs/calibration.md for the default.
    prior_width: float = 0.05
    #: Output noise standard deviation (output units), for units whose observations file does not
    #: record one; None: estimated from the residuals of a least-squares fit of each year.
    noise_std: Optional[float] = None
    #: Add the previous year's posterior variance to the year-to-year prior variance (the
    #: Kalman predictive variance of a random walk): prior std = sqrt((w * range)^2 + var).
    prior_carry_variance: bool = True
    rhat_warn: float = 1.05
    ess_warn: float = 400.0
    #: A year whose R-hat or ESS misses the marks above is sampled again with chains twice
    #: as long (thinned to the same number of kept draws), at most this many times; still
    #: poor after that, the year is "unconverged" and its unit's prognosis "unreliable".
    max_extensions: int = 2
    #: Goodness of fit (docs/calibration.md): a year "misses the plant" when the RMS of its
    #: standardised residual at the posterior mean exceeds ``fit_min_rms`` (in noise standard
    #: deviations) AND the chi-square or Ljung-Box test rejects at ``fit_alpha``.
    fit_alpha: float = 1e-3
    fit_min_rms: float = 1.5
    #: A year sits "on the box edge" when more than ``edge_share`` of its posterior draws lie
    #: within ``edge_margin`` (fraction of the input's range) of a bound of the design box.
    edge_margin: float = 0.02
    edge_share: float = 0.25
    #: Pooled draws per year stored in ``posterior.h5``, evenly thinned over every chain; the
    #: summary statistics use every draw. 1000 keeps about all the effective samples (bulk
    #: ESS 600-1800 of 6000 draws with the defaults) and twice forecast's ``observed_samples``
    #: (docs/calibration.md, "Stored draws").
    keep_draws: int = 1000
    #: Worker processes (units run in parallel); 0 means one per core, 1 runs in-process.
    workers: int = 0
    #: ``dask``: the chains run on a Dask cluster (the ``dask`` section; docs/cluster.md).
    executor: Literal["process", "dask"] = "process"
    #: Further channels (keys of ``model.channels``) in the likelihood besides the output,
    #: each with its own noise; None: every channel the observations carry and the surrogate
    #: models; []: the output only.
    channels: Optional[tuple[str, ...]] = None
    #: How either method samples: ``vectorised`` (numpy, every unit's chains at once:
    #: random-walk Metropolis run until the ESS is met, calibrate/vectorised.py, or the joint
    #: method's Gibbs sweeps, calibrate/joint_vectorised.py) or ``openturns`` (OpenTURNS'
    #: samplers, one chain per task: the reference). Same model, same diagnostics;
    #: docs/calibration.md compares them.
    sampler: Literal["vectorised", "openturns"] = "vectorised"
    #: ``sequential``: the paper's method, each year sampled in turn with a prior centred on
    #: the previous year's estimate (calibrate/sequential.py). ``joint``: each unit's whole
    #: history in one posterior with a linear trend per input (restarted at maintenance
    #: events) and its year-to-year scatter inside (calibrate/joint.py; docs/calibration.md).
    #: ``auto``: ``joint`` when the observations hold a fleet whose year-to-year sd
    #: ``forecast`` can pool (``forecast.pool_sigma`` and at least ``forecast.pool_min_units``
    #: units), else ``sequential``: on benchmarks/prognosis.py the pooled joint method is
    #: the better calibrated one, the unpooled one is not (docs/forecast.md, "The default
    #: method").
    method: Literal["auto", "sequential", "joint"] = "auto"
    #: ``joint`` only: moves of the whole trend (levels, slopes, scatter) per Gibbs sweep,
    #: each one surrogate call over the unit's years; the years' own moves are one each.
    joint_trend_moves: int = 5

    def _check(self):
        if self.chains < 2:
            yield "chains", "must be >= 2 (split R-hat needs several chains)", self.chains
        if self.samples < 100:
            yield "samples", "must be >= 100", self.samples
        if self.burn_in < 0:
            yield "burn_in", "must be >= 0", self.burn_in
        if self.prior_width <= 0:
            yield "prior_width", "must be > 0", self.prior_width
        if self.noise_std is not None and self.noise_std <= 0:
            yield "noise_std", "must be > 0 (or null to estimate it)", self.noise_std
        if self.rhat_warn <= 1:
            yield "rhat_warn", "must be > 1", self.rhat_warn
        if self.ess_warn < 0:
            yield "ess_warn", "must be >= 0", self.ess_warn
        if self.workers < 0:
            yield "workers", "must be >= 0", self.workers
        if self.keep_draws < 1:
            yield "keep_draws", "must be >= 1", self.keep_draws
        if self.max_extensions < 0:
            yield "max_extensions", "must be >= 0", self.max_extensions
        if self.joint_trend_moves < 1:
            yield "joint_trend_moves", "must be >= 1", self.joint_trend_moves
        if not 0 < self.fit_alpha < 1:
            yield "fit_alpha", "must lie in (0, 1)", self.fit_alpha
        if self.fit_min_rms < 1:
            yield "fit_min_rms", "must be >= 1 (a residual at the noise level fits)", \
                self.fit_min_rms
        if not 0 <= self.edge_margin < 0.5:
            yield "edge_margin", "must lie in [0, 0.5)", self.edge_margin
        if not 0 < self.edge_share <= 1:
            yield "edge_share", "must lie in (0, 1]", self.edge_share


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

    def _check(self):
        if self.pool_min_units < 2:
            yield "pool_min_units", "must be >= 2 (one unit cannot inform a fleet's prior)", \
                self.pool_min_units
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

    def _check(self):
        if self.min_years < 3:
            yield "min_years", "must be >= 3 (a trend with intervals needs 3 years)", \
                self.min_years
        if not 0 < self.alpha < 1:
            yield "alpha", "must lie in (0, 1)", self.alpha
        if not 0 <= self.lambda_value <= 1:
            yield "lambda_value", "must lie in [0, 1]", self.lambda_value


@dataclass(frozen=True)
class WindowSpec:
    start: float
    stop: float


@dataclass(frozen=True)
class DiagnoseConfig:
    """Settings of ``diagnose`` (the sim-to-real gap); docs/diagnose.md explains each."""

    #: Named time windows of the record (seconds), for locating the gap; empty: the record
    #: split into thirds named early, middle and late (see :func:`diagnose_windows`).
    windows: dict[str, WindowSpec] = field(default_factory=dict)
    #: Significance level of the gap tests (family-wise: Bonferroni over years and tests).
    alpha: float = 0.01
    #: Minimum BIC gain to accept an effect (or a further one).
    bic_gain: float = 10.0
    #: Candidates whose fitted BIC lie within this of the best are reported as one group.
    group_bic: float = 6.0
    max_effects: int = 2
    #: Candidate effects (FMU parameters, keys of model.effects); empty: all of them.
    candidates: tuple[str, ...] = ()
    #: Confirmation fits try the screened onset year and this many years either side.
    onset_search: int = 1
    #: Effect values per side of the baseline on the screening grid.
    screen_points: int = 8
    #: Candidates confirmed by full fits (the best screened first; any other whose screening
    #: score is at least half the best's too); 0: every candidate.
    confirm_first: int = 3
    #: Candidates confirmed by a full fit when looking for a further effect.
    confirm_further: int = 3
    #: Below this percentage of the excess gap closed, the verdict is "unexplained".
    min_closed: float = 50.0
    #: An accepted effect that closes at least this percentage of the excess gap is the
    #: verdict even when the remainder still fails the noise tests.
    explained_closed: float = 90.0
    #: The degradation inputs are fitted in their design box widened by this fraction of
    #: its width on each side (a twin far outside its box is itself a sign of a gap).
    fit_margin: float = 0.1
    #: Lags of the Ljung-Box test of structure in a year's residual.
    ljung_box_lags: int = 5
    #: Noise of an unrecorded channel, as a fraction of its healthy plateau, for choosing
    #: the channel that would separate a group.
    channel_noise_fraction: float = 0.01
    #: Worker processes over units; 0 means one per core.
    workers: int = 0
    #: ``dask``: the units run on a Dask cluster (the ``dask`` section; docs/cluster.md).
    executor: Literal["process", "dask"] = "process"

    def _check(self):
        for name, w in self.windows.items():
            if not w.start < w.stop:
                yield f"windows.{name}.stop", f"must be greater than start ({w.start})", w.stop
        if not 0 < self.alpha < 1:
            yield "alpha", "must lie in (0, 1)", self.alpha
        if self.bic_gain < 0:
            yield "bic_gain", "must be >= 0", self.bic_gain
        if self.group_bic < 0:
            yield "group_bic", "must be >= 0", self.group_bic
        if self.max_effects < 1:
            yield "max_effects", "must be >= 1", self.max_effects
        if self.onset_search < 0:
            yield "onset_search", "must be >= 0", self.onset_search
        if self.screen_points < 2:
            yield "screen_points", "must be >= 2", self.screen_points
        if self.confirm_first < 0:
            yield "confirm_first", "must be >= 0 (0: every candidate)", self.confirm_first
        if self.confirm_further < 1:
            yield "confirm_further", "must be >= 1", self.confirm_further
        if not 0 <= self.min_closed <= 100:
            yield "min_closed", "must lie in [0, 100]", self.min_closed
        if not self.min_closed <= self.explained_closed <= 100:
            yield "explained_closed", f"must lie in [min_closed ({self.min_closed}), 100]", \
                self.explained_closed
        if self.fit_margin < 0:
            yield "fit_margin", "must be >= 0", self.fit_margin
        if self.ljung_box_lags < 1:
            yield "ljung_box_lags", "must be >= 1", self.ljung_box_lags
        if self.channel_noise_fraction <= 0:
            yield "channel_noise_fraction", "must be > 0", self.channel_noise_fraction
        if self.workers < 0:
            yield "workers", "must be >= 0", self.workers


@dataclass(frozen=True)
class ReportConfig:
    """The report page (docs/report.md)."""

    #: A fleet of more units than this opens on a fleet overview (verdict counts, every unit
    #: ranked by P(unsafe), time to failure across the fleet), and per-unit figures are drawn
    #: for at most this many units: those asked for with ``report --unit``, then the units at
    #: risk in rank order. Smaller fleets get every unit's figures.
    detail_units: int = 12
    #: Processes that lay out and write the figures while the next ones are built (0: one
    #: per core; 1: all in the report's own process).
    workers: int = 0

    def _check(self):
        if self.detail_units < 1:
            yield "detail_units", "must be >= 1", self.detail_units
        if self.workers < 0:
            yield "workers", "must be >= 0 (0: one per core)", self.workers


@dataclass(frozen=True)
class DaskConfig:
    """Where the stages whose ``executor`` is ``dask`` run (docs/cluster.md).

    ``address`` null: a ``LocalCluster`` on this machine, as many worker processes as the
    stage's ``workers`` (0: one per core), one thread each; ``tcp://host:8786``: the running
    scheduler there (its workers must run one thread each). ``timeout``: seconds allowed to
    reach the scheduler or start the local workers before the command fails."""

    address: Optional[str] = None
    timeout: float = 10.0

    def _check(self):
        if self.address is not None and (not self.address.strip()
                                         or any(c.isspace() for c in self.address)):
            yield "address", "expected a scheduler address such as tcp://host:8786, or " \
                "null for a local cluster", self.address
        if self.timeout <= 0:
            yield "timeout", "must be > 0 (seconds)", self.timeout


@dataclass(frozen=True)
class Config:
    """A whole resolved twinmon configuration."""

    model: ModelConfig
    #: The safety criterion (health indicator and its limit).
    safety: SafetyConfig
    seed: int = 0
    simulate: SimulateConfig = SimulateConfig()
    reduce: ReduceConfig = ReduceConfig()
    calibrate: CalibrateConfig = CalibrateConfig()
    forecast: ForecastConfig = ForecastConfig()
    backtest: BacktestConfig = BacktestConfig()
    diagnose: DiagnoseConfig = DiagnoseConfig()
    fabricate: Optional[FabricateConfig] = None
    #: The Dask cluster of ``executor: dask`` (never changes a result).
    dask: DaskConfig = DaskConfig()
    report: ReportConfig = ReportConfig()
    #: Where this config came from (not a YAML key).
    source: Path = field(default=Path("<memory>"), compare=False)
    #: The merged mapping after overrides (not a YAML key): a base for derived configs.
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def indicator_variable(self) -> str:
        """The FMU variable the health indicator is computed from."""
        return self.safety.indicator.variable or self.model.output.variable

    def diagnose_windows(self) -> dict[str, "WindowSpec"]:
        """The named windows of ``diagnose``: the config's, or the record in thirds."""
        if self.diagnose.windows:
            return dict(self.diagnose.windows)
        t = self.model.output.times.times
        # Cut half-way between samples so every sample falls in exactly one window.
        edges = np.quantile(np.concatenate([[0.0], t]), [1 / 3, 2 / 3])
        return {"early": WindowSpec(0.0, float(edges[0])),
                "middle": WindowSpec(float(edges[0]), float(edges[1])),
                "late": WindowSpec(float(edges[1]), float(t[-1]) + 1.0)}

    def _check(self):
        if not 0 <= self.seed < 2 ** 32:
            yield "seed", "must lie in [0, 2**32 - 1] (OpenTURNS and numpy seeds)", self.seed
        for section in ("reduce", "calibrate"):
            for i, ch in enumerate(getattr(self, section).channels or ()):
                if ch not in self.model.channels:
                    yield f"{section}.channels.{i}", "not a key of model.channels (channels: " \
                        f"{', '.join(self.model.channels) or 'none'})", ch
        comps = self.model.components
        for unit, spec in (self.fabricate.units if self.fabricate else {}).items():
            for i, ev in enumerate(spec.events):
                if ev.component not in comps:
                    yield f"fabricate.units.{unit}.events.{i}.component", \
                        f"not a component of model.inputs (components: {', '.join(comps)})", \
                        ev.component

    def section_yaml(self, *names: str) -> str:
        """The resolved YAML of the named sections, recorded in artifacts as provenance.

        Settings that decide how the work is spread over processes but cannot change a
        result (``EXECUTION_ONLY``) are left out, so changing them does not make ``twinmon
        run`` redo a stage."""
        out = {n: to_plain(getattr(self, n)) for n in names}
        if "calibrate" in out and self.calibrate.method == "auto":
            # auto picks the method by forecast's pooling settings, so they decide calibrate's
            # result: recorded with it (changing them re-runs calibrate, refuses --update).
            out["calibrate"]["auto_by"] = {"forecast.pool_sigma": self.forecast.pool_sigma,
                                           "forecast.pool_min_units":
                                               self.forecast.pool_min_units}
        for section, keys in EXECUTION_ONLY.items():
            if isinstance(out.get(section), dict):
                for k in keys:
                    out[section].pop(k, None)
        return yaml.safe_dump(out, sort_keys=True)


_NOT_KEYS = {"source", "raw"}

#: Per section, the keys that spread the work over processes without changing any result.
EXECUTION_ONLY = {"simulate": ("workers", "executor", "chunk_size"),
                  "calibrate": ("workers", "executor"), "diagnose": ("workers", "executor"),
                  "dask": ("address", "timeout")}


# ---------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------
def load_config(path: str | os.PathLike, overrides: typing.Sequence[str] = ()) -> Config:
    """Load, merge (``extends``), override and validate a YAML config.

    Parameters
    ----------
    path : path-like
        The YAML file.
    overrides : sequence of str
        ``"a.b.c=value"`` items; the value is parsed as YAML (so ``3``, ``0.5``, ``true``,
        ``[1, 2]`` keep their types).

    Raises
    ------
    ConfigError
        On a missing file, malformed YAML, an unknown key or an invalid value; the message
        names the file, the YAML path and the value.
    """
    path = Path(path)
    raw = _load_yaml_tree(path, seen=())
    for item in overrides:
        _apply_override(raw, item, path)
    return config_from_mapping(raw, path)


def config_from_mapping(raw: Mapping[str, Any], source: Path = Path("<memory>")) -> Config:
    """Validate an already-merged mapping into a :class:`Config` (paths relative to
    ``source``'s folder)."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{source}: top level must be a mapping, got {type(raw).__name__}")
    raw = copy.deepcopy(dict(raw))
    model = raw.get("model")
    if isinstance(model, dict) and isinstance(model.get("channels"), (list, tuple)):
        # A plain list of channel names is the short form of {name: {}}.
        chans = model["channels"]
        if not all(isinstance(c, str) for c in chans):
            bad = next(c for c in chans if not isinstance(c, str))
            raise ConfigError(f"{source}: model.channels: expected FMU variable names, got {bad!r}")
        model["channels"] = {c: {} for c in chans}
    _refuse_placeholders(raw, (), source)
    cfg = _build(Config, raw, (), source)
    return dataclasses.replace(cfg, source=source, raw=raw)


#: What ``twinmon init`` writes for each value only the user can give.
PLACEHOLDER = "<fill in>"


def _refuse_placeholders(value: Any, path: tuple, source: Path) -> None:
    # A starter config must not load until every placeholder is replaced, whatever the
    # type of the key (a units string would otherwise load and reach the report).
    if isinstance(value, str) and PLACEHOLDER in value:
        raise ConfigError(f"{_where(source, path)}: still {value!r}, the placeholder "
                          "`twinmon init` wrote; fill in the value")
    if isinstance(value, dict):
        for k, v in value.items():
            if isinstance(k, str) and PLACEHOLDER in k:
                raise ConfigError(f"{_where(source, path + (k,))}: the key is still the "
                                  "placeholder `twinmon init` wrote; fill it in")
            _refuse_placeholders(v, path + (k,), source)
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            _refuse_placeholders(v, path + (i,), source)


def _load_yaml_tree(path: Path, seen: tuple) -> dict:
    if path.resolve() in seen:
        raise ConfigError(f"{path}: 'extends' forms a cycle")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, expected a YAML file") from None
    except OSError as exc:
        raise ReadError(f"{path}: cannot read config: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}: line {line}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x}); "
                          "save the config as UTF-8") from None
    try:
        data = yaml.load(text, Loader=StrictLoader)
    except DuplicateKeyError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}: malformed YAML at {where}{problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    parent = data.pop("extends", None)
    if parent is None:
        return _absolutise_paths(data, path.parent)
    if not isinstance(parent, str):
        raise ConfigError(f"{path}: extends: expected a file name, got {parent!r}")
    base = _load_yaml_tree(path.parent / parent, seen + (path.resolve(),))
    return _merge(base, _absolutise_paths(data, path.parent))


def _absolutise_paths(data: dict, folder: Path) -> dict:
    # model.fmu is written relative to the YAML file that names it, so that a config that
    # extends another from elsewhere still finds the FMU.
    model = data.get("model")
    if isinstance(model, dict) and isinstance(model.get("fmu"), str):
        fmu = Path(model["fmu"])
        if not fmu.is_absolute():
            model["fmu"] = os.path.normpath(folder / fmu)
    return data


class DuplicateKeyError(yaml.YAMLError):
    """A mapping names the same key twice (PyYAML would silently keep the last)."""


# libyaml's parser when PyYAML was built with it (the wheels are): a fleet config that lists
# 1000 units parses in 0.2 s instead of 2.2 s; the constructor and resolver stay Python.
_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class StrictLoader(_SafeLoader):
    """PyYAML's safe loader, stricter and kinder: duplicate keys are an error, and numbers
    such as ``1e6`` or ``4e2`` (YAML 1.1 wants ``1.0e+6``) are read as floats."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.get(key)
            except TypeError:
                continue  # an unhashable key: PyYAML reports it itself
            if first is not None:
                raise DuplicateKeyError(
                    f"line {key_node.start_mark.line + 1}: key {key!r} appears twice in one "
                    f"mapping (first on line {first}); remove one")
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


# YAML 1.1's float rule needs a dot and a signed exponent; accept what people write too.
StrictLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$""", re.X),
    list("-+0123456789"))


def _merge(base: dict, top: dict) -> dict:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _apply_override(raw: dict, item: str, source: Path) -> None:
    if "=" not in item:
        raise ConfigError(f"--set {item!r}: expected KEY.PATH=VALUE")
    key, _, text = item.partition("=")
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"--set {item!r}: empty key")
    try:
        value = yaml.load(text, Loader=StrictLoader)
    except yaml.YAMLError:
        raise ConfigError(f"--set {item!r}: value {text!r} is not valid YAML") from None
    node = raw
    for i, part in enumerate(parts[:-1]):
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            raise ConfigError(
                f"--set {item!r}: {'.'.join(parts[:i + 1])} is not a mapping in {source}")
        node = child
    if parts == ["model", "fmu"] and isinstance(value, str):
        value = os.path.abspath(value)
    node[parts[-1]] = value


def _where(source: Path, path: tuple) -> str:
    return f"{source}: {'.'.join(str(p) for p in path) or '<top>'}"


def _build(tp: Any, value: Any, path: tuple, source: Path) -> Any:
    """Turn ``value`` (parsed YAML) into type ``tp``, or raise ConfigError naming ``path``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build_dataclass(tp, value, path, source)
    if origin is typing.Union:  # Optional[X]
        if value is None:
            return None
        inner = [a for a in args if a is not type(None)]
        return _build(inner[0], value, path, source)
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{_where(source, path)}: expected one of "
                              f"{', '.join(map(str, args))}, got {value!r}")
        return value
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{_where(source, path)}: expected a mapping, got {value!r}")
        return {str(k): _build(args[1], v, path + (k,), source) for k, v in value.items()}
    if origin is tuple:
        if isinstance(value, str) or not isinstance(value, (list, tuple)):
            raise ConfigError(f"{_where(source, path)}: expected a list, got {value!r}")
        return tuple(_build(args[0], v, path + (i,), source) for i, v in enumerate(value))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{_where(source, path)}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{_where(source, path)}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{_where(source, path)}: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{_where(source, path)}: expected a finite number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{_where(source, path)}: expected a string, got {value!r}")
        return value
    if tp is Path:
        if not isinstance(value, str) or not value:
            raise ConfigError(f"{_where(source, path)}: expected a path, got {value!r}")
        return Path(value)
    raise TypeError(f"config type {tp!r} is not supported")  # programming error


def _build_dataclass(cls: type, value: Any, path: tuple, source: Path) -> Any:
    if not isinstance(value, dict):
        raise ConfigError(f"{_where(source, path)}: expected a mapping, got {value!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in _NOT_KEYS}
    unknown = [k for k in value if not isinstance(k, str) or k not in fields]
    if unknown:
        key = unknown[0]
        raise ConfigError(f"{_where(source, path + (key,))}: unknown key (value {value[key]!r}); "
                          f"expected one of {', '.join(fields)}")
    kwargs = {}
    for name, f in fields.items():
        if name in value:
            kwargs[name] = _build(hints[name], value[name], path + (name,), source)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{_where(source, path + (name,))}: required key is missing")
    obj = cls(**kwargs)
    check = getattr(obj, "_check", None)
    if check is not None:
        for key, msg, got in check():
            raise ConfigError(f"{_where(source, path + (key,))}: {msg}, got {got!r}")
    return obj


def to_plain(obj: Any) -> Any:
    """A config object as plain YAML-able Python (for printing and provenance)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)
                if f.name not in _NOT_KEYS}
    if isinstance(obj, dict):
        return {k: to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj
