"""The ``safety`` section: the health indicator and the limit that makes a unit unsafe.

:class:`IndicatorSpec` computes one number from one recorded transient; :class:`UnsafeIf`
is its limit; :class:`SafetyConfig` adds the failure probability that dates a failure.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional


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
            # Both, under extends, is mostly the base's side beside the new one.
            yield "above", "give exactly one of above or below (a config that extends " \
                "another keeps its side unless set to null, e.g. below: null)", \
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
