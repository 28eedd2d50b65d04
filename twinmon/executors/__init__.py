"""Executors run batches of FMU simulations; swap one for another through the config.

``base.Executor`` is the interface; ``local`` holds the serial and process-pool executors.
A distributed backend only has to implement :meth:`Executor.map`.
"""
from .base import Executor, RunResult, SimulationSpec
from .local import InterruptGuard, ProcessExecutor, SerialExecutor, start_pool, stop_pool


def make_executor(kind: str, workers: int = 0) -> Executor:
    """Executor by config name (``"process"`` or ``"serial"``); ``workers=0``: one per core."""
    if workers < 0:
        from ..errors import ConfigError
        raise ConfigError(f"workers: expected 0 (one per core) or a positive count, got {workers}")
    if kind == "serial":
        return SerialExecutor()
    if kind == "process":
        return ProcessExecutor(workers)
    raise ValueError(f"unknown executor {kind!r}")


__all__ = ["Executor", "RunResult", "SimulationSpec", "SerialExecutor", "ProcessExecutor",
           "make_executor", "start_pool", "stop_pool", "InterruptGuard"]
