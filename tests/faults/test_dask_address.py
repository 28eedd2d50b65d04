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


def test_an_address_that_speaks_another_protocol_is_a_config_error(work):
    """A service that speaks first (an SSH banner) was read as Dask's frames: a MemoryError
    for exabytes and a 95-line traceback, exit 1. Now exit 3, the address named."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held = []

    def serve():
        while True:
            try:
                c = srv.accept()[0]
            except OSError:
                return
            c.sendall(b"SSH-2.0-OpenSSH_9.0\r\n" + b"\xff" * 64)
            held.append(c)
    threading.Thread(target=serve, daemon=True).start()
    address = f"tcp://127.0.0.1:{srv.getsockname()[1]}"
    try:
        r = twinmon("simulate", "-c", work / "small.yaml", "--set", "simulate.executor=dask",
                    "--set", f"dask.address={address}", "--set", "dask.timeout=3",
                    "-o", work / "e" / "sim.h5", cwd=work, timeout=120)
    finally:
        for c in held:
            c.close()
        srv.close()
    assert r.returncode == 3, r.stderr
    first = r.stderr.strip().splitlines()[0]
    assert first.startswith(f"twinmon: config error: dask.address: {address} does not "
                            "answer as a Dask scheduler"), r.stderr
