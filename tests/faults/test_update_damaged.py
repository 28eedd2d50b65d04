"""``--update`` over a damaged output: what is continued is read whole first, so damage is
an artifact error (exit 5) and nothing is written. Before, a flipped byte in the kept draws
was copied into the new posterior with exit 0, and a truncated posterior or gap.h5 gave
exit 8 (I/O) instead of 5."""
from __future__ import annotations

import os

import h5py

from .conftest import Snapshot, assert_fails, twinmon


def _flip_a_byte_of_the_draws(path):
    with h5py.File(path, "r") as f:
        ds = f["units/Colt/samples"]
        offset = ds.id.get_chunk_info(0).byte_offset + 100
    with open(path, "r+b") as fh:
        fh.seek(offset)
        b = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([b[0] ^ 0x10]))


def _truncate(path):
    os.truncate(path, os.path.getsize(path) // 2)


def _calibrate_update(work):
    return twinmon("calibrate", "-c", work / "small.yaml", "--surrogate", work / "surrogate.h5",
                   "--observations", work / "fleet.h5", "-o", work / "posterior.h5",
                   "--update", cwd=work)


def test_update_over_a_flipped_byte_in_the_posterior(work):
    _flip_a_byte_of_the_draws(work / "posterior.h5")
    snap = Snapshot(work)
    assert_fails(_calibrate_update(work), 5, str(work / "posterior.h5"), "damaged")
    snap.check()


def test_update_over_a_truncated_posterior(work):
    _truncate(work / "posterior.h5")
    snap = Snapshot(work)
    assert_fails(_calibrate_update(work), 5, str(work / "posterior.h5"))
    snap.check()


def test_diagnose_update_over_a_truncated_gap(work):
    _truncate(work / "gap.h5")
    snap = Snapshot(work)
    r = twinmon("diagnose", "-c", work / "small.yaml", "--observations", work / "fleet.h5",
                "-o", work / "gap.h5", "--update", cwd=work)
    assert_fails(r, 5, str(work / "gap.h5"))
    snap.check()
