"""What a failed command leaves behind: nothing. Before, a full disk left an empty
``.<out>.lock`` beside every failed writer, ``simulate -j -5`` (exit 3) an empty
``.partial``, and report printed numpy's "All-NaN slice" warnings."""
from __future__ import annotations

import shutil
import subprocess

import h5py
import numpy as np
import pytest

from .conftest import assert_fails, assert_ok, twinmon


@pytest.fixture
def full_disk(tmp_path):
    """A 64 kB tmpfs, filled up (needs the right to mount: skipped without it)."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                       capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (not root)")
    try:
        try:
            with open(mnt / "filler", "wb") as fh:
                fh.write(b"\0" * 128 * 1024)
        except OSError:
            pass
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


@pytest.mark.parametrize("writer", ["reduce", "fabricate", "simulate"])
def test_full_disk_leaves_no_lock(work, full_disk, writer):
    cfg = work / "small.yaml"
    out = full_disk / "out.h5"
    args = {"reduce": ("reduce", "-c", cfg, "--simulations", work / "simulations.h5"),
            "fabricate": ("fabricate", "-c", cfg, "--truth", full_disk / "t.h5"),
            "simulate": ("simulate", "-c", cfg)}[writer]
    r = twinmon(*args, "-o", out, cwd=work)
    assert_fails(r, 8, str(full_disk), "No space left on device")
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler"]


def test_simulate_with_negative_workers_leaves_nothing(work):
    out = work / "j" / "sim.h5"
    r = twinmon("simulate", "-c", work / "small.yaml", "-j", "-5", "-o", out, cwd=work)
    assert_fails(r, 3, "workers", "-5")
    assert not out.parent.exists() or not any(out.parent.iterdir()), \
        sorted(p.name for p in out.parent.iterdir())


def test_report_prints_no_numpy_warnings(work):
    """A posterior whose diagnostics are all NaN (every year unreliable)."""
    post = work / "nan_posterior.h5"
    shutil.copy(work / "posterior.h5", post)
    with h5py.File(post, "r+") as f:
        for unit in f["units"]:
            ds = f[f"units/{unit}/record"]
            rec = ds[()]
            for name in ("rhat", "ess"):
                rec[name] = np.nan
            ds[...] = rec
    r = twinmon("report", "-c", work / "small.yaml", "--posterior", post, "-o", work / "rep",
                cwd=work)
    assert_ok(r)
    assert "Warning" not in r.stderr and "All-NaN" not in r.stderr, r.stderr
