"""Exit codes and messages of the remaining cases: unreadable configs, numbers written 1e6,
a CSV with a byte-order mark, the built FMU's mode, `run` checking its inputs before it writes
anything."""
from __future__ import annotations

import os
import shutil
import stat

import h5py
import numpy as np
import pytest

from .conftest import Snapshot, assert_fails, assert_ok, twinmon, twinmon_many


def test_folder_as_config_exit_3(work):
    snap = Snapshot(work)
    r = twinmon("simulate", "-c", work, "-o", work / "s.h5", cwd=work)
    assert_fails(r, 3, str(work), "folder")
    assert not (work / "s.h5").exists()
    snap.check()


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads a file whatever its mode")
def test_unreadable_config_exit_8(work):
    cfg = work / "locked.yaml"
    cfg.write_text(f"extends: {work / 'small.yaml'}\n")
    cfg.chmod(0)
    try:
        r = twinmon("simulate", "-c", cfg, "-o", work / "s.h5", cwd=work)
        assert_fails(r, 8, "locked.yaml")
    finally:
        cfg.chmod(0o644)


def test_exponent_numbers_accepted(work):
    """``3e1`` in the YAML file and ``4e0`` in --set are numbers (PyYAML alone reads them as
    strings)."""
    cfg = work / "exp.yaml"
    cfg.write_text(f"extends: {work / 'small.yaml'}\n"
                   "model:\n"
                   "  inputs:\n"
                   "    motor_damping: {high: 3e1}\n"
                   "simulate: {train_size: 4, test_size: 0, executor: serial}\n")
    out = work / "s.h5"
    r = twinmon("simulate", "-c", cfg, "--set", "model.inputs.pump_coef.high=4e0",
                "--set", "model.output.times.stop=5e1", "-o", out, cwd=work)
    assert_ok(r)
    with h5py.File(out, "r") as f:
        assert np.allclose(f["bounds"][()], [[4.0, 30.0], [2.2, 4.0]])
        assert f["time"][-1] == 50.0


def test_csv_with_bom_accepted(work, repo_root):
    csv = work / "bom.csv"
    csv.write_bytes(b"\xef\xbb\xbfunit,year,time,m_flow\nA,1,2,10\nA,1,4,12\n")
    out = work / "o.h5"
    r = twinmon("import-csv", csv, "-c", repo_root / "configs" / "pump.yaml", "-o", out,
                cwd=work)
    assert_ok(r)
    with h5py.File(out, "r") as f:
        assert f["units/A/m_flow"][()].tolist() == [[10.0, 12.0]]


def test_built_fmu_mode_0644(tmp_path, repo_root, pump_fmu):
    """The FMU build writes through a private temporary file (mode 0600): the result must be
    readable by others, like any build product (0644)."""
    src = tmp_path / "PumpCircuit"
    shutil.copytree(repo_root / "fmus" / "PumpCircuit", src,
                    ignore=shutil.ignore_patterns(".build"))
    old = os.umask(0o022)
    try:
        r = twinmon("build-fmu", src, "--no-validate", cwd=tmp_path)
    finally:
        os.umask(old)
    assert_ok(r)
    built = list((src / ".build").glob("*/PumpCircuit.fmu"))
    assert len(built) == 1, built
    assert stat.S_IMODE(built[0].stat().st_mode) == 0o644, oct(built[0].stat().st_mode)
    assert stat.S_IMODE(pump_fmu.stat().st_mode) == 0o644, oct(pump_fmu.stat().st_mode)


def test_run_checks_inputs_before_writing(work):
    """`run` with a missing --observations (or --gap-observations, --truth) stops with exit 4
    before simulate writes anything: the workdir is not even created."""
    snap = Snapshot(work)
    base = ["run", "-c", work / "small.yaml"]
    r_obs, r_gap, r_truth = twinmon_many(
        [*base, "--observations", work / "nope.h5", "--workdir", work / "wd1"],
        [*base, "--observations", work / "fleet.h5", "--gap-observations", work / "nope.h5",
         "--workdir", work / "wd2"],
        [*base, "--observations", work / "fleet.h5", "--truth", work / "nope.h5",
         "--workdir", work / "wd3"], cwd=work)
    assert_fails(r_obs, 4, "nope.h5", "--observations")
    assert_fails(r_gap, 4, "nope.h5", "--gap-observations")
    assert_fails(r_truth, 4, "nope.h5", "--truth")
    for wd in ("wd1", "wd2", "wd3"):
        assert not (work / wd).exists()
    snap.check()
