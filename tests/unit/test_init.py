"""Tests of twinmon.init and ``twinmon init``: a starter config from an FMU's model description."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from twinmon.config import load_config
from twinmon.errors import ConfigError, SimulationError
from twinmon.fmu import build_fmu, describe_fmu
from twinmon.init import FILL, starter_config, write_starter_config

ROOT = Path(__file__).resolve().parents[2]
DCDRIVE = ROOT / "fmus" / "DCDrive"
DCDRIVE3 = ROOT / "fmus" / "DCDrive3"
PUMP = ROOT / "fmus" / "PumpCircuit"


@pytest.fixture(scope="module", params=["dcdrive", "dcdrive3", "pump"])
def fmu(request) -> Path:
    """Each shipped FMU, as a built .fmu file."""
    return build_fmu({"dcdrive": DCDRIVE, "dcdrive3": DCDRIVE3, "pump": PUMP}[request.param])


def test_starter_parses_and_names_everything(fmu, tmp_path):
    out = write_starter_config(fmu, tmp_path / "my.yaml")
    text = out.read_text()
    data = yaml.safe_load(text)
    assert (tmp_path / data["model"]["fmu"]).resolve() == fmu.resolve()   # relative to the YAML
    info = describe_fmu(fmu)
    assert data["model"]["fmi_type"] == "CoSimulation"
    for v in info.tunable_parameters():                      # candidate inputs and effects
        assert re.search(rf"#\s+variable: {re.escape(v.name)}$", text, re.M), v.name
        assert re.search(rf"#\s+{re.escape(v.name)}: \{{baseline: ", text), v.name
    for v in info.recordable():                              # candidates for output/channels
        assert re.search(rf"#\s+{re.escape(v.name)}\s+{v.type}\s", text), v.name
    assert FILL in text
    # until filled in, loading fails with one line naming the first missing key
    with pytest.raises(ConfigError, match="model.inputs: required key is missing") as e:
        load_config(out)
    assert "\n" not in str(e.value)


def _fill(text: str, inputs: dict, output: str, kind_lines: list[str], unsafe: str) -> str:
    """What a user does: uncomment `inputs:` and some candidates, give the box, the output,
    the indicator and its limit."""
    lines = text.splitlines()
    out, block = [], None
    for ln in lines:
        m = re.match(r"^  #   (\w+):$", ln)
        if ln == "  # inputs:":
            out.append("  inputs:")
            continue
        if m:
            block = m.group(1) if m.group(1) in inputs else None
            if block:
                out.append(f"    {block}:")
            continue
        if block and ln.startswith("  #     "):
            body = ln[len("  #     "):]
            key = body.split(":")[0]
            if key in inputs[block]:
                body = f"{key}: {inputs[block][key]}"
            if not body.startswith("#"):
                out.append("      " + body)
            continue
        block = None
        if ln.startswith("    # variable: "):
            out.append(f"    variable: {output}")
            continue
        if ln.startswith("    # kind: "):
            out.extend(kind_lines)
            continue
        if ln.startswith("  # unsafe_if: "):
            out.append(f"  unsafe_if: {unsafe}")
            continue
        out.append(ln)
    return "\n".join(out) + "\n"


def test_filled_starter_loads(tmp_path):
    """The DC drive starter, filled in as configs/dcdrive.yaml is, loads."""
    out = write_starter_config(DCDRIVE, tmp_path / "dc.yaml")
    filled = _fill(out.read_text(),
                   {"bearing_b": {"low": "0.0005", "high": "0.006",
                                  "normal_rate_tolerance": "5.0e-5"},
                    "winding_r": {"low": "0.6", "high": "3.5",
                                  "normal_rate_tolerance": "0.008"}},
                   "tacho.w", ["    kind: mean", "    window: [2.0, 3.0]"], "{below: 250.0}")
    assert FILL not in re.sub(r"(?m)^\s*#.*$", "", filled)      # only comments keep it
    (tmp_path / "dc.yaml").write_text(filled)
    cfg = load_config(tmp_path / "dc.yaml")
    assert [s.variable for s in cfg.model.inputs.values()] == ["bearing.b", "winding.R"]
    assert cfg.model.inputs["bearing_b"].nominal == 0.001
    assert cfg.model.inputs["winding_r"].units == "Ohm"
    assert cfg.model.output.variable == "tacho.w"
    assert cfg.safety.indicator.kind == "mean" and cfg.safety.unsafe_if.below == 250.0
    assert Path(cfg.model.fmu).resolve() == DCDRIVE.resolve()


def test_source_folder_and_relative_path(tmp_path):
    (tmp_path / "configs").mkdir()
    text = starter_config(PUMP, base_dir=ROOT / "configs")
    data = yaml.safe_load(text)
    assert data["model"]["fmu"] == "../fmus/PumpCircuit"
    assert "motor.D" in text and "pump.b2" in text and "sensor.m_flow" in text
    assert data["model"]["output"]["times"] == {"start": 0.5, "stop": 50.0, "step": 0.5}


def test_refuses_to_overwrite(tmp_path):
    out = tmp_path / "my.yaml"
    out.write_text("keep me\n")
    with pytest.raises(ConfigError, match="already exists.*--force"):
        write_starter_config(DCDRIVE, out)
    assert out.read_text() == "keep me\n"
    write_starter_config(DCDRIVE, out, force=True)
    assert "bearing.b" in out.read_text()


def test_bad_fmu_is_one_line(tmp_path):
    bad = tmp_path / "bad.fmu"
    bad.write_bytes(b"")
    with pytest.raises(SimulationError, match="bad.fmu") as e:
        starter_config(bad)
    assert "\n" not in str(e.value)


def test_cli_init(tmp_path, monkeypatch):
    from twinmon.cli import main
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    r = runner.invoke(main, ["init", str(DCDRIVE3), "-o", "dc3.yaml", "--json"])
    assert r.exit_code == 0, r.output
    assert "dc3.yaml" in r.output and "winding.R" in r.output
    # Written relative to the YAML's folder when they share more than the root.
    fmu = yaml.safe_load((tmp_path / "dc3.yaml").read_text())["model"]["fmu"]
    assert (tmp_path / fmu).resolve() == DCDRIVE3.resolve()
    r = runner.invoke(main, ["init", str(DCDRIVE3), "-o", "dc3.yaml"])
    assert r.exit_code == 3 and "already exists" in r.output
    r = runner.invoke(main, ["init", str(DCDRIVE3), "-o", "dc3.yaml", "--force"])
    assert r.exit_code == 0
    r = runner.invoke(main, ["init", str(DCDRIVE3)])                  # default name
    assert r.exit_code == 0 and (tmp_path / "DCDrive3.yaml").is_file()
    r = runner.invoke(main, ["init", "nowhere.fmu"])
    assert r.exit_code == 6 and "nowhere.fmu" in r.output


def test_a_placeholder_left_anywhere_stops_the_load(tmp_path):
    """The DC drive starter filled in except the output's units: `init` wrote them as
    "<fill in>" (the FMU's first output declares none here), uncommented. Loading must fail
    naming that key, not go on to a report that prints "(channel x, <fill in>)"."""
    out = write_starter_config(DCDRIVE, tmp_path / "dc.yaml")
    filled = _fill(out.read_text(),
                   {"bearing_b": {"low": "0.0005", "high": "0.006",
                                  "normal_rate_tolerance": "5.0e-5"}},
                   "tacho.w", ["    kind: mean", "    window: [2.0, 3.0]"], "{below: 250.0}")
    assert re.search(r"(?m)^    units: \"rad/s\"$", filled)
    (tmp_path / "dc.yaml").write_text(filled.replace('    units: "rad/s"',
                                                     f'    units: "{FILL}"'))
    with pytest.raises(ConfigError, match=r"dc.yaml: model.output.units: still '<fill in>'"
                                          r", the placeholder `twinmon init` wrote") as e:
        load_config(tmp_path / "dc.yaml")
    assert e.value.exit_code == 3 and "\n" not in str(e.value)
    # any type of key, inside lists and as a mapping key too
    (tmp_path / "dc.yaml").write_text(filled)
    for override, where in ((f"safety.indicator.window=[2.0, '{FILL}']",
                             "safety.indicator.window.1"),
                            (f"model.channels={{'{FILL}': {{}}}}", f"model.channels.{FILL}"),
                            (f"safety.indicator.label='{FILL}'", "safety.indicator.label")):
        with pytest.raises(ConfigError, match=re.escape(where)):
            load_config(tmp_path / "dc.yaml", [override])


def test_start_values_are_listed_as_candidate_effects(tmp_path):
    """The DC drive's states declare initial="exact" and a start: candidate effects (a
    machine not starting from rest), listed after the parameters."""
    text = write_starter_config(DCDRIVE, tmp_path / "dc.yaml").read_text()
    for name in ("state.i", "state.w", "tacho.y"):
        assert re.search(rf"(?m)^  #   {re.escape(name)}: \{{baseline: 0.0, ", text), name
    assert not re.search(r"(?m)^  #   der\(state.w\): \{baseline", text)
