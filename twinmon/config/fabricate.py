"""The ``fabricate`` section: synthetic plant data made from known input trajectories.

:class:`FabricateConfig` lists the fabricated units (:class:`UnitSpec`): each input's true
yearly trajectory (:class:`TrajectorySpec`), effects switched on (:class:`InjectedEffect`),
an additive disturbance (:class:`Disturbance`) and maintenance events
(:class:`FabricateEvent`); plus the years, the noise and the seed.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

from .schema import to_plain


@dataclass(frozen=True)
class TrajectoryChange:
    """A change of a part's wear from service year ``year`` on: the input jumps by ``size``
    (a sudden fault) and, when ``slope`` is given, ages at that rate from then on (``0``: it
    stays where the jump left it)."""

    year: int
    size: float = 0.0
    slope: Optional[float] = None


@dataclass(frozen=True)
class TrajectorySpec:
    """True yearly trajectory of one input, as a function of the part's age ``a`` (years
    since it was new: ``year - 1``, or since its replacement):
    ``start + slope * g(a) + curvature * a**2`` plus jitter, where ``g(a) = a`` for linear
    wear and ``g(a) = (exp(growth * a) - 1) / growth`` for exponential wear (its rate is
    ``slope`` when new and grows by ``exp(growth)`` a year); then ``changes`` in order."""

    start: float
    slope: float = 0.0
    #: Standard deviation of the year-to-year jitter, in the input's units.
    jitter: float = 0.0
    #: Quadratic term (accelerating wear when it has the slope's sign), per year squared.
    curvature: float = 0.0
    #: Exponential growth of the wear rate, per year; 0: linear.
    growth: float = 0.0
    #: Steps and changes of rate, in service years (``[{year, size[, slope]}]``).
    changes: tuple[TrajectoryChange, ...] = ()

    def _check(self):
        for i, c in enumerate(self.changes):
            if c.year < 2:
                yield f"changes.{i}.year", "must be >= 2 (a change needs a year before it)", \
                    c.year
            if i and c.year <= self.changes[i - 1].year:
                yield f"changes.{i}.year", \
                    f"must be after the previous change's year ({self.changes[i - 1].year})", \
                    c.year


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
    #: False: the part is replaced but the plant does not record it (the observations
    #: carry no event; the truth file does, among ``unrecorded_events``).
    recorded: bool = True


@dataclass(frozen=True)
class UnitSpec:
    trajectories: dict[str, TrajectorySpec]
    effects: dict[str, InjectedEffect] = field(default_factory=dict)
    disturbance: Optional[Disturbance] = None
    #: Maintenance events, ``[{year, component[, action, note, recorded]}]``.
    events: tuple[FabricateEvent, ...] = ()
    #: The unit's record ends in this year (a thin history); None: ``fabricate.years``.
    last_year: Optional[int] = None
    #: Years the plant did not record (the unit still ages through them).
    missing_years: tuple[int, ...] = ()
    #: Share of the output's samples lost at random (NaN in the observations).
    nan_fraction: float = 0.0

    def _check(self):
        if self.last_year is not None and self.last_year < 1:
            yield "last_year", "must be >= 1", self.last_year
        if not 0 <= self.nan_fraction < 1:
            yield "nan_fraction", "must lie in [0, 1)", self.nan_fraction


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
            end = spec.last_year or self.years
            if end > self.years:
                yield f"units.{unit}.last_year", f"must be <= years ({self.years})", end
            for i, y in enumerate(spec.missing_years):
                if not 1 <= y < end:
                    yield f"units.{unit}.missing_years.{i}", \
                        f"must lie in [1, {end - 1}] (the record's last year stays)", y
            seen = set()
            for i, ev in enumerate(spec.events):
                # Year 1 is the first recording: an event then has no "before" to end.
                if not 2 <= ev.year <= self.years:
                    yield f"units.{unit}.events.{i}.year", \
                        f"must lie in [2, {self.years}] (after the first year, within years)", \
                        ev.year
                if ev.recorded and (ev.year > end or ev.year in spec.missing_years):
                    yield f"units.{unit}.events.{i}.year", \
                        "a recorded event needs that year's recording (it is after the " \
                        "unit's last year or among its missing_years)", ev.year
                if (ev.year, ev.component) in seen:
                    yield f"units.{unit}.events.{i}", \
                        f"a second event for {ev.component!r} in year {ev.year}", to_plain(ev)
                seen.add((ev.year, ev.component))
