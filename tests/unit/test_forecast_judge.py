"""Detection on the health indicator, the joint box test and attribution
(twinmon.forecast.detection, .covariance, .attribution), and the time-to-failure scores of
the back-test."""
from __future__ import annotations

import numpy as np
import pytest

from twinmon.backtest import ttf_scores
from twinmon.forecast.attribution import AMBIGUOUS, attribute
from twinmon.forecast.covariance import filter_error_covariance, slope_covariance
from twinmon.forecast.detection import box_distance, box_test, box_test_uniform, indicator_drift
from twinmon.forecast.trend import fit_trend
from twinmon.safety import median_failure_year

RATE, TOL = np.array([0.0, -0.02]), np.array([0.25, 0.03])
GRAD = np.array([1.0, -4.0])        # indicator units per input unit
YEARS = np.arange(1, 11)


def _indicator(slope, noise, rng, n_o=200, base=15.0):
    """Yearly indicator draws: a line plus year-to-year scatter, posterior spread 0.05."""
    centre = base + slope * (YEARS - 1) + noise * rng.standard_normal(YEARS.size)
    return centre[:, None] + 0.05 * rng.standard_normal((YEARS.size, n_o))


def test_indicator_drift_rejects_only_beyond_what_normal_ageing_produces():
    rng = np.random.default_rng(0)
    normal = float(GRAD @ RATE)                 # 0.08 per year
    band = float(np.sum(np.abs(GRAD) * TOL))    # 0.37 per year either way
    p = []
    for slope in (normal, normal + 0.5 * band, normal + 2.5 * band):
        d = indicator_drift(YEARS, _indicator(slope, 0.1, rng), GRAD, RATE, TOL, +1, 0.01)
        p.append(d.p_value)
        assert abs(d.slope - slope) < 0.1
    assert p[0] > 0.3 and p[1] > 0.01 and p[2] < 1e-4
    # the unsafe side only: a falling indicator is not a fault when unsafe is above
    d = indicator_drift(YEARS, _indicator(-1.0, 0.1, rng), GRAD, RATE, TOL, +1, 0.01)
    assert d.p_value > 0.99 and not d.abnormal
    # sense -1 (unsafe below): the same falling indicator is abnormal
    d = indicator_drift(YEARS, _indicator(-1.0, 0.1, rng), GRAD, RATE, TOL, -1, 0.01)
    assert d.abnormal


def test_the_null_of_normal_ageing_by_quadrature_is_the_monte_carlo_one():
    """The sum of uniform terms by quadrature (two terms, and three, binned) gives the
    p-value 10^6 Monte Carlo draws give, within their error."""
    from scipy import stats

    from twinmon.forecast.detection import uniform_sum
    rng = np.random.default_rng(9)
    for half in (np.array([0.3, 0.05]), np.array([0.2, 0.1, 0.15]), np.array([0.4, 0.0])):
        u, w = uniform_sum(half)
        assert w.sum() == pytest.approx(1.0) and float(w @ u) == pytest.approx(0.0, abs=1e-12)
        mc = rng.uniform(-1, 1, (10 ** 6, half.size)) @ half
        for excess, se in ((0.5, 0.1), (0.2, 0.15), (0.9, 0.2)):
            p = float(w @ stats.t.sf((excess - u) / se, 8))
            ref = stats.t.sf((excess - mc) / se, 8)
            assert abs(p - ref.mean()) < 4 * ref.std() / 1e3 + 1e-6, (half, excess, p)


def test_indicator_drift_skips_years_where_the_level_is_never_reached():
    rng = np.random.default_rng(2)
    v = _indicator(0.5, 0.1, rng)
    v[-3:] = np.inf
    d = indicator_drift(YEARS, v, GRAD, RATE, TOL, +1, 0.01)
    assert d.years.tolist() == list(range(1, 8))
    v[2:] = np.inf
    d = indicator_drift(YEARS, v, GRAD, RATE, TOL, +1, 0.01)
    assert np.isnan(d.p_value) and not d.abnormal


def _trends(slopes, scatter, rng, corr=0.0):
    """OLS trends of two inputs with correlated year-to-year scatter [n, 2]."""
    L = np.linalg.cholesky(np.array([[1, corr], [corr, 1]]))
    e = (rng.standard_normal((YEARS.size, 2)) @ L.T) * scatter
    vals = np.array([10.0, 3.6]) + np.outer(YEARS, slopes) + e
    out = [fit_trend(YEARS, vals[:, i]) for i in range(2)]
    return [t for t, _ in out], np.column_stack([r for _, r in out])


def test_box_test_is_calibrated_inside_and_powerful_outside():
    rng = np.random.default_rng(3)
    scatter = np.array([0.3, 0.02])
    p_in = []
    for _ in range(200):   # slopes on the box's degrading corner: the least favourable null
        tr, res = _trends(RATE + np.array([1, -1]) * TOL, scatter, rng)
        C = slope_covariance(tr, res)
        p_in.append(box_test(np.array([t.slope for t in tr]), C, 8, RATE, TOL, [1, -1])[0])
    assert np.mean(np.array(p_in) < 0.05) <= 0.06
    tr, res = _trends(RATE + np.array([0.0, -3.0]) * TOL, scatter, rng)
    p, b0 = box_test(np.array([t.slope for t in tr]), slope_covariance(tr, res), 8, RATE, TOL,
                     [1, -1])
    assert p < 1e-3 and np.isclose(b0[1], RATE[1] - TOL[1], atol=1e-6)
    # improving faster than normal is not a fault (one-sided)
    tr, res = _trends(RATE + np.array([0.0, 3.0]) * TOL, scatter, rng)
    assert box_test(np.array([t.slope for t in tr]), slope_covariance(tr, res), 8, RATE, TOL,
                    [1, -1])[0] == 1.0


def test_box_distance_is_the_bounded_least_squares_projection():
    from scipy.optimize import lsq_linear
    rng = np.random.default_rng(7)
    sd = np.array([0.06, 0.02])
    C = np.outer(sd, sd) * np.array([[1.0, 0.9], [0.9, 1.0]])
    lo, hi = np.array([-np.inf, -0.05]), np.array([0.25, np.inf])
    B = np.array([0.2, -0.05]) + 3 * sd * rng.standard_normal((50, 2))
    Li = np.linalg.inv(np.linalg.cholesky(C))
    ref = [float(np.sum((Li @ (b - lsq_linear(Li, Li @ b, bounds=(lo, hi)).x)) ** 2))
           for b in B]
    assert np.allclose(box_distance(B, C, lo, hi), ref, atol=1e-8)


def test_uniform_null_box_test_holds_its_level_and_beats_the_least_favourable_one():
    """Healthy slopes anywhere in the band (uniform, as the null assumes): false alarms at
    the level; a pump fault twice the tolerance beyond normal, hidden along the ridge of two
    correlated estimates: p well below the least favourable test's."""
    rng = np.random.default_rng(8)
    sd = np.array([0.06, 0.02])
    C = np.outer(sd, sd) * np.array([[1.0, 0.85], [0.85, 1.0]])
    L = np.linalg.cholesky(C)
    p = [box_test_uniform(RATE + TOL * rng.uniform(-1, 1, 2) + L @ rng.standard_normal(2), C,
                          1000, RATE, TOL, [1, -1], rng) for _ in range(300)]
    assert np.mean(np.array(p) < 0.05) <= 0.08
    b = np.array([-0.05, RATE[1] - 2 * TOL[1] - 0.005])
    p_u = box_test_uniform(b, C, 8, RATE, TOL, [1, -1], rng)
    p_lf = box_test(b, C, 8, RATE, TOL, [1, -1])[0]
    assert p_u < 0.02 and p_u < p_lf / 4
    assert box_test_uniform(RATE, C, 8, RATE, TOL, [1, -1], rng) == 1.0


def test_filter_error_covariance_carries_errors_along_the_unidentified_direction():
    """Year posteriors tight along one direction, loose along the other (two inputs trading
    off; the prior decides there): the errors stay correlated across years along the loose
    direction only (an AR(1) there), and the slope's variance grows there."""
    d, n = 2, YEARS.size
    v = np.array([1.0, 1.0]) / np.sqrt(2)
    u = np.array([1.0, -1.0]) / np.sqrt(2)
    P = np.repeat((0.0001 * np.outer(v, v) + 0.008 * np.outer(u, u))[None], n, axis=0)
    E = filter_error_covariance(P, np.array([0.01, 0.01]))
    assert E.shape == (n, n, d, d) and np.allclose(E[3, 3], P[3])
    assert np.allclose(E[4, 3], E[3, 4].T)
    assert u @ E[5, 4] @ u > 0.5 * (u @ P[4] @ u)       # carried along the ridge
    assert abs(v @ E[5, 4] @ v) < 0.1 * (v @ P[4] @ v)   # not across it
    indep = filter_error_covariance(P, None)
    assert np.all(indep[5, 4] == 0)
    rng = np.random.default_rng(9)
    tr, res = _trends(np.array([0.0, -0.02]), np.array([0.01, 0.01]), rng)
    C_ind = slope_covariance(tr, res, YEARS, indep)
    C_car = slope_covariance(tr, res, YEARS, E)
    assert u @ C_car @ u > 2 * (u @ C_ind @ u)
    assert np.allclose(C_ind, slope_covariance(tr, res, YEARS, P))   # [n, d, d] as before


def test_median_failure_year_is_the_first_year_more_likely_unsafe_than_not():
    years = np.array([11, 12, 13, 14])
    assert median_failure_year(years, np.array([0.01, 0.2, 0.5, 0.9])) == 13
    assert median_failure_year(years, np.array([0.01, 0.2, 0.4, 0.49])) is None


def test_attribution_names_a_clear_fault_and_says_ambiguous_on_a_ridge():
    rng = np.random.default_rng(4)
    tr, res = _trends(np.array([0.0, -0.12]), np.array([0.1, 0.005]), rng)
    # attribute's own generator: the data below do not depend on how many draws it takes
    a = attribute(tr, ["d", "b"], ["motor", "pump"], slope_covariance(tr, res), RATE, TOL,
                  [1, -1], 0.8, np.random.default_rng(3))
    assert a.verdict == "pump" and a.probabilities["pump"] > 0.95
    assert abs(sum(a.sets.values()) - 1) < 1e-9
    # Strongly correlated estimates whose slopes sit between "motor" and "pump": the joint
    # distribution straddles both explanations.
    tr, res = _trends(np.array([0.3, -0.06]), np.array([0.8, 0.2]), rng, corr=0.97)
    a = attribute(tr, ["d", "b"], ["motor", "pump"], slope_covariance(tr, res), RATE, TOL,
                  [1, -1], 0.8, np.random.default_rng(5))
    assert a.verdict == AMBIGUOUS
    assert 0.1 < a.probabilities["motor"] < 0.95 and 0.1 < a.probabilities["pump"] < 0.95


def test_attribution_from_posterior_slope_draws_counts_them():
    """The joint method's slope draws are used as they are: the probabilities are the
    fractions of draws beyond each band, among the draws beyond any."""
    rng = np.random.default_rng(8)
    # RATE (0, -0.02), TOL (0.25, 0.03): the pump's band ends at -0.05.
    draws = np.column_stack([rng.normal(1.0, 0.05, 4000), rng.normal(-0.05, 0.02, 4000)])
    tr, _ = _trends(np.array([0.0, -0.02]), np.array([0.1, 0.005]), rng)   # not used
    a = attribute(tr, ["d", "b"], ["motor", "pump"], np.eye(2), RATE, TOL, [1, -1], 0.8,
                  np.random.default_rng(3), draws=draws)
    assert a.probabilities["motor"] == 1.0
    assert a.probabilities["pump"] == np.mean(draws[:, 1] < -0.05)
    # the pump half in, half out: not sure whether it is one component or two
    assert a.verdict == AMBIGUOUS
    a = attribute(tr, ["d", "b"], ["motor", "pump"], np.eye(2), RATE, TOL, [1, -1], 0.8,
                  np.random.default_rng(3), draws=draws + [0, 0.03])
    assert a.verdict == "motor" and a.probabilities["pump"] < 0.1


def test_posterior_covariance_widens_the_slopes_along_the_ridge():
    rng = np.random.default_rng(6)
    tr, res = _trends(np.array([0.0, -0.02]), np.array([0.05, 0.005]), rng)
    P = np.array([[0.25, 0.0045], [0.0045, 0.0001]])      # per-year posterior, corr 0.9
    C0 = slope_covariance(tr, res)
    C1 = slope_covariance(tr, res, YEARS, np.repeat(P[None], YEARS.size, axis=0))
    assert np.all(np.diag(C1) > np.diag(C0))
    assert C1[0, 1] / np.sqrt(C1[0, 0] * C1[1, 1]) > 0.5


def test_ttf_scores_follow_the_alpha_lambda_definition():
    cuts = np.array([5, 6, 7, 8, 9])
    # end of life 12: true RUL 7..3; the prediction is right from cut 7 on
    s = ttf_scores(cuts, np.array([15, 14, 12, 12, 12]), 12, 7, alpha=0.2, lam=0.5)
    assert s.cut_lambda == 8 or s.cut_lambda == 9        # 5 + 0.5 * 7 = 8.5
    assert s.alpha_lambda and s.relative_accuracy == 1.0
    assert s.prognostic_horizon == 12 - 7
    # censored predictions (none within the horizon) count as horizon + 1
    s = ttf_scores(cuts, np.array([-1, -1, -1, -1, -1]), 12, 1)
    assert not s.alpha_lambda and s.prognostic_horizon == 0.0
    assert ttf_scores(cuts, np.zeros(5, int), 4, 7) is None


def test_a_repair_restarts_the_component_trend():
    """A replaced part: its inputs' trend starts at the repair; with fewer than 3 years since,
    normal ageing is assumed and the slope test never rejects."""
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.trend import repair_years, segment_trend

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    comp = cfg.model.inputs[cfg.model.input_names[1]].component
    name = cfg.model.input_names[1]
    spec = cfg.model.inputs[name]
    since = repair_years(cfg, SimpleNamespace(events=[(6, comp, "replaced")]), YEARS)
    assert since[name] == 6 and since[cfg.model.input_names[0]] == 1
    # worn fast before the repair, new part after: the fit sees only years 6..10
    vals = np.where(YEARS < 6, 3.6 - 0.2 * (YEARS - 1), 3.6 + spec.normal_rate * (YEARS - 6))
    t = segment_trend(YEARS, vals, 6, spec)
    assert abs(t.slope - spec.normal_rate) < 1e-9 and t.n == 5
    t = segment_trend(YEARS, vals, 9, spec)            # two years since: assumed
    assert t.slope == spec.normal_rate and not t.rejects and "repaired in year 9" in t.test


def test_indicator_drift_takes_a_joint_posteriors_slope_draws_over_its_smoothed_years():
    """A joint posterior's yearly values lie close to its trend: their OLS slope error is
    far too small. With the posterior's slope draws the test uses their mean and spread."""
    rng = np.random.default_rng(3)
    normal = float(GRAD @ RATE)
    band = float(np.sum(np.abs(GRAD) * TOL))
    slope = normal + 1.05 * band                    # just past the band's edge
    smooth = _indicator(slope, 0.0, rng)            # years on the line: OLS se ~ 0
    ols = indicator_drift(YEARS, smooth, GRAD, RATE, TOL, +1, 0.01)
    draws = slope + 0.15 * rng.standard_normal(4000)
    post = indicator_drift(YEARS, smooth, GRAD, RATE, TOL, +1, 0.01, slope_draws=draws)
    assert ols.slope_se < 0.01 and ols.abnormal
    assert abs(post.slope - draws.mean()) < 1e-12
    assert abs(post.slope_se - draws.std(ddof=1)) < 1e-12
    # 1.05 bands out with sd 0.15 (0.4 of a band): a slope inside the band is plausible
    # (p 0.039 against the OLS fit's < 0.01 at alpha 0.01).
    assert ols.p_value < 0.01 < 0.02 < post.p_value and not post.abnormal
    assert post.years.tolist() == YEARS.tolist()    # the yearly values still shown


def test_wear_rates_pooled_over_a_repair_weigh_each_segment_by_its_precision():
    """history_slope_draws: per input, each draw's segment slopes averaged with weights
    1 / variance; an input with one segment keeps its slope; no restart at all, None.
    Three inputs, the second repaired twice."""
    from twinmon.forecast.judge import history_slope_draws
    rng = np.random.default_rng(5)
    n = 20000
    start = np.array([[1, 1, 1], [-1, 4, -1], [-1, 8, -1]])
    slope = np.zeros((n, 3, 3))
    slope[:, 0, 0] = 0.1 + 0.01 * rng.standard_normal(n)
    # the repaired input: a long early segment (sd 0.02), then two short ones (sd 0.04, 0.08)
    for s, sd in enumerate((0.02, 0.04, 0.08)):
        slope[:, s, 1] = -0.08 + sd * rng.standard_normal(n)
    slope[:, 0, 2] = 2.0 + 0.5 * rng.standard_normal(n)
    h = history_slope_draws({"start": start, "slope": slope})
    assert h.shape == (n, 3)
    assert np.array_equal(h[:, 0], slope[:, 0, 0]) and np.array_equal(h[:, 2], slope[:, 0, 2])
    # precision weighting: sd 1 / sqrt(1/0.02^2 + 1/0.04^2 + 1/0.08^2) = 0.0175
    assert abs(h[:, 1].mean() + 0.08) < 0.001
    assert abs(h[:, 1].std() - 0.0175) < 0.0005
    assert history_slope_draws({"start": start[:1], "slope": slope[:, :1]}) is None


def test_detectable_multiples_say_what_fault_a_record_would_show_half_the_time():
    """Per input, the fault (in tolerances) a record shows half the time: large for a
    short record, small for a long one; the indicator's bound sits at its test's critical
    value exactly; an input the indicator cannot see is judged by the slopes alone; an
    input with no tolerance has none. A healthy verdict on a record too short to show a
    fault of ``forecast.detectable_multiple`` tolerances is unreliable, naming the inputs."""
    from scipy import stats

    from twinmon.config import load_config
    from twinmon.forecast.detection import detectable_multiples, t_sf, uniform_sum
    from twinmon.forecast.judge import describe_blind

    from ..conftest import CONFIGS
    rng = np.random.default_rng(4)
    level, dof = 0.005, 10 ** 6
    found = {}
    for label, sd in (("long", np.array([0.08, 0.016])), ("short", np.array([1.0, 0.15]))):
        draws = rng.normal(RATE, sd, (4000, 2))
        drift = indicator_drift(YEARS, _indicator(0.08, 0.1, rng), GRAD, RATE, TOL, +1, 0.01,
                                slope_draws=draws @ GRAD)
        C = np.diag(sd ** 2)
        m = detectable_multiples(drift, C, dof, TOL, np.array([1, -1]), level)
        found[label] = m
        by_inputs = 1 + stats.t.isf(level, dof) * sd / TOL
        assert np.all(m <= by_inputs + 1e-12)
        # Where the indicator's bound is the smaller, its excess is the critical value.
        u, w = uniform_sum(drift.normal_halfwidth)
        for i in np.flatnonzero(m < by_inputs - 1e-9):
            e = m[i] * drift.normal_halfwidth[i]
            p = float(w @ t_sf((e - u) / drift.slope_se, drift.dof))
            assert p == pytest.approx(level, rel=1e-6), (label, i)
            # The tail is Student's t's; with a posterior's 10^6 dof, the normal's.
            assert float(w @ stats.t.sf((e - u) / drift.slope_se, drift.dof)) == \
                pytest.approx(level, rel=1e-4)
    assert np.all(found["long"] < 4) and np.all(found["short"] > 4), found
    # An input that moves the indicator towards safe: only its slope can show its fault.
    drift = indicator_drift(YEARS, _indicator(0.08, 0.1, rng), GRAD, RATE, TOL, +1, 0.01)
    sd = np.array([0.3, 0.05])
    m = detectable_multiples(drift, np.diag(sd ** 2), dof, TOL, np.array([-1, -1]),
                             level)
    assert m[0] == pytest.approx(1 + stats.t.isf(level, dof) * sd[0] / TOL[0], rel=1e-9)
    m = detectable_multiples(drift, np.diag(sd ** 2), dof, np.array([0.25, 0.0]),
                             np.array([1, -1]), level)
    assert np.isfinite(m[0]) and np.isnan(m[1])
    # No slope error at all (too few years): nothing is bounded by the slopes.
    nan_drift = indicator_drift(YEARS[:2], _indicator(0.08, 0.1, rng)[:2], GRAD, RATE, TOL,
                                +1, 0.01)
    m = detectable_multiples(nan_drift, np.full((2, 2), np.nan), 1, TOL,
                             np.array([1, -1]), level)
    assert np.all(np.isinf(m))

    cfg = load_config(CONFIGS / "pump.yaml")
    drift.detectable = np.array([2.1, 9.3])
    why = describe_blind(cfg, drift, YEARS[:3])
    names = cfg.model.input_names
    assert why.startswith("prognosis unreliable: with 3 year(s) of record")
    assert f"a fault of {names[1]} up to 9.3x would" in why and names[0] not in why
    drift.detectable = np.array([np.inf, 9.3])
    why = describe_blind(cfg, drift, YEARS[:2])
    assert f"of {names[0]} of any size, or of {names[1]} up to 9.3x" in why
    drift.detectable = np.array([2.1, 3.9])
    assert describe_blind(cfg, drift, YEARS) == ""
    drift.detectable = np.array([2.1, 9.3])
    off = load_config(CONFIGS / "pump.yaml", ["forecast.detectable_multiple=0"])
    assert describe_blind(off, drift, YEARS[:3]) == ""


def test_a_healthy_verdict_says_how_large_a_fault_its_record_shows():
    """describe_power names each input's fault the record shows half the time (any size
    where nothing bounds it; none for an input without a tolerance), and says nothing for a
    forecast that did not record them."""
    from twinmon.config import load_config
    from twinmon.forecast.judge import describe_power

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    a, b = cfg.model.input_names
    drift = indicator_drift(YEARS, _indicator(0.08, 0.1, np.random.default_rng(5)), GRAD,
                            RATE, TOL, +1, 0.01)
    drift.detectable = np.array([1.43, 2.91])
    why = describe_power(cfg, drift)
    assert f"half the time from {a} 1.4x, {b} 2.9x the input's normal-ageing tolerance" in why
    assert why.endswith("a smaller one may go unseen")
    drift.detectable = np.array([np.inf, np.nan])
    why = describe_power(cfg, drift)
    assert f"from {a} of any size the" in why and b not in why
    drift.detectable = np.zeros(0)
    assert describe_power(cfg, drift) == "" and describe_power(cfg, None) == ""


def test_t_tail_is_students_and_the_normals_from_a_posteriors_dof():
    """t_sf is scipy's Student t tail; from NORMAL_DOF on, the normal's, within 1e-5."""
    from scipy import stats

    from twinmon.forecast.detection import NORMAL_DOF, t_sf
    x = np.linspace(-6, 6, 101)
    for dof in (1, 3, 8, 30):
        assert np.array_equal(t_sf(x, dof), stats.t.sf(x, dof))
    for dof in (NORMAL_DOF, 10 ** 6):
        assert np.max(np.abs(t_sf(x, dof) - stats.t.sf(x, dof))) < 1e-5


def test_detectable_size_when_the_normal_band_is_tiny_beside_the_slope_error():
    """A band far narrower than the indicator's slope error: the indicator's critical
    excess is the tail's own quantile times the error, a finite size, not 'any size'."""
    from dataclasses import replace

    from twinmon.forecast.detection import detectable_multiples, t_isf
    rng = np.random.default_rng(5)
    level = 0.005
    for dof in (8, 10 ** 6):
        drift = indicator_drift(YEARS, _indicator(0.08, 0.1, rng), GRAD, RATE, TOL, +1, 0.01)
        drift = replace(drift, normal_halfwidth=np.array([1e-9, 1e-9]) * drift.slope_se,
                        dof=dof)
        # Slopes so uncertain that only the indicator bounds the fault.
        m = detectable_multiples(drift, np.diag([1e40, 1e40]), dof, TOL, np.array([1, -1]),
                                 level)
        crit = t_isf(level, dof) * drift.slope_se
        assert np.all(np.isfinite(m))
        assert np.allclose(m * drift.normal_halfwidth, crit, rtol=1e-6)


def test_year_ranges_write_runs_of_years():
    from twinmon.forecast.judge import year_ranges
    assert year_ranges([1, 2, 3, 5, 7, 8]) == "1-3, 5, 7-8"
    assert year_ranges([4]) == "4"
    assert year_ranges([]) == ""


@pytest.mark.parametrize("chains", [False, True])
def test_an_unconverged_unit_is_unreliable_with_the_figures_of_its_draws(chains):
    """Weighted draws (no chains) are judged by their effective number; chains by R-hat and
    ESS: the reason names the years as runs and the figures against their thresholds."""
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.judge import prognosis_status

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "dcdrive.yaml")
    years = np.arange(1, 9)
    status = np.array(["ok", "ok", "unconverged", "unconverged", "unconverged", "ok",
                       "unconverged", "unconverged"])
    ess = np.full((8, 2), 900.0)
    ess[2:5], ess[6:] = 37.0, 120.0
    rhat = np.full((8, 2), 1.001)
    rhat[3, 1] = 1.2
    acc = np.full((8, 4), 0.3) if chains else np.full((8, 4), np.nan)
    up = SimpleNamespace(status=status, years=years, ess=ess, rhat=rhat, acceptance=acc,
                         fit={"extensions": np.full(8, 2)})
    st, why = prognosis_status(up, cfg, [])
    assert st == "unreliable"
    assert "year(s) 3-5, 7-8" in why
    if chains:
        assert "longer chains" in why and "R-hat up to 1.200" in why and "ESS down to 37" in why
    else:
        assert "rests on 37 effective draws" in why and "doubled 2 time(s)" in why
        assert "chains" not in why
        up.fit = {"extensions": np.zeros(8)}
        assert "doubled" not in prognosis_status(up, cfg, [])[1]


def test_a_unit_on_the_box_edge_is_withheld_naming_the_bound_it_leans_on():
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.judge import prognosis_status

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "dcdrive.yaml")
    years = np.arange(1, 6)
    status = np.array(["ok", "ok", "ok", "edge", "edge"])
    share = np.zeros((5, 2))
    share[3:, 0] = [0.4, 0.9]
    # On the high edge, where a bearing's wear takes its friction: worn past the box.
    mean = np.tile([0.0059, 1.0], (5, 1))
    up = SimpleNamespace(status=status, years=years, mean=mean,
                         fit={"edge_share": share, "window_rms": np.zeros(5)})
    st, why = prognosis_status(up, cfg, [])
    assert st == "withheld"
    assert "bearing_friction sit on the design box's high edge" in why
    assert "90 % of the posterior in year 5" in why and "of 0.006 N.m.s/rad" in why
    assert "widen model.inputs.bearing_friction.high" in why
    from twinmon.forecast.judge import box_bound_of
    assert box_bound_of(why) == "model.inputs.bearing_friction.high"
    # On the low edge, its sound side (a friction near the least the box allows): the box
    # cuts the estimates' spread, but no part is worn past it. Unreliable, not withheld;
    # one such year before the last is not enough.
    up.mean = np.tile([0.00052, 1.0], (5, 1))
    st, why = prognosis_status(up, cfg, [])
    assert st == "unreliable" and box_bound_of(why) is None
    assert ("bearing_friction lean on the design box's low edge of 0.0005 N.m.s/rad, its "
            "sound side, in year(s) 4-5") in why
    assert "lower model.inputs.bearing_friction.low if the model allows it" in why
    up.status = np.array(["ok", "ok", "ok", "edge", "ok"])
    assert prognosis_status(up, cfg, []) == ("ok", "")
    up.status = status
    # The last year misses the plant too. On the low edge, the side a bearing's wear does
    # not take it (its friction degrades up), the edge makes up for something the twin
    # lacks: the misfit is named. On the high edge, worn past the box: the box, with the
    # misfit said. A misfit off the edge is a misfit.
    up.status = np.array(["ok", "ok", "ok", "edge", "misfit"])
    up.fit.update(rms=np.ones(5), window=np.zeros(5, int))
    st, why = prognosis_status(up, cfg, [])
    assert why.startswith("prognosis withheld: the twin misses the plant by")
    up.mean = np.tile([0.0059, 1.0], (5, 1))
    st, why = prognosis_status(up, cfg, [])
    assert "bearing_friction sit on the design box's high edge" in why
    assert "and the twin misses the plant in year(s) 5" in why
    assert box_bound_of(why) == "model.inputs.bearing_friction.high"
    up.fit["edge_share"] = np.where(np.arange(5)[:, None] == 4, 0.0, share)
    st, why = prognosis_status(up, cfg, [])
    assert why.startswith("prognosis withheld: the twin misses the plant by")
    assert box_bound_of(why) is None


def test_a_new_part_is_extended_at_the_rate_its_predecessor_wore():
    """An input replaced one year before the record's end: each draw's future rate is its
    segments' rates pooled by their precision (the new segment's weak prior weighs almost
    nothing), its curvature and growth dropped; an input with one segment, and a part of
    three years, keep their own."""
    from twinmon.forecast.chunk import new_parts_as_before
    from twinmon.forecast.judge import history_slope_draws
    rng = np.random.default_rng(3)
    n = 400
    years = np.arange(1, 11)
    start = np.array([[1, 1], [10, -1]])
    slope = np.stack([np.column_stack([rng.normal(0.9, 0.05, n), rng.normal(-0.02, 0.01, n)]),
                      np.column_stack([rng.normal(0.0, 3.0, n), np.full(n, np.nan)])], axis=1)
    now = rng.normal(1.0, 0.1, (n, 4, 2))
    trend = {"start": start, "slope": slope, "intercept": np.zeros_like(slope), "now": now}
    out = new_parts_as_before(trend, {"a": 10, "b": 1}, years, ["a", "b"])
    hist = history_slope_draws(trend)
    assert np.array_equal(out["now"][:, 1, 0], hist[:, 0])
    assert np.all(out["now"][:, 2:, 0] == 0.0)
    assert np.array_equal(out["now"][:, :, 1], now[:, :, 1])
    assert abs(float(np.mean(out["now"][:, 1, 0])) - 0.9) < 0.05
    assert trend["now"] is now and np.array_equal(now, trend["now"])       # not modified
    # The joint method's segments: the last one's slope replaced.
    joint = {k: v for k, v in trend.items() if k != "now"}
    out = new_parts_as_before(joint, {"a": 10, "b": 1}, years, ["a", "b"])
    assert np.array_equal(out["slope"][:, 1, 0], hist[:, 0])
    assert np.array_equal(out["slope"][:, 0, 0], slope[:, 0, 0])
    # Three years of the new part: its own trend.
    assert new_parts_as_before(trend, {"a": 8, "b": 1}, years, ["a", "b"]) is trend


def test_simes_rejects_where_bonferroni_does_and_when_views_agree():
    from twinmon.forecast.detection import simes
    assert simes([0.009, 0.5, float("nan")], 0.03)           # below alpha / 2
    assert not simes([0.016, 0.5], 0.03)
    assert simes([0.016, 0.02], 0.03)                          # both below alpha
    assert not simes([float("nan")], 0.03) and not simes([], 0.03)


def test_a_late_rise_of_the_wear_rate_is_judged_on_the_current_rate():
    """A pump whose wear rate rose late: its chord over the record lies half a tolerance
    beyond the band's edge (p 0.06), its rate at the last year four. With most of the
    posterior on wear that changed, the inputs' current rates are tested too and name the
    pump; where the line explains the unit, they are not looked at."""
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.judge import judge

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    names = cfg.model.input_names
    assert names == ["motor_damping", "pump_coef"]
    rng = np.random.default_rng(5)
    n = 4000
    chord = np.column_stack([rng.normal(0.0, 0.05, n), rng.normal(-0.065, 0.02, n)])
    current = np.column_stack([rng.normal(0.0, 0.08, n), rng.normal(-0.17, 0.03, n)])
    trends = {nm: fit_trend(YEARS, rng.normal(0.0, 1.0, YEARS.size))[0] for nm in names}
    for nm, t in trends.items():
        t.component = cfg.model.inputs[nm].component
    plan = dict(years=YEARS, since=1, slope_draws=chord, history_draws=None, trends=trends,
                rate_draws=current, changed=0.94)
    ind_obs = 15.0 + 0.01 * rng.standard_normal((YEARS.size, 50))
    directions = {"motor_damping": SimpleNamespace(sign=1),
                  "pump_coef": SimpleNamespace(sign=-1)}
    drift, att = judge(cfg, "U1", plan, ind_obs, np.zeros(2), directions, set())
    assert drift.p_inputs > cfg.forecast.alpha
    assert drift.p_inputs_rate < 1e-3
    assert drift.abnormal and att.verdict == "pump"
    plan["changed"] = 0.2
    drift, att = judge(cfg, "U1", plan, ind_obs, np.zeros(2), directions, set())
    assert np.isnan(drift.p_inputs_rate)
    assert not drift.abnormal and att.verdict == "healthy"


def test_level_cause_names_the_inputs_whose_restoration_makes_the_unit_safe():
    """A unit unsafe with no drift: the inputs that alone bring it back when set to nominal
    are named; when none does alone, those that move the indicator towards safe, most
    first (the pump's t90: above the limit is unsafe, so a lower t90 is a gain)."""
    from twinmon.config import load_config
    from twinmon.forecast.plan import level_cause, restore_points
    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    state = np.array([28.5, 3.5])
    pts = restore_points(cfg, state)
    assert np.allclose(pts, [[10.0, 3.5], [28.5, 3.61], [10.0, 3.61]])
    lv = level_cause(cfg, state, np.array([False, True]), np.array([12.0, 33.0]), 34.0)
    assert list(lv) == ["motor_damping"] and lv["motor_damping"]["safe"]
    assert lv["motor_damping"]["value"] == 28.5 and lv["motor_damping"]["nominal"] == 10.0
    # Neither alone: both move t90 down, the pump's the more.
    lv = level_cause(cfg, state, np.array([True, True]), np.array([33.0, 31.0]), 34.0)
    assert list(lv) == ["pump_coef", "motor_damping"]
    assert not any(v["safe"] for v in lv.values())
    # A restoration that makes it worse, or a level never reached (inf), names nothing.
    assert level_cause(cfg, state, np.array([True, True]), np.array([35.0, np.inf]),
                       34.0) == {}
    # A new unit is past the limit too (the nominal point, last): no part is to blame.
    assert level_cause(cfg, state, np.array([True, True, True]),
                       np.array([33.0, 31.0, 31.5]), 34.0) == {}
    assert list(level_cause(cfg, state, np.array([True, True, False]),
                            np.array([33.0, 31.0, 20.0]), 34.0)) == ["pump_coef", "motor_damping"]
    from twinmon.forecast.plan import level_plan, nominal_plan
    both = {n: {"value": v, "nominal": 1.0, "restored": 25.0, "safe": True}
            for n, v in (("motor_damping", 28.5), ("pump_coef", 3.5))}
    text = level_plan(cfg, both, 0.9, 10)
    assert text.startswith("Inspect/replace the motor or the pump now")
    assert "restoring any one of them makes it safe" in text
    text = level_plan(cfg, {n: {**v, "safe": False} for n, v in both.items()}, 0.9, 10)
    assert text.startswith("Inspect/replace the motor and the pump now")
    assert "no one of them restored alone makes it safe" in text
    text = nominal_plan(cfg, 31.5, 0.97, 10)
    assert text.startswith("Check the limit: the unit is past it (P(unsafe) 0.97 in year 10), "
                           "but so is a new unit")
    assert "unsafe by safety.unsafe_if (above 30" in text


def test_a_failure_year_from_the_bend_alone_is_not_confirmed():
    """A unit with no fault found whose failure year only its bent draws reach is
    unreliable; one whose straight-line draws reach it too, or with a fault, is not."""
    from twinmon.config import load_config
    from twinmon.forecast.judge import describe_bend
    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    fut = np.arange(11, 18)
    p_all = np.array([0.0, 0.01, 0.03, 0.15, 0.3, 0.4, 0.5])
    p_line = np.array([0.0, 0.0, 0.0, 0.02, 0.04, 0.06, 0.08])
    bent = {"line": 0.7, "accelerating": 0.25, "change": 0.05}
    why = describe_bend(cfg, bent, fut, p_all, 14, p_line, healthy=True)
    assert why.startswith("prognosis unreliable: no input wears faster than normal ageing")
    assert "P(unsafe) 0.15 in year 14, the straight-line draws 0.02" in why
    assert describe_bend(cfg, bent, fut, p_all, 14, p_line + 0.05, True) == ""   # line too
    assert describe_bend(cfg, bent, fut, p_all, 14, p_line, healthy=False) == ""
    assert describe_bend(cfg, bent, fut, p_all, None, p_line, True) == ""
    assert describe_bend(cfg, {}, fut, p_all, 14, None, True) == ""    # a line-only posterior
    # Too few line draws to tell: by the shapes' shares.
    assert describe_bend(cfg, bent, fut, p_all, 14, None, True) == ""
    why = describe_bend(cfg, {"line": 0.2, "accelerating": 0.7, "change": 0.1}, fut, p_all,
                        14, None, True)
    assert "a straight line 0.20 of the posterior (accelerating 0.70, a change 0.10)" in why


def test_a_part_beyond_normal_ageing_the_safe_way_is_named_not_called_normal():
    """An input drifting far beyond its band, but away from the limit: no risk by the
    indicator, so no fault; the plan does not call it normal ageing and asks to check it."""
    from twinmon.config import load_config
    from twinmon.forecast.plan import maintenance_plan
    from twinmon.forecast.trend import Trend, safe_way, slope_test
    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")

    def trend(slope, se, rate, tol, direction, comp):
        t = Trend(intercept=0.0, slope=slope, slope_se=se, slope_ci=(slope, slope),
                  residual_std=0.1, n=10, x_mean=5.5, sxx=82.5, component=comp)
        return slope_test(t, rate, tol, direction, cfg.forecast.alpha)
    # The motor's damping falls 1/yr (its degrading direction is up); the pump ages normally.
    trends = {"motor_damping": trend(-1.0, 0.1, 0.0, 0.25, +1, "motor"),
              "pump_coef": trend(-0.02, 0.01, -0.02, 0.03, -1, "pump")}
    assert not trends["motor_damping"].rejects
    away = safe_way(trends, cfg.forecast.alpha)
    assert list(away) == ["motor_damping"] and away["motor_damping"] < 1e-4
    plan = maintenance_plan(trends, np.arange(11, 18), np.zeros(7), None, 10, 0.0,
                            cfg.safety, cfg=cfg)
    assert plan.startswith("No action for safety: no component wears towards the limit")
    assert "pump within normal ageing" in plan and "motor within" not in plan
    assert "motor_damping drifts -1/yr, beyond normal ageing (+0 +- 0.25/yr) but away from " \
        "the limit" in plan and plan.endswith("check the motor.")
    # Within its band, or beyond it towards the limit (a fault, not this): nothing.
    trends["motor_damping"] = trend(-0.1, 0.1, 0.0, 0.25, +1, "motor")
    assert safe_way(trends, cfg.forecast.alpha) == {}
    trends["motor_damping"] = trend(1.0, 0.1, 0.0, 0.25, +1, "motor")
    assert safe_way(trends, cfg.forecast.alpha) == {}


def test_an_input_beyond_normal_alone_is_watched_not_called_normal():
    """A unit judged healthy while one input's own slope test rejects: no fault is named
    (the unit's tests together did not confirm it), but the part is watched, and named
    first when the unit has a failure year."""
    from twinmon.config import load_config
    from twinmon.forecast.detection import IndicatorDrift
    from twinmon.forecast.plan import unconfirmed
    from twinmon.forecast.trend import Trend, slope_test
    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")

    def trend(slope, se, rate, tol, direction, comp):
        t = Trend(intercept=0.0, slope=slope, slope_se=se, slope_ci=(slope, slope),
                  residual_std=0.1, n=10, x_mean=5.5, sxx=82.5, component=comp)
        return slope_test(t, rate, tol, direction, cfg.forecast.alpha)
    trends = {"motor_damping": trend(0.55, 0.12, 0.0, 0.25, +1, "motor"),
              "pump_coef": trend(-0.02, 0.01, -0.02, 0.03, -1, "pump")}
    assert trends["motor_damping"].rejects and not trends["pump_coef"].rejects
    drift = IndicatorDrift(years=np.arange(1, 11), values=np.zeros(10), slope=0.1,
                           slope_se=0.05, dof=8, normal_slope=0.0,
                           normal_halfwidth=np.array([0.1]), gradient=np.ones(2), sense=1,
                           p_value=0.06, abnormal=False)
    drift.p_inputs = 0.07
    fut, p = np.arange(11, 18), np.array([0.0, 0.0, 0.06, 0.2, 0.4, 0.6, 0.7])
    watch, plan = unconfirmed(cfg, trends, drift, 13, fut, p)
    assert watch == {"motor": "its slope alone beyond normal ageing"}
    assert plan.startswith("Inspect the motor first: motor_damping's slope +0.55/yr (p = ")
    assert "not once the unit's inputs are tested together (indicator p = 0.06, inputs " \
        "jointly p = 0.07): no fault is named" in plan
    watch, plan = unconfirmed(cfg, trends, drift, None, fut, np.zeros(7))
    assert plan.startswith("No action for safety: P(unsafe) stays <= 0.05 through year 17")
    assert plan.endswith("watch the motor (next year's record will tell).")
    trends["motor_damping"] = trend(0.1, 0.12, 0.0, 0.25, +1, "motor")
    assert unconfirmed(cfg, trends, drift, 13, fut, p) is None


def test_collapsed_slope_draws_fall_back_on_the_yearly_regression():
    """Posterior slope draws that collapsed onto one point (an unconverged weighting) have
    no covariance: the joint tests take the yearly means' regression instead of stopping
    the forecast with "Singular matrix"."""
    from twinmon.forecast.judge import _spread
    rng = np.random.default_rng(0)
    good = rng.standard_normal((500, 4))
    assert _spread(good) is good and _spread(None) is None
    assert _spread(np.tile(good[:1], (500, 1))) is None
    two = good[rng.integers(0, 2, 500)]            # two distinct draws in four dimensions
    assert _spread(two) is None
    assert _spread(good[:, :1]) is not None       # one input


def test_an_ambiguous_plan_names_the_sure_part_and_leaves_the_sound_one_out():
    """Four components: the rotor surely at fault, two in doubt, the spindle all but surely
    sound. The plan names the rotor, the others as possible, never the spindle."""
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.attribution import Attribution
    from twinmon.forecast.plan import maintenance_plan
    from twinmon.forecast.trend import Trend, slope_test
    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    comps = ["rotor", "prefilter", "vee-belt", "spindle"]
    trends = {}
    for c in comps:
        t = Trend(intercept=0.0, slope=0.0, slope_se=0.1, slope_ci=(0.0, 0.0),
                  residual_std=0.1, n=10, x_mean=5.5, sxx=82.5, component=c)
        trends[c + "_x"] = slope_test(t, 0.0, 0.25, +1, cfg.forecast.alpha)

    def plan_for(probs):
        return maintenance_plan(trends, np.arange(11, 18), np.r_[0.0, np.ones(6)], 12, 10,
                                0.0, cfg.safety, drift=SimpleNamespace(abnormal=False),
                                attribution=Attribution(AMBIGUOUS, probs, {}), cfg=cfg)
    plan = plan_for({"rotor": 1.0, "prefilter": 0.61, "vee-belt": 0.56, "spindle": 0.0})
    assert plan.startswith("Inspect/replace the rotor before year 11 ends")
    assert "which others wear too: rotor 1.00, prefilter 0.61, vee-belt 0.56" in plan
    assert "spindle within normal ageing" in plan and "or the spindle" not in plan
    # None sure: the candidates, most probable first, joined by "or".
    plan = plan_for({"rotor": 0.7, "prefilter": 0.61, "vee-belt": 0.0, "spindle": 0.0})
    assert plan.startswith("Inspect/replace the rotor or the prefilter before year 11 ends")
