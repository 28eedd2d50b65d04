"""A crash in an FMU's native code, turned into twinmon's one-line simulation error.

An FMU is foreign native code: for some inputs it may abort (a failed ``assert`` in
generated C) or fault instead of returning ``fmi2Error``. In a pool worker that only ends
the worker, and the parent reports it in one line. In the command's own process (one
worker, one unit, ``executor: serial``, ``check``) it would end the command with the
shell's "Aborted (core dumped)" and status 134 or 139. So every FMU call is made inside
:func:`running`, which records what is being run, and the fatal signals (``SIGSEGV``,
``SIGBUS``, ``SIGFPE``, ``SIGILL``, ``SIGABRT``) get a native handler (:func:`install`)
that, during such a call, writes ``twinmon: simulation error: <fmu>: the FMU's native
code crashed (SIGABRT) running <parameters>`` on stderr and ends the process with
:class:`~twinmon.errors.SimulationError`'s exit code. The artifacts are written atomically
(a temporary file renamed into place), so nothing written before is lost; the leftovers of
the interrupted write are what a ``kill -9`` leaves, cleaned up by the next run
(``simulate`` resumes from its partial file). A pool worker's stderr goes nowhere: there
the line is also left as a note in the pool's scratch folder (:func:`leave_notes_in`),
which the parent reads when it finds the worker dead (:func:`crash_note`), so that its own
one line names the input too.

Outside an FMU call the handler gives the signal back to the handler it replaced (the
default: a core dump; Python's ``faulthandler`` when enabled) and raises it again: a crash
elsewhere is not reported as the FMU's.

The handler runs Python in a signal context. That is safe enough here because it only
formats a line, writes it with one system call and leaves with ``os._exit``, never
returning into the crashed code; a crash inside the memory allocator itself could still
hang it, as it would hang any crash reporter.
"""
from __future__ import annotations

import ctypes
import os
import shutil
import signal
from contextlib import contextmanager
from typing import Iterator, Mapping, Optional

from ..errors import SimulationError
from .common import format_params

FATAL = tuple(s for s in (getattr(signal, n, None) for n in
                          ("SIGSEGV", "SIGBUS", "SIGFPE", "SIGILL", "SIGABRT")) if s)

#: (FMU path, parameters, extracted folder) of the FMU call under way here, else None.
_current: Optional[tuple] = None
#: Where this process (a pool worker) leaves the line of its crash for its parent.
_note_dir: Optional[str] = None
#: The process the handlers were installed in (a forked worker inherits them, and its state).
_installed_pid: Optional[int] = None
_HANDLER = ctypes.CFUNCTYPE(None, ctypes.c_int)
_callback = None            # kept alive: the C handler points into it
_previous: dict = {}        # signal -> the C handler it replaced
_libc = None


def _on_fatal(signum: int) -> None:
    now = _current
    if now is not None:
        try:
            line = (f"{now[0]}: the FMU's native code crashed ({signal.Signals(signum).name}) "
                    f"running {format_params(now[1])}")
            if _note_dir:
                try:
                    fd = os.open(os.path.join(_note_dir, f"crash-{os.getpid()}.txt"),
                                 os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                    os.write(fd, line.encode(errors="replace"))
                    os.close(fd)
                except OSError:
                    pass
            os.write(2, f"twinmon: {SimulationError.family}: {line}\n".encode(errors="replace"))
        finally:
            if now[2]:
                shutil.rmtree(now[2], ignore_errors=True)
            os._exit(SimulationError.exit_code)
    # Not the FMU's: the handler before ours takes it, raised again.
    _libc.signal(signum, _previous.get(signum))
    os.kill(os.getpid(), signum)


def install() -> None:
    """Install the native handler of :data:`FATAL` in this process (once; a no-op where the
    C library cannot be reached)."""
    global _callback, _installed_pid, _libc
    if _installed_pid == os.getpid():
        return
    try:
        libc = ctypes.CDLL(None)
        libc.signal.restype = ctypes.c_void_p
        libc.signal.argtypes = (ctypes.c_int, ctypes.c_void_p)
    except (OSError, AttributeError):
        return
    _libc = libc
    _callback = _callback or _HANDLER(_on_fatal)
    address = ctypes.cast(_callback, ctypes.c_void_p).value
    for s in FATAL:
        old = libc.signal(int(s), address)
        if old != address:
            _previous[int(s)] = old
    _installed_pid = os.getpid()


@contextmanager
def running(fmu, params: Mapping[str, float], folder: Optional[str] = None
            ) -> Iterator[None]:
    """Mark an FMU call under way: a fatal signal inside it is reported as the FMU's crash,
    naming ``fmu`` and the run's ``params`` (formatted only then); ``folder`` (the extracted
    FMU) is removed before the process ends."""
    global _current
    outer, _current = _current, (fmu, params, folder)
    try:
        yield
    finally:
        _current = outer


def leave_notes_in(folder: str) -> None:
    """In a pool worker: leave the line of a crash in ``folder`` (the pool's scratch folder)
    for the parent, as ``crash-<pid>.txt``."""
    global _note_dir
    _note_dir = folder


def crash_note(folder: Optional[str]) -> Optional[str]:
    """The line a crashed worker left in ``folder`` (:func:`leave_notes_in`), if any."""
    if not folder:
        return None
    try:
        names = sorted(n for n in os.listdir(folder) if n.startswith("crash-"))
        for n in names:
            with open(os.path.join(folder, n), encoding="utf-8", errors="replace") as f:
                text = f.read().strip()
            if text:
                return text
    except OSError:
        pass
    return None
