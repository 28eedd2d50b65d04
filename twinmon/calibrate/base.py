"""The two interfaces of calibration: a method (the statistical model and how a unit's work is
cut into chains) and a sampler (how those chains are drawn).

A :class:`Method` turns one unit's data into a :class:`UnitRun`: an object that plans its
next chains (:meth:`UnitRun.plan`), takes their draws (:meth:`UnitRun.finish`), and gives the
unit's :class:`~.posterior.UnitPosterior` when done. A :class:`Sampler` finishes the runs of
a whole calibration (:class:`Work`), in this process or over a pool of workers. Each method
names the samplers that can draw its posterior (:attr:`Method.samplers`), one per
``calibrate.sampler`` value.

A method is one module of :mod:`.methods` holding a ``Method`` subclass whose ``name`` is the
module's name; ``calibrate.method`` picks it (:func:`.methods.method_named`).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable, ClassVar, Mapping, Optional, Protocol, Sequence

import numpy as np

from ..config import Config
from ..errors import ConfigError
from .posterior import UnitPosterior


class UnitRun(Protocol):
    """One unit's calibration in progress.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    flows : ndarray, shape [n_y, n_out]
        Observations on the surrogate's grid (stacked channels side by side); NaN = missing.
    noise : ndarray, shape [n_y] or [n_y, n_ch]
        Noise standard deviation per year (per channel), output units.
    seed : int
        The unit's seed.
    source : str
        Where the noise came from (``file``, ``config``, ``estimated``).
    k : int
        Years finished so far (the progress count).
    """

    years: np.ndarray
    flows: np.ndarray
    noise: np.ndarray
    seed: int
    source: str
    k: int

    @property
    def done(self) -> bool: ...

    def plan(self) -> list:
        """The next chains' tasks (picklable), one per chain."""

    def finish(self, results: list) -> None:
        """Take the tasks' results (in :meth:`plan`'s order): the years they finish, or a
        longer run asked for when they did not converge."""

    def result(self) -> UnitPosterior:
        """The unit's posterior, once :attr:`done`."""

    def resume(self, posterior: UnitPosterior) -> None:
        """Keep the first years of an earlier posterior of this unit and continue after
        them (``calibrate --update``)."""


@dataclass
class Work:
    """A calibration's units, for a :class:`Sampler` to finish.

    Attributes
    ----------
    cfg : Config
    model : Surrogate or StackedSurrogate
        What the likelihood predicts through.
    runs : dict unit -> UnitRun
        Every unit of the calibration; a sampler finishes those not ``done`` (in place: an
        entry may be replaced by a :class:`~.update.Kept` holding its result).
    resume : dict unit -> UnitPosterior
        The stored posteriors the runs continue after (``--update``; empty otherwise).
    output : path-like
        The posterior to write (named by the errors of a failed pool).
    progress : callable(done, total), optional
        Called as unit-years complete.
    pool_args : tuple
        ``(initializer, initargs)`` of calibrate's worker processes
        (:func:`.shared.init_worker`).
    """

    cfg: Config
    model: object
    runs: dict
    resume: Mapping[str, UnitPosterior]
    output: object
    progress: Optional[Callable[[int, int], None]]
    pool_args: tuple
    #: Called with a unit's name once the sampler has finished it (its run ``done``):
    #: calibrate writes the unit to the posterior file then and keeps only its statistics.
    #: A sampler that never calls it leaves every unit to be written at the end.
    emit: Optional[Callable[[str], None]] = None

    def finished(self, unit: str) -> None:
        """``runs[unit]`` is done: hand it to :attr:`emit`."""
        if self.emit is not None:
            self.emit(unit)

    @property
    def total(self) -> int:
        """Unit-years of the calibration, done or not."""
        return sum(len(r.years) for r in self.runs.values())

    def tick(self) -> None:
        """Report the unit-years done so far to ``progress``."""
        if self.progress:
            self.progress(sum(r.k for r in self.runs.values()), self.total)


class Sampler(ABC):
    """How a method's chains are drawn (``calibrate.sampler``)."""

    #: The ``calibrate.sampler`` value that selects it.
    name: ClassVar[str]

    @abstractmethod
    def finish(self, work: Work) -> None:
        """Finish every run of ``work.runs`` that is not done. Results do not depend on the
        number of workers."""


class Method(ABC):
    """A calibration method (``calibrate.method``): the model of a unit's inputs over its
    years, and the samplers that can draw it."""

    #: The ``calibrate.method`` value that selects it (its module's name in :mod:`.methods`).
    name: ClassVar[str]
    #: ``calibrate --update`` keeps what it stored of a unit's years and works only on the
    #: years added since (True: the sequential method samples them, the laplace method
    #: summarises them, then draws the unit again), or samples a unit with new years again
    #: whole (False).
    continues_years: ClassVar[bool]
    #: Whether a unit's maintenance events enter its posterior (the trend's segments restart
    #: at them): ``--update`` then calibrates again a unit whose events changed, even one
    #: without a new year.
    uses_events: ClassVar[bool] = False

    def can_continue(self, posterior: UnitPosterior) -> bool:
        """Whether a stored posterior of a unit holds what :attr:`continues_years` needs
        (one written before it was recorded does not: the unit is calibrated again whole)."""
        return True

    @property
    @abstractmethod
    def samplers(self) -> Mapping[str, Sampler]:
        """The samplers of this method by ``calibrate.sampler`` value."""

    @abstractmethod
    def start(self, model, cfg: Config, years: np.ndarray, flows: np.ndarray, noise,
              seed: int, source: str, events: Sequence = ()) -> UnitRun:
        """The work of one unit: its years [n_y], observations [n_y, n_out], noise standard
        deviation (scalar, [n_y] or per channel), seed, noise source and maintenance events
        ``(year, component, action)``."""

    def sampler(self, name: str) -> Sampler:
        """The sampler ``calibrate.sampler: name`` of this method."""
        try:
            return self.samplers[name]
        except KeyError:
            raise ConfigError(f"calibrate.sampler: {name!r} cannot sample the {self.name} "
                              f"method (it has {', '.join(sorted(self.samplers))})") from None
