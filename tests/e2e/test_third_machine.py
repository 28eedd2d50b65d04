"""The whole chain on the water heater of fmus/HeatTank: three degradation inputs (the pump and
the DC drive have two), a time-to-reach indicator that does not start from zero, a gap fleet
whose units are not the fleet's, in the smoke sizes of ``run --smoke``."""
from __future__ import annotations

import json
import re

from ..conftest import CONFIGS, write_yaml
from .test_cli_errors import twinmon


def test_smoke_run_of_a_three_input_machine_with_another_gap_fleet(tmp_path):
    fleet = write_yaml(tmp_path / "fleet.yaml", {"extends": str(CONFIGS / "heattank_fleet.yaml"),
                                                 "fabricate": {"years": 6}})
    gapc = write_yaml(tmp_path / "gap.yaml", {"extends": str(CONFIGS / "heattank_gap.yaml"),
                                              "fabricate": {"years": 6}})
    obs, gap = tmp_path / "fleet.h5", tmp_path / "gap_fleet.h5"
    for cfg, out in ((fleet, obs), (gapc, gap)):
        r = twinmon("fabricate", "-c", cfg, "-o", out)
        assert r.returncode == 0, r.stderr
    work = tmp_path / "work"
    r = twinmon("run", "-c", CONFIGS / "heattank.yaml", "--observations", obs,
                "--gap-observations", gap, "--workdir", work, "--smoke", "--json",
                "--set", "simulate.workers=1", "--set", "calibrate.workers=1",
                "--set", "diagnose.workers=1", "--set", "report.workers=1")
    assert r.returncode == 0, r.stderr
    summary = json.loads((work / "report" / "summary.json").read_text())
    # Birch is a unit of the gap fleet only: diagnosed, drawn, not a unit of the fleet.
    assert set(summary["units"]) == {"Ash", "Beech", "Cedar", "Dogwood"}
    assert summary["sections"]["diagnose"] == "rendered"
    html = re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "",
                  (work / "report" / "index.html").read_text())
    assert "Birch" in html and "heat-up time" in html and "water temperature" in html
    for other in ("mass flow", "t90", "m_flow", "rad/s", "settled speed", "tacho", "pump"):
        assert other not in html, other
    # (A report without the observations keeps a gap fleet's units of the fleet's names
    # out of its summary: tests/unit/test_report.py.)
