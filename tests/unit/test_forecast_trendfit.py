"""forecast, the trend-fit gate (twinmon/forecast/trendfit.py): one-year-ahead errors of the
posterior's trend model pass on histories it follows, fail on those it cannot, and reject
at about their level on histories drawn from the model itself, with 1, 2 and 3 inputs."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats

from twinmon.config import load_config
from twinmon.forecast.trendfit import (check_trend_fit, cut_indices, describe_latest,
                                       describe_miss,
                                       standardise)

from ..conftest import CONFIGS, write_yaml

YEARS = np.arange(1, 11)
SHAPES = {"line": 0.6, "accelerating": 0.2, "change": 0.2}
LINE = {"line": 1.0}
#: Per input: the site sd (input units) and the year-to-year sd; the sites' correlation.
SITE_SD = {"motor_damping": 0.3, "pump_coef": 0.05, "extra": 0.02}
SIGMA = {"motor_damping": 0.15, "pump_coef": 0.01, "extra": 0.005}
RHO = 0.9


class Fleet:
    """The fleet's log-normal prior of sigma, as :class:`~twinmon.calibrate.fleet.FleetPrior`
    gives it to the gate."""

    def __init__(self, names):
        self.median = np.array([SIGMA[n] for n in names])
        self.tau = np.full(len(names), 0.5)


@pytest.fixture(scope="module")
def configs(tmp_path_factory):
    """The pump's config with 1, 2 and 3 inputs (a third made up: the gate reads names,
    boxes and normal rates from the config, nothing of the pump)."""
    pump = load_config(CONFIGS / "pump.yaml")
    one = dataclasses.replace(pump, model=dataclasses.replace(
        pump.model, inputs={"motor_damping": pump.model.inputs["motor_damping"]}))
    path = write_yaml(tmp_path_factory.mktemp("trendfit") / "three.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "model": {"inputs": {"extra": {"variable": "pump.eta", "low": 0.0, "high": 1.0,
                                       "nominal": 0.5, "units": "1", "normal_rate": 0.0,
                                       "normal_rate_tolerance": 0.01}}}})
    return {1: one, 2: pump, 3: load_config(path)}


def _sites(cfg):
    """Each year's site covariance [K, d, d]: the pump's inputs trade off (correlation 0.9)."""
    sd = np.array([SITE_SD[n] for n in cfg.model.input_names])
    d = sd.size
    C = RHO * np.outer(sd, sd) + (1 - RHO) * np.diag(sd ** 2)
    return np.repeat(C[None], YEARS.size, axis=0), np.array(
        [SIGMA[n] for n in cfg.model.input_names])[:d]


def _history(cfg, rng, path=None):
    """Sites of one unit: ``path`` [K, d] (default: a line) plus year-to-year variation
    and each site's error."""
    cov, sigma = _sites(cfg)
    d = cov.shape[1]
    if path is None:
        path = cfg.model.bounds.mean(axis=1) + np.outer(YEARS - 5.5, 0.02 * np.ptp(
            cfg.model.bounds, axis=1))
    theta = path + rng.standard_normal((YEARS.size, d)) * sigma
    x = theta + np.einsum("kij,kj->ki", np.linalg.cholesky(cov),
                          rng.standard_normal((YEARS.size, d)))
    return x, cov


def _check(cfg, x, cov, priors=SHAPES, starts=None):
    d = x.shape[1]
    starts = starts or [np.array([YEARS[0]])] * d
    return check_trend_fit(cfg, YEARS, x, cov, starts, priors, Fleet(cfg.model.input_names))


def test_cut_years_need_three_years_of_the_segment_in_force():
    """Years 4 on are predicted; a repair in year 6 of one input restarts its count, so
    years 6-8 are not (the new level is unknown until three years of it)."""
    one = [np.array([1])]
    assert list(YEARS[cut_indices(YEARS, one)]) == [4, 5, 6, 7, 8, 9, 10]
    repaired = [np.array([1]), np.array([1, 6])]
    assert list(YEARS[cut_indices(YEARS, repaired)]) == [4, 5, 9, 10]


def test_the_years_weights_before_a_cut_are_a_slice_of_the_units():
    from twinmon.calibrate.gaussian_trend import weights_of, year_weight_table, year_weights
    rng = np.random.default_rng(5)
    A = rng.standard_normal((10, 2, 3))
    cov = A @ np.swapaxes(A, 1, 2)
    sigma = np.exp(rng.standard_normal((16, 2)))
    table = year_weight_table(cov, sigma)
    for k in (3, 7, 10):
        for a, b in zip(weights_of(table, k), year_weights(cov[:k], sigma)):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=0)


def test_rosenblatt_errors_are_independent_standard_normals_under_a_mixture():
    """Draws of a two-component, correlated Gaussian mixture standardise to independent
    N(0, 1) values (the transform the gate's chi-square rests on)."""
    rng = np.random.default_rng(0)
    w = np.array([0.3, 0.7])
    mean = np.array([[0.0, 0.0], [1.5, -1.0]])
    S = np.array([[[1.0, 0.8], [0.8, 1.0]], [[0.5, -0.2], [-0.2, 2.0]]])
    pick = rng.choice(2, 4000, p=w)
    y = mean[pick] + np.einsum("nij,nj->ni", np.linalg.cholesky(S[pick]),
                               rng.standard_normal((4000, 2)))
    z = np.array([standardise(v, w, mean, S)[0] for v in y])
    assert np.allclose(z.mean(axis=0), 0, atol=0.06)
    assert np.allclose(z.std(axis=0), 1, atol=0.05)
    assert abs(np.corrcoef(z.T)[0, 1]) < 0.05
    assert stats.kstest(z[:, 1], "norm").pvalue > 0.01


def test_a_straight_line_passes_and_an_outlying_year_fails(configs):
    """A line with the fleet's scatter passes; the same history with year 6's first input
    off by seven site sd fails, and the reason names year 6 and the input."""
    cfg = configs[2]
    x, cov = _history(cfg, np.random.default_rng(1))
    fit = _check(cfg, x, cov)
    assert fit.p_value > 0.05
    assert list(fit.years) == list(range(4, 11))
    x[5, 0] += 7 * SITE_SD["motor_damping"]
    fit = _check(cfg, x, cov)
    assert fit.p_value < 0.01
    assert 6 in fit.as_dict(0.01)["missed_years"]
    reason = describe_miss(cfg, fit, 0.01)
    assert reason.startswith("prognosis unreliable: the trend missed year(s) 6")
    assert "motor_damping" in reason and "above the forecast" in reason


def test_a_surprising_latest_year_alone_is_named(configs):
    """The latest year off the trend of the years before, by less than the whole history's
    check needs (it corrects for the years' number) but beyond alpha alone: named, since
    the forecast starts from it; the same offset in an earlier year is not; a line, not."""
    cfg = configs[2]
    x, cov = _history(cfg, np.random.default_rng(1))
    assert describe_latest(cfg, _check(cfg, x, cov), 10, 0.01) == ""
    found = {}
    for k in (9, 6):
        y = x.copy()
        y[k, 1] -= 4.5 * SITE_SD["pump_coef"]
        fit = _check(cfg, y, cov)
        found[k] = (fit, describe_latest(cfg, fit, 10, 0.01))
    fit, why = found[9]
    assert fit.year_p[-1] < 0.01 <= fit.p_value, (fit.year_p, fit.p_value)
    assert why.startswith("prognosis unreliable: the latest year, 10, is not where the trend "
                          f"of the years before put it (p = {fit.year_p[-1]:.2g}; pump_coef lay")
    assert "below that forecast" in why
    assert found[6][1] == ""
    # A record whose last year the check did not predict says nothing.
    assert describe_latest(cfg, fit, 11, 0.01) == "" and describe_latest(cfg, None, 10, 0.01) == ""


def test_accelerating_wear_passes_when_the_shapes_include_it(configs):
    """Wear that accelerates (quadratic: the rate goes from 0.3 to 2.4 a year, 36 site sd
    of bend over the record): the shapes' model, with its accelerating shape, follows it;
    the straight line alone misses it."""
    cfg = configs[2]
    t = YEARS.astype(float)
    path = np.column_stack([10 + 0.1 * t + 0.12 * t ** 2, 3.7 - 0.02 * t])
    passed = sum(_check(cfg, *_history(cfg, np.random.default_rng(s), path)).p_value > 0.01
                 for s in range(10))
    failed = sum(_check(cfg, *_history(cfg, np.random.default_rng(s), path),
                        priors=LINE).p_value < 0.01 for s in range(10))
    assert passed >= 9 and failed >= 8


@pytest.mark.parametrize("kind", ["zigzag", "oscillation"])
def test_wear_that_reverses_or_oscillates_fails(configs, kind):
    """The first input rises, falls back and rises again (two changes of rate), or
    oscillates (period 4 years): neither a line, a curve nor one change follows it."""
    cfg = configs[2]
    t = YEARS.astype(float)
    if kind == "zigzag":
        first = 10 + np.where(t <= 4, t, np.where(t <= 7, 8 - t, t - 6))
    else:
        first = 12 + 0.2 * t + 1.2 * np.sin(np.pi * t / 2)
    path = np.column_stack([first, 3.7 - 0.02 * t])
    failed = sum(_check(cfg, *_history(cfg, np.random.default_rng(s), path)).p_value < 0.01
                 for s in range(10))
    assert failed >= 9


@pytest.mark.slow
@pytest.mark.parametrize("d", [1, 2, 3])
def test_rejects_at_about_its_level_on_histories_of_the_model(configs, d):
    """Lines with the fleet's scatter (sigma drawn from the fleet's prior, the sites'
    errors correlated): at alpha 0.01 the gate rejects at most 3 %."""
    cfg = configs[d]
    rng = np.random.default_rng(10 + d)
    cov, sigma = _sites(cfg)
    fleet = Fleet(cfg.model.input_names)
    n, rejected = 150, 0
    for _ in range(n):
        s = sigma * np.exp(0.5 * rng.standard_normal(d))
        slope = 0.02 * np.ptp(cfg.model.bounds, axis=1) * rng.uniform(-1, 1, d)
        path = cfg.model.bounds.mean(axis=1) + np.outer(YEARS - 5.5, slope)
        theta = path + rng.standard_normal((YEARS.size, d)) * s
        x = theta + np.einsum("kij,kj->ki", np.linalg.cholesky(cov),
                              rng.standard_normal((YEARS.size, d)))
        fit = check_trend_fit(cfg, YEARS, x, cov, [np.array([1])] * d, SHAPES, fleet)
        rejected += fit.p_value < 0.01
    assert rejected / n <= 0.03


def test_the_shapes_weighed_are_the_ones_the_posterior_recorded(configs, tmp_path):
    """The gate weighs ``calibrate.shapes`` as the posterior's provenance recorded them (a
    posterior drawn with the line alone is judged as a line), else the config's."""
    import h5py
    import yaml

    from twinmon.forecast.trendfit import recorded_shapes
    cfg = configs[2]
    path = tmp_path / "post.h5"
    with h5py.File(path, "w") as f:
        f.attrs["config"] = yaml.safe_dump({"calibrate": {"shapes": {"line": 1.0}}})
    assert recorded_shapes(cfg, path) == {"line": 1.0}
    assert recorded_shapes(cfg, tmp_path / "absent.h5") == dict(cfg.calibrate.shapes)


def test_a_change_the_data_favour_restarts_the_check_there():
    """The posterior's change year restarts the check (as a repair does) when its
    probability is at least its prior share; a change the data do not favour does not."""
    from twinmon.forecast.trendfit import change_year
    shape = {"line": 0.5, "accelerating": 0.1, "change": 0.4, "change_year": 6}
    assert change_year(shape, SHAPES) == 6
    assert change_year({**shape, "line": 0.8, "change": 0.1}, SHAPES) is None
    assert change_year({}, SHAPES) is None and change_year(shape, LINE) is None
    # Each input's own year when the summary has them: only those inputs restart.
    per = {**shape, "change_year": 5, "change_years": [5, None]}
    assert change_year(per, SHAPES) == [5, None]


def test_each_input_restarts_the_check_in_its_own_change_year(configs):
    """A change year per input starts a segment for the inputs that change only."""
    from types import SimpleNamespace

    from twinmon.forecast.trendfit import unit_sites
    cfg = configs[2]
    up = SimpleNamespace(years=YEARS, mean=np.zeros((YEARS.size, 2)), site=None, events=())
    cov = np.tile(np.eye(2), (YEARS.size, 1, 1))
    _, _, starts = unit_sites(cfg, up, cov, {}, (), [5, None])
    assert [list(s) for s in starts] == [[1, 5], [1]]
    _, _, starts = unit_sites(cfg, up, cov, {}, (), 7)
    assert [list(s) for s in starts] == [[1, 7], [1, 7]]
