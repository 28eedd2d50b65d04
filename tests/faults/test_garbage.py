"""Garbage in must not exit 0: implausible observations, a posterior holding absurd draws, a
config with duplicate keys, a workdir that does not exist, a negative worker count."""
from __future__ import annotations

import h5py

from .conftest import Snapshot, assert_fails, twinmon, twinmon_many


def _calibrate(work, obs):
    return ["calibrate", "-c", work / "small.yaml", "--surrogate", work / "surrogate.h5",
            "--observations", obs, "-o", work / f"new_posterior_{obs.stem}.h5"]


def test_implausible_observations_calibrate_exit_4(work):
    """One output value of 1e30; every flow negated (a sign or channel mistake)."""
    huge, negated = work / "huge.h5", work / "negated.h5"
    for path in (huge, negated):
        path.write_bytes((work / "fleet.h5").read_bytes())
    with h5py.File(huge, "a") as f:
        f["units/Park/m_flow"][1, 5] = 1e30
    with h5py.File(negated, "a") as f:
        for unit in f["units"]:
            ds = f[f"units/{unit}/m_flow"]
            ds[...] = -ds[()]
    snap = Snapshot(work)
    r_huge, r_neg = twinmon_many(_calibrate(work, huge), _calibrate(work, negated), cwd=work)
    assert_fails(r_huge, 4, "huge.h5", "/units/Park/m_flow", "1e+30")
    assert_fails(r_neg, 4, "negated.h5", "m_flow")
    # One output each: commands side by side into one output stop at its lock (exit 8).
    assert not any(work.glob("new_posterior*.h5"))
    snap.check()


def test_posterior_with_absurd_draw_forecast_exit_5(work):
    post = work / "posterior.h5"
    with h5py.File(post, "a") as f:
        ds = f["units/Monk/samples"]
        a = ds[()]
        a[2, 7, 0] = 1e30          # draws are stored in single precision
        ds[...] = a
    snap = Snapshot(work)
    r = twinmon("forecast", "-c", work / "small.yaml", "--posterior", post,
                "--surrogate", work / "surrogate.h5", "-o", work / "new_forecast.h5", cwd=work)
    line = assert_fails(r, 5, "posterior.h5", "/units/Monk/samples")
    # The value as a user writes it, not a numpy repr ("np.float64(1e+30)").
    assert "np.float64" not in line and "1e+30" in line, line
    assert not (work / "new_forecast.h5").exists()
    snap.check()


def test_duplicate_key_negative_workers_missing_workdir(work):
    cfg = work / "dup.yaml"
    cfg.write_text(f"extends: {work / 'small.yaml'}\n"
                   "simulate:\n"
                   "  train_size: 4\n"
                   "  train_size: 5\n")
    snap = Snapshot(work)
    r_dup, r_workers, r_report = twinmon_many(
        ["simulate", "-c", cfg, "-o", work / "s.h5"],
        # A negative worker count on the command line.
        ["simulate", "-c", work / "small.yaml", "-j", "-5", "-o", work / "s.h5"],
        # A workdir that does not exist: not an empty report with exit 0.
        ["report", "-c", work / "small.yaml", "--workdir", work / "no_such_folder"],
        cwd=work)
    assert_fails(r_dup, 3, "dup.yaml", "line 4", "train_size")
    assert_fails(r_workers, 3, "-5")
    assert_fails(r_report, 5, "no_such_folder")
    assert not (work / "s.h5").exists() and not (work / "no_such_folder").exists()
    snap.check()
