"""Implausible observations: refused (exit 4, one line naming the file and the place) by every
stage that reads them, not only calibrate. Before, years -3..0, fractional years (silently
truncated) and year 10**12 passed everywhere; flows of zero or 1e-300 passed calibrate with
warnings; diagnose and report exited 0 on flows of 1e30, negated, x1000 or on another time
grid."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from .conftest import Snapshot, assert_fails, twinmon

OUTPUT = "m_flow"          # the small config's model.output.name


def _years(values):
    def damage(f):
        g = f["units/Colt"]
        del g["years"]
        g.create_dataset("years", data=np.asarray(values))
    return damage


def _flow(transform):
    def damage(f):
        ds = f[f"units/Colt/{OUTPUT}"]
        ds[...] = transform(ds[()])
    return damage


def _time(f):
    f["time"][...] = f["time"][()] * 2


DAMAGE = {
    "years -3..0": (_years([-3, -2, -1, 0]), "years"),
    "year 0": (_years([0, 1, 2, 3]), "years"),
    "fractional years": (_years([1.0, 2.5, 3.0, 4.0]), "whole year"),
    "year 1e12": (_years([1, 2, 3, 10**12]), "years"),
    "all-zero flow": (_flow(np.zeros_like), OUTPUT),
    "flow 1e-300": (_flow(lambda y: np.full_like(y, 1e-300)), OUTPUT),
    "flow 1e30": (_flow(lambda y: np.full_like(y, 1e30)), OUTPUT),
    "negated flow": (_flow(lambda y: -y), OUTPUT),
    "flow x1000": (_flow(lambda y: 1000 * y), OUTPUT),
    "another time grid": (_time, "time grid"),
}

STAGES = {
    "calibrate": lambda w, obs: ("calibrate", "-c", w / "small.yaml", "--surrogate",
                                 w / "surrogate.h5", "--observations", obs, "-o", w / "p2.h5"),
    "diagnose": lambda w, obs: ("diagnose", "-c", w / "small.yaml", "--observations", obs,
                                "-o", w / "g2.h5"),
    "report": lambda w, obs: ("report", "-c", w / "small.yaml", "--observations", obs,
                              "-o", w / "rep"),
}


#: Each damage through at least one stage (every stage runs the same check; a pair per case
#: keeps the suite fast).
PAIRS = [("years -3..0", "diagnose"), ("year 0", "report"), ("fractional years", "calibrate"),
         ("year 1e12", "diagnose"), ("all-zero flow", "calibrate"),
         ("flow 1e-300", "calibrate"), ("flow 1e30", "diagnose"), ("negated flow", "report"),
         ("flow x1000", "diagnose"), ("flow x1000", "report"),
         ("another time grid", "report"), ("another time grid", "calibrate")]


@pytest.mark.parametrize("case,stage", PAIRS)
def test_implausible_observations(work, case, stage):
    damage, fragment = DAMAGE[case]
    obs = work / "bad.h5"
    obs.write_bytes((work / "fleet.h5").read_bytes())
    with h5py.File(obs, "r+") as f:
        damage(f)
    snap = Snapshot(work)
    r = twinmon(*STAGES[stage](work, obs), cwd=work)
    assert_fails(r, 4, str(obs), fragment)
    snap.check()
    for out in ("p2.h5", "g2.h5", "rep"):
        assert not (work / out).exists()
