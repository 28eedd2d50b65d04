"""forecast's trend-shape gate: wear that accelerates makes a prognosis unreliable."""
from __future__ import annotations

import numpy as np
import pytest

from twinmon.calibrate import calibrate
from twinmon.config import load_config
from twinmon.fabricate import fabricate
from twinmon.forecast import forecast
from twinmon.forecast.trend import acceleration_test
from twinmon.reduce import reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml


def test_acceleration_test_is_one_sided_in_the_degrading_direction():
    rng = np.random.default_rng(3)
    years = np.arange(1, 11)
    noise = 0.02 * rng.standard_normal(10)
    bend = 1.0 + 0.02 * years + 0.02 * years ** 2 + noise
    assert acceleration_test(years, bend, +1) < 1e-4
    assert acceleration_test(years, bend, -1) > 0.99        # it bends away from failure
    assert acceleration_test(years[:4], bend[:4], +1) == 1.0  # too few years to tell
    # On straight lines its p-values are uniform: 5 % of them below 0.05.
    p = [acceleration_test(years, 1.0 + 0.1 * years + 0.02 * rng.standard_normal(10), +1)
         for _ in range(600)]
    assert 0.03 < np.mean(np.array(p) < 0.05) < 0.075


@pytest.fixture(scope="module")
def dcdrive_fleet(tmp_path_factory):
    """A DC drive (not the pump) fleet: a bearing whose friction grows exponentially, one
    that wears at a steady faulty rate, a healthy unit; calibrated year by year."""
    from twinmon.fmu import build_fmu
    from ..conftest import ROOT
    build_fmu(ROOT / "fmus" / "DCDrive")
    tmp = tmp_path_factory.mktemp("shape")
    steady = {"winding_resistance": {"start": 1.0, "slope": 0.003, "jitter": 0.002}}
    cfg_path = write_yaml(tmp / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "simulate": {"train_size": 48, "test_size": 8},
        "calibrate": {"method": "sequential"},
        "forecast": {"samples": 400, "observed_samples": 100},
        "fabricate": {"years": 10, "noise_std": 1.5, "seed": 7, "units": {
            "Acc": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 1.5e-5,
                                                          "growth": 0.35, "jitter": 5e-6},
                                     **steady}},
            "Lin": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 1.5e-4,
                                                          "jitter": 5e-6}, **steady}},
            "Ok": {"trajectories": {"bearing_friction": {"start": 0.0009, "slope": 0.0,
                                                         "jitter": 5e-6}, **steady}}}}})
    cfg = load_config(cfg_path)
    fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
    simulate(cfg, tmp / "sim.h5")
    reduce(cfg, tmp / "sim.h5", tmp / "sur.h5")
    calibrate(cfg, tmp / "sur.h5", tmp / "obs.h5", tmp / "post.h5")
    return cfg_path, tmp


def test_accelerating_wear_is_unreliable_and_a_line_is_not(dcdrive_fleet):
    cfg_path, tmp = dcdrive_fleet
    s = forecast(load_config(cfg_path), tmp / "post.h5", tmp / "sur.h5", tmp / "fc.h5")
    acc, lin, ok = (s.units[u] for u in ("Acc", "Lin", "Ok"))
    assert acc.root_cause != "healthy" and acc.status == "unreliable"
    assert "bearing_friction's yearly estimates accelerate" in acc.status_reason
    assert acc.status_reason in acc.plan
    assert lin.root_cause != "healthy" and lin.status == "ok"
    assert ok.root_cause == "healthy" and ok.status == "ok"
    # The gate off: the same forecast says ok.
    off = forecast(load_config(cfg_path, ["forecast.shape_alpha=0"]), tmp / "post.h5",
                   tmp / "sur.h5", tmp / "fc_off.h5")
    assert off.units["Acc"].status == "ok"
    assert off.units["Acc"].failure_year == acc.failure_year
