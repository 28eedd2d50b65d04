"""A broken or foreign FMU, or a config naming variables the FMU lacks: ``simulate`` and ``run``
end within the timeout with exit 6 and one line (never a hang, whatever the executor); a batch
in which some runs fail honestly is kept, not lost."""
from __future__ import annotations

import json
import shutil
import subprocess
import zipfile

import h5py
import numpy as np
import pytest

from .conftest import TIMEOUT, Snapshot, assert_fails, assert_ok, start, twinmon

EXECUTORS = ("process", "serial")


def _bad_fmus(folder, pump_fmu):
    """name -> path of: zip magic + garbage; the real FMU cut to half its bytes; the real FMU
    with an intact modelDescription.xml but garbage in place of its shared library."""
    garbage = folder / "garbage.fmu"
    garbage.write_bytes(b"PK\x03\x04" + bytes(range(256)) * 8)
    half = folder / "half.fmu"
    data = pump_fmu.read_bytes()
    half.write_bytes(data[:len(data) // 2])
    badso = folder / "badso.fmu"
    with zipfile.ZipFile(pump_fmu) as src, zipfile.ZipFile(badso, "w") as dst:
        for item in src.infolist():
            body = src.read(item)
            if item.filename.endswith(".so"):
                body = b"\x7fELF" + b"\x00garbage" * 64
            dst.writestr(item, body)
    return {"garbage": garbage, "half": half, "badso": badso}


def _run_matrix(tmp_path, overrides, extra=()):
    """``simulate`` and ``run``, each under the process and the serial executor, started
    together (the four are independent); returns {(command, executor): CompletedProcess}."""
    cfg, obs = tmp_path / "small.yaml", tmp_path / "fleet.h5"
    procs = {}
    for executor in EXECUTORS:
        sets = [a for o in [*overrides, f"simulate.executor={executor}"] for a in ("--set", o)]
        procs["simulate", executor] = start(
            "simulate", "-c", cfg, *sets, "-o", tmp_path / f"sim-{executor}" / "s.h5",
            cwd=tmp_path)
        procs["run", executor] = start(
            "run", "-c", cfg, *sets, "--observations", obs, "--workdir",
            tmp_path / f"wd-{executor}", cwd=tmp_path)
    results = {}
    for key, p in procs.items():
        try:
            out, err = p.communicate(timeout=TIMEOUT)
        except subprocess.TimeoutExpired:
            for q in procs.values():
                q.kill()
            pytest.fail(f"{key}: no answer within {TIMEOUT} s (hang) with {overrides}")
        results[key] = subprocess.CompletedProcess(p.args, p.returncode, out, err)
    return results


@pytest.mark.parametrize("which", ["garbage", "half", "badso"])
def test_corrupt_fmu_exit_6_no_hang(work, pump_fmu, which):
    fmu = _bad_fmus(work, pump_fmu)[which]
    snap = Snapshot(work)
    results = _run_matrix(work, [f"model.fmu={fmu}"])
    for (command, executor), r in results.items():
        line = assert_fails(r, 6, str(fmu))
        assert "simulation error" in line, (command, executor, line)
    # No simulations artifact. (With "badso" the FMU opens only inside the runner, so an
    # empty <output>.partial may stay behind; the next simulate replaces it: the FMU differs.)
    for executor in EXECUTORS:
        assert not (work / f"sim-{executor}" / "s.h5").exists()
        assert not (work / f"wd-{executor}" / "simulations.h5").exists()
    snap.check()


def test_corrupt_fmu_message_names_config_key(work, pump_fmu):
    """The line for a corrupt FMU says which config key pointed at it (like a misnamed
    variable does): ``model.fmu``."""
    fmu = _bad_fmus(work, pump_fmu)["garbage"]
    r = twinmon("simulate", "-c", work / "small.yaml", "--set", f"model.fmu={fmu}",
                "-o", work / "s.h5", cwd=work)
    assert_fails(r, 6, str(fmu), "model.fmu")


@pytest.mark.parametrize("override, key, name, closest", [
    ("model.output.variable=sensor.mflow", "model.output.variable", "sensor.mflow",
     "sensor.m_flow"),
    ("model.nonphysical=nonphysicl", "model.nonphysical", "nonphysicl", "nonphysical"),
    ("model.fixed={pump.b3: 1.0}", "model.fixed.pump.b3", "pump.b3", "pump.b2"),
    # An input whose variable the FMU lacks: no "24 runs, 24 failed" exit 0.
    ("model.inputs.pump_coef.variable=pump.b3", "model.inputs.pump_coef.variable", "pump.b3",
     "pump.b2"),
], ids=["output", "nonphysical", "fixed", "input"])
def test_misnamed_variable_exit_6_names_key_and_closest(work, override, key, name, closest):
    snap = Snapshot(work)
    results = _run_matrix(work, [override])
    for (command, executor), r in results.items():
        line = assert_fails(r, 6, key, repr(name), "closest:")
        near = line.split("closest:", 1)[1]
        assert closest in near, (command, executor, line)
    for executor in EXECUTORS:
        assert not (work / f"sim-{executor}" / "s.h5").exists()
        assert not (work / f"wd-{executor}").exists(), "run created its workdir before failing"
    snap.check()


def test_some_runs_fail_batch_kept(work):
    """Motor damping up to 2e7 N.m.s/rad makes the pump loop so stiff that the FMU's own
    integrator gives up ("more than 200000 internal steps") for the upper part of the box,
    while the lower part runs: the batch must be kept, failures recorded run by run."""
    cfg = work / "small.yaml"
    out = work / "mixed.h5"
    snap = Snapshot(work)
    r = twinmon("simulate", "-c", cfg, "--set", "simulate.train_size=8",
                "--set", "simulate.test_size=0", "--set", "simulate.executor=process",
                "--set", "model.inputs.motor_damping.high=2e7", "-o", out, "--json", cwd=work)
    assert_ok(r)
    summary = json.loads(r.stdout)
    assert 0 < summary["failures"] < 8, summary
    assert any("runs failed" in w for w in summary["warnings"]), summary
    with h5py.File(out, "r") as f:
        status = f["train/status"][()]
        messages = [m.decode() if isinstance(m, bytes) else m for m in f["train/message"][()]]
        Y = f["train/Y"][()]
    assert set(np.unique(status)) == {0, 1}, status
    assert np.isfinite(Y[status == 0]).all()
    assert all(("internal steps" in m) == bool(s) for m, s in zip(messages, status)), messages
    snap.check()


def test_no_fmu_extraction_left_in_tmp(work):
    """Every worker extracts the FMU into a temporary folder: a finished simulate (process
    and serial executors) leaves none behind in $TMPDIR."""
    import os
    tmpdir = work / "tmpdir"
    tmpdir.mkdir()
    env = {**os.environ, "TMPDIR": str(tmpdir)}
    for executor in EXECUTORS:
        r = twinmon("simulate", "-c", work / "small.yaml", "--set", "simulate.train_size=200",
                    "--set", "simulate.test_size=0", "--set", f"simulate.executor={executor}",
                    "-o", work / f"s-{executor}.h5", cwd=work, env=env)
        assert_ok(r)
        left = sorted(p.name for p in tmpdir.iterdir())
        assert not left, f"{executor}: {len(left)} folders left in $TMPDIR: {left[:4]}"
