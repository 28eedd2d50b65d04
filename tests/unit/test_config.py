"""Config loading: validation, overrides, extends, and errors that name file, path and value."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinmon.config import load_config
from twinmon.errors import ConfigError

from ..conftest import CONFIGS, write_yaml


def test_paper_config_loads_with_its_values():
    cfg = load_config(CONFIGS / "pump.yaml")
    assert cfg.model.input_names == ["motor_damping", "pump_coef"]
    assert cfg.model.inputs["motor_damping"].variable == "motor.D"
    assert cfg.model.inputs["pump_coef"].variable == "pump.b2"
    assert cfg.simulate.train_size == 128 and cfg.simulate.test_size == 64
    t = cfg.model.output.times.times
    assert t.shape == (25,) and t[0] == 2.0 and t[-1] == 50.0
    assert set(cfg.model.effects) == {"sensor.tau", "sensor.gain", "valve.opening_time",
                                      "pipe.fouling", "pump.leak", "motor.start_delay",
                                      "motor.supply_ratio"}
    ind = cfg.safety.indicator
    assert ind.kind == "time_to_reach" and ind.level == 360.0 and ind.initial == 0.0
    assert cfg.safety.unsafe_if.above == 30.0 and cfg.safety.unsafe_if.below is None
    assert cfg.model.output.name == "m_flow" and cfg.model.output.units == "kg/s"
    assert cfg.model.channels["motor.w"].units == "rad/s"


def test_config_is_frozen():
    cfg = load_config(CONFIGS / "pump.yaml")
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.seed = 3


def test_the_workers_config_leaves_out_the_fabricated_fleet_only():
    """What a stage's tasks carry: every section a worker reads unchanged, the fabricated
    fleet's trajectories and the raw mapping left out."""
    import pickle
    cfg = load_config(CONFIGS / "fleet.yaml")
    assert cfg.fabricate is not None and cfg.fabricate.units and cfg.raw
    w = cfg.for_workers()
    assert w.fabricate is None and not w.raw
    sections = ("model", "safety", "seed", "simulate", "reduce", "calibrate", "forecast",
                "backtest", "diagnose", "dask", "report")
    assert w.section_yaml(*sections) == cfg.section_yaml(*sections)
    assert w.source == cfg.source and w.diagnose_windows() == cfg.diagnose_windows()
    assert len(pickle.dumps(w)) < len(pickle.dumps(cfg))


def test_extends_merges_and_keeps_fmu_path_relative_to_its_file(tmp_path):
    cfg = load_config(CONFIGS / "fleet.yaml")
    assert cfg.fabricate is not None and set(cfg.fabricate.units) == {"Park", "Colt", "Monk"}
    assert (cfg.model.fmu / "modelDescription.xml").exists()
    child = write_yaml(tmp_path / "c.yaml", {"extends": str(CONFIGS / "pump.yaml"), "seed": 5})
    assert load_config(child).seed == 5
    assert (load_config(child).model.fmu / "modelDescription.xml").exists()


def test_null_drops_an_inherited_entry_and_set_takes_dotted_names(tmp_path):
    child = write_yaml(tmp_path / "c.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "diagnose": {"windows": {"current rise": None}},
        "safety": {"unsafe_if": {"above": 300.0, "below": None}}})
    cfg = load_config(child)
    assert list(cfg.diagnose.windows) == ["acceleration", "settled"]
    assert cfg.safety.unsafe_if.above == 300.0 and cfg.safety.unsafe_if.below is None
    # An FMU parameter's dotted name is one key; null drops the entry there too.
    cfg = load_config(CONFIGS / "dcdrive.yaml", ["model.effects.tacho.gain.high=1.2",
                                                 "model.effects.supply.delay=null"])
    assert cfg.model.effects["tacho.gain"].high == 1.2 and "supply.delay" not in cfg.model.effects
    # ... whether or not the config has the entry yet.
    cfg = load_config(CONFIGS / "dcdrive.yaml", ["model.fixed.fan.c=8e-6",
                                                 "model.effects.fan.c.baseline=8e-6",
                                                 "model.effects.fan.c.low=6e-6",
                                                 "model.effects.fan.c.high=1e-5"])
    assert cfg.model.fixed["fan.c"] == 8e-6 and cfg.model.effects["fan.c"].high == 1e-5
    with pytest.raises(ConfigError, match=r"a config that extends another keeps its side "
                                          r"unless set to null"):
        load_config(CONFIGS / "dcdrive.yaml", ["safety.unsafe_if.above=300"])


def test_set_overrides_apply_before_validation():
    cfg = load_config(CONFIGS / "pump.yaml", ["simulate.train_size=16", "reduce.kernel=matern32"])
    assert cfg.simulate.train_size == 16 and cfg.reduce.kernel == "matern32"
    with pytest.raises(ConfigError, match=r"simulate.train_size: must be >= 2, got 1"):
        load_config(CONFIGS / "pump.yaml", ["simulate.train_size=1"])


@pytest.mark.parametrize("override, message", [
    ("simulate.bogus=1", r"simulate.bogus: unknown key \(value 1\)"),
    ("seed=abc", r"seed: expected an integer, got 'abc'"),
    ("simulate.design=random", r"simulate.design: expected one of lhs, sobol, halton, got 'random'"),
    ("safety.failure_probability=1.5", r"safety.failure_probability: must lie in \(0, 1\), got 1.5"),
    ("safety.indicator.kind=peak", r"safety.indicator.kind: expected one of time_to_reach, value_at"),
    ("safety.unsafe_if.below=3", r"safety.unsafe_if.above: give exactly one of above or below"),
    ("seed=-1", r"seed: must lie in \[0, 2\*\*32 - 1\]"),
    ("seed=1180591620717411303424", r"seed: must lie in \[0, 2\*\*32 - 1\]"),
    ("model.output.times.stop=2", r"model.output.times.stop: must be at least start \+ step"),
    ("model.output.times.stop=49", r"model.output.times.stop: is not start \+ a whole number of "
     r"steps \(2 \+ 23 x 2 = 48, the next 50\)"),
    ("model.inputs.pump_coef.low=5", r"model.inputs.pump_coef.high: must be greater than low"),
    ("reduce.variance_threshold=.nan", r"reduce.variance_threshold: expected a finite number"),
    ("novalue", r"expected KEY.PATH=VALUE"),
    # Mistakes a new model's config makes that would otherwise pass silently.
    ("model.inputs.pump_coef.variable=motor.D",
     r"model.inputs.pump_coef.variable: is also model.inputs.motor_damping's variable"),
    ("model.inputs.pump_coef.component=both",
     r"model.inputs.pump_coef.component: is a word the verdicts use .*, got 'both'"),
    ("model.fixed={pump.b2: 3.0}", r"model.inputs.pump_coef.variable: is held by model.fixed"),
    ("model.fixed={sensor.tau: 0.5}",
     r"model.effects.sensor.tau.baseline: must give the calibrated model, where model.fixed "
     r"holds sensor.tau at 0.5, got 0.0"),
    ("model.effects={motor.D: {baseline: 10, low: 5, high: 20}}",
     r"model.effects.motor.D: is model.inputs.motor_damping's variable, calibrated every year"),
    ("model.channels={sensor.m_flow: {units: kg/s}}",
     r"model.channels.sensor.m_flow: is model.output.variable"),
    ("diagnose.windows={late: {start: 60, stop: 80}}",
     r"diagnose.windows.late: holds no sample of the record \(model.output.times: 2 to 50 s\)"),
])
def test_bad_values_name_file_path_and_value(override, message):
    with pytest.raises(ConfigError, match=message) as exc:
        load_config(CONFIGS / "pump.yaml", [override])
    assert "\n" not in str(exc.value)


def test_time_grid_lands_on_its_decimals():
    from twinmon.config.model import TimeGrid
    t = TimeGrid(0.1, 3.0, 0.1).times
    assert t.size == 30 and 1.0 in t and t[-1] == 3.0 and t[2] == 0.3


def test_unknown_top_level_key_is_rejected(tmp_path):
    p = write_yaml(tmp_path / "typo.yaml", {"extends": str(CONFIGS / "pump.yaml"),
                                            "simulat": {"train_size": 3}})
    with pytest.raises(ConfigError, match=r"typo.yaml: simulat: unknown key"):
        load_config(p)


def test_malformed_yaml_names_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("model:\n  fmu: x\n  inputs: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: malformed YAML at line \d+"):
        load_config(p)


def test_missing_file_and_missing_required_key(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")
    p = write_yaml(tmp_path / "nomodel.yaml", {"seed": 1})
    with pytest.raises(ConfigError, match=r"nomodel.yaml: model: required key is missing"):
        load_config(p)


def test_extends_cycle_is_an_error(tmp_path):
    write_yaml(tmp_path / "a.yaml", {"extends": "b.yaml"})
    write_yaml(tmp_path / "b.yaml", {"extends": "a.yaml"})
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "a.yaml")


def test_section_yaml_is_resolved_with_defaults():
    cfg = load_config(CONFIGS / "pump.yaml")
    text = cfg.section_yaml("calibrate")
    assert "rhat_warn: 1.05" in text  # a default not written in the file
    # How the work is spread over processes cannot change a result: not provenance.
    other = load_config(CONFIGS / "pump.yaml", ["simulate.workers=1", "simulate.executor=serial",
                                                "calibrate.workers=3", "diagnose.workers=1"])
    for section in ("simulate", "calibrate", "diagnose"):
        assert other.section_yaml(section) == cfg.section_yaml(section)
    assert "workers" not in cfg.section_yaml("simulate")
    assert np.isclose(cfg.model.bounds, [[4.0, 30.0], [2.2, 4.0]]).all()


def test_calibrate_records_the_fit_settings_it_judges_its_years_with():
    """Each year's goodness of fit uses diagnose's windows (their order: the records store
    an index) and Ljung-Box lags: changing them changes the posterior, nothing else of
    diagnose does."""
    cfg = load_config(CONFIGS / "pump.yaml")
    base = cfg.section_yaml("calibrate")
    lags = load_config(CONFIGS / "pump.yaml", ["diagnose.ljung_box_lags=2"])
    assert lags.section_yaml("calibrate") != base
    wins = dict(cfg.diagnose_windows())
    swapped = {n: {"start": w.start, "stop": w.stop} for n, w in reversed(list(wins.items()))}
    other = load_config(CONFIGS / "pump.yaml", [f"diagnose.windows={swapped}"])
    assert other.section_yaml("calibrate") != base
    gain = load_config(CONFIGS / "pump.yaml", ["diagnose.bic_gain=12"])
    assert gain.section_yaml("calibrate") == base


def test_scientific_notation_without_dot_is_a_number(tmp_path):
    # YAML 1.1 reads 1e6 as a string; people write it, so it is a float here.
    cfg = load_config(CONFIGS / "pump.yaml", ["safety.unsafe_if.above=3e1",
                                               "calibrate.noise_std=4e0"])
    assert cfg.safety.unsafe_if.above == 30.0
    assert cfg.calibrate.noise_std == 4.0


def test_duplicate_keys_are_an_error_naming_the_line(tmp_path):
    p = tmp_path / "dup.yaml"
    p.write_text(f"extends: {CONFIGS / 'pump.yaml'}\nseed: 1\nseed: 2\n")
    with pytest.raises(ConfigError, match=r"dup.yaml: line 3: key 'seed' appears twice .*line 2"):
        load_config(p)


def test_non_utf8_config_is_one_line(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes(b"seed: 1\n# caf\xe9\n")
    with pytest.raises(ConfigError, match=r"latin1.yaml: line 2: not UTF-8") as exc:
        load_config(p)
    assert "\n" not in str(exc.value)


def test_channels_accept_a_plain_list_and_indicator_defaults(tmp_path):
    p = write_yaml(tmp_path / "c.yaml", {"extends": str(CONFIGS / "pump.yaml"),
                                         "model": {"channels": ["motor.w"]}})
    cfg = load_config(p)
    assert list(cfg.model.channels) == ["motor.w"]
    assert cfg.indicator_variable == "sensor.m_flow"


def test_default_diagnose_windows_split_the_record_in_thirds():
    cfg = load_config(CONFIGS / "pump.yaml", ["diagnose.windows={}"])
    w = cfg.diagnose_windows()
    assert list(w) == ["early", "middle", "late"]
    t = cfg.model.output.times.times
    counts = [int(np.sum((t >= v.start) & (t < v.stop))) for v in w.values()]
    assert sum(counts) == t.size and min(counts) >= 8


def test_fabricated_trajectories_name_a_misspelt_input_and_a_missing_one(tmp_path):
    base = {"extends": str(CONFIGS / "pump.yaml"), "fabricate": {"units": {"U": {
        "trajectories": {"motor_damping": {"start": 10.0},
                         "pump_cof": {"start": 3.6}}}}}}
    with pytest.raises(ConfigError, match=r"fabricate.units.U.trajectories.pump_cof: not an "
                                          r"input of the model \(did you mean pump_coef\?\)"):
        load_config(write_yaml(tmp_path / "a.yaml", base))
    del base["fabricate"]["units"]["U"]["trajectories"]["pump_cof"]
    with pytest.raises(ConfigError, match=r"trajectories.pump_coef: missing: every input needs "
                                          r"a trajectory \(given for\), got \['motor_damping'\]"):
        load_config(write_yaml(tmp_path / "b.yaml", base))
