"""The CLI chained stage by stage on a small config, then `twinmon run` skipping what is
up to date and re-running what changed."""
from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from ..conftest import CONFIGS, first_years, write_yaml
from .test_cli_errors import twinmon


@pytest.fixture(scope="module")
def small(tmp_path_factory, fmu_path):
    tmp = tmp_path_factory.mktemp("e2e")
    cfg = write_yaml(tmp / "small.yaml", {
        "extends": str(CONFIGS / "fleet.yaml"),
        "simulate": {"train_size": 48, "test_size": 8},
        "calibrate": {"chains": 2, "samples": 300, "burn_in": 100, "ess_warn": 100.0, "max_extensions": 1},
        "forecast": {"samples": 300, "horizon": 4},
        "fabricate": {"years": 5},
    })
    return tmp, cfg


def run_json(*args):
    r = twinmon(*args, "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def chained(small):
    """Every stage by hand through the CLI into the module's folder (each stage's JSON
    summary by name); the later tests run ``twinmon run`` on what it made."""
    tmp, cfg = small
    obs, truth = tmp / "fleet.h5", tmp / "fleet_truth.h5"
    out = {"fabricate": run_json("fabricate", "-c", cfg, "-o", obs, "--truth", truth),
           "simulate": run_json("simulate", "-c", cfg, "-o", tmp / "simulations.h5"),
           "reduce": run_json("reduce", "-c", cfg, "--simulations", tmp / "simulations.h5",
                              "-o", tmp / "surrogate.h5"),
           "calibrate": run_json("calibrate", "-c", cfg, "--surrogate", tmp / "surrogate.h5",
                                 "--observations", obs, "-o", tmp / "posterior.h5"),
           "forecast": run_json("forecast", "-c", cfg, "--posterior", tmp / "posterior.h5",
                                "--surrogate", tmp / "surrogate.h5", "-o",
                                tmp / "forecast.h5"),
           # back-test on the user's own history (no truth): cuts at years 3 and 4
           # (min_years 3)
           "backtest": run_json("backtest", "-c", cfg, "--set", "backtest.min_years=3",
                                "--posterior", tmp / "posterior.h5", "--surrogate",
                                tmp / "surrogate.h5", "-o", tmp / "backtest.h5"),
           "diagnose": run_json("diagnose", "-c", cfg, "--observations", obs, "-o",
                                tmp / "gap.h5")}
    rep = twinmon("report", "-c", cfg, "--workdir", tmp, "--observations", obs,
                  "--truth", truth, "-o", tmp / "report")
    assert rep.returncode == 0, rep.stderr
    return out


def test_stages_chain_through_the_cli(small, chained):
    tmp, cfg = small
    fab = chained["fabricate"]
    assert fab["units"] == 3 and fab["years"] == 5
    sim = chained["simulate"]
    assert sim["runs"] == 56 and sim["failures"] == 0
    red = chained["reduce"]
    assert red["modes"] >= 2 and 0.99 < red["variance_ratio"] <= 1
    assert red["test"]["max_rel_error"] < 0.05 and len(red["test"]["q2"]) == red["modes"]
    cal = chained["calibrate"]
    assert set(cal["units"]) == {"Park", "Colt", "Monk"}
    colt = cal["units"]["Colt"]
    assert colt["years"] == [1, 2, 3, 4, 5]
    for p in ("motor_damping", "pump_coef"):
        q = colt["params"][p]
        assert all(a <= m <= b for a, m, b in zip(q["q05"], q["median"], q["q95"]))
    fc = chained["forecast"]
    for u in ("Park", "Colt", "Monk"):
        f = fc["units"][u]
        assert f["root_cause"] in ("healthy", "pump", "motor", "both", "ambiguous")
        assert f["years"] == [6, 7, 8, 9] and len(f["p_unsafe"]) == 4
        assert all(0 <= p <= 1 for p in f["p_unsafe"])
        assert f["detection"]["abnormal"] == (f["root_cause"] != "healthy")
    bt = chained["backtest"]
    assert bt["units"]["Colt"]["cuts"] == [3, 4]
    # cut 3 sees years 4, 5; cut 4 sees year 5: three later observations per unit
    assert bt["pairs"] == 9 and 0 <= bt["coverage"] <= 1
    # The coverage is judged against its band, and the judgement is in the JSON and the file.
    from twinmon.backtest import coverage_verdict, read_backtest
    assert bt["coverage_band"] == [0.85, 0.95]
    assert bt["coverage_in_band"] == coverage_verdict(bt["coverage"], 9, 0.9, 0.05)[0]
    assert read_backtest(tmp / "backtest.h5").coverage_in_band == bt["coverage_in_band"]
    # ... and per record length: cut 3 (3 recorded years) has 2 later years a unit, cut 4 one.
    by = bt["coverage_by_record"]
    assert set(by) == {"3", "4"} and by["3"]["pairs"] == 6 and by["4"]["pairs"] == 3
    back = read_backtest(tmp / "backtest.h5")
    assert back.n_pairs == 9
    assert {str(n): v["pairs"] for n, v in back.by_record.items()} == {"3": 6, "4": 3}
    assert all(back.by_record[int(n)]["in_band"] == v["in_band"] for n, v in by.items())
    gap = chained["diagnose"]
    assert {u["verdict"] for u in gap["units"].values()} <= {"none", "effect", "unexplained"}
    html = (tmp / "report" / "index.html").read_text()
    assert "data:image/png;base64," in html and 'src="http' not in html
    summary = json.loads((tmp / "report" / "summary.json").read_text())
    assert set(summary["units"]) == {"Park", "Colt", "Monk"}
    # every artifact says what made it
    for name in ("simulations", "surrogate", "posterior", "forecast", "gap"):
        with h5py.File(tmp / f"{name}.h5") as f:
            assert f.attrs["schema"].startswith("twinmon.")
            assert f.attrs["config"] and f.attrs["twinmon_version"]
            assert json.loads(f.attrs["inputs"])


@pytest.fixture(scope="module")
def run_dir(small, chained):
    """A workdir holding copies of the hand-made stages' artifacts (``twinmon run`` takes
    them for its own: their records name the same config and inputs)."""
    import shutil
    tmp, _ = small
    wd = tmp / "run"
    wd.mkdir()
    for name in ("simulations", "surrogate", "posterior", "forecast", "gap"):
        shutil.copy2(tmp / f"{name}.h5", wd)
    return wd


def test_run_skips_up_to_date_stages_and_reruns_changed_ones(small, run_dir):
    tmp, cfg = small
    obs = tmp / "fleet.h5"
    # A forecast-only change re-runs forecast and the report; the stages made by hand
    # upstream of it are taken as up to date (the same config and inputs).
    changed = run_json("run", "-c", cfg, "--set", "forecast.horizon=3", "--observations", obs,
                       "--workdir", run_dir)
    ran = [s["stage"] for s in changed["stages"] if not s["skipped"]]
    assert ran == ["forecast", "report"]
    assert (run_dir / "report" / "index.html").exists()
    # Nothing changed: the report too is up to date, and run prints what it said.
    again = twinmon("run", "-c", cfg, "--set", "forecast.horizon=3", "--observations", obs,
                    "--workdir", run_dir)
    assert again.returncode == 0, again.stderr
    assert "report: up to date" in again.stderr
    said = json.loads((run_dir / "report" / "summary.json").read_text())["terminal"]
    assert said.splitlines()[0] in again.stderr and "Colt" in said


def test_run_update_diagnoses_only_the_new_years(small, run_dir):
    """`run --update` hands --update to diagnose: with gap.h5 of the first 4 years in the
    workdir (the other stages up to date), only year 5 is fitted and screened."""
    tmp, cfg = small
    obs = tmp / "fleet.h5"
    obs4 = first_years(obs, tmp / "fleet4.h5", 4)
    # The workdir and settings of the test above: its stages are up to date.
    common = ["-c", cfg, "--set", "forecast.horizon=3", "--observations", obs,
              "--workdir", run_dir]
    run_json("diagnose", "-c", cfg, "--observations", obs4, "-o", run_dir / "gap.h5")
    upd = run_json("run", *common, "--update")
    stages = {s["stage"]: s for s in upd["stages"]}
    assert [n for n, s in stages.items() if not s["skipped"]] == ["diagnose", "report"]
    u = stages["diagnose"]["summary"]["update"]
    n_units = len(stages["diagnose"]["summary"]["units"])
    assert (u["kept_years"], u["new_years"]) == (4 * n_units, n_units)


def test_same_seed_same_posterior(small, chained, tmp_path):
    """calibrate again with the same inputs and seed: the chained run's draws, bit for bit."""
    tmp, cfg = small
    run_json("calibrate", "-c", cfg, "--surrogate", tmp / "surrogate.h5",
             "--observations", tmp / "fleet.h5", "-o", tmp_path / "again.h5")
    with h5py.File(tmp / "posterior.h5") as a, h5py.File(tmp_path / "again.h5") as b:
        assert set(a["units"]) == set(b["units"]) == {"Park", "Colt", "Monk"}
        for u in a["units"]:
            assert np.array_equal(a[f"units/{u}/samples"][()], b[f"units/{u}/samples"][()])
