"""reduce: Karhunen-Loeve + GP surrogate on real FMU runs; reload predicts exactly."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinmon.config import load_config
from twinmon.errors import ArtifactError
from twinmon.reduce import read_surrogate, read_validation, reduce
from twinmon.simulate import read_simulations, simulate

from ..conftest import write_yaml


@pytest.fixture(scope="module")
def fitted(tmp_path_factory, fmu_path):
    tmp = tmp_path_factory.mktemp("reduce")
    from ..conftest import CONFIGS
    cfg_path = write_yaml(tmp / "c.yaml", {"extends": str(CONFIGS / "pump.yaml"),
                                           "simulate": {"train_size": 48, "test_size": 16}})
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    summary = reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    return cfg, tmp, summary


def test_modes_chosen_by_variance_threshold(fitted):
    cfg, tmp, summary = fitted
    s = read_surrogate(tmp / "sur.h5")
    ratios = np.cumsum(s.eigenvalues) / s.eigenvalues.sum()
    assert s.variance_ratio >= cfg.reduce.variance_threshold
    assert s.n_modes == 1 or ratios[s.n_modes - 2] < cfg.reduce.variance_threshold
    assert summary.modes == s.n_modes


def test_reloaded_surrogate_predicts_exactly_what_the_fitted_one_did(fitted):
    from twinmon.reduce import fit_surrogate
    cfg, tmp, _ = fitted
    sims = read_simulations(tmp / "sims.h5")
    fresh = fit_surrogate(sims.X["train"], sims.Y["train"], sims.time, sims.bounds,
                          sims.input_names, cfg.reduce)
    loaded = read_surrogate(tmp / "sur.h5")
    X = sims.X["test"]
    m1, v1 = fresh.predict_with_var(X)
    m2, v2 = loaded.predict_with_var(X)
    assert np.array_equal(m1, m2) and np.array_equal(v1, v2)


def test_a_coarse_surrogate_is_a_warning(fitted):
    from twinmon.reduce import error_warning
    _, _, summary = fitted
    w = error_warning(0.141, 0.02, "the output m_flow")
    assert w.startswith("the output m_flow: the surrogate's largest error on the test runs "
                        "is 14.1 % of the output's range (mean 2 %)")
    v = summary.validation
    assert error_warning(v.max_range_error, v.mean_range_error, "x") == ""   # < 1 %
    assert error_warning(0.141, 0.02, "x", capped="said already") == ""
    assert not any("largest error on the test runs" in w for w in summary.warnings)


def test_a_log_transform_of_outputs_below_zero_is_a_config_error(fitted):
    from twinmon.errors import ConfigError
    from twinmon.reduce import fit_surrogate
    cfg, tmp, _ = fitted
    sims = read_simulations(tmp / "sims.h5")
    with pytest.raises(ConfigError, match=r"reduce.transform: log needs positive outputs, "
                                          r"but run 0 has -"):
        fit_surrogate(sims.X["train"], -sims.Y["train"], sims.time, sims.bounds,
                      sims.input_names, dataclasses.replace(cfg.reduce, transform="log"))


def test_surrogate_interpolates_training_runs_and_is_accurate_on_test_runs(fitted):
    _, tmp, summary = fitted
    sims = read_simulations(tmp / "sims.h5")
    s = read_surrogate(tmp / "sur.h5")
    # Kriging interpolates the kept modes' coefficients at the training points; what is left
    # is the truncation of the discarded modes, which truncation_var accounts for.
    xi = s.coefficients(sims.X["train"])
    assert np.allclose(xi, s.xi_train, rtol=0, atol=1e-6 * np.abs(s.xi_train).max())
    z_err = np.log(s.predict(sims.X["train"])) - np.log(sims.Y["train"])
    assert np.all(np.abs(z_err) <= 6 * np.sqrt(s.truncation_var) + 1e-9)
    v = summary.validation
    assert v.n_test == 16 and v.max_rel_error < 0.02 and v.mean_rel_error < 2e-3
    assert all(q > 0.99 for q in v.q2[:2])
    assert read_validation(tmp / "sur.h5")["max_rel_error"] == pytest.approx(v.max_rel_error)


def test_predictive_variance_is_small_at_training_points_and_positive(fitted):
    _, tmp, _ = fitted
    s = read_surrogate(tmp / "sur.h5")
    sims = read_simulations(tmp / "sims.h5")
    _, v_train = s.predict_with_var(sims.X["train"][:5])
    _, v_test = s.predict_with_var(sims.X["test"][:5])
    assert np.all(v_train >= 0) and np.all(v_test > 0)
    assert v_train.mean() < v_test.mean()


def test_in_box(fitted):
    _, tmp, _ = fitted
    s = read_surrogate(tmp / "sur.h5")
    lo, hi = s.bounds[:, 0], s.bounds[:, 1]
    X = np.array([(lo + hi) / 2, lo - 1e-3, hi])
    assert s.in_box(X).tolist() == [True, False, True]


def test_input_mismatch_is_an_artifact_error(fitted):
    cfg, tmp, _ = fitted
    other = load_config(cfg.source, [])
    import dataclasses
    model = dataclasses.replace(other.model, inputs={"x": other.model.inputs["pump_coef"],
                                                     "y": other.model.inputs["motor_damping"]})
    with pytest.raises(ArtifactError, match=r"sims.h5: inputs are \['motor_damping', 'pump_coef'\]"):
        reduce(dataclasses.replace(other, model=model), tmp / "sims.h5", tmp / "bad.h5")
    assert not (tmp / "bad.h5").exists()


# ----------------------------------------------------------------------------------------
# a cap, not the variance threshold, decides the modes: said, with the key to raise

def test_a_binding_mode_cap_is_warned_with_the_key_to_raise(tmp_path):
    """The DC drive with reduce.max_modes 2: the threshold 0.99999 is out of reach, the
    warning says so, gives the variance kept and the test error, and names the key; the
    report and its terminal summary say it too."""
    from twinmon.config import load_config
    from twinmon.reduce import reduce
    from twinmon.report import report
    from twinmon.simulate import simulate
    from ..conftest import CONFIGS, write_yaml
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "simulate": {"train_size": 16, "test_size": 4, "executor": "serial"},
        "reduce": {"max_modes": 2, "channels": []}}))
    simulate(cfg, tmp_path / "sims.h5")
    s = reduce(cfg, tmp_path / "sims.h5", tmp_path / "sur.h5")
    assert s.modes == 2 and s.variance_ratio < 0.99999
    capped = [w for w in s.warnings if "capped" in w]
    assert len(capped) == 1, s.warnings
    w = capped[0]
    assert "reduce.max_modes = 2 at 2 modes" in w and "raise reduce.max_modes" in w
    assert f"{100 * s.variance_ratio:.4g} % of the variance" in w
    assert f"{100 * s.validation.max_range_error:.3g} % of the range" in w
    rep = report(cfg, tmp_path / "report", simulations=tmp_path / "sims.h5",
                 surrogate=tmp_path / "sur.h5")
    assert any("raise reduce.max_modes" in n for n in rep.notes)
    assert "raise reduce.max_modes" in (tmp_path / "report" / "index.html").read_text()
    line = next(ln for ln in rep.terminal().splitlines() if ln.startswith("surrogate:"))
    assert f"max error {100 * rep.surrogate['max_range_error']:.3g} % of the output's range " \
           "on 4 test runs" in line and "raise reduce.max_modes" in line


def test_no_cap_warning_when_the_threshold_is_reached(tmp_path):
    from twinmon.config import load_config
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    from ..conftest import CONFIGS, write_yaml
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "simulate": {"train_size": 16, "test_size": 4, "executor": "serial"},
        "reduce": {"variance_threshold": 0.99, "max_modes": 8, "channels": []}}))
    simulate(cfg, tmp_path / "sims.h5")
    s = reduce(cfg, tmp_path / "sims.h5", tmp_path / "sur.h5")
    assert s.variance_ratio >= 0.99 and not [w for w in s.warnings if "capped" in w]


def test_openturns_log_lines_are_captured_and_stderr_restored(capfd):
    """OpenTURNS' warnings during a fit (Cobyla at its evaluation limit) come back as lines
    that reduce turns into one warning naming the modes, not as coloured text on stderr."""
    import openturns as ot
    from twinmon.reduce.surrogate import ot_log_captured
    with ot_log_captured() as log:
        ot.Log.Warn("The Cobyla algorithm failed. test")
    assert any("Cobyla" in line for line in log), log
    assert "Cobyla" not in capfd.readouterr().err


def test_a_stopped_hyperparameter_search_is_one_warning_naming_the_modes(fitted):
    from twinmon.reduce import optimiser_warning
    _, tmp, summary = fitted
    s = read_surrogate(tmp / "sur.h5")
    s.optimiser_stopped = [2, 3]
    w = optimiser_warning(s, summary.validation, "the output m_flow")
    assert w.startswith(f"the output m_flow: the Gaussian process of mode(s) 2, 3 of "
                        f"{s.n_modes} stopped its hyperparameter search at the evaluation "
                        "limit")
    assert w.endswith("% of the output's range")
