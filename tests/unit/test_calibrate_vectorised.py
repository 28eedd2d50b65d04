"""calibrate's vectorised sampler and ``--update``: the batched surrogate and diagnostics equal
the reference ones, the sampler matches quadrature, results do not depend on the batching or
the workers, and an update equals a full run array for array."""
from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from twinmon.artifacts import file_sha256
from twinmon.calibrate import (_unit_seed, calibrate, ess, make_log_density, read_posterior,
                               split_rhat, year_prior)
from twinmon.calibrate.samplers import convergence, gpbatch
from twinmon.calibrate.samplers.vectorised import UnitData, calibrate_units
from twinmon.config import load_config
from twinmon.errors import ArtifactError
from twinmon.observations import read_observations, write_observations
from twinmon.reduce import read_surrogate, reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, ROOT, write_posterior_v1, write_yaml

FLEET = ROOT / "data" / "fleet.h5"     # the shipped fleet: 3 units x 10 years, noise 4 kg/s
FAST = {"sampler": "vectorised", "workers": 1, "samples": 300, "burn_in": 100,
        "ess_warn": 100, "max_extensions": 1}


@pytest.fixture(scope="module")
def setup(tmp_path_factory, fmu_path):
    """A real surrogate (FMU runs + reduce) and a fast vectorised config."""
    tmp = tmp_path_factory.mktemp("vectorised")
    cfg_path = write_yaml(tmp / "c.yaml", {"extends": str(CONFIGS / "fleet.yaml"),
                                           "simulate": {"train_size": 64, "test_size": 8},
                                           "calibrate": FAST})
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    return cfg, cfg_path, tmp, read_surrogate(tmp / "sur.h5")


def _cut(path, years: int, drop=()):
    """The shipped fleet's first ``years`` years, without the units in ``drop``."""
    obs = read_observations(FLEET)
    units = {u: dataclasses.replace(o, years=o.years[:years],
                                    channels={c: v[:years] for c, v in o.channels.items()},
                                    events=[e for e in o.events if e.year <= o.years[years - 1]])
             for u, o in obs.units.items() if u not in drop}
    write_observations(path, dataclasses.replace(obs, units=units))
    return path


def _units(cfg, names=("Park", "Colt", "Monk"), years=2):
    obs = read_observations(FLEET, cfg.model.output.name)
    return [UnitData(n, obs.units[n].years[:years], obs.output_of(n)[:years],
                       np.full(years, 4.0), _unit_seed(cfg, n), "file") for n in names]


def _assert_same_unit(a, b, where=""):
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, dict):
            assert x.keys() == y.keys(), (where, f.name)
            for k in x:
                assert np.array_equal(np.asarray(x[k]), np.asarray(y[k])), (where, f.name, k)
        elif isinstance(x, np.ndarray):
            assert np.array_equal(x, y), (where, f.name)
        else:
            assert x == y, (where, f.name)


def test_batched_surrogate_is_openturns_prediction(setup):
    _, _, _, sur = setup
    gp = gpbatch.GPBatch(sur)
    rng = np.random.default_rng(5)
    X = sur.bounds[:, 0] + rng.random((300, 2)) * np.diff(sur.bounds, axis=1).ravel()
    ref = sur.predict(X)
    assert np.max(np.abs(gp(X) / ref - 1)) < 1e-7
    # Row by row the same bits, whatever the batch around it (the sampler's determinism).
    perm = rng.permutation(len(X))
    assert np.array_equal(gp(X[perm])[np.argsort(perm)], gp(X))
    assert np.array_equal(np.vstack([gp(X[i:i + 7]) for i in range(0, 300, 7)]), gp(X))
    assert gpbatch.make_predictor(sur)[1]


def test_tabulated_surrogate_is_the_gp_prediction_row_by_row(setup, monkeypatch):
    """The forecast's table of the GP: within its tolerance of GPBatch (and of OpenTURNS)
    over the box, edges included; a row's value whatever the batch; a point outside the
    box gets GPBatch's bits; a table that fails its check is not used."""
    _, _, _, sur = setup
    gp = gpbatch.GPBatch(sur)
    table = gpbatch.GPTable(gp)
    rng = np.random.default_rng(6)
    lo, width = sur.bounds[:, 0], np.diff(sur.bounds, axis=1).ravel()
    X = lo + rng.random((400, 2)) * width
    X[:4] = lo + np.array([[0, 0], [0, 1], [1, 0], [1, 1]]) * width
    ref = gp(X)
    err = np.max(np.abs(table(X) / ref - 1))
    assert 0 < err <= gpbatch.TABLE_RTOL
    assert np.max(np.abs(table(X) / sur.predict(X) - 1)) < 1e-6
    perm = rng.permutation(len(X))
    assert np.array_equal(table(X[perm])[np.argsort(perm)], table(X))
    assert np.array_equal(np.vstack([table(X[i:i + 9]) for i in range(0, 400, 9)]), table(X))
    out = np.vstack([lo - 0.1 * width, lo + 1.2 * width, X[:3]])
    assert np.array_equal(table(out)[:2], gp(out[:2]))
    assert np.array_equal(table(out)[2:], table(X[:3]))
    # Kept per surrogate in the process; a table that fails its check leaves GPBatch.
    monkeypatch.setattr(gpbatch, "_TABLES", {})
    assert isinstance(gpbatch._numpy_form(sur, True), gpbatch.GPTable)
    monkeypatch.setattr(gpbatch, "_TABLES", {})
    monkeypatch.setattr(gpbatch, "TABLE_RTOL", 1e-15)
    with pytest.raises(ValueError, match="differs from GPBatch"):
        gpbatch.GPTable(gp)
    assert type(gpbatch._numpy_form(sur, True)) is gpbatch.GPBatch
    assert type(gpbatch._numpy_form(sur, False)) is gpbatch.GPBatch


@pytest.mark.parametrize("d", [1, 3, 4])
def test_the_table_with_other_numbers_of_inputs(d):
    """Not the pump alone: a surrogate of 1 or 3 inputs (a first-order response whose gain
    and time constant they set) is tabulated within the table's tolerance (4097 and 40
    nodes a side); with 4 inputs (16 a side) the table is refused and GPBatch serves."""
    from twinmon.config.reduce import ReduceConfig
    from twinmon.reduce.surrogate import fit_surrogate
    rng = np.random.default_rng(d)
    X, t = rng.random((64, d)), np.linspace(0.0, 10.0, 25)
    tau = 1.0 + X[:, 0] + 0.5 * X[:, -1]
    gain = 100.0 * (1.0 + 0.3 * X[:, -1] - 0.2 * X[:, 0] * X[:, d // 2])
    Y = gain[:, None] * (1.0 - np.exp(-t[None, :] / tau[:, None])) + 1.0
    sur = fit_surrogate(X, Y, t, np.tile([0.0, 1.0], (d, 1)), [f"x{i}" for i in range(d)],
                        ReduceConfig())
    gp = gpbatch.GPBatch(sur)
    if d == 4:
        with pytest.raises(ValueError, match="too few"):
            gpbatch.GPTable(gp)
        return
    table = gpbatch.GPTable(gp)
    U = rng.random((500, d))
    assert np.max(np.abs(table(U) / gp(U) - 1)) <= gpbatch.TABLE_RTOL


def test_batched_diagnostics_equal_the_reference():
    rng = np.random.default_rng(2)
    for trial in range(60):
        C, n = int(rng.integers(2, 6)), int(rng.integers(5, 700))
        x = np.zeros((C, n, 2))
        a = rng.uniform(0, 0.99)
        for i in range(1, n):     # AR(1) moves, accepted at a random rate (ties = rejections)
            moved = rng.random((C, 2)) < rng.uniform(0.05, 0.9)
            x[:, i] = np.where(moved, a * x[:, i - 1] + rng.standard_normal((C, 2)), x[:, i - 1])
        if trial % 5 == 0:
            x[0] += 2.0           # a chain stuck elsewhere
        rhat, n_eff = convergence.diagnostics(x)
        assert np.array_equal(rhat, [split_rhat(x[:, :, j]) for j in range(2)], equal_nan=True)
        assert np.array_equal(n_eff, [ess(x[:, :, j], rank_normalize=True) for j in range(2)],
                              equal_nan=True)


def _quadrature_mean(ld, n=301):
    b = ld.prior.bounds
    axes = [np.linspace(lo, hi, n) for lo, hi in b]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    lp = ld.batch(grid)
    w = np.exp(lp - lp.max())
    w /= w.sum()
    mean = w @ grid
    return mean, np.sqrt(w @ (grid - mean) ** 2)


def test_posterior_mean_matches_quadrature_both_years(setup):
    """Year 1 (uniform prior, the curved case) and year 2 (the Gaussian prior built from
    year 1's stored mean and variance): the delayed-acceptance chains target the exact
    posterior."""
    cfg, _, _, sur = setup
    cfg = dataclasses.replace(cfg, calibrate=dataclasses.replace(cfg.calibrate, ess_warn=800,
                                                                 samples=1500))
    (unit,) = _units(cfg, ("Monk",), years=2)
    p = calibrate_units(sur, cfg, [unit])["Monk"]
    for k in range(2):
        prior = year_prior(cfg, None if k == 0 else p.mean[0], None if k == 0 else p.var[0])
        total = 4.0 ** 2 + sur.predict_var(prior.location[None])[0]
        ld = make_log_density(sur, unit.flows[k], total, prior)
        mean, sd = _quadrature_mean(ld)
        # the draws' Monte Carlo error: sd / sqrt(ESS), ESS >= 800
        assert np.all(np.abs(p.mean[k] - mean) < 4 * sd / np.sqrt(p.ess[k])), (k, p.mean[k], mean)
        assert np.allclose(np.sqrt(p.var[k]), sd, rtol=0.12), (k, np.sqrt(p.var[k]), sd)
        assert p.fit["converged"][k] and np.all(p.ess[k] >= 800)


def test_results_do_not_depend_on_the_batch(setup):
    cfg, _, _, sur = setup
    units = _units(cfg)
    together = calibrate_units(sur, cfg, units)
    alone = calibrate_units(sur, cfg, [units[1]])
    _assert_same_unit(together["Colt"], alone["Colt"], "Colt")
    assert not np.array_equal(together["Colt"].mean, together["Park"].mean)


def test_update_equals_a_full_run(setup, tmp_path):
    """Years 1..3 of two units, then an update with years 1..5 and a third unit: the arrays
    equal a full 1..5 run's, bit for bit, on one worker and on two."""
    cfg, _, _, _ = setup
    sur = setup[2] / "sur.h5"
    short, long = _cut(tmp_path / "o3.h5", 3, drop=("Monk",)), _cut(tmp_path / "o5.h5", 5)
    calibrate(cfg, sur, long, tmp_path / "full.h5")
    calibrate(cfg, sur, short, tmp_path / "upd.h5")
    cfg2 = dataclasses.replace(cfg, calibrate=dataclasses.replace(cfg.calibrate, workers=2))
    s = calibrate(cfg2, sur, long, tmp_path / "upd.h5", update=True)
    assert s.update["kept_years"] == 6 and s.update["new_years"] == 9
    assert s.update["new_units"] == ["Monk"] and not s.update["redone_units"]
    full, upd = read_posterior(tmp_path / "full.h5"), read_posterior(tmp_path / "upd.h5")
    assert sorted(full.units) == sorted(upd.units)
    for u in full.units:
        _assert_same_unit(full.units[u], upd.units[u], u)
    # Nothing new: everything kept, nothing sampled.
    s = calibrate(cfg, sur, long, tmp_path / "upd.h5", update=True)
    assert s.update["new_years"] == 0
    for u in full.units:
        _assert_same_unit(full.units[u], read_posterior(tmp_path / "upd.h5").units[u], u)


def test_update_with_the_openturns_sampler_equals_a_full_run(setup, tmp_path):
    """Continuing this layout (the kept draws left in the file, the new ones appended) and
    the first one (``twinmon.posterior/1``, read whole and written again)."""
    cfg, _, tmp, _ = setup
    cc = dataclasses.replace(cfg.calibrate, sampler="openturns", samples=150, burn_in=50,
                             chains=2, ess_warn=50, max_extensions=0)
    cfg = dataclasses.replace(cfg, calibrate=cc)
    short, long = _cut(tmp_path / "o2.h5", 2, drop=("Monk", "Colt")), \
        _cut(tmp_path / "o3.h5", 3, drop=("Monk", "Colt"))
    calibrate(cfg, tmp / "sur.h5", long, tmp_path / "full.h5")
    calibrate(cfg, tmp / "sur.h5", short, tmp_path / "upd.h5")
    post = read_posterior(tmp_path / "upd.h5")
    write_posterior_v1(tmp_path / "upd1.h5", tmp_path / "upd.h5", {"Park": post.units["Park"]})
    full = read_posterior(tmp_path / "full.h5").units["Park"]
    for name in ("upd.h5", "upd1.h5"):
        s = calibrate(cfg, tmp / "sur.h5", long, tmp_path / name, update=True)
        assert s.update["kept_years"] == 2
        assert s.posterior["Park"].samples_from == (2 if name == "upd.h5" else 0)
        _assert_same_unit(full, read_posterior(tmp_path / name).units["Park"], name)


def test_update_redoes_a_unit_whose_data_changed_and_refuses_another_config_or_version(setup, tmp_path):
    cfg, _, tmp, _ = setup
    sur = tmp / "sur.h5"
    short = _cut(tmp_path / "o2.h5", 2, drop=("Monk", "Colt"))
    calibrate(cfg, sur, short, tmp_path / "post.h5")
    obs = read_observations(_cut(tmp_path / "o3.h5", 3, drop=("Monk", "Colt")))
    obs.units["Park"].channels["m_flow"][0, 5] += 1.0        # a corrected year-1 sample
    write_observations(tmp_path / "o3.h5", obs)
    s = calibrate(cfg, sur, tmp_path / "o3.h5", tmp_path / "post.h5", update=True)
    assert s.update["redone_units"] == ["Park"] and s.update["kept_years"] == 0
    other = dataclasses.replace(cfg, calibrate=dataclasses.replace(cfg.calibrate, samples=400))
    with pytest.raises(ArtifactError, match=r"another config \(calibrate.samples 300 -> 400\)"):
        calibrate(other, sur, tmp_path / "o3.h5", tmp_path / "post.h5", update=True)
    # Another twinmon's posterior is not continued (its years may come from other code).
    with h5py.File(tmp_path / "post.h5", "r+") as f:
        f.attrs["twinmon_version"] = "0.0.9"
    before = file_sha256(tmp_path / "post.h5")
    with pytest.raises(ArtifactError, match=r"post\.h5: made by twinmon 0\.0\.9, this is "
                                            r"twinmon .*re-run calibrate without --update"):
        calibrate(cfg, sur, tmp_path / "o3.h5", tmp_path / "post.h5", update=True)
    assert file_sha256(tmp_path / "post.h5") == before


def test_cli_update_prints_what_it_kept(setup, tmp_path):
    from twinmon.cli import main
    _, cfg_path, tmp, _ = setup
    short, long = _cut(tmp_path / "o2.h5", 2, drop=("Monk", "Colt")), \
        _cut(tmp_path / "o3.h5", 3, drop=("Monk", "Colt"))
    args = ["calibrate", "-c", str(cfg_path), "--surrogate", str(tmp / "sur.h5"),
            "-o", str(tmp_path / "post.h5")]
    r = CliRunner().invoke(main, args + ["--observations", str(short)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, args + ["--observations", str(long), "--update", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["update"]["kept_years"] == 2
    r = CliRunner().invoke(main, args + ["--observations", str(long), "--update",
                                         "--set", "calibrate.chains=3"])
    assert r.exit_code == 5 and "calibrate.chains 4 -> 3" in r.output


def test_a_year_that_runs_out_of_steps_still_reports_its_r_hat(setup):
    """Chains stopped at their longest run before the ESS mark was met: the year is
    unconverged, and its R-hat is the chains' (not NaN, which the prognosis' reason then
    printed as 'R-hat up to nan')."""
    cfg, _, _, sur = setup
    cfg = dataclasses.replace(cfg, calibrate=dataclasses.replace(
        cfg.calibrate, ess_warn=100000, samples=200, burn_in=50, max_extensions=0))
    (unit,) = _units(cfg, ("Monk",), years=1)
    p = calibrate_units(sur, cfg, [unit])["Monk"]
    assert not p.fit["converged"][0]
    assert np.all(np.isfinite(p.rhat[0])) and np.all(p.rhat[0] > 0.9), p.rhat[0]
