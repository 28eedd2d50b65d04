"""calibrate, laplace method's trend shapes (twinmon/calibrate/shapes.py): the shapes'
posterior probabilities against a brute-force quadrature, and what they do on histories
that accelerate, step, or run straight."""
from __future__ import annotations

import numpy as np
from scipy import stats

from twinmon.calibrate.shapes import ShapeMixture, build_shapes, describe_shape, shape_summary
from twinmon.calibrate.trend import design_matrix, trend_predictive

YEARS = np.arange(1, 11)
WIDE = np.array([[-1e9, 1e9]] * 2)
PRIORS = {"line": 0.6, "accelerating": 0.2, "change": 0.2}


def _mixture(x, err, priors=PRIORS, A=0.2, seed=0):
    """One unit, one segment per input, sites ``x`` [K, d] with independent errors ``err``
    [K, d]; slope priors N(0, 10^2), levels flat (as the laplace method builds them)."""
    K, d = x.shape
    X, _ = design_matrix(YEARS, np.array([YEARS[0]]))
    Mk = np.zeros((K, d, 2 * d))
    for i in range(d):
        Mk[:, i, 2 * i:2 * i + 2] = X
    cov = np.einsum("ki,ij->kij", err ** 2, np.eye(d))
    prec = np.tile([0.0, 0.01], d)
    shapes = build_shapes(YEARS, x, cov, Mk, prec, np.zeros(2 * d), np.full(d, A),
                          np.tile([False, True], d), np.full(d, YEARS[0]), priors,
                          np.random.default_rng(seed))
    return ShapeMixture(shapes)


def test_shape_probabilities_match_a_quadrature():
    """One input bending a little: the line's and the accelerating shape's posterior
    probabilities on the sites equal those of the marginal likelihoods integrated over sigma
    on a fine grid (the years' joint Gaussian written out whole, the same priors)."""
    rng = np.random.default_rng(3)
    t = YEARS.astype(float)
    err = rng.uniform(0.05, 0.1, len(t))
    x = (0.1 * (t - 5.5) + 0.007 * (t - 5.5) ** 2 + rng.normal(0, 0.05, len(t))
         + err * rng.standard_normal(len(t)))[:, None]
    mix = _mixture(x, err[:, None], {"line": 0.5, "accelerating": 0.5})
    # The line and the quadratic form, even odds.
    mix.shapes = [sh for sh in mix.shapes if sh.growth == 0.0]
    assert [sh.code for sh in mix.shapes] == [0, 1]
    for sh in mix.shapes:
        sh.log_prior = np.log(0.5)
    _, probs = mix.sigma_points(np.random.default_rng(1))
    acc = mix.shapes[1].model
    A, grid = 0.2, np.linspace(1e-5, 2.0, 20001)
    prior_s = np.log(2 / (np.pi * A * (1 + (grid / A) ** 2)))
    logz = []
    for model in (mix.shapes[0].model, acc):
        M = model.Mk[:, 0, :]
        P = model.prior_P.copy()
        P[0, 0] = 1e-2                       # the flat level: wide next to the data
        C0 = np.linalg.inv(P)
        # The years' joint Gaussian at every sigma of the grid at once (its log density
        # through a batched Cholesky factor, checked against scipy's at a few points).
        r = x[:, 0] - M @ model.prior_mean
        S = np.diag(err ** 2)[None] + grid[:, None, None] ** 2 * np.eye(len(t)) + M @ C0 @ M.T
        L = np.linalg.cholesky(S)
        z = np.linalg.solve(L, np.broadcast_to(r, (len(grid), len(t)))[..., None])[..., 0]
        ll = -0.5 * (np.einsum("gk,gk->g", z, z) + len(t) * np.log(2 * np.pi)) \
            - np.log(np.einsum("gkk->gk", L)).sum(axis=1)
        for j in (0, 7000, 20000):
            ref = stats.multivariate_normal(M @ model.prior_mean, S[j]).logpdf(x[:, 0])
            assert abs(ll[j] - ref) < 1e-8 * max(1.0, abs(ref))
        lw = ll + prior_s
        # The wide level prior, the same in both models, cancels in their ratio.
        logz.append(np.log(np.trapezoid(np.exp(lw - lw.max()), grid)) + lw.max())
    p_acc = 1.0 / (1.0 + np.exp(logz[0] - logz[1]))
    assert abs(probs[1] - p_acc) < 0.02, (probs, p_acc)
    assert 0.05 < p_acc < 0.95          # a case where the evidence is not one-sided


def test_a_change_in_one_input_matches_a_quadrature():
    """Two inputs, the first stepping in year 6: the posterior probability of its change
    alone (its two coefficients under the unit-information prior) against the line equals
    that of the marginal likelihoods integrated over both sigmas on a grid (the years'
    joint Gaussian written out whole)."""
    rng = np.random.default_rng(4)
    t = YEARS.astype(float)
    err = np.full((len(t), 2), 0.06)
    x = np.column_stack([0.03 * t + 0.18 * (t >= 6), -0.02 * t]) + \
        rng.normal(0, 0.04, err.shape) + err * rng.standard_normal(err.shape)
    mix = _mixture(x, err, {"line": 0.5, "change": 0.5}, A=0.1)
    mix.shapes = [sh for sh in mix.shapes if sh.code == 0 or sh.change_years == (6, -1)]
    assert len(mix.shapes) == 2, [sh.change_years for sh in mix.shapes]
    for sh in mix.shapes:
        sh.log_prior = np.log(0.5)
    _, probs = mix.sigma_points(np.random.default_rng(1))
    A, g = 0.1, np.geomspace(1e-4, 1.0, 120)
    prior_s = np.log(2 / (np.pi * A * (1 + (g / A) ** 2)))
    s0, s1 = np.meshgrid(g, g, indexing="ij")
    logz = []
    for sh in mix.shapes:
        m = sh.model
        M = m.Mk.reshape(len(t) * 2, -1)                 # years x inputs stacked
        P = m.prior_P.copy()
        P[[0, 2], [0, 2]] = 1e-2                         # the flat levels: wide, cancel
        r = x.ravel() - M @ m.prior_mean
        C = M @ np.linalg.inv(P) @ M.T
        var = (err ** 2).ravel()[None] + np.stack([s0.ravel() ** 2, s1.ravel() ** 2], 1)[
            :, np.tile([0, 1], len(t))]                  # [grid, years x inputs]
        V = C[None] + var[:, :, None] * np.eye(r.size)
        L = np.linalg.cholesky(V)
        z = np.linalg.solve(L, np.broadcast_to(r, (len(V), r.size))[..., None])[..., 0]
        lw = (-0.5 * np.sum(z * z, axis=1) - np.log(np.einsum("nii->ni", L)).sum(axis=1)
              ).reshape(s0.shape) + prior_s[:, None] + prior_s[None, :]
        logz.append(np.log(np.trapezoid(np.trapezoid(np.exp(lw - lw.max()), g), g))
                    + lw.max())
    p_change = 1.0 / (1.0 + np.exp(logz[0] - logz[1]))
    assert abs(probs[1] - p_change) < 0.02, (probs, p_change)
    assert 0.05 < p_change < 0.95


def test_the_screen_of_the_changes_is_the_models_evidence():
    """The screen's block update of the line's evidence equals each change combination's
    own evidence on the screen's grid (the models built whole)."""
    from twinmon.calibrate.gaussian_trend import log_evidence_at
    from twinmon.calibrate.shape_screen import screen, screen_grid
    rng = np.random.default_rng(7)
    t = YEARS.astype(float)
    err = np.full((len(t), 2), 0.04)
    x = np.column_stack([0.5 * (t >= 5), -0.4 * (t >= 8)]) + err * rng.standard_normal(err.shape)
    mix = _mixture(x, err, A=0.05)
    line = mix.shapes[0].model
    grid = screen_grid(np.full(2, 0.05))
    n_l = line.Mk.shape[2]
    checked = 0
    for sh in mix.shapes[1:]:
        E = sh.model.Mk[:, :, n_l:]
        evidence = screen(line, E, sh.model.prior_P[n_l:, n_l:], grid)
        block = evidence([list(range(E.shape[2]))])[0] - evidence([[]])[0]
        ll = log_evidence_at([line, sh.model], grid[0]) + grid[1]
        top = ll.max(axis=1, keepdims=True)
        whole = top[:, 0] + np.log(np.exp(ll - top).sum(axis=1))
        assert abs(block - (whole[1] - whole[0])) < 1e-8, (sh.change_years, block, whole)
        checked += sh.code == 2
    assert checked >= 1


def _draws(mix, n=4000, seed=2):
    """The mixture's draws on its sites: shape code, change year (the first input's that
    changes), trend at the last year [n, 3, d], sigma [n, d]."""
    coef, sigma, _, _ = mix.draw(n, np.random.default_rng(seed), WIDE[:mix.x.shape[1]])
    code, m, now = mix.decode(coef)
    return np.array([mix.shapes[c].code for c in code]), \
        np.array([mix.shapes[c].change_year for c in code]), now, sigma, \
        np.array([mix.shapes[c].growth for c in code])


def _future(now, sigma, years, growth, seed=5):
    trend = {"now": now, "now_year": YEARS[-1], "sigma": sigma, "growth": growth}
    return trend_predictive(trend, years, np.random.default_rng(seed))


def test_accelerating_wear_is_found_and_its_future_covered():
    """Two inputs, the first wearing quadratically (rate 0.05 rising to 0.4 a year), the
    second flat: the accelerating shape takes the posterior, and the 90 % interval five years
    ahead holds the quadratic's continuation, which a straight line's misses."""
    rng = np.random.default_rng(11)
    t = YEARS.astype(float)
    truth = lambda tt: 0.05 * (tt - 1) + 0.02 * (tt - 1) ** 2         # noqa: E731
    err = np.full((len(t), 2), 0.05)
    x = np.column_stack([truth(t), np.zeros_like(t)]) + err * rng.standard_normal(err.shape)
    shape, _, now, sigma, growth = _draws(_mixture(x, err))
    assert np.mean(shape == 1) > 0.9
    future = _future(now, sigma, np.array([15]), growth)[:, 0, 0]
    lo, hi = np.quantile(future, [0.05, 0.95])
    assert lo <= truth(15.0) <= hi, (lo, hi, truth(15.0))
    shape_l, _, now_l, sigma_l, growth_l = _draws(_mixture(x, err, {"line": 1.0}))
    assert np.all(shape_l == 0)
    assert np.quantile(_future(now_l, sigma_l, np.array([15]), growth_l)[:, 0, 0], 0.95) < \
        truth(15.0)


def _against_quadratic(truth, sd: float, seed: int, years: tuple):
    """Sites of wear ``truth`` on the first of two inputs (the second flat), each year's
    error ``sd``: the mixture's shape codes and growths, and the 90 % intervals [2, len(years)]
    of the first input at ``years`` from the mixture and from its quadratic form alone."""
    rng = np.random.default_rng(seed)
    t = YEARS.astype(float)
    err = np.full((len(t), 2), sd)
    x = np.column_stack([truth(t), np.zeros_like(t)]) + err * rng.standard_normal(err.shape)
    shape, _, now, sigma, growth = _draws(_mixture(x, err))
    quadratic = _mixture(x, err)
    quadratic.shapes = [sh for sh in quadratic.shapes if sh.code == 1 and sh.growth == 0.0]
    _, _, now_q, sigma_q, growth_q = _draws(quadratic)
    at = np.array(years)
    return shape, growth, *(np.quantile(_future(n, s_, at, g)[:, :, 0], [0.05, 0.95], axis=0)
                            for n, s_, g in ((now, sigma, growth), (now_q, sigma_q, growth_q)))


def test_exponential_wear_is_covered_ahead():
    """Wear growing exponentially at 0.25 a year (between the exponential forms' rates): the
    accelerating shape takes the posterior, and the 90 % intervals three and six years ahead
    hold the truth, where a quadratic alone falls short six years ahead."""
    truth = lambda tt: 0.1 * np.expm1(0.25 * (tt - 1)) / 0.25        # noqa: E731
    shape, _, band, quadratic = _against_quadratic(truth, 0.05, 21, (13, 16))
    assert np.mean(shape == 1) > 0.9
    for j, year in enumerate((13.0, 16.0)):
        assert band[0, j] <= truth(year) <= band[1, j], (year, band[:, j], truth(year))
    assert quadratic[1, 1] < truth(16.0)


def test_power_law_wear_is_covered_ahead_where_a_quadratic_runs_ahead():
    """Wear growing as a^1.4 from the first year (an exponent between the power forms'):
    the accelerating shape takes the posterior, most of it on the power forms, and the 90 %
    intervals three and seven years ahead hold the truth, where a quadratic alone (its
    curvature the record's mean, larger than the last years') runs above it."""
    from twinmon.calibrate.shape_columns import POWER_EXPONENTS
    truth = lambda tt: 0.3 * (tt - 1) ** 1.4                        # noqa: E731
    shape, growth, band, quadratic = _against_quadratic(truth, 0.03, 31, (13, 17))
    assert np.mean(shape == 1) > 0.9
    assert np.mean(np.isin(-growth, POWER_EXPONENTS)) > 0.5
    for j, year in enumerate((13.0, 17.0)):
        assert band[0, j] <= truth(year) <= band[1, j], (year, band[:, j], truth(year))
    assert quadratic[0, 1] > truth(17.0)


def test_a_power_forms_map_is_its_quadratic_at_the_last_year():
    """The power form's map to the trend at the last year extends it by its value, rate and
    half its second derivative there: within 2 % of the power law's rise seven years on."""
    from twinmon.calibrate.shape_columns import POWER_EXPONENTS, _accelerating_forms
    t = YEARS.astype(float)
    seg = np.ones((1, len(t)), bool)
    forms = _accelerating_forms(t, seg, PRIORS, 1.0)
    powers = [f for f in forms if f[3] < 0]
    assert [-f[3] for f in powers] == list(POWER_EXPONENTS)
    u = np.arange(1.0, 8.0)
    for _, cols, _, g in powers:
        col, _, (level, rate, curv, amp) = cols[0]
        b, A = -g, t[-1] - t[0]
        exact = (A + u) ** b - A ** b
        assert np.allclose(col[:, 0] - col[-1, 0], (t - t[0]) ** b - A ** b)
        assert amp == 0.0 and np.isclose(level, col[-1, 0])
        assert np.all(np.abs(rate * u + curv * u ** 2 - exact) <= 0.02 * exact[-1])


def test_a_step_is_placed_in_its_year_and_not_extended():
    """Wear that steps up by 0.5 in year 7 and stays (sigma's prior scale 0.05): the change
    shape takes the posterior with its year right, and the future stays at the new level
    where a line through the history would climb on."""
    rng = np.random.default_rng(12)
    t = YEARS.astype(float)
    err = np.full((len(t), 2), 0.04)
    x = np.column_stack([0.5 * (t >= 7), np.zeros_like(t)]) + err * rng.standard_normal(err.shape)
    shape, year, now, sigma, growth = _draws(_mixture(x, err, A=0.05))
    assert np.mean(shape == 2) > 0.9
    assert np.mean(year[shape == 2] == 7) > 0.9
    future = _future(now, sigma, np.array([16]), growth)[:, 0, 0]
    lo, hi = np.quantile(future, [0.05, 0.95])
    assert lo <= 0.5 <= hi, (lo, hi)
    # The rate after the step is the four years' own (0.03 a year in this draw of the
    # noise), well below the line's through the whole history, which climbs to 0.92.
    line = np.polyval(np.polyfit(t, x[:, 0], 1), 16.0)
    assert np.median(future) < line - 0.15, (np.median(future), line)


def test_two_inputs_stepping_in_different_years_each_keep_their_year():
    """The first input steps up by 0.5 in year 5, the second down by 0.4 in year 8, each flat
    otherwise: the change draws place each step in its own year, and each input's future
    follows the line through its years since its step. One year shared by the inputs (the
    change shape before each input had its own) reads the later step as a rate and
    extends it."""
    rng = np.random.default_rng(14)
    t = YEARS.astype(float)
    err = np.full((len(t), 2), 0.04)
    x = np.column_stack([0.5 * (t >= 5), -0.4 * (t >= 8)]) + \
        err * rng.standard_normal(err.shape)
    mix = _mixture(x, err, A=0.05)
    coef, sigma, _, _ = mix.draw(4000, np.random.default_rng(2), WIDE)
    code, _, now = mix.decode(coef)
    shape = np.array([mix.shapes[c].code for c in code])
    years = np.array([mix.shapes[c].change_years for c in code])            # [n, 2]
    assert np.mean(shape == 2) > 0.9
    assert np.mean((years[shape == 2] == [5, 8]).all(axis=1)) > 0.8, years[shape == 2][:5]
    first = np.array([mix.shapes[c].change_year for c in code])
    summary = shape_summary({"shape": shape, "change_years": years, "change_year": first})
    assert summary["change_years"] == [5, 8] and summary["change"] > 0.9
    assert "years 5 and 8" in describe_shape(summary)
    growth = np.array([mix.shapes[c].growth for c in code])
    future = _future(now, sigma, np.array([16]), growth)[:, 0]
    since = [np.polyval(np.polyfit(t[t >= y], x[t >= y, i], 1), 16.0)
             for i, y in enumerate((5, 8))]
    for i in range(2):
        lo, hi = np.quantile(future[:, i], [0.05, 0.95])
        assert lo <= since[i] <= hi, (i, lo, hi, since[i])
    # The same data under one year shared by both inputs: the shared-year model built
    # whole, each year's combination with both inputs changing.
    from twinmon.calibrate.shapes import Shape, _change_columns, _extended
    shared = _mixture(x, err, {"line": 0.6, "accelerating": 0.2}, A=0.05)
    line = shared.shapes[0]
    W = np.linalg.inv(line.model.cov + np.diag([0.05, 0.05]) ** 2)
    for y in range(4, 9):
        cols = _change_columns(t, np.ones(len(t), bool), 0, 2, y) + \
            _change_columns(t, np.ones(len(t), bool), 1, 2, y)
        sh = _extended(line, 2, cols, np.log(0.2 / 5), W, np.tile([0.0, 0.01], 2),
                       np.zeros(4), np.full(2, 0.05), (y, y), 0.0)
        assert isinstance(sh, Shape)
        shared.shapes.append(sh)
    coef, sigma_s, _, _ = shared.draw(4000, np.random.default_rng(2), WIDE)
    code_s, _, now_s = shared.decode(coef)
    growth_s = np.array([shared.shapes[c].growth for c in code_s])
    late = _future(now_s, sigma_s, np.array([16]), growth_s)[:, 0, 1]
    assert abs(np.median(late) - since[1]) > 2 * abs(np.median(future[:, 1]) - since[1]), \
        (np.median(late), np.median(future[:, 1]), since[1])


def test_a_change_each_input_needs_is_weighed_whole_and_one_it_does_not_is_not():
    """Occam's razor among the change's combinations: one input stepping keeps its
    change alone (no combination adds the flat input's change), two inputs stepping keep
    the combination of both."""
    rng = np.random.default_rng(15)
    t = YEARS.astype(float)
    err = np.full((len(t), 2), 0.04)
    one = np.column_stack([0.5 * (t >= 6), np.zeros_like(t)])
    mix = _mixture(one + err * rng.standard_normal(err.shape), err, A=0.05)
    changes = [sh.change_years for sh in mix.shapes if sh.code == 2]
    assert (6, -1) in changes and all(y[1] == -1 for y in changes if y[0] >= 0), changes
    two = np.column_stack([0.5 * (t >= 6), 0.5 * (t >= 6)])
    mix = _mixture(two + err * rng.standard_normal(err.shape), err, A=0.05)
    _, probs = mix.sigma_points(np.random.default_rng(1))
    best = mix.shapes[int(np.argmax(probs))]
    assert best.change_years == (6, 6), [(sh.change_years, p) for sh, p in
                                         zip(mix.shapes, probs)]


def test_a_straight_line_stays_the_line():
    """Twenty straight-line units: the line keeps most of the posterior (BIC-like Bayes
    factors of the unit-information prior), and the mixture's 90 % interval of the last
    year's rate covers the true rate in about 90 % of them."""
    rng = np.random.default_rng(13)
    t = YEARS.astype(float)
    p_line, hits = [], 0
    for u in range(20):
        slope = rng.uniform(0.02, 0.1)
        err = np.full((len(t), 2), 0.05)
        x = np.column_stack([slope * t, -0.5 * slope * t]) + err * rng.standard_normal(err.shape)
        shape, _, now, _, _ = _draws(_mixture(x, err, seed=u), n=2000, seed=u)
        p_line.append(np.mean(shape == 0))
        lo, hi = np.quantile(now[:, 1, 0], [0.05, 0.95])
        hits += lo <= slope <= hi
    assert np.median(p_line) > 0.7, p_line
    assert hits >= 16, hits


def test_stacked_small_factors_and_forward_solves_match_lapack():
    from twinmon.calibrate.stacked import forward_solve, small_cholesky
    rng = np.random.default_rng(3)
    # Entry by entry (many of n <= 4), and LAPACK's (few, or n = 5).
    for shape, n in (((30, 64), 2), ((12, 64), 4), ((3,), 2), ((64,), 5)):
        A = rng.standard_normal(shape + (n, n + 2))
        V = A @ np.swapaxes(A, -1, -2)
        L = small_cholesky(V)
        np.testing.assert_allclose(L, np.linalg.cholesky(V), rtol=0, atol=1e-12)
        B = rng.standard_normal(shape + (n, 3))
        np.testing.assert_allclose(forward_solve(L, B), np.linalg.solve(L, B), rtol=0,
                                   atol=1e-10)


def test_a_summary_without_change_draws_names_no_change_year_and_stays_quiet():
    """Draws that all lie on the line and the accelerating shape: no input's change year,
    and no warning of numpy's (a mean over no draws) on the user's terminal."""
    import warnings
    shape = np.array([0, 0, 1, 0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        summary = shape_summary({"shape": shape, "change_year": np.full(4, -1),
                                 "change_years": np.full((4, 2), -1)})
    assert summary["change_year"] is None and summary["change_years"] == [None, None]
    assert summary["line"] == 0.75 and summary["change"] == 0.0
