"""The joint method's fast path: its Gibbs sampler over every chain of many units at once, in
numpy.

The model, the blocks and their proposals are the joint method's
(:mod:`~twinmon.calibrate.methods.joint`, which samples them with OpenTURNS' ``Gibbs``, one
chain per task: the reference); what changes is how they are run:

* **All years' blocks in one step.** Given the trend (levels, slopes, ``s``) the years'
  ``eps_k`` are independent, so the K per-year random-walk blocks of a sweep are proposed
  and accepted together, each on its own Metropolis ratio (the same transition as updating
  them one after the other): one surrogate call for every year of every chain.
* **Batched surrogate.** Every block's proposals of a sweep, for all chains of all units in
  the batch, go through :class:`.gpbatch.GPBatch` (the Karhunen-Loeve + Gaussian-process
  prediction as array arithmetic, tabulated by :class:`.gpbatch.GPTable`) in one call,
  instead of one OpenTURNS call per chain and block through a Python callback. A trend
  move evaluates the K years of every chain at once.
* **Adaptation as OpenTURNS'.** During the burn-in each block's proposal scale is adapted
  every :data:`~twinmon.calibrate.shared.ADAPT_PERIOD` of its moves on its acceptance rate
  (range and factors of OpenTURNS' random walk); the ``joint_trend_moves`` trend moves of a
  sweep share one scale (OpenTURNS keeps one per block).

Determinism: each chain (row) draws its random numbers from its own generator, seeded by the
task (``JointTask.seed``), a fixed number of sweeps at a time, and every row is computed
without reference to the others (element-wise operations, per-row sums, einsum rather than
BLAS), so a chain's draws do not depend on which chains share its batch or on the number of
workers. They differ from the OpenTURNS path's draws (another generator, another order of the
year blocks); the posterior is the same (``tests/unit/test_calibrate_joint.py`` compares them).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..base import Sampler, Work
from ..shared import (ADAPT_DOWN, ADAPT_PERIOD, ADAPT_RANGE, ADAPT_UP, JointTask, sampling_pool,
                      unit_groups)
from ..trend import Layout, slope_prior
from .gpbatch import make_predictor, worker_predict

#: Sweeps whose random numbers a chain draws from its generator at once.
RNG_CHUNK = 64


def _signature(t: JointTask) -> tuple:
    """Tasks that can share a batch: same years count, segment layout and run length."""
    return (t.obs.shape, tuple(X.shape for X in t.X), t.trend_moves, t.samples, t.burn_in,
            t.thin)


def run_joint_tasks(predict: Callable[[np.ndarray], np.ndarray], tasks: list[JointTask]
                    ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Run the Gibbs chains of ``tasks`` (any units, any mix), batched where they match.

    Parameters
    ----------
    predict : callable, X [m, d] -> [m, n_out]
        The surrogate's batch prediction (:func:`.gpbatch.make_predictor`).
    tasks : list of JointTask
        One chain each (:meth:`~twinmon.calibrate.methods.joint.JointRun.plan`).

    Returns
    -------
    list, one per task, of ``(draws [samples, D], acceptance [K], trend_acceptance)``
        What :func:`~twinmon.calibrate.methods.joint.run_joint_task` returns for the task.
    """
    groups: dict[tuple, list[int]] = {}
    for i, t in enumerate(tasks):
        groups.setdefault(_signature(t), []).append(i)
    out: list = [None] * len(tasks)
    for idx in groups.values():
        for i, r in zip(idx, _run_batch(predict, [tasks[i] for i in idx])):
            out[i] = r
    return out


class _Rows:
    """The fixed per-row arrays of a batch of chains that share a layout."""

    def __init__(self, tasks: list[JointTask]):
        t0 = tasks[0]
        K, d = t0.obs.shape[0], t0.bounds.shape[0]
        self.lay = lay = Layout(K, d, [X.shape[1] for X in t0.X])
        R = len(tasks)
        self.R, self.K, self.d = R, K, d
        self.n_beta = sum(lay.n_coef)
        # Likelihood per year: observation (missing -> 0) and weight 1/variance (0 where missing).
        obs = np.array([t.obs for t in tasks], float)                      # [R, K, n_out]
        var = np.broadcast_to(np.array([np.broadcast_to(t.noise_var, t.obs.shape)
                                        for t in tasks], float), obs.shape)
        miss = np.isnan(obs)
        self.y = np.where(miss, 0.0, obs)
        self.w = np.where(miss, 0.0, 1.0 / var)
        self.M = np.array([lay.mean_map(t.X) for t in tasks])             # [R, K*d, n_beta]
        self.lo = np.asarray(t0.bounds[:, 0], float)
        self.hi = np.asarray(t0.bounds[:, 1], float)
        # The slopes' priors, per row [R, n_slopes] (the mask is the layout's).
        priors = [slope_prior(t, lay) for t in tasks]
        self.slope = priors[0][0]
        self.slope_mean = np.array([p[1] for p in priors])
        self.slope_prec = np.array([p[2] for p in priors])
        self.A2 = np.array([np.asarray(t.cauchy_scale, float) ** 2 for t in tasks])   # [R, d]
        # Proposals' Cholesky factors: per year [R, K, d, d], the trend's [R, p, p].
        self.L_eps = np.linalg.cholesky(np.array([t.eps_cov for t in tasks], float))
        self.L_trend = np.linalg.cholesky(np.array([t.trend_cov for t in tasks], float))

    def theta(self, z: np.ndarray) -> np.ndarray:
        """Years' inputs [R, K, d] from states z [R, D]."""
        lay = self.lay
        beta = z[:, lay.n_eps:lay.size - lay.d]
        m = np.einsum("rqb,rb->rq", self.M, beta).reshape(self.R, self.K, self.d)
        eps = z[:, :lay.n_eps].reshape(self.R, self.K, self.d)
        return m + z[:, None, lay.size - lay.d:] * eps

    def log_prior(self, z: np.ndarray) -> np.ndarray:
        """Trend and eps priors [R] (the joint log-density less the likelihood)."""
        lay = self.lay
        eps = z[:, :lay.n_eps]
        b = z[:, lay.n_eps:lay.size - lay.d][:, self.slope] - self.slope_mean
        s = z[:, lay.size - lay.d:]
        return -0.5 * (np.sum(eps * eps, axis=1) + np.sum(b * b * self.slope_prec, axis=1)) \
            - np.sum(np.log1p(s * s / self.A2), axis=1)

    def logliks(self, predict, theta: np.ndarray, rows: np.ndarray, years: np.ndarray
                ) -> np.ndarray:
        """Year log-likelihoods [m] at points theta [m, d] of (rows, years) [m]; -inf outside
        the box (the surrogate is not called there)."""
        out = np.full(len(theta), -np.inf)
        ok = np.all((theta >= self.lo) & (theta <= self.hi), axis=1)
        if ok.any():
            r = self.y[rows[ok], years[ok]] - predict(theta[ok])
            out[ok] = -0.5 * np.sum(r * r * self.w[rows[ok], years[ok]], axis=1)
        return out


def _run_batch(predict, tasks: list[JointTask]) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Gibbs chains of tasks that share :func:`_signature`, in lockstep (see the module
    docstring)."""
    t0 = tasks[0]
    rows = _Rows(tasks)
    lay, R, K, d = rows.lay, rows.R, rows.K, rows.d
    p = len(lay.trend)
    moves = t0.trend_moves
    n_burn, n_all = t0.burn_in, t0.burn_in + t0.samples * t0.thin
    rngs = [np.random.default_rng(int(t.seed)) for t in tasks]
    # Per sweep and row: the years' and the trend moves' normals, a uniform per move.
    n_norm, n_unif = K * d + moves * p, K + moves

    z = np.array([t.start for t in tasks], float)                           # [R, D]
    theta = rows.theta(z)
    all_rows = np.repeat(np.arange(R), K)
    all_years = np.tile(np.arange(K), R)
    ll = rows.logliks(predict, theta.reshape(R * K, d), all_rows, all_years).reshape(R, K)
    lprior = rows.log_prior(z)

    eps_scale = np.ones((R, K))
    trend_scale = np.ones(R)
    eps_acc = np.zeros((R, K))            # accepted moves since the last adaptation
    trend_acc = np.zeros(R)
    draws = np.empty((R, t0.samples, lay.size))
    eps_cols = np.arange(lay.n_eps)
    trend_cols = np.array(lay.trend)

    normals = uniforms = None
    for sweep in range(n_all):
        c = sweep % RNG_CHUNK
        if c == 0:   # each row's next chunk of random numbers, from its own generator
            n = min(RNG_CHUNK, n_all - sweep)
            normals = np.stack([g.standard_normal((n, n_norm)) for g in rngs], axis=1)
            uniforms = np.log(np.stack([g.random((n, n_unif)) for g in rngs], axis=1))
        zn, lu = normals[c], uniforms[c]                                   # [R, ...]

        # The years' blocks, all at once (independent given the trend). Screening these
        # proposals on each year's Laplace approximation first (delayed acceptance, as the
        # sequential sampler does) was tried: it saved surrogate calls but lost more in
        # ESS per CPU second (seed 11 units: 150-170 against 200 without), the trend's
        # moves most (the approximation's errors add up over the years).
        eps = z[:, :lay.n_eps].reshape(R, K, d)
        step = np.einsum("rkij,rkj->rki", rows.L_eps, zn[:, :K * d].reshape(R, K, d))
        eps_new = eps + eps_scale[:, :, None] * step
        theta_new = theta + z[:, None, lay.size - d:] * (eps_new - eps)
        ll_new = rows.logliks(predict, theta_new.reshape(R * K, d), all_rows,
                              all_years).reshape(R, K)
        d_prior = -0.5 * (np.sum(eps_new * eps_new, axis=2) - np.sum(eps * eps, axis=2))
        acc = np.isfinite(ll_new)            # outside the box: rejected
        acc[acc] = lu[:, :K][acc] < (ll_new - ll + d_prior)[acc]
        eps = np.where(acc[:, :, None], eps_new, eps)
        z[:, eps_cols] = eps.reshape(R, K * d)
        theta = np.where(acc[:, :, None], theta_new, theta)
        ll = np.where(acc, ll_new, ll)
        lprior = rows.log_prior(z)
        eps_acc += acc

        # The trend's moves: levels, slopes and s together; every year changes.
        for j in range(moves):
            zt = zn[:, K * d + j * p:K * d + (j + 1) * p]
            prop = z.copy()
            prop[:, trend_cols] += trend_scale[:, None] * np.einsum("rij,rj->ri",
                                                                   rows.L_trend, zt)
            th = rows.theta(prop)
            # A year outside the box makes the state impossible: no surrogate call.
            inside = np.all((th >= rows.lo) & (th <= rows.hi), axis=(1, 2))
            a = np.zeros(R, bool)
            lp_p = rows.log_prior(prop)
            r_in = np.flatnonzero(inside)
            if r_in.size:
                ll_p = rows.logliks(predict, th[r_in].reshape(-1, d), np.repeat(r_in, K),
                                    np.tile(np.arange(K), r_in.size)).reshape(-1, K)
                ratio = ll_p.sum(axis=1) - ll[r_in].sum(axis=1) + lp_p[r_in] - lprior[r_in]
                a[r_in] = lu[r_in, K + j] < ratio
                ll[r_in[a[r_in]]] = ll_p[a[r_in]]
            z = np.where(a[:, None], prop, z)
            theta = np.where(a[:, None, None], th, theta)
            lprior = np.where(a, lp_p, lprior)
            trend_acc += a

        if sweep < n_burn:
            if (sweep + 1) % ADAPT_PERIOD == 0 or sweep + 1 == n_burn:
                period = (sweep % ADAPT_PERIOD) + 1
                eps_scale *= _adapt(eps_acc / period)
                trend_scale *= _adapt(trend_acc / (period * moves))
                eps_acc[:] = 0
                trend_acc[:] = 0
        else:
            after = sweep - n_burn
            if (after + 1) % t0.thin == 0:
                draws[:, after // t0.thin] = z
    # The counts were reset at the end of the burn-in: these are the kept sweeps' rates.
    n_after = n_all - n_burn
    eps_rate, trend_rate = eps_acc / max(n_after, 1), trend_acc / max(n_after * moves, 1)
    return [(draws[r], eps_rate[r], float(trend_rate[r])) for r in range(R)]


def _adapt(rate: np.ndarray) -> np.ndarray:
    """Factor on a proposal scale for a block's acceptance rate over the last period."""
    return np.where(rate < ADAPT_RANGE[0], ADAPT_DOWN,
                    np.where(rate > ADAPT_RANGE[1], ADAPT_UP, 1.0))


# ---------------------------------------------------------------------------------------
# The stage's entry (called by calibrate())
# ---------------------------------------------------------------------------------------
def _work(tasks: list[JointTask]) -> list:
    """One batch of chains in a worker process."""
    return run_joint_tasks(worker_predict(), tasks)


class JointVectorisedSampler(Sampler):
    """The joint method's numpy sampler (``calibrate.sampler: vectorised``, the default):
    finishes every pending :class:`~twinmon.calibrate.methods.joint.JointRun` of the work.

    Each round plans every unfinished unit's chains (first runs, or longer runs of units
    whose R-hat/ESS missed the marks), splits the units into groups (whole units, see
    :func:`~twinmon.calibrate.shared.unit_groups`), runs each group's chains in one batch in
    a worker (``calibrate.workers``: 0 = one per core, 1 = in this process) and hands each
    unit its chains. Results do not depend on the split.
    """

    name = "vectorised"

    def finish(self, work: Work) -> None:
        import os

        cfg, runs = work.cfg, work.runs
        pending = [u for u, r in runs.items() if not r.done]
        workers = min(cfg.calibrate.workers or len(os.sched_getaffinity(0)), len(pending))
        dask_cluster = cfg.calibrate.executor == "dask" and cfg.dask.address
        if not pending:
            return

        def rounds(submit):
            while True:
                active = [u for u in pending if not runs[u].done]
                if not active:
                    return
                plans = {u: runs[u].plan() for u in active}
                groups = unit_groups(active, max(workers, 1))
                for group, result in zip(groups, submit([[t for u in g for t in plans[u]]
                                                         for g in groups])):
                    i = 0
                    for u in group:
                        n = len(plans[u])
                        runs[u].finish(result[i:i + n])
                        i += n
                work.tick()

        if workers <= 1 and not dask_cluster:
            predict = make_predictor(work.model)[0]
            rounds(lambda batches: [run_joint_tasks(predict, b) for b in batches])
            return
        from concurrent.futures import wait

        from ...executors import InterruptGuard, open_pool
        pool = open_pool(cfg, "calibrate", max(workers, 1), *work.pool_args)
        with sampling_pool(pool, work.output), InterruptGuard() as guard:
            def submit(batches):
                futures = [pool.submit(_work, b) for b in batches]
                # Poll, so that a Ctrl-C stops the work within a fraction of a second.
                while wait(futures, timeout=0.2).not_done:
                    guard.check()
                guard.check()
                return [f.result() for f in futures]
            rounds(submit)
