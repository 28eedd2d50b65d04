"""``--update`` racing a full run into the same output: the output lock is taken before the
stage reads what it will continue, so the second writer stops at once instead of planning
from the old file and writing a mix of two posteriors."""
from __future__ import annotations

import json

from .conftest import TIMEOUT, Snapshot, assert_fails, start, twinmon, wait_for
from twinmon.artifacts import read_provenance


def test_calibrate_update_while_a_full_calibrate_runs(work):
    cfg = work / "small.yaml"
    out = work / "posterior.h5"
    lock = work / ".posterior.h5.lock"
    snap = Snapshot(work / "fleet.h5", work / "surrogate.h5")
    full = start("calibrate", "-c", cfg, "--surrogate", work / "surrogate.h5",
                 "--observations", work / "fleet.h5", "-o", out,
                 "--set", "calibrate.samples=3000", "--json", cwd=work)
    # Held from the start (sampling this design takes several seconds), not only at the
    # final write.
    assert wait_for(lock.exists, 4, full) and full.poll() is None, \
        "calibrate did not take the output lock before sampling"
    update = twinmon("calibrate", "-c", cfg, "--surrogate", work / "surrogate.h5",
                     "--observations", work / "fleet.h5", "-o", out, "--update", cwd=work)
    assert_fails(update, 8, str(out), "is being written by", "calibrate")
    o, e = full.communicate(timeout=TIMEOUT)
    assert full.returncode == 0, e
    assert json.loads(o)
    prov = read_provenance(out)
    assert "samples: 3000" in prov["config"], "the posterior is not the full run's"
    assert not lock.exists()
    snap.check()
