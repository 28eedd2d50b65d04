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
