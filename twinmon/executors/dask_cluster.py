"""The connection to a ``dask.distributed`` cluster: a client of a running scheduler
(``dask.address``), reached within ``dask.timeout``, or a ``LocalCluster`` of one-thread
worker processes started on this machine and closed with every worker gone. The pools and the
executor built on it are in :mod:`twinmon.executors.dask`.
"""
from __future__ import annotations

import logging
import os
import shutil
import signal
import tempfile


#: Connecting to a scheduler, or starting the local workers, may take this long (s) by
#: default (``dask.timeout``).
DEFAULT_TIMEOUT = 10.0


def _require_distributed():
    from ..errors import ConfigError
    try:
        import distributed
    except ImportError:
        raise ConfigError("executor: dask needs the 'distributed' package: "
                          "pip install 'twinmon[dask]'") from None
    return distributed


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


def _listening(address: str, timeout: float) -> None:
    """Raise ``ConfigError`` at once when nothing listens at ``address`` (a refused or
    unroutable TCP connection): a Dask client would retry until ``timeout``, then twice as
    long while it closes, and the message would blame the handshake."""
    import socket

    from ..config.dask import scheduler_host_port
    from ..errors import ConfigError
    hp = scheduler_host_port(address)
    if hp is None:
        raise ConfigError(f"dask.address: {address!r} is not a TCP scheduler address "
                          "(tcp://host:port)")
    try:
        with socket.create_connection(hp, timeout=timeout):
            pass
    except OSError as exc:
        raise ConfigError(f"dask.address: cannot reach the Dask scheduler at {address}: "
                          f"{exc.strerror or type(exc).__name__} (nothing listens there?)") \
            from None


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
            _listening(address, timeout)
            try:
                self.client = _client_within(distributed, address, timeout)
            except (OSError, TimeoutError, ValueError) as exc:
                raise ConfigError(f"dask.address: cannot reach the Dask scheduler at "
                                  f"{address} within {timeout:g} s "
                                  f"({_one_line(exc)})") from None
            except Exception as exc:  # noqa: BLE001 -- a service speaking another protocol
                # Something that answers first in its own protocol (an SSH banner) is read
                # as Dask's length-prefixed frames: a MemoryError for exabytes, a decoding
                # error, a TypeError. None of it is twinmon's to show as a traceback.
                raise ConfigError(f"dask.address: {address} does not answer as a Dask "
                                  f"scheduler ({type(exc).__name__}: {_one_line(exc)})") \
                    from None
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
