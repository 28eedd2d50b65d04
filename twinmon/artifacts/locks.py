"""Output locks: one writer per output, held from planning to the rename (:func:`locks_output`),
released by the kernel when the holder dies."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable, Iterator

from ..errors import OutputBusyError


_held: dict[str, list] = {}


def _forget_locks_in_child() -> None:
    """In a forked child (a pool worker): close the inherited lock descriptors, so that the
    lock dies with the process that took it, not with the last of its children. Only closed,
    never unlocked: ``flock`` belongs to the open file, and unlocking here would release the
    parent's lock."""
    for fd, _ in _held.values():
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_locks_in_child)


def lock_path(path: str | os.PathLike) -> Path:
    """The hidden lock file beside ``path``. The path is made absolute and normal first
    (without following links), so that ``.`` or ``out/..`` name their folder."""
    path = Path(os.path.abspath(path))
    return path.with_name(f".{path.name}.lock")


@contextlib.contextmanager
def output_lock(path: str | os.PathLike, command: str = "twinmon") -> Iterator[None]:
    """Hold an advisory lock on ``path`` (a file or a folder) while writing it.

    The lock is ``flock`` on a hidden ``.<name>.lock`` file beside ``path`` holding the
    holder's PID and command: the kernel drops it when the holder dies (even by ``kill -9``).
    Forked children do not keep it (their copy of the descriptor is closed at fork), and a
    lock whose recorded holder is dead (kept by some other process that inherited it) is
    taken over with a warning on stderr. Re-entrant within one process.

    Raises
    ------
    OutputBusyError
        Another process holds the lock; the message names it. Nothing was touched.
    """
    import fcntl
    import sys
    path = Path(path)
    key = str(path.resolve())
    if key in _held:
        _held[key][1] += 1
        try:
            yield
        finally:
            _held[key][1] -= 1
        return
    lp = lock_path(path)
    lp.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lp, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip() or "another process"
            pid = _holder_pid(holder)
            if pid is not None and not _alive(pid) and _unlink_if_same(lp, fd):
                os.close(fd)
                sys.stderr.write(f"twinmon: warning: {path}: the lock of {holder} was left by a "
                                 "process that is gone; taking it over\n")
                continue
            os.close(fd)
            raise OutputBusyError(f"{path} is being written by {holder}; wait for it to finish "
                                  "or choose another output") from None
        # The previous holder unlinks the lock file on release: if we locked a file that is
        # no longer the one under that name, start again with the current one.
        try:
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    argv = " ".join(Path(sys.argv[0]).name if i == 0 else a for i, a in enumerate(sys.argv[:2]))
    try:
        os.pwrite(fd, f"{argv or command} (pid {os.getpid()})".encode(), 0)
    except OSError as exc:
        # A full disk: the writer cannot write its output either; leave no empty lock file.
        try:
            os.unlink(lp)
        except OSError:
            pass
        os.close(fd)
        raise OSError(exc.errno, f"cannot write: {exc.strerror}", str(path)) from None
    _held[key] = [fd, 1]
    try:
        yield
    finally:
        del _held[key]
        try:
            os.unlink(lp)          # while still locked, so no one else holds this inode
        except OSError:
            pass
        os.close(fd)


def _holder_pid(holder: str) -> int | None:
    """The PID in a lock file's ``<command> (pid N)`` text, or None."""
    import re
    m = re.search(r"\(pid (\d+)\)\s*$", holder)
    return int(m.group(1)) if m else None


def _unlink_if_same(lp: Path, fd: int) -> bool:
    """Remove the lock file ``lp`` if it is still the one open as ``fd`` (a new holder may
    have replaced it meanwhile: that one is not stale)."""
    try:
        if os.stat(lp).st_ino != os.fstat(fd).st_ino:
            return True             # already replaced: try again with the current one
        os.unlink(lp)
        return True
    except FileNotFoundError:
        return True
    except OSError:
        return False


def locks_output(arg: str, command: str) -> Callable:
    """Decorate a stage function so that it holds the output lock of its argument ``arg``
    for the whole call: from before it reads what it will overwrite or continue (an
    ``--update`` plans from the output's present content) to the rename of the new file.
    Locking only at the write let two writers plan from the same old file and the last one
    replace the other's work. The lock is re-entrant: :func:`write_artifact` inside takes it
    again at no cost."""
    import functools
    import inspect

    def wrap(func):
        sig = inspect.signature(func)

        @functools.wraps(func)
        def locked(*args, **kwargs):
            bound = sig.bind(*args, **kwargs)
            bound.apply_defaults()
            target = bound.arguments[arg]
            if target is None:                  # nothing written
                return func(*args, **kwargs)
            parent = Path(target).parent
            made = not parent.exists()
            parent.mkdir(parents=True, exist_ok=True)
            try:
                with output_lock(target, command):
                    return func(*args, **kwargs)
            except BaseException:
                if made:                        # a failed stage leaves no empty folder
                    try:
                        parent.rmdir()
                    except OSError:
                        pass
                raise
        return locked
    return wrap


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
