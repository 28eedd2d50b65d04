"""A Ctrl-C that Python swallowed is still honoured.

Python's SIGINT handler raises ``KeyboardInterrupt`` wherever the main thread is. Raised
inside a weak-reference callback or a ``__del__`` (matplotlib's caches, h5py's objects), it
is printed as "Exception ignored" and dropped: the command went on, wrote its output and
exited 0. The handler here records the interrupt before raising it, and the points that
make a result final (an artifact renamed into place, a report installed) call
:func:`raise_if_interrupted` first; the command's end turns a recorded interrupt into exit
130 whatever swallowed it.
"""
from __future__ import annotations

import signal

#: Set by :func:`on_sigint` until the next command starts (:func:`reset`).
_pending = False


def on_sigint(signum, frame) -> None:
    """SIGINT: record it, then raise ``KeyboardInterrupt`` as Python's own handler does."""
    global _pending
    _pending = True
    raise KeyboardInterrupt


def pending() -> bool:
    """Whether a SIGINT arrived since :func:`reset`."""
    return _pending


def reset() -> None:
    global _pending
    _pending = False


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` when a SIGINT arrived and was swallowed: called before a
    result is made final, so that an interrupted command leaves what was there."""
    if _pending:
        raise KeyboardInterrupt


def install():
    """Make :func:`on_sigint` the SIGINT handler (main thread only); returns the handler it
    replaced, or None when it could not (another thread, or SIGINT ignored by the parent, as
    for a background job: then nothing changes)."""
    try:
        old = signal.getsignal(signal.SIGINT)
        if old is signal.SIG_IGN:
            return None
        return signal.signal(signal.SIGINT, on_sigint)
    except ValueError:
        return None
