"""The CLI on bad input: one line on stderr naming file, place and value; a distinct exit code
per error family; nothing already written is lost."""
from __future__ import annotations

import subprocess
import sys

import h5py
import pytest

from twinmon.artifacts import file_sha256

from ..conftest import CONFIGS, write_yaml


def twinmon(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "twinmon", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def one_line(stderr: str) -> str:
    lines = [l for l in stderr.splitlines() if l.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


def test_malformed_yaml_exit_3(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("model: [1, 2\n")
    r = twinmon("simulate", "-c", bad, "-o", tmp_path / "s.h5")
    assert r.returncode == 3
    line = one_line(r.stderr)
    assert line.startswith("twinmon: config error:") and "bad.yaml" in line and "line" in line


def test_unknown_key_exit_3(tmp_path):
    r = twinmon("simulate", "-c", CONFIGS / "pump.yaml", "--set", "simulate.trainsize=3",
                "-o", tmp_path / "s.h5")
    assert r.returncode == 3
    assert "pump.yaml: simulate.trainsize: unknown key (value 3)" in one_line(r.stderr)


def test_bad_csv_exit_4(tmp_path):
    csv = tmp_path / "m.csv"
    csv.write_text("unit,year,time,m_flow\nA,1,2,nan-ish\n")
    r = twinmon("import-csv", csv, "-c", CONFIGS / "pump.yaml", "-o", tmp_path / "o.h5")
    assert r.returncode == 4
    assert "m.csv: line 2: column 'm_flow' is 'nan-ish'" in one_line(r.stderr)


def test_missing_and_wrong_schema_artifact_exit_5(tmp_path):
    r = twinmon("reduce", "-c", CONFIGS / "pump.yaml", "--simulations", tmp_path / "none.h5",
                "-o", tmp_path / "s.h5")
    assert r.returncode == 5
    assert "none.h5: file not found" in one_line(r.stderr)
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as f:
        f.attrs["schema"] = "twinmon.posterior/1"
    r = twinmon("reduce", "-c", CONFIGS / "pump.yaml", "--simulations", wrong,
                "-o", tmp_path / "s.h5")
    assert r.returncode == 5
    assert ("wrong.h5: schema is 'twinmon.posterior/1', expected 'twinmon.simulations/1'"
            in one_line(r.stderr))


def test_fmu_that_cannot_be_built_exit_6(tmp_path):
    src = tmp_path / "Broken"
    (src / "sources").mkdir(parents=True)
    (src / "modelDescription.xml").write_text(
        (CONFIGS.parent / "fmus" / "PumpCircuit" / "modelDescription.xml").read_text())
    (src / "sources" / "model.c").write_text("this is not C;\n")
    r = twinmon("build-fmu", src)
    assert r.returncode == 6
    assert str(src) in one_line(r.stderr)


def test_failed_stage_keeps_previous_artifact(tmp_path, fmu_path):
    cfg = write_yaml(tmp_path / "c.yaml", {"extends": str(CONFIGS / "pump.yaml"),
                                           "simulate": {"train_size": 8, "test_size": 0}})
    out = tmp_path / "s.h5"
    assert twinmon("simulate", "-c", cfg, "-o", out).returncode == 0
    before = file_sha256(out)
    r = twinmon("simulate", "-c", cfg, "--set", "simulate.train_size=-1", "-o", out)
    assert r.returncode == 3
    assert file_sha256(out) == before


def test_verbose_shows_traceback_and_json_is_clean(tmp_path, fmu_path):
    r = twinmon("-v", "simulate", "-c", CONFIGS / "pump.yaml", "--set", "seed=x",
                "-o", tmp_path / "s.h5")
    assert r.returncode == 3 and "Traceback" in r.stderr
    cfg = write_yaml(tmp_path / "c.yaml", {"extends": str(CONFIGS / "pump.yaml"),
                                           "simulate": {"train_size": 8, "test_size": 2}})
    r = twinmon("simulate", "-c", cfg, "-o", tmp_path / "s.h5", "--json")
    assert r.returncode == 0
    import json
    summary = json.loads(r.stdout)
    assert summary["runs"] == 10 and summary["failures"] == 0 and summary["runs_per_s"] > 0


def test_an_openturns_interruption_is_a_ctrl_c(monkeypatch):
    """OpenTURNS catches a Ctrl-C that arrives inside its C++ with a handler of its own and
    raises "Interruption in OT::..."; that came out as a traceback and exit 1. Another
    RuntimeError is still a bug, not an interrupt."""
    from click.testing import CliRunner

    import twinmon.check
    from twinmon.cli import main

    def interrupted(*args, **kwargs):
        raise RuntimeError("Interruption in OT::Function::operator ()(OT::Sample const &) "
                           "const")
    monkeypatch.setattr(twinmon.check, "check", interrupted)
    r = CliRunner().invoke(main, ["check", "-c", str(CONFIGS / "pump.yaml")])
    assert r.exit_code == 130 and "twinmon: interrupted" in r.output

    def broken(*args, **kwargs):
        raise RuntimeError("something else")
    monkeypatch.setattr(twinmon.check, "check", broken)
    r = CliRunner().invoke(main, ["check", "-c", str(CONFIGS / "pump.yaml")])
    assert isinstance(r.exception, RuntimeError) and r.exit_code not in (0, 130)
