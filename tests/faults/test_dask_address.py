"""``dask.address`` naming something that is not a Dask scheduler: exit 3 with one line
within about ``dask.timeout``, nothing left behind. Before, a socket that accepts and never
speaks, or one that never accepts, kept ``simulate`` waiting for good (no output, its
``.lock`` and ``.partial`` left)."""
from __future__ import annotations

import socket
import threading
import time

import pytest

from .conftest import assert_fails, twinmon

pytest.importorskip("distributed")


@pytest.fixture(params=["accepts, never speaks", "never accepts"])
def silent_address(request):
    """A loopback socket that is no Dask scheduler."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    held = []
    if request.param == "accepts, never speaks":
        srv.listen(8)

        def accept():
            while True:
                try:
                    held.append(srv.accept()[0])
                except OSError:
                    return
        threading.Thread(target=accept, daemon=True).start()
    else:
        # Listening, never accepting: the kernel completes the connection into the backlog,
        # and nobody ever reads from it.
        srv.listen(8)
    yield f"tcp://127.0.0.1:{srv.getsockname()[1]}"
    for c in held:
        c.close()
    srv.close()


def test_simulate_with_an_address_that_is_no_scheduler(work, silent_address):
    out = work / "d" / "sim.h5"
    t0 = time.monotonic()
    r = twinmon("simulate", "-c", work / "small.yaml", "--set", "simulate.executor=dask",
                "--set", f"dask.address={silent_address}", "--set", "dask.timeout=3",
                "-o", out, cwd=work, timeout=60)
    elapsed = time.monotonic() - t0
    assert_fails(r, 3, "dask.address", silent_address)
    # 3 s of timeout, plus starting Python and importing dask on a busy machine.
    assert elapsed < 25, f"took {elapsed:.1f} s"
    left = sorted(p.name for p in out.parent.iterdir()) if out.parent.exists() else []
    assert left == [], left
