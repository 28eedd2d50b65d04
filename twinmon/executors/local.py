"""Executors on this machine: in-process, and one worker process per core.

Each worker extracts the FMU and instantiates it once, then resets it between runs: that
is what makes batch simulation several times faster than one ``simulate_fmu`` call per run.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
from contextlib import contextmanager
from typing import Iterator, Mapping, Optional, Sequence

from .base import Executor, RunResult, SimulationSpec, run_one
from .threads import one_blas_thread_for_good


def _open(spec: SimulationSpec):
    from ..fmu import FMUModel
    return FMUModel(spec.fmu, spec.outputs, spec.times, fmi_type=spec.fmi_type,
                    start_values=dict(spec.fixed))


class SerialExecutor(Executor):
    """Runs everything in this process (debugging, tiny batches).

    Parameters
    ----------
    keep_open : bool
        Keep the FMU instance from one :meth:`map` to the next (a pool worker that runs a
        batch per task) until :meth:`close`, instead of extracting it for every batch.
    """

    def __init__(self, keep_open: bool = False):
        self._keep = keep_open
        self._model = self._spec = None

    def map(self, spec, params):
        if not self._keep:
            with _open(spec) as model:
                for index, p in params:
                    yield run_one(model, index, p)
            return
        if self._model is not None and self._spec is not spec:
            self.close()
        if self._model is None:
            self._model, self._spec = _open(spec), spec
        for index, p in params:
            yield run_one(self._model, index, p)

    def close(self) -> None:
        if self._model is not None:
            model, self._model, self._spec = self._model, None, None
            model.close()


# ---------------------------------------------------------------------------------------
# Worker processes shared by every stage that fans out (simulate, calibrate, diagnose)
# ---------------------------------------------------------------------------------------
def detach_worker() -> None:
    """First thing in every worker process: leave the terminal's process group and ignore
    SIGINT. Ctrl-C is then the parent's alone: it stops the pool and says so in one line,
    instead of every worker printing a traceback (or dying inside native code, which leaves a
    pool waiting forever)."""
    try:
        os.setpgrp()
    except OSError:
        pass
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # stop_pool() terminates workers with SIGTERM: leave through SystemExit so that
    # multiprocessing's finalizers (the extracted FMU folder) still run. The command's death
    # has a signal of its own (die_with_parent).
    signal.signal(signal.SIGTERM, _exit_on_term)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # Neither the command's stdout nor its stderr stays open in a worker: a worker outliving
    # its parent would otherwise keep a `twinmon ... | tee log` pipeline waiting.
    # A worker's errors reach the parent through its results, which reports them in one
    # line; what a worker would print itself when a pool is torn down (multiprocessing's
    # EOFError from a closed queue, a native solver's complaint about an interrupted
    # callback) is noise on the user's terminal. Both Python's and the C library's stderr go.
    devnull = os.open(os.devnull, os.O_RDWR)
    for fd in (0, 1, 2):
        os.dup2(devnull, fd)
    os.close(devnull)
    sys.stdin = open(os.devnull)
    sys.stdout = open(os.devnull, "w")
    sys.stderr = open(os.devnull, "w")


def die_with_parent(parent: int, scratch: str = "") -> None:
    """Make this worker end when ``parent`` (the command) dies, even by ``kill -9``: Linux
    sends it SIGUSR1 (``PR_SET_PDEATHSIG``), on which the worker closes what it opened (its
    extracted FMU), removes the pool's ``scratch`` folder (the parent, dead, cannot) and
    leaves. Without it, orphaned workers live on, holding the command's output and its
    scratch folder. Elsewhere than Linux this is a no-op.

    Why not SIGTERM, which :func:`stop_pool` sends: Linux signals the death of the *thread*
    that forked the worker, and a process killed by ``kill -9`` loses its threads one by one,
    so the first signal often comes while ``getppid()`` still names the dying command. Only a
    signal of its own tells the worker, without guessing, that its command is ending."""
    global _parent, _scratch
    _parent, _scratch = parent, scratch
    if scratch:
        from multiprocessing.util import Finalize
        # A worker that leaves some other way once the command is gone; exitpriority 0:
        # after the FMU instance (10) is closed.
        Finalize(None, _remove_if_orphan, (parent, scratch), exitpriority=0)
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        signal.signal(_PARENT_DIED, _on_parent_death)
        libc.prctl(PR_SET_PDEATHSIG, int(_PARENT_DIED), 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:      # the parent died before prctl took effect
        _on_parent_death()


#: The signal Linux sends a worker when its command dies (``PR_SET_PDEATHSIG``).
_PARENT_DIED = signal.SIGUSR1

#: PID of the command that started this worker (0: not a pool worker), and the pool's
#: scratch folder.
_parent = 0
_scratch = ""


def _on_parent_death(signum=None, frame=None) -> None:
    # Nobody will read a result, and a SystemExit raised inside a task would be caught by the
    # pool and sent back as that task's result (the worker then waits for the next task
    # forever): clean up and leave now.
    from multiprocessing import util
    try:
        util._run_finalizers(0)
        if _scratch:
            import shutil
            shutil.rmtree(_scratch, ignore_errors=True)
    finally:
        os._exit(0)


def _remove_if_orphan(parent: int, scratch: str) -> None:
    if os.getppid() != parent:
        import shutil
        shutil.rmtree(scratch, ignore_errors=True)


def _exit_on_term(signum, frame):
    if _parent and os.getppid() != _parent:
        _on_parent_death()
    raise SystemExit(0)


class sigint_deferred:
    """Hold SIGINT back while worker processes are forked, so that no child starts life with
    Python's default handler, and no Ctrl-C lands inside the fork machinery. A Ctrl-C
    pressed meanwhile is delivered when the block ends."""

    def __enter__(self):
        self._old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        return self

    def __exit__(self, *exc):
        signal.pthread_sigmask(signal.SIG_SETMASK, self._old)
        return False


class InterruptGuard:
    """Ctrl-C as a flag, raised as ``KeyboardInterrupt`` only where the code asks
    (:meth:`check`) and on leaving the block.

    Python raises ``KeyboardInterrupt`` wherever the main thread happens to be; inside a
    weakref callback or a ``__del__`` (the pool and h5py run many) it is printed as "Exception
    ignored" and lost, and the command goes on to exit 0. Outside the main thread (no signal
    handlers there) the guard does nothing."""

    def __enter__(self) -> "InterruptGuard":
        self.hit = False
        try:
            self._old = signal.signal(signal.SIGINT, self._on_sigint)
        except ValueError:              # not the main thread
            self._old = None
        return self

    def _on_sigint(self, signum, frame) -> None:
        self.hit = True

    def check(self) -> None:
        if self.hit:
            raise KeyboardInterrupt

    def __exit__(self, typ, exc, tb) -> bool:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        if self.hit and typ is None:
            raise KeyboardInterrupt
        return False


def start_pool(workers: int, initializer=None, initargs=()):
    """A ``ProcessPoolExecutor`` of ``workers`` detached processes, all started now.

    A worker that dies makes the pool raise ``BrokenProcessPool`` (a ``multiprocessing.Pool``
    would wait forever for its task)."""
    import shutil
    import tempfile
    import weakref
    from concurrent.futures import ProcessPoolExecutor, wait
    ctx = mp.get_context("fork" if hasattr(os, "fork") else "spawn")
    # The workers' temporary files (extracted FMUs) go to a folder of the parent's, removed
    # with the pool: a worker killed (a crash, stop_pool's SIGKILL inside native code) cannot
    # clean up after itself, and its extracted FMU would stay in $TMPDIR for good.
    scratch = tempfile.mkdtemp(prefix="twinmon-pool-")
    with sigint_deferred():
        pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_detached,
                                   initargs=(initializer, initargs, scratch, os.getpid()))
        # Removed as soon as the pool is shut down (shutdown_pool, stop_pool), not when the
        # pool object is collected: a command killed between the two would leave it behind.
        pool._twinmon_scratch = weakref.finalize(pool, shutil.rmtree, scratch, True)
        pool._twinmon_scratch_dir = scratch
        # Start every worker inside the block (a fork context starts them all at the first
        # submit) and let each finish its initializer.
        wait([pool.submit(_noop) for _ in range(workers)])
    return pool


def _drop_scratch(pool) -> None:
    cleanup = getattr(pool, "_twinmon_scratch", None)
    if cleanup is not None:
        cleanup()


def shutdown_pool(pool) -> None:
    """Shut ``pool`` down once its work is done: wait for the workers, then remove their
    scratch folder at once."""
    pool.shutdown(wait=True)
    _drop_scratch(pool)


def stop_pool(pool) -> None:
    """Stop a pool at once: queued work cancelled, running workers terminated (after an
    error or a Ctrl-C nobody wants their results)."""
    procs = list(getattr(pool, "_processes", {}).values())   # no public API for this
    # Workers first (SIGTERM: a quiet SystemExit), then the queues: closed under a reading
    # worker, they would make it print an EOFError traceback.
    for p in procs:
        if p.is_alive():
            p.terminate()
    import time
    deadline = time.monotonic() + 2.0
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
    for p in procs:
        if p.is_alive():          # inside native code (a long sampler call): no cleanup there
            p.kill()
            p.join(1)
    pool.shutdown(wait=False, cancel_futures=True)
    # Let the pool's manager thread finish closing its wake-up pipe now: left to race with
    # the interpreter's exit hook, which writes to that pipe, it printed "Exception ignored
    # ... OSError: Bad file descriptor" after a one-line error (Python 3.11's check of the
    # pipe and its write are not atomic).
    manager = getattr(pool, "_executor_manager_thread", None)   # no public API either
    if manager is not None:
        manager.join(2.0)
    _drop_scratch(pool)


@contextmanager
def closing_pool(pool, broken: Exception, interrupted: Optional[Exception] = None):
    """Use ``pool`` for one stage's work: shut down cleanly after it, stopped at once
    (:func:`stop_pool`) after an error or a Ctrl-C, so no queued task starts.

    A dead worker (``BrokenProcessPool``, also raised by the Dask pool) becomes ``broken``
    and a Ctrl-C (``KeyboardInterrupt``) becomes ``interrupted`` when given: each a one-line
    :class:`~twinmon.errors.TwinmonError` naming the stage's output."""
    from concurrent.futures.process import BrokenProcessPool
    ok = False
    try:
        yield pool
        ok = True
    except BrokenProcessPool:
        # A worker that crashed inside an FMU left its own line: it names the input.
        raise (worker_crash(pool) or broken) from None
    except KeyboardInterrupt:
        if interrupted is None:
            raise
        raise interrupted from None
    finally:
        if ok:
            shutdown_pool(pool)
        else:
            stop_pool(pool)


def worker_crash(pool):
    """The :class:`~twinmon.errors.SimulationError` a worker of ``pool`` left when an FMU
    crashed in it (:func:`twinmon.fmu.guard.crash_note`), or None."""
    from ..errors import SimulationError
    from ..fmu.guard import crash_note
    note = crash_note(getattr(pool, "_twinmon_scratch_dir", None))
    return SimulationError(note) if note else None


def _init_detached(initializer, initargs, scratch: str = "", parent: int = 0) -> None:
    detach_worker()
    # One worker per core: each one's BLAS on one thread (.threads).
    one_blas_thread_for_good()
    if parent:
        die_with_parent(parent, scratch)
    if scratch:
        import tempfile

        from ..fmu.guard import leave_notes_in
        # tempfile caches its folder: a forked worker would otherwise keep the parent's.
        tempfile.tempdir = scratch
        os.environ["TMPDIR"] = scratch
        # Its stderr goes nowhere: a crash in an FMU leaves its line there for the parent.
        leave_notes_in(scratch)
    if initializer is not None:
        initializer(*initargs)


def _noop() -> None:
    return None


# ---------------------------------------------------------------------------------------
# Simulation workers
# ---------------------------------------------------------------------------------------
_worker_model = None
_worker_error = ""


def _init_worker(spec: SimulationSpec) -> None:
    global _worker_model, _worker_error
    from multiprocessing.util import Finalize
    try:
        _worker_model = _open(spec)
        # Pool workers leave by os._exit: atexit handlers and weakref finalizers do not run,
        # but multiprocessing's own finalizers do. Without this, every worker would leave its
        # extracted FMU folder behind in $TMPDIR.
        Finalize(_worker_model, _worker_model.close, exitpriority=10)
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

    Used as a context manager, the pool (and each worker's FMU instance) is kept across
    ``map`` calls of the same spec: ``simulate`` forks once, not once per chunk. A worker that
    cannot open the FMU, or that dies (a crash inside the FMU's C code), ends the batch at once
    with a :class:`~twinmon.errors.SimulationError` naming the reason: never a hang or an
    endless respawn. Workers are detached from the terminal (:func:`detach_worker`).

    Parameters
    ----------
    workers : int
        Number of processes; 0 means one per core available to this process.
    """

    def __init__(self, workers: int = 0):
        if workers < 0:
            raise ValueError(f"workers must be >= 0, got {workers}")
        self._workers = workers or len(os.sched_getaffinity(0))
        self._pool = None
        self._spec = None
        self._in_context = False

    @property
    def workers(self) -> int:
        return self._workers

    def __enter__(self) -> "ProcessExecutor":
        self._in_context = True
        return self

    def __exit__(self, *exc) -> None:
        self._in_context = False
        self.close()

    def close(self) -> None:
        if self._pool is not None:
            shutdown_pool(self._pool)
            self._pool, self._spec = None, None

    def _pool_for(self, spec: SimulationSpec):
        if self._pool is not None and self._spec is not spec:
            self.close()
        if self._pool is None:
            self._pool = start_pool(self._workers, _init_worker, (spec,))
            self._spec = spec
        return self._pool

    def map(self, spec: SimulationSpec,
            params: Sequence[tuple[int, Mapping[str, float]]]) -> Iterator[RunResult]:
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        from ..errors import SimulationError

        params = list(params)
        if self._pool is None and (self._workers <= 1 or len(params) < 2 * self._workers):
            # A pool costs ~0.1 s to start: not worth it for a handful of runs.
            yield from SerialExecutor().map(spec, params)
            return
        size = max(1, min(16, len(params) // (4 * self._workers)))
        chunks = [params[i:i + size] for i in range(0, len(params), size)]
        ok = False
        try:
            pool = self._pool_for(spec)
            pending = {pool.submit(_work_chunk, c) for c in chunks}
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    try:
                        results = fut.result()
                    except WorkerStartError as exc:
                        raise SimulationError(str(exc)) from None
                    except BrokenProcessPool:
                        raise worker_crash(pool) or SimulationError(
                            f"{spec.fmu}: a worker process died while running the FMU (a crash "
                            "in its native code?); re-run with simulate.executor=serial to see "
                            "which input") from None
                    yield from results
            ok = True
        finally:
            if not ok and self._pool is not None:
                # An error or a Ctrl-C: nobody waits for the queued chunks.
                stop_pool(self._pool)
                self._pool, self._spec = None, None
            elif not self._in_context:
                self.close()
