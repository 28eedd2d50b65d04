"""Executors on this machine: in-process, and one worker process per core.

Each worker extracts the FMU and instantiates it once, then resets it between runs: that
is what makes batch simulation several times faster than one ``simulate_fmu`` call per run.
"""
from __future__ import annotations

import multiprocessing as mp
import os
from typing import Iterator, Mapping, Sequence

from .base import Executor, RunResult, SimulationSpec, run_one


def _open(spec: SimulationSpec):
    from ..fmu import FMUModel
    return FMUModel(spec.fmu, spec.outputs, spec.times, fmi_type=spec.fmi_type,
                    start_values=dict(spec.fixed))


class SerialExecutor(Executor):
    """Runs everything in this process (debugging, tiny batches)."""

    def map(self, spec, params):
        with _open(spec) as model:
            for index, p in params:
                yield run_one(model, index, p)


_worker_model = None


def _init_worker(spec: SimulationSpec) -> None:
    global _worker_model
    _worker_model = _open(spec)


def _work(item):
    index, params = item
    return run_one(_worker_model, index, params)


class ProcessExecutor(Executor):
    """A pool of worker processes, one FMU instance each.

    Parameters
    ----------
    workers : int
        Number of processes; 0 means one per core available to this process.
    """

    def __init__(self, workers: int = 0):
        self._workers = workers or len(os.sched_getaffinity(0))

    @property
    def workers(self) -> int:
        return self._workers

    def map(self, spec: SimulationSpec,
            params: Sequence[tuple[int, Mapping[str, float]]]) -> Iterator[RunResult]:
        params = list(params)
        if self._workers <= 1 or len(params) < 2 * self._workers:
            # A pool costs ~0.1 s to start: not worth it for a handful of runs.
            yield from SerialExecutor().map(spec, params)
            return
        ctx = mp.get_context("fork" if hasattr(os, "fork") else "spawn")
        chunk = max(1, min(16, len(params) // (4 * self._workers)))
        with ctx.Pool(self._workers, initializer=_init_worker, initargs=(spec,)) as pool:
            yield from pool.imap_unordered(_work, params, chunksize=chunk)
