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
"""
from __future__ import annotations

import atexit
import concurrent.futures as cf
import hashlib
import logging
import os
import shutil
import signal
import tempfile
import uuid
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path, PurePath
from typing import Any, Callable, Iterator, Mapping, Sequence

from .base import Executor, RunResult, SimulationSpec, run_one

#: Connecting to a scheduler, or starting the local workers, may take this long (s) by
#: default (``dask.timeout``).
DEFAULT_TIMEOUT = 10.0
#: FMU runs per task at most, and tasks per worker aimed at (see :meth:`DaskExecutor.map`).
MAX_CHUNK = 256
CHUNKS_PER_WORKER = 2


def _require_distributed():
    from ..errors import ConfigError
    try:
        import distributed
    except ImportError:
        raise ConfigError("executor: dask needs the 'distributed' package: "
                          "pip install 'twinmon[dask]'") from None
    return distributed


# ---------------------------------------------------------------------------------------
def _client_within(distributed, address: str, timeout: float):
    """A ``distributed.Client`` of ``address``, or ``TimeoutError`` after ``timeout`` s.

    ``Client(timeout=...)`` bounds reaching the address, not the handshake after it: a
    socket that accepts and never speaks (or an HTTP server, or a full backlog) kept it
    waiting for good. The client is made in a daemon thread, abandoned if it has not
    answered in time (a late connection is closed when it comes)."""
    import threading
    box: dict = {}

    def connect():
        try:
            box["client"] = distributed.Client(address, timeout=timeout, set_as_default=False)
        except BaseException as exc:  # noqa: BLE001 -- handed to the caller
            box["error"] = exc
        if box.get("late") and "client" in box:
            box["client"].close()

    t = threading.Thread(target=connect, name="twinmon-dask-connect", daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        box["late"] = True
        raise TimeoutError("no Dask handshake: is it a Dask scheduler?")
    if "error" in box:
        raise box["error"]
    return box["client"]


# The connection: a client, and the LocalCluster it owns when there is no address
# ---------------------------------------------------------------------------------------
class DaskConnection:
    """A client of a Dask scheduler; with ``address=None``, a ``LocalCluster`` of
    ``workers`` processes of one thread each, started now and closed by :meth:`close`.

    Parameters
    ----------
    workers : int
        Local worker processes; 0 means one per core. Ignored with an ``address``.
    address : str, optional
        A running scheduler (``tcp://host:8786``).
    timeout : float
        Seconds to connect to the scheduler, or to start the local workers.

    Raises
    ------
    ConfigError
        The scheduler at ``address`` could not be reached within ``timeout`` (the message
        names the address).
    SimulationError
        The local workers could not start (the message says why).
    """

    def __init__(self, workers: int = 0, address: str | None = None,
                 timeout: float = DEFAULT_TIMEOUT):
        distributed = _require_distributed()
        import dask

        from ..errors import ConfigError, SimulationError
        from .local import sigint_deferred
        self.address = address
        self.cluster = None
        self.client = None
        self._scratch = None
        self._children_before: set = set()
        self._pids: list[int] = []
        # Dask logs what it recovers from (a slow event loop, a worker restarted) on stderr;
        # what matters here reaches the command through the tasks' results, in one line.
        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        if address:
            try:
                self.client = _client_within(distributed, address, timeout)
            except (OSError, TimeoutError, ValueError) as exc:
                raise ConfigError(f"dask.address: cannot reach the Dask scheduler at "
                                  f"{address} within {timeout:g} s "
                                  f"({_one_line(exc)})") from None
            self.workers = max(1, len(self.client.scheduler_info()["workers"]))
            return
        self.workers = workers or len(os.sched_getaffinity(0))
        # Everything the workers write in $TMPDIR (the extracted FMU, its copy) goes in a
        # folder removed with the cluster, however the workers end.
        self._scratch = tempfile.mkdtemp(prefix="twinmon-dask-")
        self._children_before = _children()
        try:
            # A worker that dies (a crash in an FMU's C code) fails its task at once rather
            # than being retried on the next worker, as a process pool does. Workers are
            # forked, as the process pool's are: spawned, each would start a fresh Python and
            # import everything again (~4 s instead of ~0.3 s on a busy 2-core machine).
            method = "fork" if hasattr(os, "fork") else "spawn"
            with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                                  "distributed.worker.multiprocessing-method": method,
                                  "temporary-directory": self._scratch,
                                  # The worker's statistical profiler wakes every 10 ms for
                                  # the GIL, which an FMU run gives up at every C call.
                                  "distributed.worker.profile.enabled": False,
                                  # Event-loop watchdogs and resource monitors waking many times
                                  # a second: 1.27 -> 0.92 CPU s of the workers on 4096 runs.
                                  "distributed.admin.tick.interval": "1s",
                                  "distributed.admin.system-monitor.interval": "5s",
                                  "distributed.worker.memory.monitor-interval": "1s"}), \
                    sigint_deferred():
                # Started with SIGINT blocked (inherited), the workers never see a Ctrl-C:
                # it is the parent's alone, as for the process pool.
                self.cluster = distributed.LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True,
                    dashboard_address=None, silence_logs=logging.CRITICAL,
                    # The scheduler serves HTTP (health, metrics) even without a dashboard,
                    # on port 8787 by default: a second command beside this one would warn
                    # on stderr. A free port of this machine instead.
                    scheduler_kwargs={"dashboard": False,
                                      "dashboard_address": "127.0.0.1:0"},
                    local_directory=self._scratch, death_timeout=timeout,
                    env={"TMPDIR": self._scratch})
                self.client = distributed.Client(self.cluster, timeout=timeout,
                                                 set_as_default=False)
                self._pids = list(self.client.run(_detach_local_worker,
                                                  self._scratch).values())
        except BaseException as exc:
            self.close(kill=True)
            if isinstance(exc, Exception):
                raise SimulationError(f"cannot start {self.workers} local Dask workers: "
                                      f"{_one_line(exc)}") from None
            raise

    def close(self, kill: bool = False) -> None:
        """Close the client and, when this connection started it, the local cluster: its
        worker processes are gone when this returns. ``kill``: do not wait for running
        tasks (after an error or a Ctrl-C)."""
        if kill and self.cluster is not None:
            for nanny in list(self.cluster.workers.values()):
                close_gracefully = getattr(nanny, "close_gracefully", None)
                if close_gracefully is not None:
                    close_gracefully()          # a nanny must not restart what is killed
            for pid in self._pids:
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        try:
            if self.client is not None:
                self.client.close()
            if self.cluster is not None:
                self.cluster.close()
        finally:
            self.client = self.cluster = None
            if self._scratch is not None:
                # A worker the nanny was restarting as the cluster closed (after a crash), or
                # one of a cluster that failed to start, can outlive the close: any child
                # process born since the cluster started is one of its workers.
                for proc in _children() - self._children_before:
                    _kill(proc)
                shutil.rmtree(self._scratch, ignore_errors=True)
                self._scratch = None

    def __enter__(self) -> "DaskConnection":
        return self

    def __exit__(self, typ, exc, tb) -> None:
        self.close(kill=typ is not None)


def _detach_local_worker(scratch: str) -> int:
    """Run once in each local worker process (its main thread): out of the terminal's
    process group, SIGINT ignored, stderr to /dev/null, as a process-pool worker is; its
    temporary files in ``scratch``, which the parent removes with the cluster."""
    from .local import detach_worker
    detach_worker()
    # A forked worker inherits the parent's cached temporary folder, not $TMPDIR.
    os.environ["TMPDIR"] = tempfile.tempdir = scratch
    signal.signal(signal.SIGTERM, signal.SIG_DFL)   # the nanny's terminate stays a terminate
    return os.getpid()


def _children() -> set:
    import psutil          # a dependency of distributed
    try:
        return set(psutil.Process().children())
    except psutil.Error:
        return set()


def _kill(proc) -> None:
    import psutil
    try:
        proc.kill()
        proc.wait(2)
    except psutil.Error:
        pass


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


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
