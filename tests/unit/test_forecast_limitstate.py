"""The limit-state model outside the surrogate's box (twinmon/forecast/limitstate.py): the
points it answers are unsafe by the FMU too, P(unsafe) is the all-FMU answer, and the answer
does not depend on the batch, the worker or the machine the config describes."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinmon.config import load_config
from twinmon.errors import ConfigError
from twinmon.forecast import (SOURCE_FMU, SOURCE_MODEL, build_limit_state,
                              degrading_directions, forecast_units)
from twinmon.forecast import limitstate
from twinmon.reduce import read_surrogate, reduce
from twinmon.safety import Indicator
from twinmon.simulate import as_parameters, run_batch, simulate, spec_for

from ..conftest import CONFIGS, write_yaml
from .test_forecast import BOTH, HEALTHY, MOTOR, PUMP, write_synthetic_posterior


def _outside_points(cfg, n, rng):
    """n points of the model's region outside the design box, denser near the box."""
    dirs = {name: type("D", (), {"sign": 0})() for name in cfg.model.input_names}
    lo, hi = limitstate.region(cfg, dirs)
    return limitstate._candidates(lo, hi, np.asarray(cfg.model.bounds, float), n, rng)


def _fmu_unsafe(cfg, X):
    spec = spec_for(cfg)
    ind = Indicator.from_config(cfg)
    batch = run_batch(spec, as_parameters(cfg, X))
    value = np.where(batch.ok, ind(spec.times, batch.outputs[ind.variable]), np.nan)
    nph = (batch.outputs[cfg.model.nonphysical][:, -1] > 0.5) if cfg.model.nonphysical \
        else np.zeros(len(X), bool)
    with np.errstate(invalid="ignore"):
        bad = ind.sense * (value - ind.limit) > 0
    return bad | nph | ~batch.ok | np.isnan(value), value


@pytest.fixture(scope="module")
def pump(tmp_path_factory, fmu_path):
    """A real surrogate of the pump and a four-unit synthetic posterior whose failing units
    leave the box."""
    tmp = tmp_path_factory.mktemp("limitstate")
    cfg = load_config(write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "pump.yaml"), "simulate": {"executor": "serial"},
        "forecast": {"samples": 300, "observed_samples": 40}}))
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    write_synthetic_posterior(tmp / "post.h5", cfg, {"Healthy": HEALTHY, "Pumpy": PUMP,
                                                     "Motory": MOTOR, "Bothy": BOTH})
    sur = read_surrogate(tmp / "sur.h5")
    dirs = degrading_directions(cfg, sur)
    model, why = build_limit_state(cfg, dirs)
    assert model is not None, why
    return cfg, tmp, sur, dirs, model


def test_the_points_it_answers_are_unsafe_by_the_fmu(pump):
    """Every point the model calls surely unsafe is unsafe by the FMU (600 points of its
    region outside the box, none seen while it learnt), and it answers most of them."""
    cfg, _, _, _, model = pump
    X = _outside_points(cfg, 600, np.random.default_rng(3))
    sure, value = model.classify(X)
    unsafe, truth = _fmu_unsafe(cfg, X)
    assert sure.sum() > 100
    assert not np.any(sure & ~unsafe)
    # Its estimate of the indicator lies past the limit, and near the FMU's where finite.
    ind = Indicator.from_config(cfg)
    assert np.all(ind.sense * (value[sure] - ind.limit) > 0)
    both = sure & np.isfinite(truth) & np.isfinite(value)
    assert np.median(np.abs(value[both] - truth[both])) < 0.05 * abs(ind.limit)


def test_p_unsafe_is_the_all_fmu_answer(pump):
    """The forecast with the model gives the all-FMU forecast's P(unsafe) within Monte Carlo
    error, the same failure years and verdicts, and the indicator's quantiles on the safe
    side of the limit exactly."""
    cfg, tmp, sur, dirs, model = pump
    from twinmon.calibrate import read_posterior
    post = read_posterior(tmp / "post.h5")
    learnt, _, _ = forecast_units(cfg, post, sur, workers=1, directions=dirs, limit_state=model)
    fmu, _, _ = forecast_units(cfg, post, sur, workers=1, directions=dirs, limit_state=None)
    n = cfg.forecast.samples
    used = 0
    for unit, a in learnt.items():
        b = fmu[unit]
        used += int(np.sum(a.source == SOURCE_MODEL))
        # The points the model answered went through the FMU in the all-FMU forecast.
        assert np.all(b.source[a.source == SOURCE_MODEL] == SOURCE_FMU)
        p = b.p_unsafe
        assert np.all(np.abs(a.p_unsafe - p) <= 3 * np.sqrt(p * (1 - p) / n) + 1.0 / n)
        assert a.failure_year == b.failure_year and a.root_cause == b.root_cause
        assert a.median_failure_year == b.median_failure_year
        # Every point the model answered is unsafe in the all-FMU forecast.
        ind = Indicator.from_config(cfg)
        fmu_unsafe = (ind.sense * (np.nan_to_num(b.indicator, nan=np.inf) - ind.limit) > 0) \
            | b.nonphysical
        assert np.all(fmu_unsafe[a.source == SOURCE_MODEL])
        # Quantiles that fall on the safe side are computed from the same safe values.
        qa, qb = a.indicator_quantiles([0.05, 0.5]), b.indicator_quantiles([0.05, 0.5])
        safe = ind.sense * (qb - ind.limit) <= 0
        assert np.array_equal(qa[safe], qb[safe])
    assert used > 0


def test_a_point_is_answered_the_same_in_any_batch(pump):
    """classify works row by row: a point's answer does not depend on the batch around it
    (the forecast's result is the same whatever the workers and chunks)."""
    cfg, _, _, _, model = pump
    X = _outside_points(cfg, 200, np.random.default_rng(4))
    sure, value = model.classify(X)
    for lo in range(0, 200, 7):
        s, v = model.classify(X[lo:lo + 7])
        assert np.array_equal(s, sure[lo:lo + 7])
        assert np.array_equal(v, value[lo:lo + 7], equal_nan=True)


def test_the_same_config_learns_the_same_model(pump):
    cfg, _, _, dirs, model = pump
    again, _ = build_limit_state(cfg, dirs)
    assert np.array_equal(again.U, model.U) and np.array_equal(again.alpha, model.alpha)
    assert again.runs == model.runs and again.runs < 400


def test_its_own_runs_set_how_sure_it_must_be(pump, monkeypatch):
    """Leave-one-out on its own runs: no safe run would be called surely unsafe at the sds
    it uses; a model that would need more than MAX_SURE sds is refused with the reason."""
    cfg, _, _, dirs, model = pump
    z = _margins(model)
    assert z.size == model.runs and np.any(z <= 0) and np.any(z > 0)
    assert model.sure_sd >= limitstate.SURE
    assert np.all(limitstate._loo_u(model, z)[z <= 0] < model.sure_sd)
    monkeypatch.setattr(limitstate, "MAX_SURE", -5.0)
    refused, why = build_limit_state(cfg, dirs)
    assert refused is None and "leave-one-out" in why


def _margins(model):
    """The runs' margins the model was conditioned on (``alpha`` = K^-1 (z - beta))."""
    K = np.linalg.inv(model.kinv)
    return K @ model.alpha + model.beta


def test_outside_box_fmu_sends_every_point_to_the_fmu_and_bad_values_are_refused(pump, tmp_path):
    cfg, _, _, dirs, _ = pump
    off = dataclasses.replace(cfg, forecast=dataclasses.replace(cfg.forecast,
                                                                outside_box="fmu"))
    assert limitstate.forecast_limit_state(off, dirs, True) == (None, "")
    # An indicator of another variable than the surrogate's output: every point is the FMU's.
    speed = dataclasses.replace(cfg, safety=dataclasses.replace(
        cfg.safety, indicator=dataclasses.replace(cfg.safety.indicator, variable="motor.w")))
    assert limitstate.forecast_limit_state(speed, dirs, True) == (None, "")
    path = write_yaml(tmp_path / "bad.yaml", {"extends": str(CONFIGS / "pump.yaml"),
                                              "forecast": {"outside_box": "guess"}})
    with pytest.raises(ConfigError, match="outside_box"):
        load_config(path)


def test_another_machine_below_its_limit(tmp_path):
    """The DC drive: unsafe when its speed falls below a limit, a stall flag for its
    non-physical mode; the model learns its margin and never answers a point the FMU calls
    safe."""
    cfg = load_config(CONFIGS / "dcdrive.yaml")
    simulate(cfg, tmp_path / "sims.h5")
    reduce(cfg, tmp_path / "sims.h5", tmp_path / "sur.h5")
    dirs = degrading_directions(cfg, read_surrogate(tmp_path / "sur.h5"))
    model, why = build_limit_state(cfg, dirs)
    assert model is not None, why
    assert model.sense == -1
    X = _outside_points(cfg, 400, np.random.default_rng(5))
    sure, value = model.classify(X)
    unsafe, _ = _fmu_unsafe(cfg, X)
    assert sure.sum() > 20 and not np.any(sure & ~unsafe)


def test_a_box_that_is_not_physical_is_learnt_too(tmp_path):
    """The DC drive stalls in its box's top corner, so the surrogate cannot be trusted
    everywhere in it: the model learns the box too, the surrogate answers only the points
    the model is sure are safe, and P(unsafe) is the all-FMU forecast's within Monte Carlo
    error."""
    from twinmon.calibrate import read_posterior
    from twinmon.forecast import box_is_physical, forecast_limit_state
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"), "simulate": {"executor": "serial"},
        "forecast": {"samples": 300, "observed_samples": 40}}))
    assert not box_is_physical(cfg)
    simulate(cfg, tmp_path / "sims.h5")
    reduce(cfg, tmp_path / "sims.h5", tmp_path / "sur.h5")
    sur = read_surrogate(tmp_path / "sur.h5")
    write_synthetic_posterior(tmp_path / "post.h5", cfg, {
        "Sound": [(0.001, 0.0), (1.0, 0.003)],
        "Bearing": [(0.001, 4e-4), (1.0, 0.003)],          # leaves the box in the horizon
        "Winding": [(0.001, 0.0), (1.0, 0.25)]}, scatter=(5e-5, 0.02),
        post_std=(1e-4, 0.03))
    dirs = degrading_directions(cfg, sur)
    model, why = forecast_limit_state(cfg, dirs, False)
    assert model is not None and model.covers_box, why
    post = read_posterior(tmp_path / "post.h5")
    learnt, _, _ = forecast_units(cfg, post, sur, workers=1, directions=dirs, box_ok=False,
                                  limit_state=model)
    fmu, _, _ = forecast_units(cfg, post, sur, workers=1, directions=dirs, box_ok=False,
                               limit_state=None)
    n = cfg.forecast.samples
    from twinmon.forecast import SOURCE_SURROGATE
    for unit, a in learnt.items():
        p = fmu[unit].p_unsafe
        assert np.all(np.abs(a.p_unsafe - p) <= 3 * np.sqrt(p * (1 - p) / n) + 2.0 / n), unit
        assert a.failure_year == fmu[unit].failure_year, unit
        assert np.all(fmu[unit].source != SOURCE_SURROGATE)        # every point to the FMU
    assert any(np.any(a.source == SOURCE_SURROGATE) for a in learnt.values())
    assert any(np.any(a.source == SOURCE_MODEL) for a in learnt.values())
