"""The reference sampler (``calibrate.sampler: openturns``): each chain is one task run by
OpenTURNS (the method's task runner: random-walk Metropolis-Hastings for a sequential
unit-year, Gibbs for a joint unit), in this process or spread over calibrate's worker pool.

The parallel grain is the chain: every unit's chains of the same round (a sequential method's
year, a joint unit's whole run) go to the workers at once, and the next round is planned when
they are back. Results do not depend on the number of workers.
"""
from __future__ import annotations

import os
from typing import Callable

from ..base import Sampler, Work
from ..shared import sampling_pool, worker


class OpenTurnsSampler(Sampler):
    """Runs each task of a method's :meth:`~.base.UnitRun.plan` with ``run_task``.

    Parameters
    ----------
    run_task : callable(surrogate, task) -> result
        The method's chain (module-level: a worker pool pickles it by name).
    """

    name = "openturns"

    def __init__(self, run_task: Callable):
        self.run_task = run_task

    def finish(self, work: Work) -> None:
        cfg, runs = work.cfg, work.runs
        if all(r.done for r in runs.values()):      # nothing new (--update)
            return
        n_tasks = len(runs) * cfg.calibrate.chains
        workers = min(cfg.calibrate.workers or len(os.sched_getaffinity(0)), n_tasks)
        # On a Dask cluster (an address) the cluster's workers do the work, whatever the count.
        if workers <= 1 and not (cfg.calibrate.executor == "dask" and cfg.dask.address):
            for run in runs.values():
                while not run.done:
                    run.finish([self.run_task(work.model, t) for t in run.plan()])
                    work.tick()
            return
        # Years of one unit are sequential (each prior is centred on the previous estimate),
        # so the parallel grain is the chain: every unit's chains of the same year at once.
        from ...executors import InterruptGuard, open_pool
        # A forked worker has the surrogate already; a Dask worker gets it sent, once.
        pool = open_pool(cfg, "calibrate", workers, *work.pool_args)   # process or Dask pool
        with sampling_pool(pool, work.output), InterruptGuard() as guard:
            self._run_parallel(pool, work, guard)

    def _run_parallel(self, pool, work: Work, guard) -> None:
        from concurrent.futures import wait
        while True:
            active = [r for r in work.runs.values() if not r.done]
            if not active:
                return
            plans = [r.plan() for r in active]
            futures = [pool.submit(run_in_worker, self.run_task, t) for p in plans for t in p]
            # Poll, so that a Ctrl-C stops long chains within a fraction of a second.
            while wait(futures, timeout=0.2).not_done:
                guard.check()
            guard.check()
            results = [f.result() for f in futures]
            i = 0
            for run, plan in zip(active, plans):
                run.finish(results[i:i + len(plan)])
                i += len(plan)
            work.tick()


def run_in_worker(run_task: Callable, task):
    """``run_task`` on a worker process's surrogate
    (:func:`~twinmon.calibrate.shared.init_worker`)."""
    return run_task(worker["surrogate"], task)
