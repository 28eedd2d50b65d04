"""fabricate: synthetic fleets from the real FMU; the shipped data regenerate identically."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from twinmon.config import load_config
from twinmon.errors import ConfigError
from twinmon.fabricate import fabricate, read_truth
from twinmon.observations import read_observations

from ..conftest import CONFIGS, ROOT, write_yaml


@pytest.mark.parametrize("name", ["fleet", "fleet_gap"])
def test_shipped_data_regenerate_identically(tmp_path, name, fmu_path):
    cfg_path = CONFIGS / f"{name}.yaml"
    if not cfg_path.exists():
        pytest.skip(f"{cfg_path} not shipped")
    cfg = load_config(cfg_path)
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    for new, old in ((tmp_path / "o.h5", ROOT / "data" / f"{name}.h5"),
                     (tmp_path / "t.h5", ROOT / "data" / f"{name}_truth.h5")):
        with h5py.File(new) as a, h5py.File(old) as b:
            names = []
            a.visit(names.append)
            other = []
            b.visit(other.append)
            assert names == other
            for n in names:
                if isinstance(a[n], h5py.Dataset):
                    assert np.array_equal(a[n][()], b[n][()], equal_nan=True), n


def test_shipped_fleet_matches_the_issue(fmu_path):
    truth = read_truth(ROOT / "data" / "fleet_truth.h5")
    obs = read_observations(ROOT / "data" / "fleet.h5")
    assert set(obs.units) == {"Park", "Colt", "Monk"}
    for u in obs.units.values():
        assert np.array_equal(u.years, np.arange(1, 11))
        assert u.noise_std["m_flow"] == pytest.approx(4.0)  # 1 % of 400 kg/s
    slope = {u: {k: np.polyfit(truth.years[u], v, 1)[0] for k, v in truth.inputs[u].items()}
             for u in truth.inputs}
    assert abs(slope["Park"]["motor_damping"]) < 0.2 and -0.05 < slope["Park"]["pump_coef"] < 0
    assert slope["Colt"]["pump_coef"] == pytest.approx(-0.1, abs=0.02)
    assert slope["Monk"]["motor_damping"] == pytest.approx(1.2, abs=0.15)


def test_noise_level_and_truth_separation(small_fleet_config, tmp_path):
    cfg = load_config(small_fleet_config)
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    obs = read_observations(tmp_path / "o.h5")
    with h5py.File(tmp_path / "t.h5") as f:
        clean = {u: f[f"units/{u}/m_flow_clean"][()] for u in obs.units}
    with h5py.File(tmp_path / "o.h5") as f:
        names = []
        f.visit(names.append)
    assert not any("inputs" in n or "clean" in n for n in names)  # no truth in observations
    resid = np.concatenate([(obs.output_of(u) - clean[u]).ravel() for u in obs.units])
    assert resid.std() == pytest.approx(4.0, rel=0.15)
    assert abs(resid.mean()) < 4.0 * 4 / np.sqrt(resid.size)


def test_injected_effect_starts_at_onset(tmp_path, fmu_path):
    p = write_yaml(tmp_path / "eff.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "fabricate": {"years": 4, "noise_fraction": 0.0, "units": {
            "A": {"trajectories": {"motor_damping": {"start": 10.0},
                                   "pump_coef": {"start": 3.61}}},
            "B": {"trajectories": {"motor_damping": {"start": 10.0},
                                   "pump_coef": {"start": 3.61}},
                  "effects": {"sensor.tau": {"value": 2.0, "onset": 3}}},
            "C": {"trajectories": {"motor_damping": {"start": 10.0},
                                   "pump_coef": {"start": 3.61}},
                  "disturbance": {"amplitude": 8.0, "period": 10.0, "onset": 2}}}}})
    cfg = load_config(p)
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    obs = read_observations(tmp_path / "o.h5")
    a, b, c = (obs.output_of(u) for u in "ABC")
    assert np.array_equal(a[:2], b[:2])                 # identical before onset
    assert np.all(b[2:, :5] < a[2:, :5] - 1.0)          # a lagging meter reads low while rising
    assert np.array_equal(a[0], c[0]) and not np.allclose(a[1], c[1])
    truth = read_truth(tmp_path / "t.h5")
    assert np.isnan(truth.effects["B"]["sensor.tau"][:2]).all()
    assert np.all(truth.effects["B"]["sensor.tau"][2:] == 2.0)
    assert truth.disturbance["C"]["amplitude"] == 8.0


def test_missing_trajectory_is_a_config_error(tmp_path, fmu_path):
    p = write_yaml(tmp_path / "bad.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "fabricate": {"units": {"A": {"trajectories": {"motor_damping": {"start": 10.0}}}}}})
    with pytest.raises(ConfigError, match=r"fabricate.units.A.trajectories.pump_coef: missing: every input needs"):
        fabricate(load_config(p), tmp_path / "o.h5", tmp_path / "t.h5")
    assert not (tmp_path / "o.h5").exists()


def test_truth_records_the_future_without_changing_the_record(tmp_path, fmu_path):
    """The truth file carries forecast.horizon future years drawn like the recorded ones
    (trend, jitter, a replaced part's age), from their own stream: the observations and the
    recorded truth are those of the same fleet without them."""
    spec = {"extends": str(CONFIGS / "pump.yaml"),
            "forecast": {"horizon": 6},
            "fabricate": {"years": 4, "seed": 5, "units": {
                "A": {"trajectories": {"motor_damping": {"start": 10.0, "slope": 0.5,
                                                         "jitter": 0.2},
                                       "pump_coef": {"start": 3.6, "slope": -0.05}}},
                "B": {"trajectories": {"motor_damping": {"start": 10.0, "slope": 0.5},
                                       "pump_coef": {"start": 3.6, "slope": -0.05}},
                      "events": [{"year": 3, "component": "pump"}]}}}}
    cfg = load_config(write_yaml(tmp_path / "f.yaml", spec))
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    truth = read_truth(tmp_path / "t.h5")
    for u in "AB":
        assert np.array_equal(truth.future_years[u], np.arange(5, 11))
    # No jitter: exactly the trajectory; B's pump is aged from its replacement in year 3.
    assert np.allclose(truth.future_inputs["B"]["motor_damping"], 10.0 + 0.5 * np.arange(4, 10))
    assert np.allclose(truth.future_inputs["B"]["pump_coef"], 3.6 - 0.05 * np.arange(2, 8))
    dev = truth.future_inputs["A"]["motor_damping"] - (10.0 + 0.5 * np.arange(4, 10))
    assert 0 < np.abs(dev).max() < 5 * 0.2
    # A longer horizon draws more years; the record, observations included, is unchanged.
    spec["forecast"]["horizon"] = 9
    cfg9 = load_config(write_yaml(tmp_path / "f9.yaml", spec))
    fabricate(cfg9, tmp_path / "o9.h5", tmp_path / "t9.h5")
    t9 = read_truth(tmp_path / "t9.h5")
    assert np.array_equal(t9.future_years["A"], np.arange(5, 14))
    a, b = read_observations(tmp_path / "o.h5"), read_observations(tmp_path / "o9.h5")
    for u in "AB":
        assert np.array_equal(a.output_of(u), b.output_of(u))
        for n in truth.inputs[u]:
            assert np.array_equal(truth.inputs[u][n], t9.inputs[u][n])


@pytest.mark.parametrize("damage", ["no_inputs", "short"])
def test_damaged_future_in_truth_is_an_artifact_error(tmp_path, damage):
    """A truth file whose recorded future is damaged: one ArtifactError naming the file and
    the dataset, not a KeyError or an IndexError later in forecast."""
    import shutil
    from twinmon.errors import ArtifactError
    t = tmp_path / "t.h5"
    shutil.copy(ROOT / "data" / "fleet_truth.h5", t)
    with h5py.File(t, "a") as f:
        if damage == "no_inputs":
            del f["units/Colt/future/inputs"]
        else:
            v = f["units/Colt/future/inputs/pump_coef"][()]
            del f["units/Colt/future/inputs/pump_coef"]
            f["units/Colt/future/inputs/pump_coef"] = v[:-1]
    with pytest.raises(ArtifactError, match=r"t\.h5: .*/units/Colt/future/"):
        read_truth(t)


@pytest.fixture(scope="module")
def dcdrive_fmu_built():
    from twinmon.fmu import build_fmu
    return build_fmu(ROOT / "fmus" / "DCDrive")


def _dcdrive_fleet(tmp_path, units: dict, years: int = 8):
    """A DC drive fleet (not the pump: the shapes are the model's business, not the
    fabricator's) without noise, so the truth can be compared exactly."""
    spec = {"extends": str(CONFIGS / "dcdrive.yaml"), "forecast": {"horizon": 3},
            "fabricate": {"years": years, "noise_std": 0.0, "seed": 3, "units": units}}
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", spec))
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    return cfg, read_observations(tmp_path / "o.h5"), read_truth(tmp_path / "t.h5")


def test_trajectory_shapes(tmp_path, dcdrive_fmu_built):
    """Exponential wear, a step with a new rate after it, and a step on an exponential
    part replaced in between: each follows its formula; the jitter-free truth equals it."""
    flat = {"start": 1.0}
    units = {
        "Exp": {"trajectories": {"bearing_friction": {"start": 0.001, "slope": 1e-5,
                                                      "growth": 0.3},
                                 "winding_resistance": flat}},
        "Step": {"trajectories": {"bearing_friction": {"start": 0.001, "slope": 1e-5,
                                                       "changes": [{"year": 5, "size": 2e-4,
                                                                    "slope": 0.0}]},
                                  "winding_resistance": flat}},
        "Repl": {"trajectories": {"bearing_friction": {"start": 0.001, "slope": 2e-5,
                                                       "changes": [{"year": 3, "size": 1e-4},
                                                                   {"year": 7, "size": 5e-5}]},
                                  "winding_resistance": flat},
                 "events": [{"year": 5, "component": "bearing"}]}}
    cfg, obs, truth = _dcdrive_fleet(tmp_path, units)
    age = np.arange(8.0)
    exp = 0.001 + 1e-5 * np.expm1(0.3 * age) / 0.3
    assert np.allclose(truth.inputs["Exp"]["bearing_friction"], exp, rtol=1e-12)
    step = np.where(age >= 4, 0.001 + 1e-5 * 4 + 2e-4, 0.001 + 1e-5 * age)
    assert np.allclose(truth.inputs["Step"]["bearing_friction"], step, rtol=1e-12)
    # The step of year 3 belonged to the part replaced in year 5; the new part, fitted at
    # the start of year 5, is 2 years old in year 7 when its own step comes.
    new_age = age - 4
    repl = np.where(age < 4, 0.001 + 2e-5 * age + np.where(age >= 2, 1e-4, 0.0),
                    0.001 + 2e-5 * new_age + np.where(age >= 6, 5e-5, 0.0))
    assert np.allclose(truth.inputs["Repl"]["bearing_friction"], repl, rtol=1e-12)
    # The future continues the shapes: the step's unit stays flat after its step.
    assert np.allclose(truth.future_inputs["Step"]["bearing_friction"], step[-1])
    assert truth.future_inputs["Exp"]["bearing_friction"][0] == pytest.approx(
        0.001 + 1e-5 * np.expm1(0.3 * 8) / 0.3)


def test_thin_irregular_records_and_unrecorded_repairs(tmp_path, dcdrive_fmu_built):
    """A record that ends early, missing years and lost samples leave the plant's file as
    a plant would have it; an unrecorded repair changes the inputs but only the truth file
    knows of it; the fleet's other units are the same as without these options."""
    tr = {"bearing_friction": {"start": 0.001, "slope": 2e-5, "jitter": 1e-5},
          "winding_resistance": {"start": 1.0, "slope": 0.01, "jitter": 0.002}}
    plain = {"A": {"trajectories": tr}, "B": {"trajectories": tr}}
    (tmp_path / "plain").mkdir()
    _, obs0, truth0 = _dcdrive_fleet(tmp_path / "plain", plain)
    odd = {"A": {"trajectories": tr},
           "B": {"trajectories": tr, "last_year": 6, "missing_years": [2, 4],
                 "nan_fraction": 0.2,
                 "events": [{"year": 3, "component": "bearing", "recorded": False},
                            {"year": 5, "component": "winding"}]}}
    (tmp_path / "odd").mkdir()
    _, obs, truth = _dcdrive_fleet(tmp_path / "odd", odd)
    assert np.array_equal(obs.units["B"].years, [1, 3, 5, 6])
    assert np.array_equal(truth.years["B"], [1, 3, 5, 6])
    assert np.array_equal(truth.future_years["B"], [7, 8, 9])
    y = obs.output_of("B")
    assert 0.05 < np.isnan(y).mean() < 0.4
    assert [(e.year, e.component) for e in obs.units["B"].events] == [(5, "winding")]
    assert [(e.year, e.component) for e in truth.events["B"]] == [(3, "bearing"),
                                                                    (5, "winding")]
    assert truth.unrecorded["B"] == [(3, "bearing")] and truth.unrecorded["A"] == []
    # Unit A is untouched by B's options (same draws).
    assert np.array_equal(obs.output_of("A"), obs0.output_of("A"))
    assert np.array_equal(truth.inputs["A"]["bearing_friction"],
                          truth0.inputs["A"]["bearing_friction"])


@pytest.mark.parametrize("unit, key", [
    ({"missing_years": [8]}, "missing_years.0"),
    ({"last_year": 9}, "last_year"),
    ({"missing_years": [1, 3], "last_year": 3}, "missing_years.1"),
    ({"events": [{"year": 4, "component": "bearing"}], "missing_years": [4]}, "events.0.year"),
    ({"nan_fraction": 1.0}, "nan_fraction"),
])
def test_bad_record_options_name_the_key(tmp_path, unit, key):
    tr = {"bearing_friction": {"start": 0.001}, "winding_resistance": {"start": 1.0}}
    p = write_yaml(tmp_path / "bad.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "fabricate": {"years": 8, "units": {"U": {"trajectories": tr, **unit}}}})
    with pytest.raises(ConfigError, match=rf"fabricate.units.U.{key}"):
        load_config(p)


def test_changes_must_be_in_order(tmp_path):
    p = write_yaml(tmp_path / "bad.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "fabricate": {"years": 8, "units": {"U": {"trajectories": {
            "bearing_friction": {"start": 0.001, "changes": [{"year": 5}, {"year": 4}]},
            "winding_resistance": {"start": 1.0}}}}}})
    with pytest.raises(ConfigError, match=r"bearing_friction.changes.1.year"):
        load_config(p)


def test_truth_effects_carry_the_configs_units(tmp_path):
    """The DC drive gap fleet injects a tachometer lag (tacho.tau, given in s under
    model.effects): the truth file records it in s, not without units."""
    import h5py
    cfg = load_config(write_yaml(tmp_path / "gap.yaml", {
        "extends": str(CONFIGS / "dcdrive_gap.yaml"), "fabricate": {"years": 6}}))
    assert cfg.model.effects["tacho.tau"].units == "s"
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    with h5py.File(tmp_path / "t.h5") as f:
        injected = [(u, n) for u in f["units"] for n in f[f"units/{u}"].get("effects", {})]
        assert injected
        for u, n in injected:
            assert f[f"units/{u}/effects/{n}"].attrs["units"] == cfg.model.effects[n].units
