"""Artifacts of different runs given together: refused (exit 5, one line naming the two
files) by every stage that combines them. Before the lineage check each of these exited 0
and reported, scored or diagnosed a mix."""
from __future__ import annotations

import pytest

from .conftest import Snapshot, assert_fails, assert_ok, twinmon


@pytest.fixture(scope="module")
def other(built, tmp_path_factory):
    """Artifacts of another run beside the shared ones: a surrogate learnt from another
    design (another seed), another fleet (another fabricate seed) and its posterior."""
    root = tmp_path_factory.mktemp("other_run")
    src = built["root"]
    cfg = src / "small.yaml"
    for args in (("simulate", "-c", cfg, "--set", "seed=7", "-o", root / "simulations.h5"),
                 ("reduce", "-c", cfg, "--set", "seed=7", "--simulations",
                  root / "simulations.h5", "-o", root / "surrogate.h5"),
                 ("fabricate", "-c", cfg, "--set", "fabricate.seed=99", "-o",
                  root / "fleet.h5"),
                 ("calibrate", "-c", cfg, "--surrogate", built["wd"] / "surrogate.h5",
                  "--observations", root / "fleet.h5", "-o", root / "posterior.h5")):
        assert_ok(twinmon(*args, cwd=root))
    return root


def _check(work, r, *names):
    line = assert_fails(r, 5, *map(str, names))
    assert "was not made from" in line or "another model" in line, line


def test_backtest_with_a_posterior_of_another_surrogate(work, other):
    snap = Snapshot(work)
    r = twinmon("backtest", "-c", work / "small.yaml", "--posterior", work / "posterior.h5",
                "--surrogate", other / "surrogate.h5", "-o", work / "bt.h5", cwd=work)
    _check(work, r, work / "posterior.h5", other / "surrogate.h5")
    assert not (work / "bt.h5").exists()
    snap.check()


def test_diagnose_with_a_posterior_of_another_box(work):
    snap = Snapshot(work)
    r = twinmon("diagnose", "-c", work / "small.yaml", "--set",
                "model.inputs.motor_damping.high=40.0", "--observations", work / "fleet.h5",
                "--posterior", work / "posterior.h5", "-o", work / "gap2.h5", cwd=work)
    _check(work, r, work / "posterior.h5", "model.inputs")
    assert not (work / "gap2.h5").exists()
    snap.check()


@pytest.mark.parametrize("mix", ["forecast of another posterior", "surrogate of another box",
                                 "observations of another fleet"])
def test_report_of_a_mixed_set(work, other, mix):
    # The file of the other run: beside this run's forecast, another posterior; beside
    # this run's posterior, another surrogate or another fleet.
    role = {"forecast of another posterior": "posterior", "surrogate of another box":
            "surrogate", "observations of another fleet": "observations"}[mix]
    given = {"observations": work / "fleet.h5", "surrogate": work / "surrogate.h5",
             "posterior": work / "posterior.h5", "forecast": work / "forecast.h5"}
    mixed = other / ("fleet.h5" if role == "observations" else f"{role}.h5")
    given[role] = mixed
    snap = Snapshot(work)
    r = twinmon("report", "-c", work / "small.yaml", "-o", work / "rep",
                *[a for k, v in given.items() for a in (f"--{k}", v)], cwd=work)
    _check(work, r, mixed)
    assert not (work / "rep").exists()
    snap.check()


def test_report_of_one_run_is_accepted(built):
    """The check does not refuse a set that belongs together: the shared artifacts' own
    ``twinmon run`` made its report from the observations, simulations, surrogate,
    posterior, forecast and gap of that one run."""
    stages = {s["stage"]: s for s in built["run_json"]["stages"]}
    assert not stages["report"]["skipped"]
    assert (built["wd"] / "report" / "index.html").is_file()
