"""``kill -9`` of a command running a process pool: its workers must not outlive it.

Orphaned workers used to keep the output's lock (inherited at fork), the pool's scratch
folder and the command's stdout/stderr (a ``| tee`` never ended); the next run of the same
command exited 8, naming the dead process as the writer."""
from __future__ import annotations

import os
import signal
import subprocess

import h5py
import numpy as np

from .conftest import assert_ok, cmd, twinmon, wait_for


def _children(pid: int) -> set[int]:
    """Every descendant of ``pid`` (from /proc)."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for t in tasks:
            try:
                kids = open(f"/proc/{p}/task/{t}/children").read().split()
            except OSError:
                continue
            for k in map(int, kids):
                if k not in out:
                    out.add(k)
                    todo.append(k)
    return out


def _running(pid: int) -> bool:
    """A live process (not a zombie waiting to be reaped)."""
    try:
        state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _cpu_seconds(pids) -> float:
    """User + system CPU time used so far by ``pids`` (from /proc)."""
    total = 0
    for pid in pids:
        try:
            fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])      # utime, stime (clock ticks)
    return total / os.sysconf("SC_CLK_TCK")


def _describe(pids) -> list[str]:
    out = []
    for pid in pids:
        try:
            out.append(f"{pid}: " + open(f"/proc/{pid}/cmdline").read().replace("\0", " "))
        except OSError:
            out.append(str(pid))
    return out


def test_kill9_of_simulate_with_a_pool(work, tmp_path):
    cfg = work / "small.yaml"
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = {**os.environ, "TMPDIR": str(scratch)}
    design = ["--set", "simulate.train_size=2000", "--set", "simulate.test_size=200",
              "--set", "simulate.executor=process", "--set", "simulate.chunk_size=100"]
    out = work / "k" / "sim.h5"
    out.parent.mkdir()
    partial = out.with_name("sim.h5.partial")
    p = subprocess.Popen(cmd("simulate", "-c", cfg, *design, "-j", "2", "-o", out),
                         cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    workers: set[int] = set()
    try:
        # Mid-run: the pool is up and some runs are in the partial file.
        assert wait_for(lambda: len(_children(p.pid)) >= 2 and partial.exists()
                        and partial.stat().st_size > 50_000, 60, p), \
            "simulate never got going with its pool"
        assert p.poll() is None, "simulate ended before it could be killed"
        workers = _children(p.pid)
        assert any(scratch.glob("twinmon-pool-*"))
        p.kill()
        # stdout and stderr reach end-of-file: no worker holds them (a `| tee` ends).
        try:
            p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            raise AssertionError("the killed command's stdout/stderr are still held open "
                                 "(by its workers?)") from None
        assert wait_for(lambda: not any(_running(w) for w in workers), 15), \
            f"workers outlived the killed command: {_describe(w for w in workers if _running(w))}"
        assert wait_for(lambda: not any(scratch.glob("twinmon-*")), 10), \
            f"left in TMPDIR: {sorted(x.name for x in scratch.iterdir())}"

        r = twinmon("simulate", "-c", cfg, *design, "-j", "2", "-o", out, "--json", cwd=work,
                    env=env)
        assert_ok(r)
        assert not any(scratch.glob("twinmon-*"))
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        for w in workers:               # only on failure: orphans of the killed command
            if _running(w):
                os.kill(w, signal.SIGKILL)

    ref = work / "ref.h5"
    assert_ok(twinmon("simulate", "-c", cfg, *design, "--set", "simulate.executor=serial",
                      "-o", ref, cwd=work, env=env))
    with h5py.File(out, "r") as a, h5py.File(ref, "r") as b:
        for split in ("train", "test"):
            for name in ("X", "Y", "status"):
                np.testing.assert_array_equal(a[f"{split}/{name}"][()], b[f"{split}/{name}"][()],
                                              err_msg=f"{split}/{name}")


def test_lock_of_a_dead_holder_is_taken_over(work):
    """A lock still held (by some process that inherited it) but recorded by a dead PID is
    stale: taken over with a warning, the command runs (it exited 8 naming the dead PID)."""
    import sys
    import textwrap

    from .conftest import dead_pid
    out = work / "sim.h5"
    lock = work / ".sim.h5.lock"
    holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import fcntl, os, sys, time
        fd = os.open({str(lock)!r}, os.O_RDWR | os.O_CREAT)
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, b"twinmon simulate (pid {dead_pid()})")
        print("held", flush=True)
        time.sleep(60)
        """)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        r = twinmon("simulate", "-c", work / "small.yaml", "-o", out, cwd=work)
        assert_ok(r)
        assert "taking it over" in r.stderr and str(out) in r.stderr, r.stderr
        assert out.is_file() and not lock.exists()
    finally:
        holder.kill()
        holder.wait()


def test_kill9_of_calibrate_with_a_pool(work, tmp_path):
    """The same for calibrate's sampling pool (OpenTURNS chains, one task each): workers
    gone, scratch gone, the lock free; the re-run equals a run on one process."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    env = {**os.environ, "TMPDIR": str(scratch)}
    # Long enough chains (~5 s of sampling) that the kill lands while they run, not after
    # the pool has shut down.
    args = ["-c", work / "small.yaml", "--surrogate", work / "surrogate.h5",
            "--observations", work / "fleet.h5"]
    out = work / "k" / "posterior.h5"
    out.parent.mkdir()
    p = subprocess.Popen(cmd("calibrate", *args, "--set", "calibrate.sampler=openturns",
                             "--set", "calibrate.samples=8000",
                             "--set", "calibrate.workers=2", "-o", out),
                         cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    workers: set[int] = set()
    try:
        assert wait_for(lambda: len(_children(p.pid)) >= 2, 60, p), \
            "calibrate never started its pool"
        workers = _children(p.pid)
        # Chains under way: the workers have sampled for a while.
        assert wait_for(lambda: _cpu_seconds(workers) > 1.0, 60, p), \
            "calibrate's workers never started sampling"
        assert p.poll() is None, "calibrate ended before it could be killed"
        assert any(scratch.glob("twinmon-pool-*"))
        p.kill()
        try:
            p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            raise AssertionError("the killed command's stdout/stderr are still held open") \
                from None
        assert wait_for(lambda: not any(_running(w) for w in workers), 15), \
            f"workers outlived the killed command: {_describe(w for w in workers if _running(w))}"
        assert wait_for(lambda: not any(scratch.glob("twinmon-*")), 10), \
            f"left in TMPDIR: {sorted(x.name for x in scratch.iterdir())}"
        assert not out.exists()
        # The re-run and its one-process reference with the default sampler and chains:
        # what is checked is that nothing of the killed run is in the way, and that the
        # workers do not change the draws, not the long chains themselves.
        r = twinmon("calibrate", *args, "--set", "calibrate.workers=2", "-o", out, cwd=work,
                    env=env)
        assert_ok(r)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        for w in workers:
            if _running(w):
                os.kill(w, signal.SIGKILL)
    ref = work / "ref.h5"
    assert_ok(twinmon("calibrate", *args, "--set", "calibrate.workers=1", "-o", ref, cwd=work,
                      env=env))
    with h5py.File(out, "r") as a, h5py.File(ref, "r") as b:
        for unit in b["units"]:
            np.testing.assert_array_equal(a[f"units/{unit}/samples"][()],
                                          b[f"units/{unit}/samples"][()], err_msg=unit)
