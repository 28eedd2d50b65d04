"""An output named as one of the command's inputs: refused at once (exit 2, one line), the
input untouched. Before the check, each of these overwrote the input and exited 0."""
from __future__ import annotations

import os

import pytest

from .conftest import Snapshot, assert_fails, twinmon

CASES = {
    "calibrate -o = --observations": (
        "calibrate -c small.yaml --surrogate surrogate.h5 --observations fleet.h5 -o fleet.h5",
        "--observations"),
    "calibrate -o = --surrogate": (
        "calibrate -c small.yaml --surrogate surrogate.h5 --observations fleet.h5 "
        "-o ./surrogate.h5", "--surrogate"),
    "reduce -o = --simulations": (
        "reduce -c small.yaml --simulations simulations.h5 -o simulations.h5", "--simulations"),
    "forecast -o = --posterior": (
        "forecast -c small.yaml --posterior posterior.h5 --surrogate surrogate.h5 "
        "-o posterior.h5", "--posterior"),
    "backtest -o = --posterior": (
        "backtest -c small.yaml --posterior posterior.h5 --surrogate surrogate.h5 "
        "-o posterior.h5", "--posterior"),
    "diagnose -o = --observations (a symlink)": (
        "diagnose -c small.yaml --observations fleet.h5 -o link.h5", "--observations"),
    "fabricate -o = its config": ("fabricate -c small.yaml -o small.yaml", "-c"),
    "fabricate --truth = -o": ("fabricate -c small.yaml -o new.h5 --truth new.h5", "--truth"),
    "import-csv -o = the CSV": ("import-csv obs.csv -c small.yaml -o obs.csv", "CSV_FILE"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_output_is_an_input(work, case):
    line, option = CASES[case]
    os.symlink(work / "fleet.h5", work / "link.h5")
    (work / "obs.csv").write_text("unit,year,time,m_flow\n"
                                  + "".join(f"A,{y},{t},{400 - y - t}\n"
                                            for y in (1, 2) for t in (0.0, 1.0, 2.0)))
    snap = Snapshot(work)
    r = twinmon(*line.split(), cwd=work)
    assert_fails(r, 2, "usage error", option, "overwrite")
    snap.check()
    assert not (work / "new.h5").exists()
