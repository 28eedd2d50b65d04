"""calibrate, the fleet's prior of the trend forms (twinmon/calibrate/fleet_shapes.py): its
fit recovers the proportions a fleet was drawn with, ignores what a short record cannot say,
and the forecast's resampling takes a unit's draws to its posterior under it."""
from __future__ import annotations

import numpy as np
from scipy.optimize import approx_fprime

from twinmon.calibrate.fleet_shapes import _neg_log_posterior, fit_fleet_shapes
from twinmon.calibrate.shapes import available_forms, form_names, form_of, form_priors

BASE = form_priors({"line": 0.6, "accelerating": 0.2, "change": 0.2})
F = len(form_names())


def _pi(**named) -> np.ndarray:
    """Proportions over :func:`form_names` from ``name=p`` (spaces as underscores, the
    exponential's rate without its point: ``exponential_03``); the others 0."""
    key = {n.replace(" ", "_").replace(".", ""): j for j, n in enumerate(form_names())}
    out = np.zeros(F)
    for name, p in named.items():
        out[key[name]] = p
    return out


def _fleet(pi_true: np.ndarray, n: int, rng):
    """Units whose form is drawn from ``pi_true``, each seen through one noisy summary
    ``y ~ N(mu_form, I)`` whose forms' means lie 1.5 apart from their neighbours in the plane (so a unit
    alone is unsure of its form). Returns the units' posterior shares under :data:`BASE`
    [n, F] (prior times the exact likelihood of ``y``) and their forms."""
    ang = 2 * np.pi * np.arange(F) / F
    # On a circle whose neighbours lie 1.53 apart, whatever the number of forms.
    mu = 2 * np.sin(np.pi / 8) / np.sin(np.pi / F) * np.column_stack([np.cos(ang),
                                                                       np.sin(ang)])  # [F, 2]
    true = rng.choice(F, n, p=pi_true)
    y = mu[true] + rng.standard_normal((n, 2))
    log_z = -0.5 * ((y[:, None, :] - mu[None]) ** 2).sum(axis=2)
    post = BASE * np.exp(log_z - log_z.max(axis=1, keepdims=True))
    return post / post.sum(axis=1, keepdims=True), true


def test_recovers_the_proportions_a_fleet_was_drawn_with():
    """2000 units, few of whose own posteriors are sure of their form: the fitted prior is
    within 0.03 of the proportions they were drawn with, where the calibration's prior
    (0.6 on the line) is far off."""
    rng = np.random.default_rng(1)
    pi_true = _pi(line=0.3, quadratic=0.25, exponential_01=0.05, exponential_02=0.05,
                  exponential_03=0.25, exponential_04=0.05, change=0.05)
    shares, _ = _fleet(pi_true, 2000, rng)
    fit = fit_fleet_shapes(shares, np.ones_like(shares, bool), BASE, prior_units=8.0)
    assert np.abs(fit.proportions - pi_true).max() < 0.03, fit.proportions
    assert np.abs(BASE - pi_true).max() > 0.25
    assert abs(fit.proportions.sum() - 1) < 1e-12 and fit.n_units == 2000
    assert abs(fit.shape_priors()["accelerating"] - pi_true[1:-1].sum()) < 0.03


def test_a_small_fleet_stays_near_the_calibrations_prior():
    """Five units: the Dirichlet prior worth 8 units holds the fit closer to the
    calibration's prior than the same units' maximum likelihood (prior_units 0)."""
    rng = np.random.default_rng(2)
    shares, _ = _fleet(_pi(quadratic=1.0), 5, rng)
    avail = np.ones_like(shares, bool)
    held = fit_fleet_shapes(shares, avail, BASE, prior_units=8.0).proportions
    free = fit_fleet_shapes(shares, avail, BASE, prior_units=0.0).proportions
    assert np.abs(held - BASE).sum() < np.abs(free - BASE).sum()
    assert held.min() > 0.0


def test_units_too_short_for_a_shape_say_nothing_of_it():
    """Units whose segments allow the line alone (share 1 on it) leave the fit as it is on
    the other units; counted as if every form were open, they would pull it to the line."""
    rng = np.random.default_rng(3)
    shares, _ = _fleet(_pi(line=0.2, quadratic=0.4, exponential_01=0.1, exponential_02=0.1,
                           exponential_03=0.1, change=0.1), 300, rng)
    short = np.zeros((300, F))
    short[:, 0] = 1.0
    avail = np.ones((600, F), bool)
    avail[300:] = available_forms(np.array([4, 3]))        # no acceleration, no change
    both = fit_fleet_shapes(np.vstack([shares, short]), avail, BASE).proportions
    alone = fit_fleet_shapes(shares, avail[:300], BASE).proportions
    naive = fit_fleet_shapes(np.vstack([shares, short]), np.ones((600, F), bool),
                             BASE).proportions
    assert np.abs(both - alone).max() < 0.01, (both, alone)
    assert naive[0] > alone[0] + 0.2


def test_gradient_is_that_of_the_objective():
    rng = np.random.default_rng(4)
    shares, _ = _fleet(np.full(F, 1.0 / F), 40, rng)
    avail = rng.random((40, F)) < 0.8
    avail[:, 0] = True
    S = shares * avail
    S /= S.sum(axis=1, keepdims=True)
    z = rng.normal(0, 0.5, F)
    value, grad = _neg_log_posterior(z, S, avail.astype(float), BASE, 8.0)
    num = approx_fprime(z, lambda v: _neg_log_posterior(v, S, avail.astype(float), BASE,
                                                        8.0)[0], 1e-6)
    assert np.allclose(grad, num, rtol=1e-4, atol=1e-4), (grad, num)


def test_forms_of_draws_and_their_priors():
    code = np.array([0, 1, 1, 1, 1, 1, 2])
    growth = np.array([0.0, 0.0, 0.1, 0.5, -1.25, -1.75, 0.0])
    names = form_names()
    assert [names[j] for j in form_of(code, growth)] == [
        "line", "quadratic", "exponential 0.1", "exponential 0.5", "power 1.25",
        "power 1.75", "change"]
    n_acc = F - 2
    assert abs(BASE.sum() - 1) < 1e-12 and BASE[0] == 0.6 and BASE[-1] == 0.2
    assert np.allclose(BASE[1:-1], 0.2 / n_acc)
    assert available_forms(np.array([5, 2])).tolist() == [True] * (1 + n_acc) + [False]
    assert available_forms(np.array([6, 6])).all()


def test_pooled_draws_follow_the_fleets_prior():
    """A unit's draws resampled by the forecast (pooling._pool_unit): each form's share of
    them is the unit's posterior under the fleet's prior, s_f pi_f / b_f normalised."""
    from types import SimpleNamespace

    from twinmon.calibrate.fleet_shapes import FleetShapes
    from twinmon.forecast.pooling import _pool_unit
    rng = np.random.default_rng(5)
    n = 20000
    s = _pi(line=0.5, quadratic=0.1, exponential_01=0.1, exponential_02=0.1,
            exponential_03=0.05, power_15=0.05, power_175=0.05, change=0.05)
    forms = rng.choice(F, n, p=s)
    # Each form's code and growth, as the laplace method stores them.
    names = form_names()
    code = np.array([0 if names[f] == "line" else 2 if names[f] == "change" else 1
                     for f in forms])
    growth = np.array([float(names[f].split()[1]) if names[f].startswith("exponential")
                       else -float(names[f].split()[1]) if names[f].startswith("power")
                       else 0.0 for f in forms])
    pi = _pi(line=0.1, quadratic=0.5, exponential_01=0.1, exponential_02=0.1,
             exponential_03=0.05, power_15=0.05, power_175=0.05, change=0.05) + 0.01
    pi /= pi.sum()
    shapes = FleetShapes(pi, BASE, 44, 8.0)
    trend = {"sigma": np.ones((n, 2)), "shape": code, "growth": growth,
             "slope": np.zeros((n, 1, 2))}
    cfg = SimpleNamespace(seed=0)
    pooled, samples, ess = _pool_unit(cfg, "U", trend, np.zeros((3, n, 2)), None, shapes)
    got = np.bincount(form_of(pooled["shape"], pooled["growth"]), minlength=F) / n
    want = s * pi / BASE
    want /= want.sum()
    assert np.abs(got - want).max() < 0.01, (got, want)
    assert 0 < ess < n and samples.shape == (3, n, 2)


def test_units_within_normal_ageing_get_the_prior_of_units_like_them():
    """A fleet whose worn units accelerate and whose sound units follow lines: the units
    whose slopes stay within normal ageing are told apart by the forecast's slope test and
    get a prior fitted on them (mostly the line), the others the whole fleet's; with fewer
    such units than forecast.pool_min_units they take the fleet's."""
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.directions import Direction
    from twinmon.forecast.pooling import ShapePriors, _drifts, _shapes_dict, fleet_priors

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    names = cfg.model.input_names
    directions = {n: Direction(+1 if cfg.model.inputs[n].degrading == "up" else -1, "config")
                  for n in names}
    rng = np.random.default_rng(2)
    n, years = 400, np.arange(1, 11)

    def unit(worn: bool):
        # Damping slope: 1.0 a year (4 tolerances beyond normal) or 0; the draws' forms:
        # a worn unit's mostly exponential 0.3, a sound unit's nearly all the line.
        slope = np.column_stack([rng.normal(1.0 if worn else 0.0, 0.05, n),
                                 rng.normal(-0.02, 0.005, n)])[:, None, :]
        code = rng.choice([0, 1], n, p=[0.1, 0.9] if worn else [0.98, 0.02])
        growth = np.where(code == 1, 0.3, 0.0)
        trend = {"sigma": np.abs(rng.normal(0.1, 0.01, (n, 2))), "shape": code,
                 "growth": growth, "start": np.array([[1, 1]]), "slope": slope}
        return SimpleNamespace(trend=trend, years=years)

    units = {f"W{i}": unit(True) for i in range(12)}
    units.update({f"S{i}": unit(False) for i in range(8)})
    post = SimpleNamespace(units=units, path="<memory>")
    shape_priors = {"line": 0.6, "accelerating": 0.2, "change": 0.2}
    assert _drifts(cfg, units["W0"].trend, directions) and not _drifts(
        cfg, units["S0"].trend, directions)
    _, pri = fleet_priors(cfg, post, shape_priors, directions)
    assert isinstance(pri, ShapePriors) and pri.steady is not None
    assert pri.steady.n_units == 8 and pri.drifting.n_units == 20
    assert pri.blend(0.0) is pri.steady and pri.blend(1.0) is pri.drifting
    assert pri.steady.proportions[0] > 0.6 > pri.drifting.proportions[0]
    assert _shapes_dict(pri)["steady"]["units"] == 8
    # Without directions, or with too few sound units, one prior for all.
    assert fleet_priors(cfg, post, shape_priors)[1].steady is None
    few = SimpleNamespace(units={k: v for k, v in units.items() if k < "S2" or k[0] == "W"},
                          path="<memory>")
    _, pri = fleet_priors(cfg, few, shape_priors, directions)
    assert pri.steady is None and pri.blend(0.0) is pri.drifting
    assert _shapes_dict(pri)["steady"] == {"pooled": False}


def test_a_units_prior_of_the_shapes_follows_its_evidence_of_drifting():
    """The prior a unit's future is drawn under: the fleet's wear prior for a unit whose
    slope draws all lie beyond normal ageing, the sound units' for one whose draws all lie
    within it, the two averaged by the share in between; a draw counts once however many of
    its inputs are beyond, and only on an input's degrading side."""
    from twinmon.calibrate.fleet_shapes import FleetShapes
    from twinmon.config import load_config
    from twinmon.forecast.directions import Direction
    from twinmon.forecast.pooling import ShapePriors, drift_probability

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "dcdrive.yaml")
    names = cfg.model.input_names
    spec = [cfg.model.inputs[n] for n in names]
    edge = np.array([s.normal_rate + s.normal_rate_tolerance for s in spec])
    directions = {n: Direction(+1, "config") for n in names}
    w = np.full(4, 0.25)
    inside = np.tile(edge * 0.5, (4, 1))
    assert drift_probability(cfg, inside, w, directions) == 0.0
    # One draw beyond on both inputs, one on the first alone: two of four draws.
    some = inside.copy()
    some[0] = 2 * edge + 1e-3
    some[1, 0] = 2 * edge[0] + 1e-3
    assert drift_probability(cfg, some, w, directions) == 0.5
    # Past the other side of the band: not wear for an input that degrades upwards, wear
    # for one whose direction is unknown.
    low = np.tile(np.array([s.normal_rate - s.normal_rate_tolerance for s in spec]) - 1.0,
                  (4, 1))
    assert drift_probability(cfg, low, w, directions) == 0.0
    assert drift_probability(cfg, low, w, {n: Direction(0, "inferred") for n in names}) == 1.0

    base = np.array([0.6, 0.2, 0.2])
    drifting = FleetShapes(np.array([0.2, 0.7, 0.1]), base, 20, 8.0)
    steady = FleetShapes(np.array([0.8, 0.1, 0.1]), base, 8, 8.0)
    pri = ShapePriors(drifting, steady)
    assert pri.blend(1.0) is drifting and pri.blend(0.0) is steady
    half = pri.blend(0.5)
    np.testing.assert_allclose(half.proportions, [0.5, 0.4, 0.1])
    np.testing.assert_array_equal(half.base, base)
    assert ShapePriors(drifting).blend(0.3) is drifting


def test_records_too_short_to_show_a_shape_teach_the_fleet_none():
    """The fleet's prior of the shapes is learnt from units whose current segment spans
    forecast.pool_shapes_min_years: over fewer, a unit's evidence leans on the line
    whatever its wear. A fleet of 7-year records learns nothing (the calibration's prior
    stands); 8-year records are learnt from; a fleet of both learns from the long ones."""
    from types import SimpleNamespace

    from twinmon.config import load_config
    from twinmon.forecast.pooling import fleet_shape_prior

    from ..conftest import CONFIGS
    cfg = load_config(CONFIGS / "pump.yaml")
    assert cfg.forecast.pool_shapes_min_years == 8
    rng = np.random.default_rng(4)
    n = 300

    def unit(n_years: int):
        code = rng.choice([0, 1], n, p=[0.3, 0.7])
        trend = {"sigma": np.abs(rng.normal(0.1, 0.01, (n, 2))), "shape": code,
                 "growth": np.where(code == 1, 0.3, 0.0), "start": np.array([[1, 1]])}
        return SimpleNamespace(trend=trend, years=np.arange(1, n_years + 1))

    shape_priors = {"line": 0.6, "accelerating": 0.2, "change": 0.2}
    short = SimpleNamespace(units={f"U{i}": unit(7) for i in range(10)}, path="<memory>")
    assert fleet_shape_prior(cfg, short, shape_priors) is None
    long = SimpleNamespace(units={f"U{i}": unit(8) for i in range(10)}, path="<memory>")
    assert fleet_shape_prior(cfg, long, shape_priors).n_units == 10
    both = SimpleNamespace(units={**short.units, **{f"L{i}": unit(8) for i in range(6)}},
                           path="<memory>")
    assert fleet_shape_prior(cfg, both, shape_priors).n_units == 6
    cfg7 = load_config(CONFIGS / "pump.yaml", ["forecast.pool_shapes_min_years=7"])
    assert fleet_shape_prior(cfg7, short, shape_priors).n_units == 10
