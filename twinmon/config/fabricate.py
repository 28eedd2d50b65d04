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
