"""The vectorised sampler agrees with the OpenTURNS reference on a real fleet (seeded).

The shipped fleet's first three years (3 units, the real surrogate of configs/pump.yaml) are
calibrated by OpenTURNS' random-walk Metropolis-Hastings; then each unit-year is sampled by
the vectorised sampler from the SAME prior (the years before it taken from the OpenTURNS
posterior, as ``--update`` continues a posterior), so the two posteriors of a unit-year are
draws of one distribution and may differ by Monte Carlo error only: posterior means within 4
Monte Carlo standard errors (sd / sqrt(ESS) of each side, combined), 5 % and 95 % quantiles
within 4 of theirs (~2.1 sd / sqrt(ESS) for a near-Gaussian posterior); both converged (split
R-hat <= 1.01, bulk ESS >= calibrate.ess_warn).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinmon.calibrate import UnitPosterior, _unit_seed, calibrate, read_posterior
from twinmon.calibrate.samplers.convergence import first_look

pytestmark = pytest.mark.slow
from twinmon.calibrate.samplers.vectorised import UnitData, calibrate_units
from twinmon.config import load_config
from twinmon.observations import read_observations, write_observations
from twinmon.reduce import read_surrogate, reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, ROOT

YEARS = 3
K = 4.0              # Monte Carlo standard errors allowed (18 comparisons per statistic)


def _prefix(p: UnitPosterior, k: int, n_keep: int) -> UnitPosterior:
    """The first k years of a posterior (its draws cut to the vectorised sampler's count)."""
    fit = {key: np.asarray(v)[:k] for key, v in p.fit.items()}
    return dataclasses.replace(
        p, years=p.years[:k], samples=p.samples[:k, :n_keep], mean=p.mean[:k],
        median=p.median[:k], q05=p.q05[:k], q95=p.q95[:k], rhat=p.rhat[:k], ess=p.ess[:k],
        acceptance=p.acceptance[:k], noise_std=p.noise_std[:k],
        surrogate_var_ratio=p.surrogate_var_ratio[:k], fit=fit, var=p.var[:k],
        chain_end=p.chain_end[:k], digest=p.digest[:k])


@pytest.fixture(scope="module")
def both(tmp_path_factory, fmu_path):
    tmp = tmp_path_factory.mktemp("agree")
    sets = ["calibrate.rhat_warn=1.01"]
    cfg_ot = load_config(CONFIGS / "fleet.yaml", sets + ["calibrate.sampler=openturns"])
    cfg_v = load_config(CONFIGS / "fleet.yaml", sets + ["calibrate.sampler=vectorised"])
    simulate(cfg_ot, tmp / "sims.h5")
    reduce(cfg_ot, tmp / "sims.h5", tmp / "sur.h5")
    obs = read_observations(ROOT / "data" / "fleet.h5")
    obs = dataclasses.replace(obs, units={
        u: dataclasses.replace(o, years=o.years[:YEARS], events=[],
                               channels={c: v[:YEARS] for c, v in o.channels.items()})
        for u, o in obs.units.items()})
    write_observations(tmp / "obs.h5", obs)
    calibrate(cfg_ot, tmp / "sur.h5", tmp / "obs.h5", tmp / "ot.h5")
    ref = dict(read_posterior(tmp / "ot.h5").units.each())      # with its stored draws

    sur = read_surrogate(tmp / "sur.h5")
    out = {u: [] for u in ref}
    n_keep = min(cfg_v.calibrate.samples, first_look(cfg_v))
    for k in range(YEARS):
        units = [UnitData(u, obs.units[u].years[:k + 1],
                            obs.units[u].channels["m_flow"][:k + 1], p.noise_std[:k + 1],
                            _unit_seed(cfg_v, u), "file",
                            _prefix(p, k, n_keep) if k else None)
                 for u, p in ref.items()]
        for u, p in calibrate_units(sur, cfg_v, units).items():
            out[u].append(p)
    return cfg_v, ref, out


def test_both_converged(both):
    cfg, ref, vec = both
    for u, p in ref.items():
        assert np.all(p.rhat <= 1.01) and np.all(p.ess >= cfg.calibrate.ess_warn), u
        for k, q in enumerate(vec[u]):
            assert np.all(q.rhat[k] <= 1.01) and np.all(q.ess[k] >= cfg.calibrate.ess_warn), \
                (u, k, q.rhat[k], q.ess[k])
            assert q.fit["converged"][k] and q.fit["status"][k] == "ok"


def test_means_agree_within_monte_carlo_error(both):
    _, ref, vec = both
    worst = 0.0
    for u, p in ref.items():
        for k, q in enumerate(vec[u]):
            se = np.sqrt(p.var[k] / p.ess[k] + q.var[k] / q.ess[k])
            z = np.abs(q.mean[k] - p.mean[k]) / se
            worst = max(worst, z.max())
            assert np.all(z < K), (u, k, z)
            # and the spreads agree (a 10 % band: the sd of an sd estimate is ~sd/sqrt(2 ESS))
            assert np.allclose(np.sqrt(q.var[k]), np.sqrt(p.var[k]), rtol=0.10), (u, k)
    print(f"\nlargest |mean difference| / Monte Carlo se: {worst:.2f}")


def test_quantiles_agree_within_monte_carlo_error(both):
    _, ref, vec = both
    worst = 0.0
    for u, p in ref.items():
        for k, q in enumerate(vec[u]):
            sd = np.sqrt(p.var[k])
            se = 2.1 * sd * np.sqrt(1 / p.ess[k] + 1 / q.ess[k])
            for stat in ("q05", "q95", "median"):
                z = np.abs(getattr(q, stat)[k] - getattr(p, stat)[k]) / se
                worst = max(worst, z.max())
                assert np.all(z < K), (u, k, stat, z)
    print(f"\nlargest |quantile difference| / Monte Carlo se: {worst:.2f}")
