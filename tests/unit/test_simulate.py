"""simulate: the real FMU over a small design; failures recorded; resume; provenance."""
from __future__ import annotations

import json
import re

import h5py
import numpy as np
import pytest

from twinmon.artifacts import file_sha256, read_provenance
from twinmon.config import load_config
from twinmon.errors import ArtifactError
from twinmon.simulate import (STATUS_FAILED, STATUS_OK, draw_design, read_simulations,
                              simulate)

from ..conftest import write_yaml


def test_design_fills_the_box_and_is_reproducible(small_config):
    cfg = load_config(small_config)
    a, b = draw_design(cfg, 40, 7), draw_design(cfg, 40, 7)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, draw_design(cfg, 40, 8))
    lo, hi = cfg.model.bounds.T
    assert np.all(a >= lo) and np.all(a <= hi)
    # Latin hypercube: exactly one point per stratum in each input
    for j in range(2):
        strata = np.floor((a[:, j] - lo[j]) / (hi[j] - lo[j]) * 40).astype(int)
        assert sorted(strata) == list(range(40))
    for design in ("sobol", "halton"):
        c = load_config(small_config, [f"simulate.design={design}"])
        x = draw_design(c, 16, 1)
        assert x.shape == (16, 2) and np.all(x >= lo) and np.all(x <= hi)


def test_simulate_writes_runs_with_schema_and_provenance(small_config, tmp_path, fmu_path):
    cfg = load_config(small_config)
    out = tmp_path / "sims.h5"
    summary = simulate(cfg, out)
    assert summary.runs == 32 and summary.failures == 0
    sims = read_simulations(out)
    assert sims.X["train"].shape == (24, 2) and sims.Y["train"].shape == (24, 25)
    assert sims.ok["train"].all() and sims.ok["test"].all()
    # healthy-ish flows: rise from rest towards ~400 kg/s
    assert np.all(sims.Y["train"][:, 0] < sims.Y["train"][:, -1])
    assert np.all((sims.Y["train"][:, -1] > 300) & (sims.Y["train"][:, -1] < 420))
    prov = read_provenance(out)
    assert prov["schema"] == "twinmon.simulations/1"
    assert prov["seed"] == cfg.seed and prov["twinmon_version"]
    assert prov["inputs"][0]["sha256"] == file_sha256(fmu_path)
    assert "train_size: 24" in prov["config"]
    with h5py.File(out) as f:
        assert f["train/Y"].attrs["units"] == "kg/s" and f["train/Y"].attrs["description"]
    assert not (tmp_path / "sims.h5.partial").exists()


def test_same_seed_same_arrays(small_config, tmp_path):
    cfg = load_config(small_config)
    simulate(cfg, tmp_path / "a.h5")
    simulate(cfg, tmp_path / "b.h5", workers=2)
    a, b = read_simulations(tmp_path / "a.h5"), read_simulations(tmp_path / "b.h5")
    for split in ("train", "test"):
        assert np.array_equal(a.X[split], b.X[split])
        assert np.array_equal(a.Y[split], b.Y[split])


def test_process_executor_matches_serial(small_config, tmp_path):
    cfg = load_config(small_config, ["simulate.executor=process", "simulate.workers=2"])
    simulate(cfg, tmp_path / "p.h5")
    simulate(load_config(small_config), tmp_path / "s.h5")
    p, s = read_simulations(tmp_path / "p.h5"), read_simulations(tmp_path / "s.h5")
    assert np.array_equal(p.Y["train"], s.Y["train"])


def test_failing_runs_are_recorded_and_do_not_stop_the_batch(tmp_path, small_config):
    # An input reaching where the circuit's losses turn negative (pipe.fouling below -1,
    # a range the FMU does not bound): the flow runs away and the FMU's step guard fails
    # the run.
    cfg = load_config(small_config, ["model.inputs.motor_damping.variable=pipe.fouling",
                                     "model.effects.pipe.fouling=null",
                                     "model.inputs.motor_damping.low=-3",
                                     "model.inputs.motor_damping.high=0.5",
                                     "model.inputs.motor_damping.nominal=0"])
    out = tmp_path / "fail.h5"
    summary = simulate(cfg, out)
    sims = read_simulations(out)
    with h5py.File(out) as f:
        status = f["train/status"][()]
        messages = [m.decode() for m in f["train/message"][()]]
    failed = status == STATUS_FAILED
    assert 0 < summary.failures < 32
    assert failed.any() and (status == STATUS_OK).any()
    assert np.isnan(sims.Y["train"][failed]).all()
    assert all("pipe.fouling=" in m for m, bad in zip(messages, failed) if bad)
    assert all(m == "" for m, bad in zip(messages, failed) if not bad)


def test_interrupted_simulate_resumes(small_config, tmp_path, monkeypatch):
    import twinmon.simulate as sim
    cfg = load_config(small_config, ["simulate.chunk_size=8"])
    out = tmp_path / "r.h5"
    real = sim.run_batch
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(sim, "run_batch", flaky)
    with pytest.raises(Exception, match="resumes"):
        simulate(cfg, out)
    assert not out.exists() and (tmp_path / "r.h5.partial").exists()
    monkeypatch.setattr(sim, "run_batch", real)
    summary = simulate(cfg, out)
    assert summary.resumed == 16 and summary.runs == 16
    full = tmp_path / "full.h5"
    simulate(cfg, full)
    assert np.array_equal(read_simulations(out).Y["train"], read_simulations(full).Y["train"])


def test_reader_rejects_other_schema(tmp_path):
    p = tmp_path / "x.h5"
    with h5py.File(p, "w") as f:
        f.attrs["schema"] = "twinmon.surrogate/1"
    with pytest.raises(ArtifactError, match=r"x.h5: schema is 'twinmon.surrogate/1', "
                                            r"expected 'twinmon.simulations/1'"):
        read_simulations(p)
    with pytest.raises(ArtifactError, match="file not found"):
        read_simulations(tmp_path / "missing.h5")


@pytest.mark.parametrize("limit, words", [
    ({"above": 1000.0}, "no training run is unsafe"),      # t90 never that long in the box
    ({"above": 0.5}, "every training run is already unsafe"),
])
def test_a_criterion_no_run_or_every_run_meets_is_a_warning(small_config, tmp_path, limit,
                                                            words):
    from twinmon.simulate import simulate
    key = next(iter(limit))
    cfg = load_config(small_config, [f"safety.unsafe_if.{key}={limit[key]}"])
    s = simulate(cfg, tmp_path / "s.h5")
    assert len(s.warnings) == 1 and words in s.warnings[0]
    assert "t90" in s.warnings[0] and "safety.unsafe_if" in s.warnings[0]
    assert not simulate(load_config(small_config), tmp_path / "ok.h5").warnings


# ----------------------------------------------------------------------------------------
# start values as effects (the DC drive's states declare initial="exact" and a start)

def test_a_state_start_value_is_accepted_as_an_effect(tmp_path):
    """A state's start value is something FMI lets a tool set before initialisation: a
    config may screen it as an effect (the shaft already turning at switch-on)."""
    from twinmon.simulate import check_model
    from ..conftest import CONFIGS
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"effects": {"state.w": {"baseline": 0.0, "low": 0.0, "high": 100.0,
                                          "units": "rad/s"}}}}))
    check_model(cfg)                       # before: "'state.w' is a local Real, not ..."


@pytest.mark.parametrize("name, reason", [
    ("tacho.w", r"'tacho.w' is an output Real the FMU calculates \(initial=\"calculated\""),
    ("der(state.w)", r"'der\(state.w\)' is a local Real the FMU calculates"),
])
def test_a_variable_fmi_does_not_let_a_tool_set_is_refused_with_the_reason(tmp_path, name,
                                                                           reason):
    from twinmon.errors import SimulationError
    from twinmon.simulate import check_model
    from ..conftest import CONFIGS
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"effects": {name: {"baseline": 0.0, "low": 0.0, "high": 1.0}}}}))
    with pytest.raises(SimulationError, match=rf"model.effects.{re.escape(name)}: {reason}.*FMI lets no tool") as e:
        check_model(cfg)
    assert e.value.exit_code == 6 and "\n" not in str(e.value)


def test_a_design_box_beyond_the_range_the_fmu_declares_is_refused(tmp_path):
    """motor.D declares min 0: a box reaching below it asks for states the model cannot be
    in; one line names the config key, the value and the declared bound."""
    from twinmon.errors import SimulationError
    from twinmon.simulate import check_model, declared_range
    from ..conftest import CONFIGS
    ok = load_config(CONFIGS / "pump.yaml")
    rng = declared_range(ok)
    assert rng[0, 0] == 0.0 and np.isinf(rng[0, 1]) and np.all(np.isinf(rng[1]))
    cfg = load_config(write_yaml(tmp_path / "p.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "model": {"inputs": {"motor_damping": {"low": -1.0}}}}))
    with pytest.raises(SimulationError, match=r"model.inputs.motor_damping.low: -1 is below "
                                              r"the min 0 PumpCircuit.fmu declares for motor.D"):
        check_model(cfg)
