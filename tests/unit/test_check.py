"""Tests of twinmon.check (``twinmon check``): the CI smoke check of a config, its FMU,
observations and a workdir, in seconds."""
from __future__ import annotations

import json

import pytest

from twinmon.check import box_points, check
from twinmon.config import load_config

from ..conftest import CONFIGS, write_yaml
from ..e2e.test_cli_errors import twinmon

SHIPPED = sorted(CONFIGS.glob("*.yaml"))


@pytest.mark.parametrize("config", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_every_shipped_config_passes_in_seconds(config):
    res = check(config)
    assert res.ok, [p.message for p in res.problems]
    assert res.exit_code == 0 and res.seconds <= 10.0
    # the limit is reachable in each shipped box: no warning about it
    assert not [w for w in res.warnings if "reached nowhere" in w], res.warnings
    # and every unit the config states is the one its FMU declares
    assert not [w for w in res.warnings if " declares " in w], res.warnings


def test_a_unit_other_than_the_fmus_is_a_warning(tmp_path):
    """The report labels values with the config's units: a channel in W whose FMU
    declares kW would be off by a thousand, silently. Another spelling is not flagged."""
    cfg = write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"output": {"units": "rpm"},
                  "inputs": {"bearing_friction": {"units": "N*m*s/rad"}}}})
    res = check(cfg)
    assert res.ok
    bad = [w for w in res.warnings if " declares " in w]
    assert len(bad) == 1, res.warnings
    assert "dc.yaml: model.output.units: 'rpm', but DCDrive.fmu declares 'rad/s' for " \
        "tacho.w" in bad[0]


def test_box_points_are_the_nominal_point_and_the_corners():
    cfg = load_config(CONFIGS / "dcdrive.yaml")
    pts = box_points(cfg)
    assert pts[0] == ("nominal point", {"bearing_friction": 0.001, "winding_resistance": 1.0})
    assert sorted(tuple(p.values()) for _, p in pts[1:]) == [
        (0.0005, 0.6), (0.0005, 3.5), (0.006, 0.6), (0.006, 3.5)]


def test_a_misspelled_variable_is_one_line_naming_the_place(tmp_path):
    cfg = write_yaml(tmp_path / "dc.yaml", {"extends": str(CONFIGS / "dcdrive.yaml"),
                                            "model": {"channels": {"armature.I": {}}}})
    r = twinmon("check", "-c", cfg)
    assert r.returncode == 6, r.stderr
    problems = [ln for ln in r.stderr.splitlines() if ln.startswith("twinmon:")]
    assert len(problems) == 1, r.stderr
    assert "dc.yaml: model.channels.armature.I: 'armature.I' is not a variable" in problems[0]
    assert "closest: armature.i" in problems[0]


def test_a_limit_out_of_reach_is_a_warning(tmp_path):
    # (the top winding corner stalls the drive, which counts as unsafe: kept out of the box)
    cfg = write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"inputs": {"winding_resistance": {"high": 1.2}}},
        "safety": {"unsafe_if": {"below": 10.0}}})
    res = check(cfg)
    assert res.ok
    assert any("settled speed below 10 rad/s is reached nowhere" in w for w in res.warnings)

    # With the stalling corner in the box, only a non-physical run crosses the limit.
    cfg = write_yaml(tmp_path / "dc2.yaml", {"extends": str(CONFIGS / "dcdrive.yaml"),
                                             "safety": {"unsafe_if": {"below": 10.0}}})
    assert any("limit 10 reached only where the model is non-physical (stalled)" in c
               for c in check(cfg).checked)


def test_a_wear_direction_away_from_the_limit_and_a_zero_tolerance_are_warnings(tmp_path):
    cfg = write_yaml(tmp_path / "dir.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"inputs": {"bearing_friction": {"degrading": "down"},
                             "winding_resistance": {"normal_rate_tolerance": 0.0}}}})
    res = check(cfg)
    assert res.ok
    assert any("model.inputs.bearing_friction.degrading: down, but at the nominal point "
               "bearing_friction 0.0005 N.m.s/rad moves settled speed away from its limit "
               "(291 rad/s -> 301 rad/s" in w for w in res.warnings)
    assert any("model.inputs.winding_resistance.normal_rate_tolerance: 0, so any drift" in w
               for w in res.warnings)
    assert not any("degrading" in w or "tolerance" in w
                   for w in check(CONFIGS / "dcdrive.yaml").warnings)


def test_a_log_transform_of_an_output_below_zero_is_refused(tmp_path):
    # A tachometer wired the other way round reads negative speeds: reduce would stop on
    # them after the whole design had run.
    cfg = write_yaml(tmp_path / "neg.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"fixed": {"tacho.gain": -1.0},
                  "effects": {"tacho.gain": {"baseline": -1.0, "low": -1.1, "high": -0.9}}},
        "safety": {"unsafe_if": {"above": -250.0, "below": None}}})
    res = check(cfg)
    assert not res.ok
    assert "reduce.transform: log needs a positive output, but at the nominal point speed " \
        "is -65" in str(res.problems[0])
    assert check(cfg, overrides=["reduce.transform=none"]).ok


@pytest.fixture(scope="module")
def drive_obs(tmp_path_factory):
    """A fabricated DC drive fleet of 3 years (the config's channels, grid and units)."""
    from twinmon.fabricate import fabricate
    tmp = tmp_path_factory.mktemp("check")
    cfg = load_config(write_yaml(tmp / "fleet.yaml", {
        "extends": str(CONFIGS / "dcdrive_fleet.yaml"), "fabricate": {"years": 3}}))
    fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
    return tmp, tmp / "obs.h5"


def test_matching_observations_pass(drive_obs):
    tmp, obs = drive_obs
    res = check(tmp / "fleet.yaml", observations=obs)
    assert res.ok, [p.message for p in res.problems]


def test_observations_on_another_time_grid_fail(drive_obs):
    tmp, obs = drive_obs
    cfg = write_yaml(tmp / "grid.yaml", {
        "extends": str(CONFIGS / "dcdrive_fleet.yaml"),
        "model": {"output": {"times": {"start": 0.05, "stop": 3.0, "step": 0.05}}}})
    r = twinmon("check", "-c", cfg, "--observations", obs, "--json")
    assert r.returncode == 4, r.stderr
    out = json.loads(r.stdout)
    assert [p["message"] for p in out["problems"]] == [
        f"{obs}: /time: 30 samples 0.1..3 s, the config's model.output.times has 60 "
        "(0.05..3 s)"]


def test_observations_in_other_units_fail(drive_obs):
    tmp, obs = drive_obs
    cfg = write_yaml(tmp / "rpm.yaml", {"extends": str(CONFIGS / "dcdrive_fleet.yaml"),
                                        "model": {"output": {"units": "rpm"}}})
    res = check(cfg, observations=obs)
    assert res.exit_code == 4
    assert len(res.problems) == 1
    msg = res.problems[0].message
    assert "/speed is in 'rad/s', the config's model.output.units is 'rpm'" in msg


def test_a_value_no_twin_could_give_fails_as_calibrate_would(drive_obs, tmp_path):
    """A sample of -1e9 rad/s passed check, then run stopped on it at once (exit 4)."""
    import dataclasses

    from twinmon.observations import read_observations, write_observations
    tmp, obs = drive_obs
    o = read_observations(obs)
    unit = sorted(o.units)[0]
    speed = o.units[unit].channels["speed"].copy()
    speed[1, 3] = -1e9
    units = {**o.units, unit: dataclasses.replace(o.units[unit], channels={"speed": speed})}
    write_observations(tmp_path / "bad.h5", dataclasses.replace(o, units=units))
    res = check(tmp / "fleet.yaml", observations=tmp_path / "bad.h5")
    assert res.exit_code == 4
    msg = res.problems[0].message
    assert f"/units/{unit}/speed year 2 at t = " in msg and "-1e+09 rad/s" in msg
    assert "far outside anything the twin gives" in msg and "\n" not in msg
