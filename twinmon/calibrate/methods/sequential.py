"""The paper's method: each year sampled in turn, its prior centred on the previous year's.

Random-walk Metropolis-Hastings (OpenTURNS) from several chains started around the MAP
point with a proposal shaped on the Laplace covariance there: one task per chain
(:func:`run_chain_task`, ``calibrate.sampler: openturns``). The default sampler moves every
unit's chains of the same year at once in numpy
(:mod:`~twinmon.calibrate.samplers.vectorised`).
"""
from __future__ import annotations

import numpy as np

from ...config import Config
from ..base import Method
from ..density import LogDensity, find_map, make_log_density
from ..diagnostics import ess, split_rhat_many
from ..fit import FIT_FIELDS, STATUS_OK, STATUS_UNCONVERGED, year_fit
from ..posterior import UnitPosterior, thin_indices
from ..samplers.openturns import OpenTurnsSampler
from ..samplers.vectorised import VectorisedSampler
from ..shared import ChainTask, initial_states, year_prior, yearly_noise


def plan_chains(ld: LogDensity, chains: int, seed: int) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
    """Starting points and proposal covariance of one unit-year's chains.

    The proposal is Gaussian with covariance ``2.38^2/d`` times the Laplace covariance at the
    MAP (the optimal random-walk scale for a Gaussian target); the starting points are
    dispersed around the MAP (see :func:`initial_states`).

    Returns
    -------
    starts : ndarray, shape [chains, d]
    proposal_cov : ndarray, shape [d, d]
    x_map : ndarray, shape [d]
    """
    x_map, cov = find_map(ld)
    starts = initial_states(np.random.default_rng(seed), x_map, cov, ld.prior, chains)
    return starts, 2.38 ** 2 / len(x_map) * cov, x_map


def run_chain(ld: LogDensity, start: np.ndarray, proposal_cov: np.ndarray, samples: int,
              burn_in: int, seed: int, thin: int = 1) -> tuple[np.ndarray, float]:
    """One OpenTURNS random-walk Metropolis-Hastings chain, burn-in removed.

    OpenTURNS adapts the proposal scale during the burn-in only, and ``getSample(n)``
    returns the burn-in with the chain (OpenTURNS 1.27), so the first ``burn_in`` draws are
    dropped here.

    Parameters
    ----------
    ld : LogDensity
    start : ndarray, shape [d]
    proposal_cov : ndarray, shape [d, d]
    samples, burn_in : int
        Kept and discarded draws.
    seed : int
        Seed of OpenTURNS' generator for this chain.
    thin : int
        Run ``samples * thin`` steps after the burn-in and keep every ``thin``-th.

    Returns
    -------
    draws : ndarray, shape [samples, d]
    acceptance : float
        Fraction of accepted moves after the burn-in.
    """
    import openturns as ot
    d = len(start)
    proposal = ot.Normal([0.0] * d, ot.CovarianceMatrix(np.asarray(proposal_cov).tolist()))
    support = ot.Interval(ld.prior.bounds[:, 0].tolist(), ld.prior.bounds[:, 1].tolist())
    ot.RandomGenerator.SetSeed(int(seed) % (2 ** 31))
    mh = ot.RandomWalkMetropolisHastings(ld.as_openturns(), support, list(map(float, start)),
                                         proposal)
    mh.setBurnIn(burn_in)
    x = np.asarray(mh.getSample(burn_in + samples * thin))[burn_in:]
    # A continuous proposal never repeats a point: a repeated row is a rejection.
    acceptance = float(np.mean(np.any(np.diff(x, axis=0) != 0, axis=1)))
    return x[thin - 1::thin], acceptance


def sample_posterior(ld: LogDensity, chains: int, samples: int, burn_in: int,
                     seed: int, thin: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw ``chains`` random-walk Metropolis-Hastings chains from one unit-year's posterior
    (:func:`plan_chains` then :func:`run_chain` for each chain).

    Parameters
    ----------
    ld : LogDensity
    chains, samples, burn_in : int
        Number of chains, kept draws per chain, discarded draws per chain.
    seed : int
        Seeds numpy (starting points) and OpenTURNS (chain ``c`` uses ``seed + 1 + c``).
    thin : int
        Run ``samples * thin`` steps after the burn-in and keep every ``thin``-th.

    Returns
    -------
    draws : ndarray, shape [chains, samples, d]
        Post-burn-in draws, input units.
    acceptance : ndarray, shape [chains]
        Fraction of accepted moves after burn-in.
    x_map : ndarray, shape [d]
    """
    starts, cov, x_map = plan_chains(ld, chains, seed)
    out = [run_chain(ld, starts[c], cov, samples, burn_in, seed + 1 + c, thin)
           for c in range(chains)]
    return np.array([o[0] for o in out]), np.array([o[1] for o in out]), x_map



def run_chain_task(surrogate, task: ChainTask) -> tuple[np.ndarray, float]:
    """One chain of :meth:`SequentialRun.plan` (:func:`run_chain` on its unit-year's
    log-posterior): draws [samples, d] and acceptance rate."""
    ld = make_log_density(surrogate, task.obs_row, task.noise_var, task.prior)
    return run_chain(ld, task.start, task.proposal_cov, task.samples, task.burn_in, task.seed,
                     task.thin)


class SequentialRun:
    """One unit's calibration, advanced a year at a time.

    :meth:`plan` sets up the next year (prior, noise, MAP, starting points) and returns its
    chain tasks; :meth:`finish` takes their results. The serial path runs the tasks in turn,
    the parallel path spreads the tasks of every unit's year over worker processes; both give
    identical arrays.
    """

    def __init__(self, surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                 noise_source: str):
        cc = cfg.calibrate
        self.surrogate, self.cfg, self.seed, self.source = surrogate, cfg, rng_seed, noise_source
        self.years = np.asarray(years, dtype=np.int64)
        self.flows = np.atleast_2d(np.asarray(flows, float))
        n_y, d = len(self.years), len(cfg.model.input_names)
        self.noise = yearly_noise(surrogate, noise_std, n_y)
        self.stats = {k: np.empty((n_y, d))
                      for k in ("mean", "median", "q05", "q95", "rhat", "ess")}
        self.samples = np.empty((n_y, cc.chains * cc.samples, d))
        self.acc = np.empty((n_y, cc.chains))
        self.ratio = np.empty(n_y)
        self.var, self.chain_end = np.empty((n_y, d)), np.empty((n_y, cc.chains, d))
        self.fits: list[dict] = []
        self.k = 0
        self.ext = 0             # how many times year k's chains were lengthened
        self.prev = self.prev_var = None
        self.samples_from = 0    # samples[i] holds year samples_from + i

    def resume(self, p: UnitPosterior) -> None:
        """Take the first ``len(p.years)`` years from an earlier posterior of this unit (as
        they are) and continue after them (``calibrate --update``). Draws left in the file
        (``p.samples_from``) stay there; the result then holds the draws from that year on."""
        k = len(p.years)
        for key, arr in self.stats.items():
            arr[:k] = getattr(p, key)
        # The stored draws may be thinned: later years are thinned alike (see finish()).
        self.samples_from = p.samples_from
        self.samples = np.empty((len(self.years) - p.samples_from,) + p.samples.shape[1:])
        self.samples[:k - p.samples_from] = p.samples
        self.acc[:k], self.ratio[:k] = p.acceptance, p.surrogate_var_ratio
        self.var[:k], self.chain_end[:k] = p.var, p.chain_end
        self.fits = [{key: p.fit[key][i] for key in p.fit} for i in range(k)]
        self.k = k
        self.prev, self.prev_var = p.mean[k - 1], p.var[k - 1]

    @property
    def done(self) -> bool:
        return self.k >= len(self.years)

    def plan(self) -> list[ChainTask]:
        cc, k = self.cfg.calibrate, self.k
        prior = year_prior(self.cfg, self.prev, self.prev_var)
        # The surrogate's variance is held at its value at the prior's centre: computing it
        # costs ~4 likelihood evaluations and it is 3 orders of magnitude below the noise.
        s_var = self.surrogate.predict_with_var(prior.location[None, :])[1][0]
        if self.noise.ndim == 2:   # per channel: each channel's noise over its own steps
            var = self.surrogate.noise_var(self.noise[k])
            total = var + s_var
            self.ratio[k] = float(np.mean(s_var / var))
        else:
            total = self.noise[k] ** 2 + s_var
            self.ratio[k] = float(np.mean(s_var) / self.noise[k] ** 2)
        ld = make_log_density(self.surrogate, self.flows[k], total, prior)
        self._total, self._prior = total, prior
        seed = self.seed + 97 * k
        starts, cov, _ = plan_chains(ld, cc.chains, seed)
        # The year-1 posterior (uniform prior) is wider and more curved than the Laplace
        # shape of the proposal: its chains mix about half as well, so they run twice as long.
        # A year sampled again (poor R-hat or ESS) runs 2^ext times longer, thinned to the
        # same number of kept draws, from fresh seeds.
        thin = (2 if prior.is_uniform else 1) * 2 ** self.ext
        burn = cc.burn_in * 2 ** self.ext
        seed = seed + 7919 * self.ext
        return [ChainTask(prior, self.flows[k], total, starts[c], cov, cc.samples, burn,
                           seed + 1 + c, thin) for c in range(cc.chains)]

    def finish(self, results: list[tuple[np.ndarray, float]]) -> None:
        cc, k = self.cfg.calibrate, self.k
        draws = np.array([r[0] for r in results])          # [chains, samples, d]
        d = draws.shape[2]
        rhat = split_rhat_many(np.moveaxis(draws, 2, 0))                    # [d]
        n_eff = np.array([ess(draws[:, :, j], rank_normalize=True) for j in range(d)])
        converged = bool(np.all(rhat <= cc.rhat_warn) and np.all(n_eff >= cc.ess_warn))
        if not converged and self.ext < cc.max_extensions:
            self.ext += 1          # sample this year again, longer (plan() sees ext)
            return
        self.acc[k] = [r[1] for r in results]
        pooled = draws.reshape(-1, d)
        self.samples[k - self.samples_from] = pooled if len(pooled) == self.samples.shape[1] else \
            pooled[thin_indices(len(pooled), self.samples.shape[1])]
        st = self.stats
        st["mean"][k] = pooled.mean(axis=0)
        st["median"][k] = np.median(pooled, axis=0)
        st["q05"][k], st["q95"][k] = np.quantile(pooled, [0.05, 0.95], axis=0)
        st["rhat"][k], st["ess"][k] = rhat, n_eff
        fit = year_fit(self.surrogate, self.cfg, self.flows[k], self._total, pooled,
                       self._prior.bounds)
        fit.update(extensions=self.ext, converged=converged)
        if fit["status"] == STATUS_OK and not converged:
            fit["status"] = STATUS_UNCONVERGED
        self.fits.append(fit)
        self.var[k], self.chain_end[k] = pooled.var(axis=0), draws[:, -1]
        self.prev, self.prev_var = st["mean"][k], self.var[k]
        self.k += 1
        self.ext = 0

    def result(self) -> UnitPosterior:
        fit = {key: np.array([f[key] for f in self.fits]) for key in FIT_FIELDS}
        if self.fits and "channel_rms" in self.fits[0]:
            fit["channel_rms"] = np.array([f["channel_rms"] for f in self.fits])
        # noise_std is the output's; the further channels' go with UnitPosterior.channels.
        noise = self.noise[:, 0] if self.noise.ndim == 2 else self.noise
        return UnitPosterior(years=self.years, samples=self.samples, acceptance=self.acc,
                             noise_std=noise, noise_source=self.source,
                             surrogate_var_ratio=self.ratio, fit=fit, var=self.var,
                             chain_end=self.chain_end, samples_from=self.samples_from,
                             **self.stats)


def calibrate_unit(surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                   noise_source: str = "file") -> UnitPosterior:
    """Posterior of one unit's inputs for each of its years, in year order (in-process).

    Parameters
    ----------
    surrogate : Surrogate
    cfg : Config
        Uses ``model`` (box) and ``calibrate`` (chains, samples, burn-in, prior width).
    years : array of int, shape [n_y]
    flows : ndarray, shape [n_y, n_t] or [n_y, n_ch * n_t]
        Measured output (its units) on the surrogate's time grid; NaN = missing. With a
        :class:`~twinmon.calibrate.channels.StackedSurrogate`, every stacked channel's
        records side by side.
    noise_std : float or ndarray, shape [n_y]; with a stacked surrogate [n_ch] or [n_y, n_ch]
        Output (or each channel's) noise standard deviation (its units).
    rng_seed : int
        Seed of this unit's draws (year ``k`` uses ``rng_seed + 97 * k``, as
        :func:`sample_posterior` would).
    noise_source : str
        Recorded with the result.
    """
    run = SequentialRun(surrogate, cfg, years, flows, noise_std, rng_seed, noise_source)
    while not run.done:
        run.finish([run_chain_task(surrogate, t) for t in run.plan()])
    return run.result()


class SequentialMethod(Method):
    """The paper's method (``calibrate.method: sequential``): a unit's years in turn, each
    prior centred on the previous year's posterior."""

    name = "sequential"
    continues_years = True

    @property
    def samplers(self):
        return {"vectorised": VectorisedSampler(), "openturns": OpenTurnsSampler(run_chain_task)}

    def start(self, model, cfg: Config, years, flows, noise, seed: int, source: str,
              events=()) -> SequentialRun:
        return SequentialRun(model, cfg, years, flows, noise, seed, source)
