"""The ``model`` section: which FMU, which of its inputs are calibrated, what is observed.

:class:`ModelConfig` names the FMU and its calibrated (degradation) inputs
(:class:`InputSpec`), the observed output and its sample grid (:class:`OutputSpec`,
:class:`TimeGrid`), further recorded channels (:class:`ChannelSpec`) and the candidate
unmodelled effects that ``diagnose`` screens (:class:`EffectSpec`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import numpy as np


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
        elif self.step > 0:
            # In steps, not relative to their number: a long grid could otherwise end a
            # step past its stop.
            n = (self.stop - self.start) / self.step
            if abs(n - round(n)) > 1e-6:
                below = self.start + math.floor(n) * self.step
                yield "stop", (f"is not start + a whole number of steps ({self.start:g} + "
                               f"{math.floor(n)} x {self.step:g} = {below:.12g}, the next "
                               f"{below + self.step:.12g}): give one of those, or a step that "
                               f"divides {self.stop - self.start:.12g} s"), self.stop

    @property
    def times(self) -> np.ndarray:
        """Sample times, shape [n_t], seconds: ``start + k step`` rounded to 12 significant
        digits of the grid's span, so that 0.1 + 9 x 0.1 is 1.0 and not 0.9999999999999999
        (a sample a rounding error short of an FMU's event leaves it a step of 1e-16 s, and
        a window ``[2, 3]`` that should hold 3.0 misses 3.0000000000000004)."""
        n = int(round((self.stop - self.start) / self.step)) + 1
        scale = max(abs(self.start), abs(self.stop))
        decimals = 12 - int(math.ceil(math.log10(scale)))
        return np.round(self.start + self.step * np.arange(n), decimals)


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


#: Words a unit's verdict (root cause) may be besides a component: a component may not be
#: called so.
VERDICT_WORDS = ("healthy", "both", "ambiguous", "withheld")


@dataclass(frozen=True)
class ModelConfig:
    """Which FMU, which inputs are calibrated, what is observed."""

    fmu: Path
    inputs: dict[str, InputSpec]
    output: OutputSpec
    #: The FMU's interface: ``CoSimulation`` (its own solver, called straight from C) or
    #: ``ModelExchange`` (fmpy's CVode, rtol 1e-8, calling the FMU's derivatives from Python:
    #: about 25 times slower a run, for an FMU exported without a solver).
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
        if self.output.variable in self.channels:
            yield f"channels.{self.output.variable}", "is model.output.variable, recorded " \
                "already as the output", self.output.variable
        owner: dict[str, str] = {}
        for name, spec in self.inputs.items():
            # Two inputs on one FMU variable: one of them would do nothing (a dead dimension
            # of the design, a trend the data cannot see).
            if spec.variable in owner:
                yield f"inputs.{name}.variable", f"is also model.inputs.{owner[spec.variable]}" \
                    "'s variable", spec.variable
            owner.setdefault(spec.variable, name)
            if spec.variable in self.fixed:
                yield f"inputs.{name}.variable", "is held by model.fixed too", spec.variable
            word = spec.component or name
            if word in VERDICT_WORDS:
                # The verdicts' own words: "both" named a single component's fault.
                yield (f"inputs.{name}.component" if spec.component else f"inputs.{name}"), \
                    f"is a word the verdicts use ({', '.join(VERDICT_WORDS)}): choose " \
                    "another component name", word
        for name, eff in self.effects.items():
            # A candidate gap must be off in the calibrated model: diagnose adds it to a twin
            # whose degradation inputs it fits every year, at its baseline.
            if name in owner:
                yield f"effects.{name}", f"is model.inputs.{owner[name]}'s variable, " \
                    "calibrated every year: it cannot be a candidate gap too", name
            elif name in self.fixed and float(self.fixed[name]) != float(eff.baseline):
                yield f"effects.{name}.baseline", f"must give the calibrated model, where " \
                    f"model.fixed holds {name} at {self.fixed[name]:g}", eff.baseline

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
