"""The executor interface: map a simulation spec over parameter sets."""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np


@dataclass(frozen=True)
class SimulationSpec:
    """Everything a worker needs to build its own FMU instance (picklable).

    Attributes
    ----------
    fmu : Path
        The ``.fmu`` file.
    outputs : tuple of str
        FMU output variables to record.
    times : ndarray, shape [n_t]
        Sample times (s).
    fmi_type : str
        ``"CoSimulation"`` or ``"ModelExchange"``.
    fixed : mapping
        FMU parameters set on every run before the run's own.
    """

    fmu: Path
    outputs: tuple[str, ...]
    times: np.ndarray
    fmi_type: str = "CoSimulation"
    fixed: Mapping[str, float] = field(default_factory=dict)


@dataclass
class RunResult:
    """Outcome of one run: ``outputs`` maps each output to shape [n_t], or ``None`` on failure."""

    index: int
    outputs: dict[str, np.ndarray] | None
    message: str = ""

    @property
    def ok(self) -> bool:
        return self.outputs is not None


class Executor(abc.ABC):
    """Runs simulations; results may come back in any order (each carries its index)."""

    @abc.abstractmethod
    def map(self, spec: SimulationSpec,
            params: Sequence[tuple[int, Mapping[str, float]]]) -> Iterator[RunResult]:
        """Yield one :class:`RunResult` per ``(index, parameters)`` item."""

    @property
    def workers(self) -> int:
        return 1

    # An executor may keep resources (a process pool) open between ``map`` calls while used
    # as a context manager; outside one, each ``map`` call cleans up after itself.
    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release what :meth:`map` kept open (nothing, by default)."""


def run_one(model, index: int, params: Mapping[str, float]) -> RunResult:
    """Run one parameter set on an open model; a simulation failure becomes a result."""
    from ..errors import SimulationError
    try:
        return RunResult(index, model.run(params))
    except SimulationError as exc:
        return RunResult(index, None, str(exc))
