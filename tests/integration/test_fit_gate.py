"""Fit before you forecast: plant data from a twin that differs in structure (a dead time before
the motor starts and a slow valve, neither in the calibrated twin) get no prognosis, while
plant data the twin can explain keep theirs."""
from __future__ import annotations

import json

import numpy as np
import pytest

from twinmon.calibrate import STATUS_MISFIT, STATUS_OK, calibrate, read_posterior
from twinmon.config import load_config
from twinmon.fabricate import fabricate
from twinmon.forecast import STATUS_WITHHELD, forecast
from twinmon.reduce import reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml

UNITS = {
    "Steady": {"motor_damping": {"start": 10.0, "slope": 0.05},
               "pump_coef": {"start": 3.7, "slope": -0.02}},
    "Wearing": {"motor_damping": {"start": 10.0, "slope": 0.05},
                "pump_coef": {"start": 3.6, "slope": -0.10}},
    "Hot": {"motor_damping": {"start": 10.0, "slope": 1.2},
            "pump_coef": {"start": 3.65, "slope": -0.02}},
}
SMALL = {"simulate": {"train_size": 64, "test_size": 8},
         "calibrate": {"chains": 2, "samples": 400, "burn_in": 100, "ess_warn": 100.0, "max_extensions": 1},
         "forecast": {"samples": 300, "observed_samples": 40}}


def _fleet(tmp, name, effects):
    units = {u: {"trajectories": tr, "effects": effects} for u, tr in UNITS.items()}
    return write_yaml(tmp / f"{name}.yaml", {
        "extends": str(CONFIGS / "pump.yaml"), **SMALL,
        "fabricate": {"years": 6, "noise_std": 4.0, "seed": 11, "units": units}})


@pytest.fixture(scope="module")
def gate(tmp_path_factory, fmu_path):
    tmp = tmp_path_factory.mktemp("gate")
    # The plant: the pump with a 3 s dead time before the motor starts and a valve that
    # opens over 6 s -- a structure the calibrated twin (both effects off) does not have.
    wrong = load_config(_fleet(tmp, "wrong", {"motor.start_delay": {"value": 3.0},
                                              "valve.opening_time": {"value": 6.0}}))
    right = load_config(_fleet(tmp, "right", {}))
    simulate(right, tmp / "sims.h5")
    reduce(right, tmp / "sims.h5", tmp / "sur.h5")
    out = {}
    for name, cfg in (("wrong", wrong), ("right", right)):
        fabricate(cfg, tmp / f"{name}.h5", tmp / f"{name}_truth.h5")
        cal = calibrate(cfg, tmp / "sur.h5", tmp / f"{name}.h5", tmp / f"{name}_post.h5")
        fc = forecast(cfg, tmp / f"{name}_post.h5", tmp / "sur.h5", tmp / f"{name}_fc.h5")
        out[name] = (cfg, cal, fc)
    return tmp, out


def test_a_structurally_wrong_twin_gets_no_prognosis(gate):
    tmp, out = gate
    cfg, cal, fc = out["wrong"]
    for unit, p in read_posterior(tmp / "wrong_post.h5").units.items():
        assert (p.status == STATUS_MISFIT).all(), (unit, p.status)
        assert (p.fit["rms"] > 3).all()                        # far above the noise
    for unit, u in fc.units.items():
        assert u.status == STATUS_WITHHELD and not u.forced
        assert u.failure_year is None and u.root_cause == "withheld"
        assert "misses the plant by" in u.status_reason and "run 'twinmon diagnose'" in u.plan
        d = u.as_dict()
        assert d["status"] == "withheld" and d["failure_year"] is None
    # The calibration says so too, year by year, with the figures.
    assert sum("the twin misses the plant" in w for w in cal.warnings) == 3 * 6
    assert json.loads(json.dumps(cal.as_dict()))["units"]["Hot"]["fit"]["status"] == \
        ["misfit"] * 6


def test_force_flag_gives_the_prognosis_labelled(gate):
    import dataclasses
    tmp, out = gate
    cfg = out["wrong"][0]
    forced = dataclasses.replace(cfg, forecast=dataclasses.replace(cfg.forecast,
                                                                   force_prognosis=True))
    fc = forecast(forced, tmp / "wrong_post.h5", tmp / "sur.h5", tmp / "forced_fc.h5")
    for u in fc.units.values():
        assert u.status == STATUS_WITHHELD and u.forced
        assert u.root_cause != "withheld" and u.plan.startswith("FORCED despite")


def test_a_twin_that_fits_keeps_its_prognosis(gate):
    tmp, out = gate
    cfg, cal, fc = out["right"]
    for unit, p in read_posterior(tmp / "right_post.h5").units.items():
        assert (p.status == STATUS_OK).all(), (unit, p.status, p.fit["rms"])
        assert np.all(p.fit["rms"] < 1.5)
    assert {u: f.status for u, f in fc.units.items()} == dict.fromkeys(UNITS, "ok")
    assert fc.units["Hot"].root_cause == "motor"
