"""Lost work: two writers of one output, Ctrl-C, stale temporaries, and `run` redoing stages
for settings that only spread the work over processes."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess

import h5py
import numpy as np
import pytest

from .conftest import (ARTIFACTS, TIMEOUT, Snapshot, assert_fails, assert_ok, cmd, dead_pid,
                       start, twinmon, wait_for)


def test_two_simulate_into_one_output(work):
    """The second writer stops at once (exit 8, "is being written by"); the first finishes
    and its output is complete. The design (5000 serial runs, a few seconds) is smaller than
    20000 runs to keep the suite within its time budget; it still holds the lock for
    seconds after the second one starts."""
    cfg = work / "small.yaml"
    out = work / "big" / "s.h5"
    out.parent.mkdir()
    snap = Snapshot(work)
    big = ["--set", "simulate.train_size=5000", "--set", "simulate.test_size=0",
           "--set", "simulate.executor=serial"]
    first = start("simulate", "-c", cfg, *big, "-o", out, "--json", cwd=work)
    lock = out.parent / ".s.h5.lock"
    assert wait_for(lock.exists, 10, first), "the first simulate never took its lock"
    assert first.poll() is None, "the first simulate ended before the second could start"
    second = twinmon("simulate", "-c", cfg, *big, "-o", out, cwd=work)
    assert_fails(second, 8, str(out), "is being written by")
    o, e = first.communicate(timeout=TIMEOUT)
    assert first.returncode == 0, e
    summary = json.loads(o)
    assert summary["runs"] == 5000 and summary["failures"] == 0 and summary["resumed"] == 0
    with h5py.File(out, "r") as f:
        assert f["train/X"].shape == (5000, 2)
        assert (f["train/status"][()] == 0).all()
        assert np.isfinite(f["train/Y"][()]).all()
    assert not (out.parent / "s.h5.partial").exists()
    assert not lock.exists()
    snap.check()


def test_two_runs_into_one_workdir(built):
    """Made by the shared fixture (once per test run): while the first `twinmon run` (the one that built the
    shared artifacts) held its workdir, a second `run` into the same workdir was started."""
    assert built["lock_seen"], "the first run never took the workdir lock"
    second = built["concurrent_run"]
    assert second is not None, "the first run ended before the second could start"
    assert_fails(second, 8, str(built["wd"]), "is being written by")
    # The first one was not disturbed: every stage ran and wrote its artifact.
    stages = {s["stage"]: s for s in built["run_json"]["stages"]}
    assert not any(s["skipped"] for s in stages.values())
    for name in ARTIFACTS:
        assert (built["wd"] / f"{name}.h5").is_file()


def test_run_does_not_redo_stages_for_execution_settings(built, tmp_path):
    """Artifacts made by `run` with the config's workers/executor, copied elsewhere; `run`
    again there with simulate.workers=1, simulate.executor=serial and report.workers=1:
    every stage is skipped, the report too, and the report named is the copy's."""
    wd = tmp_path / "wd"
    shutil.copytree(built["wd"], wd)
    snap = Snapshot(wd)
    r = twinmon("run", "-c", built["config"], "--observations", built["root"] / "fleet.h5",
                "--workdir", wd, "--set", "simulate.workers=1", "--set",
                "simulate.executor=serial", "--set", "report.workers=1", "--json",
                cwd=tmp_path)
    assert_ok(r)
    out = json.loads(r.stdout)
    stages = {s["stage"]: s["skipped"] for s in out["stages"]}
    assert stages == {"simulate": True, "reduce": True, "calibrate": True, "forecast": True,
                      "diagnose": True, "report": True}, stages
    assert out["report"] == str(wd / "report" / "index.html")
    snap.check()


#: Seconds a Ctrl-C may take to end a command (it should take well under one second).
INTERRUPT_LIMIT = 10


def _interrupt(p: subprocess.Popen) -> subprocess.CompletedProcess:
    """SIGINT to the command's whole process group (what a terminal's Ctrl-C does)."""
    assert p.poll() is None, "the command finished before it could be interrupted"
    os.killpg(p.pid, signal.SIGINT)
    try:
        out, err = p.communicate(timeout=INTERRUPT_LIMIT)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        pytest.fail(f"still running {INTERRUPT_LIMIT} s after Ctrl-C: {p.args}")
    return subprocess.CompletedProcess(p.args, p.returncode, out, err)


#: Interrupts per test: the process executor starts a pool per chunk, and a Ctrl-C landing
#: while it forks has been seen to be lost; one try alone would often miss that.
ATTEMPTS = 3


def test_ctrl_c_simulate_exit_130_then_resume(work):
    """Ctrl-C while the process executor runs a big design: exit 130, one line saying the
    next simulate resumes, no worker traceback, the partial file kept; the next simulate
    resumes (another executor: execution settings do not break the resume)."""
    cfg = work / "small.yaml"
    # Model Exchange (fmpy's CVode) is ~20x slower per run than Co-Simulation: the design
    # stays small and still runs long enough to be interrupted mid-way.
    big = ["--set", "simulate.train_size=600", "--set", "simulate.test_size=0",
           "--set", "simulate.design=sobol", "--set", "model.fmi_type=ModelExchange"]
    snap = Snapshot(work)
    for attempt in range(ATTEMPTS):
        out = work / f"s{attempt}.h5"
        partial = work / f"s{attempt}.h5.partial"
        p = start("simulate", "-c", cfg, *big, "--set", "simulate.executor=process",
                  "-o", out, cwd=work, new_session=True)
        assert wait_for(partial.exists, 30, p), "simulate never started its partial file"
        wait_for(lambda: False, 0.4 + 0.25 * attempt, p)   # a few chunks done
        r = _interrupt(p)
        line = assert_fails(r, 130, "resume")
        assert "KeyboardInterrupt" not in r.stderr, r.stderr
        assert not out.exists() and partial.exists(), (attempt, line)
    again = twinmon("simulate", "-c", cfg, *big, "--set", "simulate.executor=serial",
                    "-o", out, "--json", cwd=work)
    assert_ok(again)
    summary = json.loads(again.stdout)
    assert summary["resumed"] > 0, summary
    assert summary["resumed"] + summary["runs"] == 600 and summary["failures"] == 0, summary
    assert not partial.exists()
    with h5py.File(out, "r") as f:
        assert (f["train/status"][()] == 0).all()
    snap.check()


def test_sigterm_simulate_exit_143_keeps_partial_and_cleans_up(work, tmp_path):
    """SIGTERM to the command alone (``kill``, ``timeout``, a scheduler's time limit; the
    workers are in their own process group and do not get it): exit 143, one line saying
    the next simulate resumes, the partial file kept, and neither the output's lock nor the
    workers' scratch folder (extracted FMUs) left behind -- Python's default for SIGTERM
    dies on the spot and leaves both."""
    cfg = work / "small.yaml"
    big = ["--set", "simulate.train_size=600", "--set", "simulate.test_size=0",
           "--set", "simulate.design=sobol", "--set", "model.fmi_type=ModelExchange",
           "--set", "simulate.executor=process"]
    scratch = tmp_path / "tmpdir"
    scratch.mkdir()
    out, partial = work / "t.h5", work / "t.h5.partial"
    p = subprocess.Popen(cmd("simulate", "-c", cfg, *big, "-o", out), cwd=work,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "TMPDIR": str(scratch)})
    assert wait_for(partial.exists, 30, p), "simulate never started its partial file"
    assert wait_for(lambda: any(scratch.glob("twinmon-pool-*")), 30, p), \
        "no worker scratch folder to clean up"
    wait_for(lambda: False, 0.3, p)
    assert p.poll() is None, "simulate finished before it could be terminated"
    p.send_signal(signal.SIGTERM)
    o, e = p.communicate(timeout=INTERRUPT_LIMIT)
    assert_fails(subprocess.CompletedProcess(p.args, p.returncode, o, e), 143, "terminated",
                 "resume")
    assert not out.exists() and partial.exists()
    assert not list(work.glob(".t.h5*lock")), list(work.iterdir())
    assert not list(scratch.iterdir()), list(scratch.iterdir())


def test_ctrl_c_calibrate_exit_130(work):
    before = sorted(f.name for f in work.iterdir())
    snap = Snapshot(work)
    # OpenTURNS' sampler runs every one of its 40 000 draws (the vectorised one stops at its
    # ESS target, within the 3 s below on an idle machine).
    p = start("calibrate", "-c", work / "small.yaml", "--set", "calibrate.samples=40000",
              "--set", "calibrate.sampler=openturns",
              "--surrogate", work / "surrogate.h5", "--observations", work / "fleet.h5",
              "-o", work / "posterior.h5", cwd=work, new_session=True)
    wait_for(lambda: False, 3.0, p)            # past the imports, inside the sampling
    r = _interrupt(p)
    assert_fails(r, 130, "interrupted")
    # The previous posterior.h5 is untouched, and nothing is left behind (no temporary, no lock).
    snap.check()
    assert sorted(f.name for f in work.iterdir()) == before


def test_stale_temporary_of_dead_writer_removed(work):
    """A `.<name>.<pid>.tmp` left by a dead process is removed by the next write of <name>;
    one of a live process is left alone."""
    dead = work / f".surrogate.h5.{dead_pid()}.tmp"
    dead.write_bytes(b"half an HDF5 file")
    live = work / f".surrogate.h5.{os.getpid()}.tmp"
    live.write_bytes(b"being written")
    r = twinmon("reduce", "-c", work / "small.yaml", "--simulations", work / "simulations.h5",
                "-o", work / "surrogate.h5", cwd=work)
    assert_ok(r)
    assert not dead.exists(), "the dead writer's temporary is still there"
    assert live.exists(), "a live process's temporary was removed"
