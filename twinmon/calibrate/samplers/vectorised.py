"""The sequential method's numpy sampler: random-walk Metropolis over every chain of every
unit's year at once.

The model is the paper's sequential one (:mod:`~twinmon.calibrate.methods.sequential`: the
same priors, likelihood, MAP and Laplace-shaped proposal, R-hat/ESS diagnostics and goodness
of fit); what changes is how it is sampled:

* **Batched surrogate.** :class:`.gpbatch.GPBatch` evaluates the Karhunen-Loeve +
  Gaussian-process surrogate as array arithmetic, one call per Metropolis step for all chains
  of all units of a batch, instead of one OpenTURNS call per point (the same prediction,
  checked against OpenTURNS when built), tabulated on a grid over the box
  (:class:`.gpbatch.GPTable`, checked against GPBatch).
* **Batched MAP.** :func:`.batch_map.batch_map` runs a projected Levenberg-Marquardt on every
  unit's standardised residuals at once (the least squares
  :func:`~twinmon.calibrate.density.find_map` solves one unit at a time), from the same start
  (the 21^d grid's best point for a uniform prior, the prior centre otherwise); the Laplace
  covariance is the same Gauss-Newton one.
* **Delayed acceptance** (Christen & Fox 2005). A proposal is screened by the Laplace
  approximation (no surrogate call) and only one it accepts goes through the surrogate,
  accepted with the ratio of the exact to the approximate Metropolis ratios: the chain
  targets the exact posterior, and the surrogate sees ~40 % of the proposals (the ESS per
  step drops by ~15 %; the CPU per unit-year by ~25 %).
* **Adaptive length.** After the burn-in, a unit-year stops as soon as its rank-normalised
  split R-hat <= ``calibrate.rhat_warn`` and bulk ESS >= ``calibrate.ess_warn`` for every
  input (first look after :func:`.convergence.first_look` steps, then extensions sized by the
  ESS, see :func:`.convergence.more_steps`), or at the longest run the OpenTURNS path may make
  (``samples * 2^max_extensions``, twice that for a uniform prior); not converged there, it
  is "unconverged" as on the OpenTURNS path. ``fit/extensions`` counts the extensions.
* **Warm start.** A year after the first starts its chains where the previous year's chains
  ended, moved by the shift of the MAP (``end_c + MAP_k - mean_{k-1}``: the previous
  posterior's spread, centred on this year's mode), so a short burn-in (a fifth) suffices;
  a start outside the box falls back to the MAP. The first year (and any year without
  stored chain ends) starts as :func:`~twinmon.calibrate.methods.sequential.plan_chains`
  does: MAP + 2 Laplace sd.

Determinism: every unit-year draws from its own generator seeded by (unit, year index)
(``unit seed + 97 k``, as the OpenTURNS path), and every row of a batch is computed without
reference to the other rows (element-wise operations and per-row sums, no BLAS products
whose blocking depends on the batch size), so a unit's result does not depend on which
units share its batch, on the number of workers, or on whether the years before were
sampled in this run or read from an earlier posterior (``calibrate --update``).

Stored draws: the summary statistics, diagnostics and the fit use all the draws; the
artifact's ``samples`` hold ``min(calibrate.samples, first_look)`` draws per chain, evenly
spaced along each chain (a fixed count, as the unit-years of a unit share one array).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ...config import Config
from ..base import Sampler, Work
from ..fit import FIT_FIELDS, STATUS_OK, STATUS_UNCONVERGED, year_fit
from ..posterior import UnitPosterior, thin_indices
from ..shared import (ADAPT_DOWN, ADAPT_PERIOD, ADAPT_RANGE, ADAPT_UP, initial_states,
                      sampling_pool, unit_groups, year_prior)
from .batch_map import Batch, batch_map, laplace_logpdf
from .convergence import converged, diagnostics, first_look, longest_run, more_steps
from .gpbatch import make_predictor, worker_predict

#: Warm-started years burn in for this fraction of ``calibrate.burn_in``.
WARM_BURN_FRACTION = 0.2
#: Screen proposals with the Laplace approximation first (delayed acceptance, see _sample_year).
DELAYED = True


# ---------------------------------------------------------------------------------------
# One unit's state across its years
# ---------------------------------------------------------------------------------------
@dataclass
class UnitData:
    """Everything needed to calibrate one unit (picklable, for a worker).

    Attributes
    ----------
    name : str
    years : ndarray of int, shape [n_y]
    flows : ndarray, shape [n_y, n_out]
        Observations on the surrogate's grid (stacked channels side by side); NaN = missing.
    noise : ndarray, shape [n_y] (or [n_y, n_ch] for a stacked surrogate)
    seed : int
        The unit's seed; year ``k`` draws from ``seed + 97 k``.
    source : str
        Where the noise came from.
    done : UnitPosterior, optional
        Years already calibrated (``calibrate --update``): kept as they are, sampling
        continues after them.
    """

    name: str
    years: np.ndarray
    flows: np.ndarray
    noise: np.ndarray
    seed: int
    source: str
    done: Optional[UnitPosterior] = None


class _UnitState:
    """One unit's results, filled a year at a time by :func:`_sample_year`."""

    def __init__(self, data: UnitData, cfg: Config, n_keep: int):
        cc = cfg.calibrate
        self.data, self.cfg = data, cfg
        n_y, d, C = len(data.years), len(cfg.model.input_names), cc.chains
        self.stats = {k: np.empty((n_y, d))
                      for k in ("mean", "median", "q05", "q95", "rhat", "ess", "var")}
        self.samples = np.empty((n_y, C * n_keep, d))
        self.acc = np.empty((n_y, C))
        self.ratio = np.empty(n_y)
        self.chain_end = np.empty((n_y, C, d))
        self.fits: list[dict] = []
        self.k = 0
        self.prev = self.prev_var = self.prev_end = None
        self.samples_from = 0    # samples[i] holds year samples_from + i
        if data.done is not None:
            self._resume(data.done)

    def _resume(self, p: UnitPosterior) -> None:
        k = len(p.years)
        for key in self.stats:
            self.stats[key][:k] = p.var if key == "var" else getattr(p, key)
        # The stored draws may be thinned further (keep_draws): later years are thinned alike.
        # Draws left in the file (p.samples_from) stay there.
        self.samples_from = p.samples_from
        self.samples = np.empty((len(self.data.years) - p.samples_from,) + p.samples.shape[1:])
        self.samples[:k - p.samples_from] = p.samples
        self.acc[:k] = p.acceptance
        self.ratio[:k] = p.surrogate_var_ratio
        self.chain_end[:k] = p.chain_end
        self.fits = [{key: p.fit[key][i] for key in p.fit} for i in range(k)]
        self.k = k
        self.prev, self.prev_var = p.mean[k - 1], p.var[k - 1]
        self.prev_end = p.chain_end[k - 1]

    @property
    def done(self) -> bool:
        return self.k >= len(self.data.years)

    def result(self) -> UnitPosterior:
        fit = {key: np.array([f[key] for f in self.fits]) for key in FIT_FIELDS}
        if self.fits and "channel_rms" in self.fits[0]:
            fit["channel_rms"] = np.array([f["channel_rms"] for f in self.fits])
        noise = self.data.noise
        noise = noise[:, 0] if noise.ndim == 2 else noise
        st = dict(self.stats)
        var = st.pop("var")
        return UnitPosterior(years=np.asarray(self.data.years, np.int64), samples=self.samples,
                             acceptance=self.acc, noise_std=noise, noise_source=self.data.source,
                             surrogate_var_ratio=self.ratio, fit=fit, var=var,
                             chain_end=self.chain_end, samples_from=self.samples_from, **st)


def _total_var(surrogate, noise_k: np.ndarray, s_var: np.ndarray) -> tuple[np.ndarray, float]:
    """Likelihood variance per step and the surrogate/noise variance ratio (as
    :class:`~twinmon.calibrate.methods.sequential.SequentialRun` computes them)."""
    noise_k = np.asarray(noise_k, float)
    if noise_k.ndim == 1 and noise_k.size > 1 or hasattr(surrogate, "noise_var"):
        var = surrogate.noise_var(np.atleast_1d(noise_k))
        return var + s_var, float(np.mean(s_var / var))
    return float(noise_k) ** 2 + s_var, float(np.mean(s_var) / float(noise_k) ** 2)


# ---------------------------------------------------------------------------------------
# Sampling one year of many units
# ---------------------------------------------------------------------------------------
def _sample_year(surrogate, predict, cfg: Config, states: list[_UnitState], n_keep: int
                 ) -> None:
    """Sample the next year of every unit in ``states`` together, and store the results."""
    cc = cfg.calibrate
    C, d = cc.chains, len(cfg.model.input_names)
    bounds = np.asarray(cfg.model.bounds, float)
    lo, hi = bounds[:, 0], bounds[:, 1]
    U = len(states)
    priors, totals, ratios, ys = [], [], [], []
    for st in states:
        k = st.k
        prior = year_prior(cfg, st.prev, st.prev_var)
        s_var = surrogate.predict_with_var(prior.location[None, :])[1][0]
        total, ratio = _total_var(surrogate, st.data.noise[k], s_var)
        total = np.broadcast_to(total, s_var.shape)
        priors.append(prior), totals.append(total), ratios.append(ratio)
        ys.append(np.asarray(st.data.flows[k], float))
    Y = np.array(ys)
    miss = np.isnan(Y)
    W = np.where(miss, 0.0, 1.0 / np.array(totals))
    uniform = np.array([p.is_uniform for p in priors])
    centre = np.array([p.location for p in priors])
    inv_std = np.array([np.zeros(d) if p.is_uniform else 1.0 / p.std for p in priors])
    batch = Batch(np.where(miss, 0.0, Y), W, centre, inv_std, lo, hi)
    x_map, cov = batch_map(predict, batch, uniform)

    # Starting points, proposal and the year's generator, per unit.
    rngs, starts, warm = [], np.empty((U, C, d)), np.zeros(U, bool)
    for u, st in enumerate(states):
        rng = np.random.default_rng(st.data.seed + 97 * st.k)
        rngs.append(rng)
        if st.prev_end is not None and not uniform[u]:
            s = st.prev_end + (x_map[u] - st.prev)
            inside = np.all((s >= lo) & (s <= hi), axis=1)
            starts[u] = np.where(inside[:, None], s, x_map[u])
            warm[u] = True
        else:
            starts[u] = initial_states(rng, x_map[u], cov[u], priors[u], C)
    chol = np.linalg.cholesky(2.38 ** 2 / d * cov)                       # [U, d, d]
    burn = np.where(warm, round(WARM_BURN_FRACTION * cc.burn_in), cc.burn_in)
    look = first_look(cfg)
    cap = np.array([longest_run(cfg, bool(f)) for f in uniform])

    # Chains laid out unit-major: row u * C + c. Each unit runs segments: burn-in periods
    # of ADAPT_PERIOD steps (the proposal scale adapts after each), then `look` steps, then
    # further steps until converged. A segment's random numbers are drawn from the unit's
    # generator when it starts, so how the batch interleaves units changes nothing.
    unit_of = np.repeat(np.arange(U), C)
    x = starts.reshape(U * C, d).copy()
    lp = batch.logpost(predict, x, unit_of)
    # Delayed acceptance: a proposal is first screened by the Laplace approximation of the
    # posterior (a Gaussian at the MAP: no surrogate call), and only a proposal it accepts
    # is evaluated through the surrogate and accepted with the ratio of the exact to the
    # approximate Metropolis ratios (Christen & Fox 2005). The chain still targets the exact
    # posterior; the surrogate runs for a third to a half of the proposals instead of all.
    prec = np.linalg.inv(cov)                                             # [U, d, d]
    lq = laplace_logpdf(x, x_map[unit_of], prec[unit_of], lo, hi)
    scale = np.ones(U * C)
    burn_left = burn.copy()
    draws = [[] for _ in range(U)]          # per unit: [C, steps, d] pieces
    accepted = np.zeros(U * C)
    seg_acc = np.zeros(U * C)
    kept = np.zeros(U, int)
    looks = np.zeros(U, int)
    result: list = [None] * U
    zbuf, lubuf = [None] * U, [None] * U
    todo, pos = np.zeros(U, int), np.zeros(U, int)

    def start_segment(u: int, n: int) -> None:
        todo[u], pos[u] = n, 0
        zbuf[u] = rngs[u].standard_normal((n, C, d))
        lubuf[u] = np.log(rngs[u].random((n, 2, C)))     # stage 1 and stage 2

    for u in range(U):
        first = min(ADAPT_PERIOD, burn_left[u]) if burn_left[u] > 0 else look
        start_segment(u, first)
    active = np.ones(U, bool)
    while active.any():
        act = np.flatnonzero(active)
        n = int(todo[act].min())
        rows = (act[:, None] * C + np.arange(C)).ravel()
        idx = unit_of[rows]
        z = np.concatenate([zbuf[u][pos[u]:pos[u] + n] for u in act], axis=1)
        lu = np.concatenate([lubuf[u][pos[u]:pos[u] + n] for u in act], axis=2)
        L = chol[idx] * scale[rows, None, None]
        xr, lpr, lqr = x[rows], lp[rows], lq[rows]
        mr, pr = x_map[idx], prec[idx]
        xs = np.empty((n, rows.size, d))
        acc_n = np.zeros(rows.size)
        for s in range(n):
            prop = xr + np.einsum("rij,rj->ri", L, z[s])
            lq_prop = laplace_logpdf(prop, mr, pr, lo, hi)
            screen = np.flatnonzero(lu[s, 0] < lq_prop - lqr) if DELAYED else \
                np.arange(rows.size)
            acc = np.zeros(rows.size, bool)
            lp_prop = np.full(rows.size, -np.inf)
            if screen.size:
                lp_prop[screen] = batch.logpost(predict, prop[screen], idx[screen])
                acc[screen] = lu[s, 1, screen] < (lp_prop[screen] - lpr[screen]) - \
                    ((lq_prop[screen] - lqr[screen]) if DELAYED else 0.0)
            xr = np.where(acc[:, None], prop, xr)
            lpr = np.where(acc, lp_prop, lpr)
            lqr = np.where(acc, lq_prop, lqr)
            xs[s] = xr
            acc_n += acc
        x[rows], lp[rows], lq[rows] = xr, lpr, lqr
        seg_acc[rows] += acc_n
        todo[act] -= n
        pos[act] += n
        for i, u in enumerate(act):
            r = slice(u * C, (u + 1) * C)
            if burn_left[u] > 0:
                if todo[u] > 0:
                    continue
                # End of a burn-in period: adapt each chain's scale on its acceptance rate.
                period = min(ADAPT_PERIOD, burn_left[u])
                rate = seg_acc[r] / period
                scale[r] *= np.where(rate < ADAPT_RANGE[0], ADAPT_DOWN,
                                     np.where(rate > ADAPT_RANGE[1], ADAPT_UP, 1.0))
                seg_acc[r] = 0
                burn_left[u] -= period
                start_segment(u, min(ADAPT_PERIOD, burn_left[u]) if burn_left[u] > 0
                              else look)
                continue
            draws[u].append(xs[:, i * C:(i + 1) * C].transpose(1, 0, 2))
            accepted[r] += seg_acc[r]
            seg_acc[r] = 0
            kept[u] += n
            if todo[u] > 0:
                continue
            chains = np.concatenate(draws[u], axis=1)
            draws[u] = [chains]
            conv, rhat, n_eff = converged(chains, cfg)
            if conv or kept[u] >= cap[u]:
                if not conv and np.isnan(rhat).all():
                    # Stopped short of the ESS mark, where converged() skips the R-hat: the
                    # year's record and its unconverged reason need it all the same.
                    rhat, n_eff = diagnostics(chains)
                result[u] = (chains, conv, rhat, n_eff)
                active[u] = False
                zbuf[u] = lubuf[u] = None
            else:
                looks[u] += 1
                start_segment(u, more_steps(cfg, kept[u], rhat, n_eff, cap[u]))

    for u, st in enumerate(states):
        chains, conv, rhat, n_eff = result[u]
        k = st.k
        N = chains.shape[1]
        pooled = chains.reshape(-1, d)
        stt = st.stats
        stt["mean"][k] = pooled.mean(axis=0)
        stt["median"][k] = np.median(pooled, axis=0)
        stt["q05"][k], stt["q95"][k] = np.quantile(pooled, [0.05, 0.95], axis=0)
        stt["var"][k] = pooled.var(axis=0)
        stt["rhat"][k], stt["ess"][k] = rhat, n_eff
        stored = chains[:, (np.arange(n_keep) * N) // n_keep].reshape(-1, d)
        width = st.samples.shape[1]
        st.samples[k - st.samples_from] = stored if len(stored) == width else \
            stored[thin_indices(len(stored), width)]
        st.acc[k] = accepted[u * C:(u + 1) * C] / N
        st.ratio[k] = ratios[u]
        st.chain_end[k] = chains[:, -1]
        fit = year_fit(surrogate, cfg, st.data.flows[k], totals[u], pooled, priors[u].bounds)
        fit.update(extensions=int(looks[u]), converged=conv)
        if fit["status"] == STATUS_OK and not conv:
            fit["status"] = STATUS_UNCONVERGED
        st.fits.append(fit)
        st.prev, st.prev_var, st.prev_end = stt["mean"][k], stt["var"][k], st.chain_end[k]
        st.k += 1


def calibrate_units(surrogate, cfg: Config, units: list[UnitData],
                    progress: Optional[Callable[[int], None]] = None,
                    predict: Optional[Callable] = None) -> dict[str, UnitPosterior]:
    """Calibrate several units together, year by year, in this process.

    Each round samples the next pending year of every unit still calibrating (units with
    fewer years, or resumed further, drop out or join at their own year index).

    Parameters
    ----------
    surrogate : Surrogate (or a stacked view)
    cfg : Config
    units : list of UnitData
    progress : callable(n), optional
        Called with the number of unit-years just finished.
    predict : callable, optional
        Batch predictor (default :func:`make_predictor`'s).

    Returns
    -------
    dict name -> UnitPosterior
        With ``var`` (posterior variance of all draws) and ``chain_end`` (each chain's last
        state) per year, what ``--update`` continues from.
    """
    if predict is None:
        predict = make_predictor(surrogate)[0]
    n_keep = min(cfg.calibrate.samples, first_look(cfg))
    states = [_UnitState(u, cfg, n_keep) for u in units]
    while True:
        active = [s for s in states if not s.done]
        if not active:
            break
        _sample_year(surrogate, predict, cfg, active, n_keep)
        if progress:
            progress(len(active))
    return {s.data.name: s.result() for s in states}


# ---------------------------------------------------------------------------------------
# The stage's entry (called by calibrate())
# ---------------------------------------------------------------------------------------


def _work(cfg: Config, units: list[UnitData]) -> dict[str, UnitPosterior]:
    """One group of units through all their years, in a worker process."""
    from ..shared import worker
    return calibrate_units(worker["surrogate"], cfg, units, predict=worker_predict())


class VectorisedSampler(Sampler):
    """The sequential method's numpy sampler (``calibrate.sampler: vectorised``, the
    default): every pending unit of the work is calibrated through its remaining years by
    :func:`calibrate_units`, its run replaced by its result (a
    :class:`~twinmon.calibrate.update.Kept`).

    The units are split into groups (:func:`~twinmon.calibrate.shared.unit_groups`), each run
    by one worker of calibrate's pool through all its years (``calibrate.workers``: 0 = one
    per core, 1 = in this process). Results do not depend on the split.
    """

    name = "vectorised"

    def finish(self, work: Work) -> None:
        import os

        from ..update import Kept
        cfg, runs, resume = work.cfg, work.runs, work.resume
        total = work.total
        done = [sum(len(p.years) for p in resume.values())]
        results = {u: r.result() for u, r in runs.items() if r.done}
        pending = [UnitData(u, r.years, r.flows, r.noise, r.seed, r.source, resume.get(u))
                   for u, r in runs.items() if not r.done]

        def tick(n: int) -> None:
            done[0] += n
            if work.progress:
                work.progress(done[0], total)

        workers = min(cfg.calibrate.workers or len(os.sched_getaffinity(0)), len(pending))
        dask_cluster = cfg.calibrate.executor == "dask" and cfg.dask.address
        if pending and workers <= 1 and not dask_cluster:
            results.update(calibrate_units(work.model, cfg, pending, tick,
                                           predict=make_predictor(work.model)[0]))
        elif pending:
            from concurrent.futures import FIRST_COMPLETED, wait
            # Imported once here, not in every forked worker (scipy.stats is not needed: the
            # goodness-of-fit p-values come from scipy.special, see diagnose.stats).
            import scipy.special  # noqa: F401

            from ...executors import InterruptGuard, open_pool
            pool = open_pool(cfg, "calibrate", max(workers, 1), *work.pool_args)
            with sampling_pool(pool, work.output), InterruptGuard() as guard:
                futures = {pool.submit(_work, cfg, g): g for g in unit_groups(pending, workers)}
                waiting = set(futures)
                while waiting:
                    # Poll, so that a Ctrl-C stops the work within a fraction of a second.
                    finished, waiting = wait(waiting, timeout=0.2, return_when=FIRST_COMPLETED)
                    guard.check()
                    for f in finished:
                        results.update(f.result())
                        tick(sum(len(u.years) - (len(u.done.years) if u.done else 0)
                                 for u in futures[f]))
        for name in runs:
            runs[name] = Kept(results[name])
