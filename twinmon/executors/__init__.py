"""Executors run batches of FMU simulations; swap one for another through the config.

``base.Executor`` is the interface; ``local`` holds the serial and process-pool executors,
``dask`` the executor and pool on a ``dask.distributed`` cluster, over the connection of
``dask_cluster`` (optional dependency, imported only when chosen). A distributed backend only
has to implement :meth:`Executor.map`.

Stages that fan out their own tasks (calibrate's chains, diagnose's units) take a pool from
:func:`open_pool` and stop it with :func:`stop_pool` after an error or a Ctrl-C; a process
pool and a Dask pool have the same ``submit``/``map``/``shutdown`` surface. Every worker
runs its BLAS on one thread (:mod:`.threads`).
"""
from .base import Executor, RunResult, SimulationSpec
from .local import (InterruptGuard, ProcessExecutor, SerialExecutor, closing_pool, start_pool,
                    stop_pool)
from .threads import one_blas_thread

#: Executor names a config may give (``simulate.executor``; ``serial`` is for FMU batches).
KINDS = ("process", "serial", "dask")


def make_executor(kind: str, workers: int = 0, dask=None) -> Executor:
    """Executor by config name (``"process"``, ``"serial"`` or ``"dask"``); ``workers=0``:
    one per core; ``dask``: the config's ``dask`` section (address, timeout)."""
    check_workers(workers)
    if kind == "serial":
        return SerialExecutor()
    if kind == "process":
        return ProcessExecutor(workers)
    if kind == "dask":
        from .dask import DaskExecutor
        return DaskExecutor(workers, **_dask_options(dask))
    raise ValueError(f"unknown executor {kind!r}")


def check_workers(workers: int) -> None:
    """A worker count must be 0 (one per core) or positive (a ``ConfigError`` otherwise)."""
    if workers < 0:
        from ..errors import ConfigError
        raise ConfigError(f"workers: expected 0 (one per core) or a positive count, got {workers}")


def open_pool(cfg, stage: str, workers: int, initializer=None, initargs=(), files=()):
    """A started pool for ``stage`` of ``cfg`` (``cfg.<stage>.executor``): ``workers``
    detached processes (``process``), or a Dask pool (``dask``: a LocalCluster of ``workers``
    processes, or the cluster at ``cfg.dask.address``), each worker set up once by
    ``initializer(*initargs)``.

    ``files``: paths the tasks open (an FMU); a Dask pool sends them to its workers and maps
    the paths in the tasks' arguments to each worker's copy (a process pool shares this
    machine's files). Stop it with ``pool.shutdown()``, or :func:`stop_pool` to drop the
    queued work."""
    kind = getattr(cfg, stage).executor
    if kind == "dask":
        from .dask import open_dask_pool
        return open_dask_pool(workers, initializer, initargs, files=files,
                              **_dask_options(cfg.dask))
    return start_pool(workers, initializer, initargs)


def _dask_options(dask) -> dict:
    if dask is None:
        return {}
    return {"address": dask.address, "timeout": dask.timeout}


__all__ = ["Executor", "RunResult", "SimulationSpec", "SerialExecutor", "ProcessExecutor",
           "check_workers", "make_executor", "open_pool", "start_pool", "stop_pool",
           "closing_pool", "InterruptGuard", "KINDS", "one_blas_thread"]
