"""Every stage on a machine that is not the pump: the DC drive of fmus/DCDrive, whose health
indicator is a settled speed (a window mean, unsafe below a level), not a rise time; and the
same model as an FMI 3.0 FMU (fmus/DCDrive3) through simulate and reduce."""
from __future__ import annotations

import json
import re

import h5py
import numpy as np
import pytest

from ..conftest import CONFIGS, write_yaml
from .test_cli_errors import twinmon

SMALL = {
    "simulate": {"train_size": 40, "test_size": 8},
    "calibrate": {"chains": 2, "samples": 300, "burn_in": 100, "ess_warn": 100.0, "max_extensions": 1},
    "forecast": {"samples": 200, "observed_samples": 40, "horizon": 5},
}


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dcdrive")
    cfg = write_yaml(tmp / "drive.yaml", {"extends": str(CONFIGS / "dcdrive_fleet.yaml"),
                                          **SMALL, "fabricate": {"years": 6}})
    gap = write_yaml(tmp / "gap.yaml", {"extends": str(CONFIGS / "dcdrive_gap.yaml"),
                                        **SMALL, "fabricate": {"years": 6}})
    return tmp, cfg, gap


def run_json(*args):
    r = twinmon(*args, "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_every_stage_runs_on_the_dc_drive(drive):
    tmp, cfg, gap_cfg = drive
    obs, truth = tmp / "fleet.h5", tmp / "fleet_truth.h5"
    fab = run_json("fabricate", "-c", cfg, "-o", obs, "--truth", truth)
    assert fab["units"] == 3 and fab["years"] == 6
    with h5py.File(obs) as f:                      # the config's channel name and units
        assert f.attrs["output"] == "speed" and f["units/Alder/speed"].attrs["units"] == "rad/s"
    sim = run_json("simulate", "-c", cfg, "-o", tmp / "simulations.h5")
    assert sim["runs"] == 48 and sim["failures"] == 0 and not sim["warnings"]
    red = run_json("reduce", "-c", cfg, "--simulations", tmp / "simulations.h5",
                   "-o", tmp / "surrogate.h5")
    # Accuracy in the output's own scale: a fraction of its range over the test runs.
    assert red["test"]["max_range_error"] < 0.02 and red["test"]["output_range"] > 100
    cal = run_json("calibrate", "-c", cfg, "--surrogate", tmp / "surrogate.h5",
                   "--observations", obs, "--truth", truth, "-o", tmp / "posterior.h5")
    assert set(cal["units"]) == {"Alder", "Birch", "Cedar"}
    assert cal["truth_check"]["winding_resistance"]["mean_rel_error"] < 0.03
    fc = run_json("forecast", "-c", cfg, "--posterior", tmp / "posterior.h5",
                  "--surrogate", tmp / "surrogate.h5", "--truth", truth,
                  "-o", tmp / "forecast.h5")
    causes = {u: f["root_cause"] for u, f in fc["units"].items()}
    # Six years are enough to see the fast faults; the words are the config's components.
    assert causes["Birch"] == "bearing" and causes["Cedar"] == "winding"
    assert causes["Alder"] == "healthy"
    for f in fc["units"].values():
        assert set(f["indicator"]) == {"median", "q05", "q95"}
        # The settled speed falls as the drive degrades: the median never rises much.
        med = [m for m in f["indicator"]["median"] if m is not None]
        assert np.all(np.diff(med) < 2.0)
    with h5py.File(tmp / "forecast.h5") as f:
        ind = json.loads(f.attrs["indicator"])
        assert ind == {"name": "settled speed", "label": "mean shaft speed over 2-3 s",
                       "units": "rad/s", "limit": 250.0, "sense": -1, "variable": "tacho.w",
                       "kind": "mean"}
    gobs = tmp / "gap_fleet.h5"
    run_json("fabricate", "-c", gap_cfg, "-o", gobs, "--truth", tmp / "gap_truth.h5")
    r = twinmon("diagnose", "-c", gap_cfg, "--observations", gobs, "-o", tmp / "gap.h5",
                "--json")
    assert r.returncode == 0, r.stderr
    gap = json.loads(r.stdout)
    verdicts = {u: g["verdict"] for u, g in gap["units"].items()}
    assert set(verdicts.values()) <= {"none", "effect", "unexplained"}
    # On the speed alone the plateau-type effects are taken up by the degradation inputs:
    # every unit says so, with the channel to record; the command says it once for all.
    hidden = {u: g["hidden"] for u, g in gap["units"].items()}
    assert all("load.extra" in h and "supply.ratio" in h for h in hidden.values()), hidden
    said = [x for x in r.stderr.splitlines() if x.startswith("every unit: hidden (")]
    assert len(said) == 1 and "load.extra" in said[0] and "supply.ratio" in said[0]
    assert "recording armature.i would show" in said[0]
    with h5py.File(tmp / "gap.h5") as f:
        names = [n.decode() if isinstance(n, bytes) else n for n in f["windows/names"][()]]
        assert names == ["current rise", "acceleration", "settled"]
    rep = twinmon("report", "-c", cfg, "--workdir", tmp, "--observations", obs,
                  "--truth", truth, "-o", tmp / "report")
    assert rep.returncode == 0, rep.stderr
    html = (tmp / "report" / "index.html").read_text()
    html = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "", html)   # words only
    assert "rad/s" in html and "settled speed" in html
    # The diagnose section's table: each unit of the gap fleet with its hidden candidates.
    table = html[html.index("Its group (posterior weight)"):]
    table = table[:table.index("</table>")]
    for u in gap["units"]:
        assert f">{u}</td>" in table
    assert table.count("<code>load.extra</code>") == len(gap["units"])
    assert "recording <code>armature.i</code> would show them" in table
    for pump_word in ("kg/s", "mass flow", "t90", "m_flow"):
        assert pump_word not in html, pump_word


def test_auto_samples_a_pooling_fleet_jointly_on_the_dc_drive(drive):
    """calibrate.method auto on another machine: with forecast.pool_min_units 3 the drive's
    three units are a fleet, calibrated with the joint model (the laplace method); forecast pools their year-to-year sd, in the
    config's names, and finds the faults the sequential method finds."""
    tmp, cfg, _ = drive
    obs, truth, sur = tmp / "fleet.h5", tmp / "fleet_truth.h5", tmp / "surrogate.h5"
    if not obs.exists():
        run_json("fabricate", "-c", cfg, "-o", obs, "--truth", truth)
    if not sur.exists():
        run_json("simulate", "-c", cfg, "-o", tmp / "simulations.h5")
        run_json("reduce", "-c", cfg, "--simulations", tmp / "simulations.h5", "-o", sur)
    # Six years of record: the shapes' prior learns from segments of 6 years here (the
    # default asks for 8, where a record can show a shape).
    pool = ("--set", "forecast.pool_min_units=3", "--set", "forecast.pool_shapes_min_years=6")
    cal = run_json("calibrate", "-c", cfg, *pool, "--surrogate", sur, "--observations", obs,
                   "-o", tmp / "joint.h5")
    assert cal["method"] == "laplace"
    assert cal["method_reason"] == ("calibrate.method auto: laplace, 3 units >= "
                                    "forecast.pool_min_units 3 share a pooled year-to-year sd")
    with h5py.File(tmp / "joint.h5") as f:
        assert f.attrs["method"] == "laplace" and "trend" in f["units/Birch"]
    fc = run_json("forecast", "-c", cfg, *pool, "--posterior", tmp / "joint.h5",
                  "--surrogate", sur, "-o", tmp / "joint_forecast.h5")
    pooling = fc["sigma_pooling"]
    assert pooling["pooled"] and pooling["units"] == 3
    assert set(pooling["median"]) == {"bearing_friction", "winding_resistance"}
    # The trend shapes' prior is the fleet's too, over the forms the laplace method weighs.
    shaped = fc["shape_pooling"]
    assert shaped["pooled"] and shaped["units"] == 3
    assert abs(sum(shaped["fleet"].values()) - 1) < 1e-3 and "quadratic" in shaped["fleet"]
    causes = {u: f["root_cause"] for u, f in fc["units"].items()}
    assert causes == {"Alder": "healthy", "Birch": "bearing", "Cedar": "winding"}


@pytest.mark.parametrize("fmi_type, executor", [("CoSimulation", "process"),
                                                ("CoSimulation", "serial"),
                                                ("ModelExchange", "process")])
def test_fmi3_fmu_simulates_like_the_fmi2_build(tmp_path, fmi_type, executor):
    """The FMI 3.0 build of the same model gives the same design results as the FMI 2.0 one,
    under either executor."""
    n = {"CoSimulation": 24, "ModelExchange": 4}[fmi_type]
    base = {"extends": str(CONFIGS / "dcdrive.yaml"),
            "simulate": {"train_size": n, "test_size": 0, "executor": executor, "workers": 2}}
    two = write_yaml(tmp_path / "fmi2.yaml", base)
    three = write_yaml(tmp_path / "fmi3.yaml", {**base, "model": {
        "fmu": str(CONFIGS.parent / "fmus" / "DCDrive3"), "fmi_type": fmi_type}})
    run_json("simulate", "-c", two, "-o", tmp_path / "s2.h5")
    run_json("simulate", "-c", three, "-o", tmp_path / "s3.h5")
    with h5py.File(tmp_path / "s2.h5") as a, h5py.File(tmp_path / "s3.h5") as b:
        np.testing.assert_allclose(b["train/Y"][()], a["train/Y"][()],
                                   rtol=1e-9 if fmi_type == "CoSimulation" else 1e-4)
        # 'stalled' is an Int32 output in the FMI 3 build: read, and equal.
        assert np.array_equal(a["train/nonphysical"][()], b["train/nonphysical"][()])
