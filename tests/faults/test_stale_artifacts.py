"""Stale or mismatched artifacts: simulations for another time grid or box, a surrogate for
another time grid, a posterior calibrated with another surrogate -> exit 5 saying what to
re-run, never a result computed from the wrong file."""
from __future__ import annotations

from .conftest import Snapshot, assert_fails, assert_ok, twinmon_many


def test_mismatched_artifacts_exit_5(work):
    cfg = work / "small.yaml"
    grid = ["--set", "model.output.times.step=4"]
    box = ["--set", "model.inputs.pump_coef.low=2.5"]
    seed = ["--set", "seed=7"]
    # Artifacts made for another time grid, another box, another seed (side by side).
    made = twinmon_many(
        ["simulate", "-c", cfg, *grid, "-o", work / "sims_grid.h5"],
        ["simulate", "-c", cfg, *box, "-o", work / "sims_box.h5"],
        ["simulate", "-c", cfg, *seed, "-o", work / "sims_seed.h5"], cwd=work)
    for r in made:
        assert_ok(r)
    made = twinmon_many(
        ["reduce", "-c", cfg, *grid, "--simulations", work / "sims_grid.h5",
         "-o", work / "sur_grid.h5"],
        ["reduce", "-c", cfg, *seed, "--simulations", work / "sims_seed.h5",
         "-o", work / "sur_seed.h5"], cwd=work)
    for r in made:
        assert_ok(r)
    snap = Snapshot(work)
    r_grid, r_box, r_cal, r_fc = twinmon_many(
        # reduce, with the config's grid and box, on simulations made for others
        ["reduce", "-c", cfg, "--simulations", work / "sims_grid.h5", "-o", work / "out0.h5"],
        ["reduce", "-c", cfg, "--simulations", work / "sims_box.h5", "-o", work / "out1.h5"],
        # calibrate with a surrogate made for another time grid
        ["calibrate", "-c", cfg, "--surrogate", work / "sur_grid.h5", "--observations",
         work / "fleet.h5", "-o", work / "out2.h5"],
        # forecast: the shared posterior was calibrated with surrogate.h5, not sur_seed.h5
        ["forecast", "-c", cfg, "--posterior", work / "posterior.h5", "--surrogate",
         work / "sur_seed.h5", "-o", work / "out3.h5"], cwd=work)
    assert_fails(r_grid, 5, "sims_grid.h5", "time grid", "simulate")
    assert_fails(r_box, 5, "sims_box.h5", "simulate")
    assert_fails(r_cal, 5, "sur_grid.h5", "re-run simulate and reduce")
    assert_fails(r_fc, 5, "posterior.h5", "sur_seed.h5")
    # One output each: commands side by side into one output stop at its lock (exit 8).
    assert not any(work.glob("out*.h5"))
    snap.check()
