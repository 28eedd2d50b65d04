"""Unit tests of twinmon.diagnose: tests of structure, noise estimate, the twin's fits through
the real FMU, the artifact and the command (tiny fabricated fleets)."""
from __future__ import annotations

import copy
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from twinmon import artifacts
from twinmon.config import config_from_mapping, load_config
from twinmon.diagnose import (JointFit, Twin, candidate_names, diagnose, diagnose_unit,
                              estimate_noise, ljung_box, noise_sf, plateau_noise,
                              pooled_onset_pvalues, read_gap)
from twinmon.diagnose.text import summary_line
from twinmon.errors import ArtifactError, ConfigError, InputDataError, Interrupted, SimulationError
from twinmon.fabricate import fabricate
from twinmon.fmu import resolve_fmu

ROOT = Path(__file__).resolve().parents[2]
PUMP = ROOT / "configs" / "pump.yaml"
SIGMA = 4.0


@pytest.fixture(scope="module")
def cfg():
    return load_config(PUMP)


@pytest.fixture(scope="module")
def fmu(cfg):
    return resolve_fmu(cfg.model.fmu)


@pytest.fixture(scope="module")
def twin(cfg, fmu):
    t = Twin(cfg, fmu, ["m_flow"], cfg.model.output.times.times, {"m_flow": SIGMA},
             list(cfg.model.effects))
    yield t
    t.close()


def small_fleet_cfg(units: dict, years: int = 3, **diag):
    raw = copy.deepcopy(dict(load_config(PUMP).raw))
    raw["fabricate"] = {"years": years, "noise_fraction": 0.01, "seed": 11, "units": units}
    if diag:
        raw["diagnose"] = diag
    return config_from_mapping(raw, PUMP)


HEALTHY = {"trajectories": {"motor_damping": {"start": 10.0, "slope": 0.1},
                            "pump_coef": {"start": 3.7, "slope": -0.02}}}


# -- statistics ------------------------------------------------------------------------------
def test_ljung_box_tells_white_from_correlated_noise():
    rng = np.random.default_rng(0)
    white = rng.standard_normal(200)
    ar = np.zeros(200)
    for i in range(1, 200):
        ar[i] = 0.8 * ar[i - 1] + rng.standard_normal()
    assert ljung_box(white, 5) > 0.01
    assert ljung_box(ar, 5) < 1e-6
    assert ljung_box(np.array([1.0, np.nan, 2.0]), 5) == 1.0   # too short: no evidence


def test_pooled_onset_pvalues_find_the_excess():
    dof = np.full(6, 23.0)
    chi2 = np.array([23.0, 22.0, 24.0, 80.0, 90.0, 85.0])
    p = pooled_onset_pvalues(chi2, dof)
    assert p.shape == (6,)
    assert int(np.argmin(p)) == 3
    assert pooled_onset_pvalues(dof, dof).min() > 0.4


def test_estimate_noise_from_the_plateau():
    rng = np.random.default_rng(1)
    t = np.arange(2.0, 52.0, 2.0)
    clean = 400 * (1 - np.exp(-t / 5.0))
    y = clean + 4.0 * rng.standard_normal((10, t.size))
    assert estimate_noise(y, t, 24.0) == pytest.approx(4.0, rel=0.2)
    with pytest.raises(InputDataError):
        estimate_noise(np.full((1, t.size), 1.0), t, 24.0)


def test_plateau_noise_counts_its_degrees_of_freedom():
    # The spread of the estimate is that of a chi-square with the dof it reports.
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 3.01, 0.1)
    est = [plateau_noise(rng.standard_normal((6, t.size)), t, 2.0) for _ in range(1500)]
    s2 = np.array([s for s, _ in est]) ** 2
    dof = est[0][1]
    assert 25 < dof < 35                          # 6 years x 9 differences, half their number
    assert np.mean(s2) == pytest.approx(1.0, abs=0.03)
    assert 2.0 / np.var(s2) == pytest.approx(dof, rel=0.15)
    # A spike is an outlier, not noise; missing samples cost their differences.
    y = rng.standard_normal((6, t.size))
    y_spiked = y.copy()
    y_spiked[2, 25] += 40.0
    assert plateau_noise(y_spiked, t, 2.0)[0] == pytest.approx(plateau_noise(y, t, 2.0)[0],
                                                               rel=0.1)
    y[:, 26] = np.nan
    assert plateau_noise(y, t, 2.0)[1] < dof
    # Five differences, three of them alike: their MAD (0.15) is no scale to cut at.
    d2 = np.array([-6.09, 3.54, -4.71, 3.62, 3.64])
    y = np.zeros(7)
    for k, d in enumerate(d2):
        y[k + 2] = d + 2 * y[k + 1] - y[k]
    s, dof = plateau_noise(y[None], np.arange(7.0), 0.0)
    assert s == pytest.approx(np.sqrt(np.mean((d2 - np.median(d2)) ** 2) / 6)) and dof < 4


def test_noise_sf_is_the_f_test_for_one_estimated_channel():
    from scipy import stats
    t = np.array([180.0, 250.0, 320.0])
    np.testing.assert_allclose(noise_sf(t, [[200.0]] * 3, [40.0]),
                               stats.f.sf(t / 200.0, 200, 40), rtol=1e-9)
    # Known noise: the chi-square test.
    np.testing.assert_allclose(noise_sf(t, [[150.0, 50.0]] * 3, [np.inf, np.inf]),
                               stats.chi2.sf(t, 200), rtol=1e-12)
    # A known channel beside an estimated one: against simulation.
    rng = np.random.default_rng(0)
    n = 400_000
    total = rng.chisquare(25, n) + 30.0 / rng.chisquare(30, n) * rng.chisquare(25, n)
    for x in (60.0, 80.0, 100.0):
        assert noise_sf([x], [[25.0, 25.0]], [np.inf, 30.0])[0] == pytest.approx(
            np.mean(total > x), rel=0.05)
    # Two and three estimated channels, each its own scale (one shared scale made the
    # p-values 3-4 times too small).
    for k in (2, 3):
        total = sum(rng.chisquare(100, n) * 20.0 / rng.chisquare(20, n) for _ in range(k))
        x = np.quantile(total, 1 - 0.0025)
        assert noise_sf([x], [[100.0] * k], [20.0] * k)[0] == pytest.approx(0.0025, rel=0.1)


# -- the twin --------------------------------------------------------------------------------
def test_vanishing_lag_runs_as_the_baseline(twin):
    theta = np.array([10.0, 3.61])
    np.testing.assert_array_equal(twin.predict(theta, {"sensor.tau": 1e-6}), twin.predict(theta))
    assert np.abs(twin.predict(theta, {"sensor.tau": 0.5}) - twin.predict(theta)).max() > 1.0


def test_a_repeated_run_comes_from_the_cache_with_the_fmus_bits(cfg, fmu, monkeypatch):
    import twinmon.diagnose.twin as tw
    monkeypatch.setattr(tw, "CACHE_RUNS", 2)
    args = (cfg, fmu, ["m_flow"], cfg.model.output.times.times, {"m_flow": SIGMA},
            list(cfg.model.effects))
    t, fresh = Twin(*args), Twin(*args)
    try:
        theta, eff = np.array([12.0, 3.4]), {"valve.opening_time": 4.0}
        first = t.run(theta, eff)
        first["sensor.m_flow"][:] = 0.0          # a caller's in-place work stays its own
        again = t.run(theta, eff)
        assert t.runs == 1
        ref = fresh.run(theta, eff)
        for name in ref:
            np.testing.assert_array_equal(again[name], ref[name])
        t.run(theta)
        t.run(theta + 0.5)                       # evicts the oldest: at most CACHE_RUNS kept
        assert len(t._cache) == 2 and t.runs == 3
        t.run(theta, eff)
        assert t.runs == 4
    finally:
        t.close()
        fresh.close()


def test_a_twin_takes_over_the_last_closed_twins_fmu_with_the_same_bits(cfg, fmu):
    """The next unit's twin reuses the FMU instance of the last one closed (no extraction
    again); its runs equal a fresh instance's, and release_spare frees it."""
    import twinmon.diagnose.twin as tw
    args = (cfg, fmu, ["m_flow"], cfg.model.output.times.times, {"m_flow": SIGMA},
            list(cfg.model.effects))
    theta, eff = np.array([12.0, 3.4]), {"valve.opening_time": 4.0}
    a = Twin(*args)
    first = a.run(theta + 1.0, eff)
    model = a.model
    a.close()
    b = Twin(*args)
    try:
        assert b.model is model and not tw._SPARE
        again, fresh = b.run(theta), Twin(*args)
        assert fresh.model is not model
        ref = fresh.run(theta)
        for name in ref:
            np.testing.assert_array_equal(again[name], ref[name])
        for name, x in fresh.run(theta + 1.0, eff).items():
            np.testing.assert_array_equal(x, first[name])
        fresh.close()
    finally:
        b.close()
        tw.release_spare()
    assert not tw._SPARE and model._fmu is None


def test_base_fit_recovers_the_inputs(twin):
    truth = np.array([14.0, 3.3])
    y = twin.predict(truth)[None]
    fit = JointFit(twin, y, np.array([1])).solve(twin.u_of([10.0, 3.61]))
    np.testing.assert_allclose(twin.theta_of(fit.x), truth, rtol=1e-4)
    assert fit.chi2_rows[0] < 1e-6


def test_joint_fit_recovers_an_effect_shared_over_years(twin):
    # Two years with different inputs share one valve opening time from year 2 on.
    thetas = np.array([[11.0, 3.6], [12.0, 3.5]])
    y = np.array([twin.predict(thetas[0]), twin.predict(thetas[1], {"valve.opening_time": 7.0})])
    prob = JointFit(twin, y[1:], np.array([2]), [("valve.opening_time", 2)])
    x0 = np.concatenate([[twin.effect_u("valve.opening_time", 5.0)],
                         twin.u_of([[13.0, 3.7]]).ravel()])
    fit = prob.solve(x0)
    ue, ut = prob.unpack(fit.x)
    assert twin.effect_of("valve.opening_time", ue[0]) == pytest.approx(7.0, abs=0.05)
    np.testing.assert_allclose(twin.theta_of(ut[0]), thetas[1], rtol=1e-3)


def test_jacobian_matches_central_differences(twin):
    y = twin.predict(np.array([12.0, 3.5]), {"sensor.tau": 0.6})[None]
    prob = JointFit(twin, y, np.array([1]), [("sensor.tau", 1)])
    x = np.array([0.3, 0.4, 0.6])
    J = prob.jacobian(x)
    h = 1e-4
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        num = (prob.residuals(x + e) - prob.residuals(x - e)) / (2 * h)
        np.testing.assert_allclose(J[:, j], num, rtol=2e-2, atol=1e-2 * np.abs(num).max())


# -- the stage -------------------------------------------------------------------------------
def test_null_unit_gives_no_gap(cfg, fmu, twin):
    rng = np.random.default_rng(5)
    years = np.arange(1, 4)
    flows = np.array([twin.run(np.array([10.0 + 0.2 * k, 3.7]))["sensor.m_flow"]
                      for k in range(3)]) + SIGMA * rng.standard_normal((3, 25))
    g = diagnose_unit(cfg, fmu, "U", cfg.model.output.times.times, years, {"m_flow": flows},
                      {"m_flow": SIGMA}, twin=twin)
    assert g.verdict == "none"
    assert g.effects == [] and g.where_years == []
    assert g.residual_before.shape == (3, 25)
    assert g.window_rms_before.shape == (3, len(cfg.diagnose.windows))
    assert 0.6 < g.rms_before < 1.4
    assert len(g.candidates) == len(cfg.model.effects)


def test_an_estimated_noise_level_is_not_read_as_a_gap(cfg, fmu, twin):
    # Eight clean years whitened by a noise level 20 % low, as an unlucky estimate from
    # the plateau's few samples gives: taken as known, the residuals look 1.56 times too
    # large in every year, a gap; with the estimate's degrees of freedom counted, none.
    rng = np.random.default_rng(5)
    years = np.arange(1, 9)
    flows = np.array([twin.run(np.array([10.0 + 0.2 * k, 3.7 - 0.02 * k]))["sensor.m_flow"]
                      for k in range(8)]) + SIGMA * rng.standard_normal((8, 25))
    args = (cfg, fmu, "U", cfg.model.output.times.times, years, {"m_flow": flows},
            {"m_flow": 0.8 * SIGMA})
    assert diagnose_unit(*args).verdict != "none"
    g = diagnose_unit(*args, noise_dof={"m_flow": 20.0})
    assert g.verdict == "none" and g.p_gap > 0.05
    # The line says how well the noise level is known.
    assert g.noise_dof == 20.0 and g.as_dict()["noise"]["estimated_dof"] == 20.0
    assert "noise estimated from the record to +-16 %" in summary_line("U", g)


def test_diagnose_writes_gap_and_reads_back(tmp_path):
    cfg = small_fleet_cfg({"A": HEALTHY,
                           "B": {**HEALTHY, "effects": {"motor.start_delay":
                                                        {"value": 1.5, "onset": 2}}}})
    fabricate(cfg, tmp_path / "obs.h5", tmp_path / "truth.h5")
    s = diagnose(cfg, tmp_path / "obs.h5", tmp_path / "gap.h5", workers=1)
    assert s.units["A"].verdict == "none"
    b = s.units["B"]
    assert b.verdict == "effect" and b.effects[0] == "motor.start_delay"
    lo, hi = b.estimate["motor.start_delay"][1:]
    assert lo <= 1.5 <= hi
    gap = read_gap(tmp_path / "gap.h5")
    assert gap.windows == list(cfg.diagnose.windows)
    rb = gap.units["B"]
    assert rb.verdict == "effect" and rb.effects == b.effects and rb.onset == b.onset
    np.testing.assert_allclose(rb.residual_before, b.residual_before)
    assert rb.predicted_after.shape == (3, 25)
    assert rb.estimate["motor.start_delay"][0] == pytest.approx(b.estimate["motor.start_delay"][0])
    with artifacts.open_artifact(tmp_path / "gap.h5", "gap") as f:
        # Every field of the per-unit records is documented once, at the root.
        doc = json.loads(f.attrs["array_fields"])
        for name in f["units/B/record"].dtype.names + f["units/B/candidates"].dtype.names:
            assert doc[name][1], name
        assert doc["residual_before"][0] == "1"
        inputs = json.loads(f.attrs["inputs"])
        assert inputs[0]["path"].endswith("obs.h5")
    # One effect: one group, its members those of `group`, each with its consequences.
    assert [[m["effect"] for m in grp["members"]] for grp in b.groups] == [b.group]
    assert rb.groups == json.loads(json.dumps(b.groups))
    assert s.units["A"].groups == [] and gap.units["A"].groups == []
    d = s.as_dict()["units"]["B"]
    assert d["groups"][0]["effect"] == "motor.start_delay"
    assert sum(m["weight"] for m in d["groups"][0]["members"]) == pytest.approx(1.0, abs=1e-5)
    # A gap.h5 written before groups were recorded reads with none.
    import h5py
    with h5py.File(tmp_path / "gap.h5", "r+") as f:
        res = json.loads(f["units/B"].attrs["result"])
        del res["groups"]
        f["units/B"].attrs["result"] = json.dumps(res)
    assert read_gap(tmp_path / "gap.h5").units["B"].groups == []
    assert set(d) >= {"verdict", "effects", "where", "shrink", "estimate"}
    assert set(d["shrink"]) == {"rms_before", "rms_after", "closed_percent"}
    assert set(d["estimate"]["motor.start_delay"]) == {"mean", "q05", "q95"}


def test_read_gap_rejects_another_artifact(tmp_path):
    with artifacts.write_artifact(tmp_path / "x.h5", "forecast") as f:
        f.attrs["x"] = 1
    with pytest.raises(ArtifactError, match="schema"):
        read_gap(tmp_path / "x.h5")


def test_unknown_candidate_is_a_config_error(tmp_path):
    cfg = small_fleet_cfg({"A": HEALTHY}, candidates=["valve.stuck"])
    with pytest.raises(ConfigError, match="valve.stuck"):
        candidate_names(cfg)


@pytest.mark.parametrize("key, value", [("alpha", 1.5), ("min_closed", 120.0),
                                        ("windows", {"x": {"start": 5.0, "stop": 1.0}}),
                                        ("max_effects", 0), ("bogus", 1)])
def test_invalid_diagnose_section_is_rejected(key, value):
    with pytest.raises(ConfigError, match=f"diagnose.*{key}"):
        small_fleet_cfg({"A": HEALTHY}, **{key: value})


def test_time_grid_mismatch_is_an_input_error(tmp_path):
    cfg = small_fleet_cfg({"A": HEALTHY}, years=1)
    fabricate(cfg, tmp_path / "obs.h5", tmp_path / "truth.h5")
    other = copy.deepcopy(dict(cfg.raw))
    other["model"]["output"]["times"] = {"start": 1.0, "stop": 50.0, "step": 1.0}
    cfg2 = config_from_mapping(other, PUMP)
    with pytest.raises(InputDataError, match="time"):
        diagnose(cfg2, tmp_path / "obs.h5", tmp_path / "gap.h5", workers=1)
    assert not (tmp_path / "gap.h5").exists()


def test_cli_json_and_summary(tmp_path):
    from twinmon.cli import main
    cfg_path = tmp_path / "fleet.yaml"
    cfg_path.write_text(f"extends: {PUMP}\nfabricate:\n  years: 3\n  seed: 3\n  units:\n"
                        "    A:\n      trajectories:\n"
                        "        motor_damping: {start: 10.0}\n        pump_coef: {start: 3.7}\n")
    runner = CliRunner()
    r = runner.invoke(main, ["fabricate", "-c", str(cfg_path), "-o", str(tmp_path / "o.h5")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(main, ["diagnose", "-c", str(cfg_path), "--observations",
                             str(tmp_path / "o.h5"), "-o", str(tmp_path / "gap.h5"), "--json",
                             "-j", "1"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["units"]["A"]["verdict"] == "none"
    assert "A: no significant gap" in r.stderr
    r = runner.invoke(main, ["diagnose", "-c", str(cfg_path), "--observations",
                             str(tmp_path / "missing.h5")])
    assert r.exit_code == 5 and "missing.h5" in r.stderr


def test_posterior_predictive_map_and_mismatched_posterior(cfg, fmu, twin):
    from twinmon.calibrate import Posterior, UnitPosterior
    from twinmon.diagnose import _posterior_for
    rng = np.random.default_rng(2)
    years = np.arange(1, 3)
    flows = np.array([twin.run(np.array([10.0, 3.7]))["sensor.m_flow"]] * 2) \
        + SIGMA * rng.standard_normal((2, 25))
    mean = np.array([[10.0, 3.7], [10.0, 3.7]])
    cov = np.array([np.diag([0.5 ** 2, 0.05 ** 2])] * 2)
    g_ml = diagnose_unit(cfg, fmu, "U", cfg.model.output.times.times, years,
                         {"m_flow": flows}, {"m_flow": SIGMA}, twin=twin)
    g_post = diagnose_unit(cfg, fmu, "U", cfg.model.output.times.times, years,
                           {"m_flow": flows}, {"m_flow": SIGMA}, twin=twin,
                           posterior=(mean, cov))
    assert np.isfinite(g_post.residual_before).all()
    assert not np.allclose(g_post.residual_before, g_ml.residual_before)
    assert g_post.verdict == g_ml.verdict == "none"
    samples = rng.normal(mean[:, None, :], [0.5, 0.05], size=(2, 50, 2))
    z = np.zeros((2, 2))
    up = UnitPosterior(np.array([1, 3]), samples, mean, mean, mean, mean, z, z,
                       np.zeros((2, 2)), np.full(2, SIGMA), "file")
    post = Posterior(cfg.model.input_names, {"U": up})
    with pytest.raises(ArtifactError, match="years"):
        _posterior_for("p.h5", post, cfg, "U", years)
    with pytest.raises(ArtifactError, match="no posterior"):
        _posterior_for("p.h5", post, cfg, "V", years)


# -- the process pool ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_units(tmp_path_factory):
    """A 2-unit, 1-year fleet: enough for diagnose to start a pool of 2 workers."""
    tmp = tmp_path_factory.mktemp("pool")
    cfg = small_fleet_cfg({"A": HEALTHY, "B": HEALTHY}, years=1)
    fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
    return cfg, tmp / "obs.h5"


def _die_in_worker(args, parent=os.getpid()):
    # A crash in the FMU's native code, as the parent sees it: the worker vanishes.
    if os.getpid() != parent:
        os._exit(1)
    raise AssertionError("the unit ran in the parent process, not in a worker")


def _report_sigint_handler(args):
    raise RuntimeError(f"SIGINT handler in the worker: {signal.getsignal(signal.SIGINT)!r}")


def test_dead_worker_is_one_simulation_error(two_units, tmp_path, monkeypatch):
    import twinmon.diagnose as dg
    cfg, obs = two_units
    monkeypatch.setattr(dg, "_job", _die_in_worker)
    with pytest.raises(SimulationError, match="worker process died") as info:
        diagnose(cfg, obs, tmp_path / "gap.h5", workers=2)
    msg = str(info.value)
    assert "\n" not in msg and str(resolve_fmu(cfg.model.fmu)) in msg
    assert not (tmp_path / "gap.h5").exists()


def test_workers_ignore_ctrl_c(two_units, tmp_path, monkeypatch):
    # Ctrl-C reaches the whole process group; only the parent may act on it.
    import twinmon.diagnose as dg
    cfg, obs = two_units
    monkeypatch.setattr(dg, "_job", _report_sigint_handler)
    with pytest.raises(RuntimeError, match="SIG_IGN"):
        diagnose(cfg, obs, tmp_path / "gap.h5", workers=2)


def test_the_default_workers_are_the_cores_this_process_may_use(two_units, tmp_path,
                                                                monkeypatch):
    """diagnose.workers 0 counts the cores the process is bound to (taskset, a batch
    scheduler), as the other stages do, not the machine's: bound to one, no pool."""
    import twinmon.diagnose as dg
    cfg, obs = two_units
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    monkeypatch.setattr(dg, "_map_units", _die_in_worker)      # a pool would fail the test
    s = diagnose(cfg, obs, tmp_path / "gap.h5")
    assert cfg.diagnose.workers == 0 and s.workers == 1 and set(s.units) == {"A", "B"}


def test_ctrl_c_is_interrupted_and_writes_nothing(two_units, tmp_path, monkeypatch):
    import twinmon.diagnose as dg

    def interrupt(args):
        raise KeyboardInterrupt
    cfg, obs = two_units
    monkeypatch.setattr(dg, "_job", interrupt)
    out = tmp_path / "gap.h5"
    with pytest.raises(Interrupted, match=r"gap\.h5: interrupted; nothing was written"):
        diagnose(cfg, obs, out, workers=1)
    assert not out.exists()


def test_confirmation_fits_follow_the_screening():
    """Full fits for the best-screened candidates and any scoring half the best; none when
    even the best screens below the floor; every candidate with confirm_first 0."""
    from twinmon.diagnose.identify import to_confirm
    sc = {n: (score, 0.0, 1, None) for n, score in
          {"a": 200.0, "b": 180.0, "c": 20.0, "d": 150.0, "e": 5.0, "f": 110.0}.items()}
    assert to_confirm(sc, 3) == {"a", "b", "d", "f"}        # f: 110 >= half of 200
    assert to_confirm(sc, 2) == {"a", "b", "d", "f"}
    assert to_confirm(sc, 0) == set(sc)
    assert to_confirm(sc, 3, floor=250.0) == set()
    assert to_confirm(sc, 0, floor=250.0) == set(sc)
    low = {n: (v, 0.0, 1, None) for n, v in {"a": 3.0, "b": -1.0, "c": 0.5}.items()}
    assert to_confirm(low, 2, floor=5.3) == set()
    assert to_confirm(low, 2) == {"a", "c"}     # the top two; b is below half of a's 3
