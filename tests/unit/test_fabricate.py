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
    with pytest.raises(ConfigError, match=r"fabricate.units.A.trajectories.pump_coef: required"):
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
