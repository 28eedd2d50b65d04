"""What a new user meets in the first hour with their own FMU and in CI, on a machine that
is not the pump (the DC drive of fmus/DCDrive): diagnose without candidate effects."""
from __future__ import annotations

import json

from ..conftest import CONFIGS, write_yaml
from .test_cli_errors import twinmon


def test_diagnose_without_candidate_effects_says_how_to_add_them(tmp_path):
    """model.effects empty: diagnose still locates the lagging tachometer's gap, says there
    is nothing to test and how to add candidates; the report draws no empty ranking."""
    cfg = write_yaml(tmp_path / "gap.yaml", {"extends": str(CONFIGS / "dcdrive_gap.yaml"),
                                             "fabricate": {"years": 8}})
    obs = tmp_path / "gap_fleet.h5"
    r = twinmon("fabricate", "-c", cfg, "-o", obs, "--truth", tmp_path / "truth.h5")
    assert r.returncode == 0, r.stderr
    none = ["--set", "model.effects={}"]
    r = twinmon("diagnose", "-c", cfg, *none, "--observations", obs, "-o", tmp_path / "gap.h5",
                "-j", "1")
    assert r.returncode == 0, r.stderr
    assert "best candidate -" not in r.stderr and "would close only" not in r.stderr
    assert "warning: no candidate effects to test (model.effects in gap.yaml is empty)" \
        in r.stderr
    birch = next(ln for ln in r.stderr.splitlines() if ln.startswith("Birch:"))
    assert "UNEXPLAINED" in birch and "model.effects" in birch and "{baseline:" in birch
    r = twinmon("report", "-c", cfg, *none, "--observations", obs, "--gap", tmp_path / "gap.h5",
                "-o", tmp_path / "report", "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    names = {f["name"] for f in s["figures"]}
    assert "diag_candidates" not in names and "diag_residual_map" in names, names
    assert any("could not name it: no candidate effects to test" in n for n in s["notes"])


def test_smoke_run_then_check_on_the_dc_drive(tmp_path):
    """run --smoke runs every stage on the DC drive fleet (its time printed, not judged: a
    test checks what is right, benchmarks what is fast); its --json is strict; check
    passes on the workdir it leaves, and fails (exit 5, one line) once the surrogate beside
    the posterior is not the one it was calibrated with."""
    import time

    from ..unit.test_jsontext import strict_loads
    cfg = write_yaml(tmp_path / "fleet.yaml", {
        "extends": str(CONFIGS / "dcdrive_fleet.yaml"), "fabricate": {"years": 6}})
    obs, wd = tmp_path / "fleet.h5", tmp_path / "out"
    r = twinmon("fabricate", "-c", cfg, "-o", obs, "--truth", tmp_path / "truth.h5")
    assert r.returncode == 0, r.stderr
    start = time.perf_counter()
    r = twinmon("run", "-c", cfg, "--observations", obs, "--workdir", wd, "--smoke", "--json")
    seconds = time.perf_counter() - start
    assert r.returncode == 0, r.stderr
    out = strict_loads(r.stdout)
    assert [s["stage"] for s in out["stages"]] == [
        "simulate", "reduce", "calibrate", "forecast", "diagnose", "report"]
    assert not any(s["skipped"] for s in out["stages"])
    assert "run --smoke: small sizes (simulate.train_size=24" in r.stderr
    sims = out["stages"][0]["summary"]
    assert sims["runs"] == 30                                   # 24 + 6: the smoke sizes
    assert (wd / "report" / "index.html").is_file()
    print(f"\nrun --smoke on the DC drive: {seconds:.1f} s")

    r = twinmon("check", "-c", cfg, "--observations", obs, "--workdir", wd, "--json")
    assert r.returncode == 0, r.stderr
    res = strict_loads(r.stdout)
    assert res["ok"] and "5 artifact(s) read" in " ".join(res["checked"])
    # the smoke run's artifacts were made with other settings than the full config's
    assert any("will redo simulate" in w for w in res["warnings"])
    r = twinmon("check", "-c", cfg, "--smoke", "--workdir", wd, "--json")   # its own sizes
    assert r.returncode == 0 and not strict_loads(r.stdout)["warnings"], r.stdout
    # another surrogate beside the posterior: the posterior no longer belongs to it
    r = twinmon("reduce", "-c", cfg, "--set", "reduce.max_modes=3", "--simulations",
                wd / "simulations.h5", "-o", wd / "surrogate.h5")
    assert r.returncode == 0, r.stderr
    r = twinmon("check", "-c", cfg, "--workdir", wd)
    assert r.returncode == 5, r.stderr
    problems = [ln for ln in r.stderr.splitlines() if ln.startswith("twinmon: artifact error")]
    assert problems and "posterior.h5: made from another surrogate.h5" in problems[0]
