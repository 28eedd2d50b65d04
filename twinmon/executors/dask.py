"""Executors on a ``dask.distributed`` cluster: a ``LocalCluster`` on this machine, or a
running scheduler (``dask.address``). See docs/cluster.md.

Two objects, both built on one :class:`DaskPool`:

* :class:`DaskExecutor`, an :class:`~twinmon.executors.base.Executor` for FMU batches
  (``simulate``, ``forecast``): each worker process extracts the FMU and instantiates it once,
  then reuses that instance for every run it is sent, as a ``ProcessExecutor`` worker does;
* :func:`open_dask_pool`, the same ``submit``/``map``/``shutdown`` surface as the process pool
  of :func:`~twinmon.executors.local.start_pool`, for the stages that fan out their own tasks
  (``calibrate``'s chains, ``diagnose``'s units).

Per-worker state: a pool's initializer and its arguments (``calibrate``'s surrogate, an FMU
spec) are sent to every worker once (scattered, broadcast) and run there before the first
task of that pool, keyed by a token; tasks carry only their own arguments.

The FMU reaches the workers as bytes, once per worker process, keyed by its SHA-256: a worker
that sees the same file at the same path (this machine, a shared file system) uses it; any
other writes the bytes to its own temporary folder and runs that copy. Error messages name the
user's path, not the copy.

Workers run ONE thread each (``LocalCluster(threads_per_worker=1)``; ``dask-worker
--nthreads 1`` on a cluster): an FMU instance is not thread-safe, and one FMU per process is
what makes the batch fast.

The connection itself (a scheduler's client within a timeout, or a LocalCluster of this
machine) is :class:`~twinmon.executors.dask_cluster.DaskConnection`.
"""
from __future__ import annotations

import atexit
import concurrent.futures as cf
import hashlib
import os
import tempfile
import uuid
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path, PurePath
from typing import Any, Callable, Iterator, Mapping, Sequence

from .base import Executor, RunResult, SimulationSpec, run_one
from .dask_cluster import DEFAULT_TIMEOUT, DaskConnection, _one_line
from .threads import one_blas_thread_for_good


#: FMU runs per task at most, and tasks per worker aimed at (see :meth:`DaskExecutor.map`).
MAX_CHUNK = 256
CHUNKS_PER_WORKER = 2


# ---------------------------------------------------------------------------------------
# Worker side: per-pool set-up (once per worker process), files, path mapping
# ---------------------------------------------------------------------------------------
@dataclass
class _Setup:
    """What every worker of a pool needs once: files by path, the initializer and its
    arguments (one object, so that ``scatter`` sends it whole)."""

    files: dict[str, tuple[str, bytes]]          # user's path -> (sha256, content)
    initializer: Callable | None = None
    initargs: tuple = ()


@dataclass
class _WorkerState:
    token: str | None = None
    error: BaseException | None = None
    paths: dict[str, str] = field(default_factory=dict)      # user's path -> worker's
    closers: list = field(default_factory=list)
    model: Any = None                                          # an FMU batch's instance


_state = _WorkerState()


def _call(token: str, setup: _Setup, fn: Callable, *args):
    """A task as a worker runs it: the pool's set-up first (once per worker and pool), then
    ``fn(*args)`` with the user's file paths mapped to this worker's."""
    if _state.token != token:
        _prepare(token, setup)
    try:
        if _state.error is not None:
            raise _state.error
        return fn(*_localise(args))
    except Exception as exc:
        raise _user_paths(exc) from None


def _prepare(token: str, setup: _Setup) -> None:
    _forget()
    _state.token = token
    try:
        _state.paths = {orig: _materialise(orig, digest, data)
                        for orig, (digest, data) in setup.files.items()}
        # As a process pool's worker (.threads); a local cluster's nanny also sets
        # OPENBLAS_NUM_THREADS=1 before it starts a worker, a remote one may not have.
        one_blas_thread_for_good()
        if setup.initializer is not None:
            setup.initializer(*_localise(setup.initargs))
    except Exception as exc:  # noqa: BLE001 -- every task of this pool reports it
        _state.error = exc


def _forget(token: str | None = None) -> None:
    """Close what the current pool's set-up opened (on a long-lived cluster worker, when
    another pool comes or this one ends)."""
    if token is not None and _state.token != token:
        return
    for close in reversed(_state.closers):
        try:
            close()
        except Exception:  # noqa: BLE001 -- best effort
            pass
    _state.token, _state.error, _state.paths, _state.closers = None, None, {}, []
    _state.model = None


def close_with_pool(close: Callable[[], None]) -> None:
    """Have ``close`` run when the current pool ends on this Dask worker (or the next pool
    comes), with what the pool's set-up opened: for what a task leaves open for the next
    tasks of its process (diagnose's spare FMU instance). Outside a Dask pool's task it does
    nothing: a process pool's worker ends with its pool, and the command's own process
    closes what it opened."""
    if _state.token is not None and close not in _state.closers:
        _state.closers.append(close)


def _materialise(orig: str, digest: str, data: bytes) -> str:
    """A path on this worker holding ``data``: the user's own when it is here and the same,
    else a copy in this worker's temporary folder, named by content."""
    try:
        if hashlib.sha256(Path(orig).read_bytes()).hexdigest() == digest:
            return orig
    except OSError:
        pass
    folder = Path(tempfile.gettempdir()) / "twinmon-dask-files" / digest[:24]
    path = folder / Path(orig).name
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        tmp = folder / f".{os.getpid()}.{uuid.uuid4().hex}"
        tmp.write_bytes(data)
        os.replace(tmp, path)          # atomic: several workers of one host may race
    return str(path)


def _localise(obj: Any) -> Any:
    """``obj`` with every user's path of a shipped file replaced by this worker's; looks
    into tuples, lists and the direct fields of dataclasses (e.g. a SimulationSpec)."""
    if not _state.paths:
        return obj
    if isinstance(obj, (str, PurePath)):
        local = _state.paths.get(str(obj))
        if local is None or local == str(obj):
            return obj
        return type(obj)(local) if isinstance(obj, PurePath) else local
    if isinstance(obj, (tuple, list)):
        return type(obj)(_localise(v) for v in obj)
    if is_dataclass(obj) and not isinstance(obj, type):
        changed = {f.name: _localise(getattr(obj, f.name)) for f in fields(obj)
                   if f.init and isinstance(getattr(obj, f.name), (str, PurePath))}
        changed = {k: v for k, v in changed.items() if v is not getattr(obj, k)}
        return replace(obj, **changed) if changed else obj
    return obj


def _user_text(text: str) -> str:
    for orig, local in _state.paths.items():
        if local != orig:
            text = text.replace(local, orig)
    return text


def _user_paths(exc: Exception) -> Exception:
    """The same error naming the user's paths instead of this worker's copies."""
    from ..errors import TwinmonError
    if isinstance(exc, TwinmonError):
        text = _user_text(exc.message)
        if text != exc.message:
            return type(exc)(text)
    return exc


# ---------------------------------------------------------------------------------------
# Client side: the pool
# ---------------------------------------------------------------------------------------
class DaskPool:
    """Tasks on a Dask cluster behind the surface of a ``ProcessPoolExecutor``: ``submit``
    returns a :class:`concurrent.futures.Future`, ``map`` yields results in order,
    ``shutdown`` ends it. A worker that dies makes the task raise ``BrokenProcessPool``,
    as in a process pool, so a stage handles both alike.

    Parameters
    ----------
    connection : DaskConnection
    initializer : callable, optional
        Run once in each worker process with ``initargs`` before its first task of this
        pool (module-level, picklable).
    initargs : tuple
    files : sequence of path-like
        Files the tasks open (an FMU): sent to the workers, and their paths in the tasks'
        and initializer's arguments mapped to each worker's copy.
    own_connection : bool
        :meth:`shutdown` closes the connection too.
    """

    def __init__(self, connection: DaskConnection, initializer=None, initargs=(),
                 files: Sequence = (), own_connection: bool = False):
        self.connection = connection
        self._own = own_connection
        self._token = uuid.uuid4().hex
        self._futures: set = set()
        shipped = {}
        for f in files:
            data = Path(f).read_bytes()
            shipped[str(f)] = (hashlib.sha256(data).hexdigest(), data)
        # Once to every worker, not with every task (a surrogate is megabytes).
        self._setup = connection.client.scatter(_Setup(shipped, initializer, tuple(initargs)),
                                                broadcast=True, hash=False)

    @property
    def workers(self) -> int:
        return self.connection.workers

    def submit(self, fn: Callable, *args) -> cf.Future:
        """Run ``fn(*args)`` on a worker (``fn`` module-level, picklable)."""
        out: cf.Future = cf.Future()
        out.set_running_or_notify_cancel()
        fut = self.connection.client.submit(_call, self._token, self._setup, fn, *args,
                                            pure=False)
        self._futures.add(fut)
        fut.add_done_callback(lambda f, out=out: self._settle(f, out))
        return out

    def _settle(self, fut, out: cf.Future) -> None:
        # Runs in Dask's callback thread once the task has ended.
        self._futures.discard(fut)
        from concurrent.futures.process import BrokenProcessPool
        try:
            if fut.status == "finished":
                out.set_result(fut.result())
                return
            if fut.status == "cancelled":
                out.set_exception(cf.CancelledError())
                return
            exc = fut.exception()
        except BaseException as e:  # noqa: BLE001 -- the client closed under us
            exc = e
        if type(exc).__name__ == "KilledWorker":
            exc = BrokenProcessPool(f"a Dask worker died while running the task ({exc})")
        elif isinstance(exc, cf.CancelledError) or type(exc).__name__ == "FutureCancelledError":
            exc = cf.CancelledError()
        try:
            out.set_exception(exc)
        except cf.InvalidStateError:
            pass

    def as_completed(self, fn: Callable, items: Sequence) -> Iterator:
        """``fn(item)`` for every item, results as they complete (any order). The results
        come back through Dask's own event loop, without the thread hop of :meth:`submit`;
        a task's error is raised here (a dead worker as ``BrokenProcessPool``). Leaving the
        loop early cancels what is left."""
        from concurrent.futures.process import BrokenProcessPool

        from distributed import as_completed
        client = self.connection.client
        futures = [client.submit(_call, self._token, self._setup, fn, item, pure=False)
                   for item in items]
        try:
            for fut, result in as_completed(futures, loop=client.loop, with_results=True,
                                            raise_errors=False):
                if fut.status == "error":
                    try:
                        fut.result()              # raises the task's own exception
                    except Exception as exc:
                        if type(exc).__name__ == "KilledWorker":
                            raise BrokenProcessPool(f"a Dask worker died while running the "
                                                    f"task ({_one_line(exc)})") from None
                        raise
                yield result
        finally:
            pending = [f for f in futures if not f.done()]
            if pending and self.connection.client is not None:
                try:
                    client.cancel(pending, force=True)
                except Exception:  # noqa: BLE001 -- the connection may be gone already
                    pass

    def map(self, fn: Callable, *iterables) -> Iterator:
        """``fn`` over the items of ``iterables``, all submitted now, results in order."""
        futures = [self.submit(fn, *args) for args in zip(*iterables)]
        try:
            for f in futures:
                yield f.result()
        finally:
            for f in futures:
                f.cancel()

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        """End the pool: with ``cancel_futures``, queued and running tasks are dropped; the
        connection is closed too when the pool owns it (its local workers are gone when
        this returns)."""
        conn = self.connection
        if conn.client is None:
            return
        try:
            if cancel_futures and self._futures:
                conn.client.cancel(list(self._futures), force=True)
            if (conn.address or not self._own) and not cancel_futures:
                # Long-lived workers (a cluster of your own, or another pool to follow): free
                # this pool's state there (its FMU instance, a surrogate). Not after a cancel:
                # a task may still be running with it; the next pool's set-up frees it then.
                conn.client.run(_forget, self._token)
        except Exception:  # noqa: BLE001 -- a lost connection has nothing left to free
            pass
        finally:
            if self._own:
                conn.close(kill=cancel_futures)


def open_dask_pool(workers: int = 0, initializer=None, initargs=(), *,
                   address: str | None = None, timeout: float = DEFAULT_TIMEOUT,
                   files: Sequence = ()) -> DaskPool:
    """A :class:`DaskPool` on its own connection (a LocalCluster of ``workers`` processes,
    or the scheduler at ``address``), closed by ``shutdown``."""
    conn = DaskConnection(workers, address, timeout)
    try:
        return DaskPool(conn, initializer, initargs, files, own_connection=True)
    except BaseException:
        conn.close(kill=True)
        raise


# ---------------------------------------------------------------------------------------
# FMU batches
# ---------------------------------------------------------------------------------------
def _open_model(spec: SimulationSpec) -> None:
    from .local import _open
    _state.model = _open(spec)
    _state.closers.append(_state.model.close)


def _work_chunk(items):
    if _state.model is None:
        from .local import WorkerStartError
        raise WorkerStartError("the worker could not open the FMU")
    results = [run_one(_state.model, index, params) for index, params in items]
    for r in results:
        if r.message:
            r.message = _user_text(r.message)
    return results


# Results of one run should not depend on the worker: make sure no FMU model survives the
# worker process without its extracted folder being removed.
atexit.register(_forget)


class DaskExecutor(Executor):
    """FMU batches on a Dask cluster, one FMU instance per worker process.

    Used as a context manager, the cluster (and each worker's FMU instance) is kept across
    ``map`` calls of the same spec; outside one, each ``map`` starts and closes its own. A
    worker that cannot open the FMU, or dies running it, ends the batch with a one-line
    :class:`~twinmon.errors.SimulationError`. The results are those of a
    :class:`~twinmon.executors.local.ProcessExecutor` on the same batch, array for array.

    Parameters
    ----------
    workers : int
        Local worker processes (0: one per core); ignored with an ``address``.
    address : str, optional
        A running Dask scheduler; none: a ``LocalCluster`` on this machine.
    timeout : float
        Seconds to reach the scheduler or start the local workers.
    """

    def __init__(self, workers: int = 0, address: str | None = None,
                 timeout: float = DEFAULT_TIMEOUT):
        if workers < 0:
            raise ValueError(f"workers must be >= 0, got {workers}")
        self._n = workers
        self.address = address
        self.timeout = timeout
        self._conn: DaskConnection | None = None
        self._pool: DaskPool | None = None
        self._spec = None
        self._in_context = False

    @property
    def workers(self) -> int:
        if self._conn is not None:
            return self._conn.workers
        return self._n or len(os.sched_getaffinity(0))

    def __enter__(self) -> "DaskExecutor":
        self._in_context = True
        return self

    def __exit__(self, typ, exc, tb) -> None:
        self._in_context = False
        self.close(kill=typ is not None)

    def close(self, kill: bool = False) -> None:
        conn, pool = self._conn, self._pool
        self._conn, self._pool, self._spec = None, None, None
        try:
            if pool is not None:
                pool.shutdown(cancel_futures=kill)
        finally:
            if conn is not None:
                conn.close(kill=kill)

    def _pool_for(self, spec: SimulationSpec) -> DaskPool:
        if self._conn is None:
            self._conn = DaskConnection(self._n, self.address, self.timeout)
        if self._pool is None or self._spec is not spec:
            if self._pool is not None:
                self._pool.shutdown()
            self._pool = DaskPool(self._conn, _open_model, (spec,), files=(spec.fmu,))
            self._spec = spec
        return self._pool

    def map(self, spec: SimulationSpec,
            params: Sequence[tuple[int, Mapping[str, float]]]) -> Iterator[RunResult]:
        from concurrent.futures.process import BrokenProcessPool

        from ..errors import SimulationError
        from .local import WorkerStartError

        params = list(params)
        ok = False
        try:
            pool = self._pool_for(spec)
            # Two to three chunks per worker: a task costs ~10 ms through the scheduler (a
            # process pool's, ~1 ms), so chunks are longer than ProcessExecutor's 16 runs;
            # enough of them still to balance the workers.
            size = max(1, min(MAX_CHUNK, -(-len(params) // (CHUNKS_PER_WORKER * pool.workers))))
            chunks = [params[i:i + size] for i in range(0, len(params), size)]
            try:
                for results in pool.as_completed(_work_chunk, chunks):
                    yield from results
            except WorkerStartError as exc:
                raise SimulationError(str(exc)) from None
            except BrokenProcessPool:
                raise SimulationError(
                    f"{spec.fmu}: a Dask worker died while running the FMU (a crash in its "
                    "native code?); re-run with simulate.executor=serial to see which "
                    "input") from None
            ok = True
        finally:
            if not ok:
                self.close(kill=True)     # an error or a Ctrl-C: nobody waits for the rest
            elif not self._in_context:
                self.close()
