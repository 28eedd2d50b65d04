"""Two damaged inputs that ended in a Python traceback: now one line and the family's exit
code."""
from __future__ import annotations

import shutil

import h5py

from .conftest import ARTIFACTS, Snapshot, assert_fails, twinmon


def test_noise_std_of_1e300(work):
    """The likelihood overflowed (OverflowError in a worker); refused as implausible."""
    obs = work / "noisy.h5"
    shutil.copy(work / "fleet.h5", obs)
    with h5py.File(obs, "r+") as f:
        f["units/Colt"].attrs["noise_std"] = '{"m_flow": 1e300}'
    snap = Snapshot(work)
    r = twinmon("calibrate", "-c", work / "small.yaml", "--surrogate", work / "surrogate.h5",
                "--observations", obs, "-o", work / "p2.h5", cwd=work)
    assert_fails(r, 4, str(obs), "noise_std", "1e+300")
    snap.check()


def test_run_with_a_posterior_whose_inputs_are_not_json(work):
    wd = work / "wd"
    wd.mkdir()
    for name in ARTIFACTS:
        shutil.copy(work / f"{name}.h5", wd / f"{name}.h5")
    with h5py.File(wd / "posterior.h5", "r+") as f:
        f.attrs["inputs"] = "not json {"
    snap = Snapshot(wd)
    r = twinmon("-q", "run", "-c", work / "small.yaml", "--observations", work / "fleet.h5",
                "--workdir", wd, cwd=work)
    assert_fails(r, 5, str(wd / "posterior.h5"), "inputs", "not JSON")
    snap.check()
