"""Executors on this machine: in-process, and one worker process per core.

Each worker extracts the FMU and instantiates it once, then resets it between runs: that
is what makes batch simulation several times faster than one ``simulate_fmu`` call per run.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
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
_worker_error = ""


def _init_worker(spec: SimulationSpec) -> None:
    # Ctrl-C is the parent's to handle: a worker that also caught it would print its own
    # traceback for every interrupted run.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    global _worker_model, _worker_error
    try:
        _worker_model = _open(spec)
    except BaseException as exc:  # noqa: BLE001 -- reported to the parent, which fails fast
        # An initializer that raises makes a pool respawn workers forever (multiprocessing)
        # or break without the reason (concurrent.futures): keep the reason and hand it to
        # the parent with the first task instead.
        _worker_error = str(exc) or type(exc).__name__


def _work_chunk(items):
    if _worker_model is None:
        raise WorkerStartError(_worker_error or "the worker could not open the FMU")
    return [run_one(_worker_model, index, params) for index, params in items]


class WorkerStartError(Exception):
    """A worker process could not open its FMU (the message says why)."""


class ProcessExecutor(Executor):
    """A pool of worker processes, one FMU instance each.

    A worker that cannot open the FMU, or that dies (a crash inside the FMU's C code), ends
    the batch at once with a :class:`~twinmon.errors.SimulationError` naming the reason:
    never a hang or an endless respawn.

    Parameters
    ----------
    workers : int
        Number of processes; 0 means one per core available to this process.
    """

    def __init__(self, workers: int = 0):
        if workers < 0:
            raise ValueError(f"workers must be >= 0, got {workers}")
        self._workers = workers or len(os.sched_getaffinity(0))

    @property
    def workers(self) -> int:
        return self._workers

    def map(self, spec: SimulationSpec,
            params: Sequence[tuple[int, Mapping[str, float]]]) -> Iterator[RunResult]:
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from concurrent.futures.process import BrokenProcessPool

        from ..errors import SimulationError

        params = list(params)
        if self._workers <= 1 or len(params) < 2 * self._workers:
            # A pool costs ~0.1 s to start: not worth it for a handful of runs.
            yield from SerialExecutor().map(spec, params)
            return
        ctx = mp.get_context("fork" if hasattr(os, "fork") else "spawn")
        size = max(1, min(16, len(params) // (4 * self._workers)))
        chunks = [params[i:i + size] for i in range(0, len(params), size)]
        pool = ProcessPoolExecutor(self._workers, mp_context=ctx, initializer=_init_worker,
                                   initargs=(spec,))
        try:
            pending = {pool.submit(_work_chunk, c) for c in chunks}
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    try:
                        results = fut.result()
                    except WorkerStartError as exc:
                        raise SimulationError(str(exc)) from None
                    except BrokenProcessPool:
                        raise SimulationError(
                            f"{spec.fmu}: a worker process died while running the FMU (a crash "
                            "in its native code?); re-run with simulate.executor=serial to see "
                            "which input") from None
                    yield from results
        finally:
            # Do not wait for queued chunks after an error or an interrupt.
            pool.shutdown(wait=True, cancel_futures=True)
