"""Fault injection: shared functions and the artifacts every case starts from.

The artifacts are made ONCE per test run by one ``twinmon run`` on a small design (24 + 8
simulations, 2 chains of 200 draws, a fleet of 3 units x 4 years) and copied into each test's
own folder, so that a case can damage its copy without touching anyone else's.

Every failing case checks the same contract (:func:`assert_fails`): the expected exit code,
exactly one non-empty line on stderr holding the expected fragment, no traceback; and
:class:`Snapshot` checks that the files present before the command are byte-identical after.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from ..conftest import CONFIGS, ROOT, made_once

#: Seconds any one command may take: a hang is a failure, never a stuck suite.
TIMEOUT = 120

#: The small design every fixture and case uses (on top of configs/fleet.yaml).
SMALL = {
    "simulate": {"train_size": 24, "test_size": 8},
    # Chains not extended for a low ESS: the cases test failures, not the mixing.
    "calibrate": {"chains": 2, "samples": 200, "burn_in": 50, "max_extensions": 0},
    # 200, not 100: with 100 samples forecast currently crashes (see test_no_traceback.py::
    # test_forecast_with_failed_twin_runs_no_traceback); the shared artifacts must not
    # depend on it.
    "forecast": {"samples": 200},
    "fabricate": {"years": 4},
}


def cmd(*args) -> list[str]:
    return [sys.executable, "-m", "twinmon", *map(str, args)]


def twinmon(*args, cwd=None, timeout=TIMEOUT, env=None) -> subprocess.CompletedProcess:
    """Run the CLI as a subprocess; a hang raises ``TimeoutExpired`` (a test failure)."""
    return subprocess.run(cmd(*args), cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=env)


def start(*args, cwd=None, new_session=False) -> subprocess.Popen:
    return subprocess.Popen(cmd(*args), cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=new_session)


def twinmon_many(*calls, cwd=None, timeout=TIMEOUT) -> list[subprocess.CompletedProcess]:
    """Run independent commands side by side (each an argument list); results in order.
    A hang in any is a failure."""
    procs = [start(*args, cwd=cwd) for args in calls]
    results = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=timeout)
            results.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    except subprocess.TimeoutExpired:
        for p in procs:
            p.kill()
        pytest.fail(f"no answer within {timeout} s (hang): {p.args}")
    return results


def lines(stderr: str) -> list[str]:
    return [l for l in stderr.splitlines() if l.strip()]


def assert_fails(r, code: int, *fragments: str) -> str:
    """Exit ``code``, exactly one non-empty stderr line containing every fragment, no
    traceback. Returns the line."""
    out = lines(r.stderr)
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == code, f"exit {r.returncode}, expected {code}; stderr:\n{r.stderr}"
    assert len(out) == 1, f"expected one stderr line, got {len(out)}:\n{r.stderr}"
    for frag in fragments:
        assert frag in out[0], f"{frag!r} not in {out[0]!r}"
    return out[0]


def assert_ok(r) -> None:
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 0, f"exit {r.returncode}; stderr:\n{r.stderr}"


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class Snapshot:
    """SHA-256 of every file under some folders (and of single files) before a command;
    :meth:`check` asserts each is still there, byte-identical."""

    def __init__(self, *roots: Path):
        self.hashes = {}
        for root in roots:
            root = Path(root)
            files = [root] if root.is_file() else [p for p in root.rglob("*") if p.is_file()]
            for p in files:
                self.hashes[p] = sha256(p)
        assert self.hashes, "nothing to snapshot"

    def check(self) -> None:
        changed = [str(p) for p, h in self.hashes.items() if not p.is_file() or sha256(p) != h]
        assert not changed, f"pre-existing files changed or removed: {changed}"


def write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def wait_for(predicate, limit: float, proc: subprocess.Popen | None = None) -> bool:
    """Poll ``predicate`` every 20 ms up to ``limit`` seconds (or until ``proc`` ends)."""
    end = time.monotonic() + limit
    while time.monotonic() < end:
        if predicate():
            return True
        if proc is not None and proc.poll() is not None:
            return predicate()
        time.sleep(0.02)
    return predicate()


@pytest.fixture(scope="session")
def pump_fmu() -> Path:
    """The real PumpCircuit ``.fmu`` (built from its C sources, cached by hash)."""
    from twinmon.fmu import build_fmu
    return Path(build_fmu(ROOT / "fmus" / "PumpCircuit"))


@pytest.fixture(scope="session")
def built(tmp_path_factory, pump_fmu):
    """Everything the cases start from, made once: ``small.yaml`` (fleet.yaml + the small
    design), ``fleet.h5`` / ``fleet_truth.h5`` (fabricate) and ``wd/`` holding the artifacts of
    one ``twinmon run`` (simulations, surrogate, posterior, forecast, gap, report).

    While that run holds ``wd``, a second ``twinmon run`` into the same ``wd`` is started: its
    result is returned for test_concurrency.py::test_two_runs_into_one_workdir (this saves a
    second full pipeline). Made once per test run (:func:`made_once`): the cases only read
    it."""
    return made_once(tmp_path_factory, "faults_built", _build)


def _build(root: Path) -> dict:
    cfg = write_yaml(root / "small.yaml", {"extends": str(CONFIGS / "fleet.yaml"), **SMALL})
    r = twinmon("fabricate", "-c", cfg, "-o", root / "fleet.h5", cwd=root)
    assert r.returncode == 0, r.stderr
    wd = root / "wd"
    first = start("run", "-c", cfg, "--observations", root / "fleet.h5", "--workdir", wd,
                  "--json", cwd=root)
    lock = root / ".wd.lock"
    held = wait_for(lock.exists, 20, first)
    second = twinmon("run", "-c", cfg, "--observations", root / "fleet.h5", "--workdir", wd,
                     cwd=root) if held and first.poll() is None else None
    out, err = first.communicate(timeout=TIMEOUT)
    assert first.returncode == 0, err
    import json
    return {"root": root, "config": cfg, "wd": wd, "run_json": json.loads(out),
            "concurrent_run": second, "lock_seen": held}


ARTIFACTS = ("simulations", "surrogate", "posterior", "forecast", "gap")


@pytest.fixture
def work(built, tmp_path) -> Path:
    """A private copy of the built artifacts: ``tmp_path`` holds small.yaml, fleet.h5,
    fleet_truth.h5 and simulations.h5, surrogate.h5, posterior.h5, forecast.h5, gap.h5."""
    src = built["root"]
    for name in ("small.yaml", "fleet.h5", "fleet_truth.h5"):
        shutil.copy2(src / name, tmp_path / name)
    for name in ARTIFACTS:
        shutil.copy2(built["wd"] / f"{name}.h5", tmp_path / f"{name}.h5")
    return tmp_path


def dead_pid() -> int:
    """A PID no process has right now."""
    pid = 999_999
    while True:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return pid
        except PermissionError:
            pass
        pid -= 1
