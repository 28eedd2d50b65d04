"""The units stream through in chunks, here or on a pool of worker processes.

:func:`iter_forecast` cuts the fleet into chunks of up to ``CHUNK_UNITS`` units
(:func:`_chunk_size`). With one worker the chunks are forecast in this process and the FMU
runs fan out on the executor; otherwise they go to a pool (``simulate.executor``:
``process`` or ``dask``) whose workers are set up once by :func:`_init_worker` (the
surrogate in numpy form, an FMU instance kept open from chunk to chunk) and run
:func:`_chunk_task`, with ``TASKS_PER_WORKER`` chunks in flight per worker
(:func:`_pooled`), so memory stays flat however many units. The initializer and the task
are module-level functions: the pool pickles them by their module path.
"""
from __future__ import annotations

import os
from typing import Optional

from ..config import Config
from .chunk import MIN_TREND_YEARS, _check_unit, _forecast_chunk, _truth_of, _TwinState
from .trendfit import recorded_shapes


#: Units per pool task: big enough that a task's FMU and surrogate batches amortise their
#: set-up, small enough that a few tasks in flight per worker hold little memory.
CHUNK_UNITS = 8
#: Tasks in flight per worker (the results wait in order to be written).
TASKS_PER_WORKER = 2


def iter_forecast(cfg: Config, post, sur, *, directions: dict, box_ok: bool,
                  posterior_path="<memory>", truth=None, truth_path=None, executor=None,
                  workers: Optional[int] = None, progress=None, fleet=None, shapes=None,
                  limit_state=None, pack: bool = False, skipped: Optional[dict] = None):
    """Forecast the units of ``post`` one chunk at a time; yields ``(unit, UnitForecast)`` in
    the posterior's order.

    With several units and workers, chunks of units go to a pool of worker processes
    (``cfg.simulate.executor``: ``process`` or ``dask``), each with the surrogate in numpy
    form and its own FMU instance for the points outside the surrogate's box; a few chunks
    are in flight at a time, so memory stays flat however many units. Otherwise the units
    are forecast here, the FMU runs on ``executor``. Every unit's random streams are keyed
    by its name, and a point's prediction does not depend on the other points of its batch:
    the result is the same whatever the workers and chunks.

    Parameters
    ----------
    post : Posterior
        ``post.units`` may be lazy (read one unit at a time).
    sur : Surrogate
    directions : dict input -> Direction
        From :func:`~.directions.degrading_directions`.
    box_ok : bool
        From :func:`~.twin.box_is_physical`.
    truth : Truth, optional
    executor : Executor, optional
        FMU runs of in-process forecasts; defaults to ``cfg.simulate.executor``.
    workers : int, optional
        Processes over units (default ``cfg.simulate.workers``; 0 = one per core).
    progress : callable, optional
        ``progress(done, total)`` over the units.
    fleet : FleetPrior, optional
        From :func:`~.pooling.fleet_sigma_prior`: the jointly calibrated units' draws are
        resampled to the fleet's prior of their year-to-year sd.
    shapes : FleetShapes, optional
        From :func:`~.pooling.fleet_shape_prior`: a laplace posterior's draws are also
        resampled to the fleet's prior of the trend forms. With ``fleet``, the one thing a
        unit's forecast takes from the rest of its fleet.
    limit_state : LimitState, optional
        From :func:`~.limitstate.build_limit_state`: answers the points outside the box it
        is sure are unsafe (the others run through the FMU).
    pack : bool
        A pool's workers send each unit back slim, its Monte Carlo arrays compressed as the
        artifact stores them (:func:`~.artifact.pack_unit`), for a caller that writes them
        and keeps the figures alone (``forecast``); in this process they stay whole.
    skipped : dict, optional
        Given, a unit with fewer than :data:`~.chunk.MIN_TREND_YEARS` calibrated years is
        left out and put here with its number of years, instead of failing the whole
        fleet: a unit new in service is forecast once its record allows a trend.

    Raises
    ------
    CalibrationError, ArtifactError
        A unit's posterior cannot be forecast (checked before any work is sent out).
    SimulationError
        A worker process died.
    """
    from ..executors import check_workers, make_executor, one_blas_thread
    from ..simulate import declared_range, spec_for
    unit_names = list(post.units)
    n = len(unit_names)
    n_workers = cfg.simulate.workers if workers is None else workers
    check_workers(n_workers)
    n_workers = min(n_workers or len(os.sched_getaffinity(0)), n)
    if cfg.simulate.executor == "serial":
        n_workers = 1
    spec = spec_for(cfg)
    context = dict(directions=directions, box_ok=box_ok, fit_windows=post.fit_windows,
                   truth_path=truth_path, fleet=fleet, shapes=shapes,
                   shape_priors=recorded_shapes(cfg, posterior_path),
                   input_range=declared_range(cfg))

    def chunk_of(names_):
        ups = []
        for u in names_:
            up = post.units[u]
            if skipped is not None and len(up.years) < MIN_TREND_YEARS:
                skipped[u] = len(up.years)
                continue
            _check_unit(cfg, posterior_path, u, up)
            ups.append((u, up, _truth_of(truth, truth_path, u)))
        return ups

    size = _chunk_size(n, n_workers)
    chunks = [unit_names[i:i + size] for i in range(0, n, size)]
    done = 0
    if n_workers <= 1 and not (cfg.simulate.executor == "dask" and cfg.dask.address):
        own = executor is None
        if own:
            # Kept open from batch to batch (a process pool started once, not per chunk).
            executor = make_executor(cfg.simulate.executor, cfg.simulate.workers,
                                     cfg.dask).__enter__()
        try:
            # One unit, or one worker: the FMU runs fan out on the executor instead. The
            # units' small factorisations on one BLAS thread, as in a pool's worker.
            state = _TwinState(cfg, sur, spec, executor, limit_state)
            for names_ in chunks:
                with one_blas_thread():
                    results = _forecast_chunk(state, chunk_of(names_), **context)
                for unit, uf in results:
                    done += 1
                    if progress:
                        progress(done + len(skipped or ()), n)
                    yield unit, uf
        finally:
            if own:
                executor.__exit__(None, None, None)
        return
    yield from _pooled(cfg, sur, spec, chunks, chunk_of, context, n_workers, progress,
                       limit_state, pack, skipped)


def _chunk_size(n_units: int, n_workers: int) -> int:
    """Units per chunk: up to ``CHUNK_UNITS``, at least four chunks per worker when the
    fleet is small (the workers finish together)."""
    return max(1, min(CHUNK_UNITS, -(-n_units // (4 * max(n_workers, 1)))))


def _pooled(cfg, sur, spec, chunks, chunk_of, context, n_workers, progress, limit_state,
            pack=False, skipped=None):
    """:func:`iter_forecast` on a pool: ``TASKS_PER_WORKER`` chunks in flight per worker,
    results yielded in the chunks' order."""
    from collections import deque

    from ..errors import Interrupted, SimulationError
    from ..executors import closing_pool, open_pool
    pool = open_pool(cfg, "simulate", n_workers, _init_worker, (cfg, sur, spec, limit_state),
                     files=(spec.fmu,))
    n, done = sum(len(c) for c in chunks), 0
    with closing_pool(pool, SimulationError(
            f"{spec.fmu}: a worker process died while forecasting (a crash in the FMU's native "
            "code?); nothing was written; re-run with simulate.workers=1 to see which unit"),
            Interrupted("forecast: interrupted; nothing was written")):
        queue, todo = deque(), iter(chunks)
        for names_ in todo:
            queue.append(pool.submit(_chunk_task, chunk_of(names_), context, pack))
            if len(queue) >= TASKS_PER_WORKER * n_workers:
                break
        while queue:
            results = queue.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                queue.append(pool.submit(_chunk_task, chunk_of(nxt), context, pack))
            for unit, uf in results:
                done += 1
                if progress:
                    progress(done + len(skipped or ()), n)
                yield unit, uf


_worker_state: Optional[_TwinState] = None


def _init_worker(cfg: Config, sur, spec, limit_state=None) -> None:
    """Pool initializer: the worker's twin, its FMU instance kept open from chunk to chunk."""
    global _worker_state
    from multiprocessing.util import Finalize

    from ..executors import SerialExecutor
    ex = SerialExecutor(keep_open=True)
    _worker_state = _TwinState(cfg, sur, spec, ex, limit_state)
    # Pool workers leave by os._exit: only multiprocessing's finalizers close the FMU.
    Finalize(ex, ex.close, exitpriority=10)


def _chunk_task(units: list, context: dict, pack: bool = False) -> list:
    results = _forecast_chunk(_worker_state, units, **context)
    if pack:
        from .artifact import pack_unit
        results = [(unit, pack_unit(uf)) for unit, uf in results]
    return results
