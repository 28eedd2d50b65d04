"""The joint model drawn without a Markov chain: each year's likelihood summarised by a
Gaussian, the trend's posterior in closed form on those summaries, and the draws weighted
back to the exact likelihood.

The model is the joint method's (:mod:`.joint`: a straight line per input and segment,
year-to-year scatter ``sigma`` with a half-Cauchy prior, weak Gaussian priors on the slopes,
flat levels, the design box holding the years, segments restarted at recorded events and at
repairs found in the years). Only the way its posterior is drawn differs
(:class:`~twinmon.calibrate.gaussian_trend.GaussianTrend`):

1. **Sites.** Each year's likelihood is approximated by a Gaussian ``N(x_k; theta_k, C_k)``
   at its maximum-likelihood point with the Gauss-Newton covariance (the Laplace
   approximation; the surrogate variance held there, as the joint method holds it), for
   every unit-year of a batch at once (:func:`summarise`).
2. **Closed form.** On those sites ``x_k ~ N(M_k beta, C_k + diag(sigma^2))``: the trend
   coefficients integrate out (generalised least squares), sigma's posterior is evaluated on
   quasi-random points under its prior, and each draw takes a sigma point by its weight,
   ``beta`` from its Gaussian conditional and the years from theirs.
3. **Expectation propagation.** Where the trend puts a year, its likelihood may not be the
   Laplace Gaussian (two inputs trading off along a curved ridge, a box edge): each site is
   moved, damped, towards the moments of the exact likelihood times the rest of the model
   (``EP_SWEEPS`` sweeps of ``EP_POINTS`` surrogate evaluations per year).
4. **Importance weights.** ``IMPORTANCE_DRAWS_PER_KEPT x calibrate.keep_draws`` draws of
   the Gaussian model are weighted by each year's exact likelihood over its site (0 outside
   the box) and resampled: the result is the joint posterior up to Monte Carlo error, not an
   approximation of it. Fewer than ``calibrate.ess_warn`` effective draws: twice as many,
   at most ``calibrate.max_extensions`` times; still fewer, the sites of the years whose
   own weights are the unevenest are widened (a proposal that reaches a likelihood the
   site sits at one end of; the weights stay exact); still fewer (every year's weights fair,
   their product over the years not), the weighted draws are moved by a Markov chain on the
   exact posterior until their copies have parted (resample-move,
   :mod:`~twinmon.calibrate.rejuvenate`); still fewer, the unit's years are "unconverged",
   as an unconverged chain's.

The draws are independent, so there is no burn-in or acceptance rate (NaN); ``ess`` is the
weights' effective number (Kish; for moved draws, the design effect of their copies), and
split R-hat is computed on the draws cut into ``calibrate.chains`` groups. Moved draws
record their trend moves' acceptance (``trend/acceptance``). On the joint method's test
unit the slopes agree with its Gibbs sampler's within half a posterior sd
(tests/unit/test_calibrate_laplace.py);
``benchmarks/prognosis.py --methods joint,laplace`` compares them on fleets.

The cost is a few thousand surrogate evaluations per unit-year (the EP points and the weighted
draws, in batches), against the Gibbs sampler's tens of thousands per chain.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ...config import Config
from ...errors import CalibrationError
from ..base import Method, Sampler, Work
from ..diagnostics import split_rhat_many
from ..fit import years_fit
from ..posterior import UnitPosterior, draw_statistics
from ..rejuvenate import rejuvenate
from ..samplers.batch_map import Batch, batch_map
from ..shared import sampling_pool, unit_groups, yearly_noise
from ..shapes import ShapeMixture, build_shapes, shape_probabilities
from ..trend import Layout, design_matrix, segment_starts, sigma_prior_scale, with_found_repairs

#: Draws of the Gaussian model weighted to the exact posterior, per kept draw
#: (``calibrate.keep_draws``).
IMPORTANCE_DRAWS_PER_KEPT = 2
#: Most units a worker's task holds. A task's results (every unit's draws, ~0.85 MB a unit)
#: sit in the main process until they are written, so this bounds calibrate's memory
#: whatever the fleet's size; 128 keeps the batched summaries' numpy calls large.
UNITS_PER_TASK = 128

# ---------------------------------------------------------------------------------------
# The years' summaries
# ---------------------------------------------------------------------------------------
@dataclass
class LaplaceTask:
    """One unit's data for :func:`summarise` (picklable, for a worker).

    Attributes
    ----------
    y : ndarray, shape [K, n_out]
        Observations (output units), NaN = missing.
    noise_var : ndarray, shape [K, n_out]
        Noise variance per sample (output units squared).
    """

    y: np.ndarray
    noise_var: np.ndarray


def summarise(surrogate, predict, tasks: list[LaplaceTask], bounds: np.ndarray
              ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Each year's maximum-likelihood point and Laplace covariance, for many units at once.

    As the joint method does year by year: a fit under the noise alone gives the point where
    the surrogate variance is held; the likelihood's variance is then noise + surrogate
    variance, and the fit is made again under it (from the first point).

    Parameters
    ----------
    surrogate : Surrogate or StackedSurrogate
        For the surrogate variance.
    predict : callable, X [m, d] -> [m, n_out]
        The batched predictor (:func:`~twinmon.calibrate.samplers.gpbatch.make_predictor`).
    tasks : list of LaplaceTask
    bounds : ndarray, shape [d, 2]

    Returns
    -------
    list of (x [K, d], cov [K, d, d], total_var [K, n_out], ratio [K]), one per task
        ``ratio`` is the mean surrogate-to-noise variance ratio of each year.
    """
    y = np.concatenate([t.y for t in tasks])
    nv = np.concatenate([t.noise_var for t in tasks])
    miss = ~np.isfinite(y)
    rows, d = len(y), len(bounds)
    centre = np.repeat(bounds.mean(axis=1)[None, :], rows, axis=0)
    uniform = np.ones(rows, bool)
    lo, hi = bounds[:, 0], bounds[:, 1]
    yz = np.where(miss, 0.0, y)
    x0, _ = batch_map(predict, Batch(yz, np.where(miss, 0.0, 1.0 / nv), centre,
                                     np.zeros((rows, d)), lo, hi), uniform)
    s_var = surrogate.predict_with_var(x0)[1]
    total = nv + s_var
    x, cov = batch_map(predict, Batch(yz, np.where(miss, 0.0, 1.0 / total), centre,
                                      np.zeros((rows, d)), lo, hi), uniform, start=x0)
    ratio = np.mean(s_var / nv, axis=1)
    out, i = [], 0
    for t in tasks:
        k = len(t.y)
        out.append((x[i:i + k], cov[i:i + k], total[i:i + k], ratio[i:i + k]))
        i += k
    return out


# ---------------------------------------------------------------------------------------
# One unit
# ---------------------------------------------------------------------------------------
def line_model(cfg: Config, years: np.ndarray, starts: list) -> tuple:
    """The straight line's design and coefficient priors on a unit's years (the joint
    method's: one line per input and segment, levels flat, slopes ``N(normal_rate,
    range^2)`` per year), the base every shape of :mod:`~twinmon.calibrate.shapes` extends.

    Parameters
    ----------
    years : ndarray of int, shape [K]
    starts : list of ndarray of int, one per input
        First year of each segment (:func:`~twinmon.calibrate.trend.segment_starts`), each
        at or before ``years[-1]``.

    Returns
    -------
    lay : Layout
    Mk : ndarray, shape [K, d, n_line]
        ``theta_k = Mk[k] @ beta``.
    prior_prec, prior_mean : ndarray, shape [n_line]
    slopes : ndarray of bool, shape [n_line]
        Which coefficients are slopes.
    centres : list of ndarray
        Each input's segments' mean recorded year (:func:`~twinmon.calibrate.trend.design_matrix`).
    """
    names = cfg.model.input_names
    designs = [design_matrix(years, s) for s in starts]
    X = [dm for dm, _ in designs]
    K, d = len(years), len(names)
    lay = Layout(K, d, [dm.shape[1] for dm in X])
    Mk = lay.mean_map(X).reshape(K, d, -1)
    span = np.diff(cfg.model.bounds, axis=1).ravel()
    prec, mean = [], []
    for i, dm in enumerate(X):
        n_seg = dm.shape[1] // 2
        # Levels flat; slopes N(normal_rate, range^2) per year, as the joint method's.
        prec += [0.0, span[i] ** -2.0] * n_seg
        mean += [0.0, cfg.model.inputs[names[i]].normal_rate] * n_seg
    slopes = np.tile([False, True], len(prec) // 2)
    return lay, Mk, np.array(prec), np.array(mean), slopes, [c for _, c in designs]


class LaplaceRun:
    """One unit's calibration with this method, with
    :class:`~twinmon.calibrate.base.UnitRun`'s interface: :meth:`plan` gives one
    :class:`LaplaceTask` (the years to summarise), :meth:`finish` takes the unit's result
    (:func:`_group`). It holds no surrogate, so that it travels to a worker as it is.

    ``calibrate --update`` (:meth:`resume`): a year's site depends on that year's data
    alone, so the stored years' sites are kept and only the new years are summarised; the
    unit is then drawn again from all its sites, as a full run draws it (same seed: the
    same arrays, bit for bit)."""

    def __init__(self, surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                 noise_source: str, events: Sequence = ()):
        self.cfg, self.seed, self.source = cfg, rng_seed, noise_source
        self.years = np.asarray(years, dtype=np.int64)
        self.flows = np.atleast_2d(np.asarray(flows, float))
        n_y = len(self.years)
        self.noise = yearly_noise(surrogate, noise_std, n_y)
        # Noise variance per year and sample (a stacked surrogate: per channel's samples).
        self.noise_var = np.array([
            surrogate.noise_var(self.noise[k]) if self.noise.ndim == 2
            else np.full(self.flows.shape[1], float(self.noise[k]) ** 2) for k in range(n_y)])
        self.events = list(events)
        self.found_repairs: list = []
        self.k = 0
        self._result: Optional[UnitPosterior] = None
        #: The stored years' sites (x, cov, var, ratio), kept by :meth:`resume`.
        self._kept: Optional[tuple] = None

    @property
    def done(self) -> bool:
        return self._result is not None

    def resume(self, p: UnitPosterior) -> None:
        """Keep the sites of ``p``'s years (the first of this unit's years, their data
        unchanged: :func:`~twinmon.calibrate.update.plan_update` checked it); only the
        years after them are summarised."""
        n = len(p.years)
        if not p.site or n > len(self.years) or \
                not np.array_equal(np.asarray(p.years), self.years[:n]):
            raise CalibrationError(f"cannot continue a posterior of years {list(p.years)} "
                                   "without their sites")
        self._kept = tuple(np.asarray(p.site[k]) for k in ("x", "cov", "var", "ratio"))

    def plan(self) -> list[LaplaceTask]:
        """The years to summarise: all of them, or those after the kept ones."""
        n = 0 if self._kept is None else len(self._kept[0])
        return [LaplaceTask(self.flows[n:], self.noise_var[n:])]

    def sites(self, new: tuple) -> tuple:
        """Every year's site (x [K, d], cov [K, d, d], var [K, n_out], ratio [K]): the kept
        years' then ``new``'s (:func:`summarise` of :meth:`plan`'s task)."""
        if self._kept is None:
            return new
        return tuple(np.concatenate([a, b]) for a, b in zip(self._kept, new))

    def finish(self, results: list) -> None:
        """Take the unit's posterior and the repairs it found (:func:`_group`)."""
        self._result, self.found_repairs = results[0]
        self.k = len(self.years)

    def _trend_model(self, x: np.ndarray, cov: np.ndarray, rng: np.random.Generator):
        """Segments (recorded events, then repairs found in the years), the layout and the
        Gaussian model of the trend: the mixture of ``calibrate.shapes`` on each input's
        current segment (:mod:`~twinmon.calibrate.shapes`)."""
        cfg = self.cfg
        starts, self.found_repairs = with_found_repairs(
            cfg, self.years, self.events, segment_starts(cfg, self.years, self.events), x, cov)
        lay, Mk, prec, mean, slopes, centres = line_model(cfg, self.years, starts)
        shapes = build_shapes(self.years, x, cov, Mk, prec, mean, sigma_prior_scale(cfg),
                              slopes, np.array([s[-1] for s in starts]), cfg.calibrate.shapes,
                              rng)
        return starts, centres, lay, ShapeMixture(shapes)

    def posterior(self, surrogate, predict, x, cov, total, ratio) -> UnitPosterior:
        """The unit's posterior from its years' summaries (:func:`summarise`): the Gaussian
        model, its sites refined, then weighted to the exact likelihood (module
        docstring); ``predict`` is the batched surrogate, ``surrogate`` checks the fit."""
        cfg, cc = self.cfg, self.cfg.calibrate
        bounds = cfg.model.bounds
        rng = np.random.default_rng(self.seed)
        starts, centres, lay, model = self._trend_model(x, cov, rng)
        K, d = x.shape
        ok = np.isfinite(self.flows)
        yz, wz = np.where(ok, self.flows, 0.0), np.where(ok, 1.0 / total, 0.0)

        def loglik(theta: np.ndarray) -> np.ndarray:
            m = theta.shape[0]
            r = yz - predict(theta.reshape(-1, d)).reshape(m, K, -1)
            return -0.5 * np.einsum("mkt,mkt,kt->mk", r, r, wz)

        model.refine(loglik, rng, bounds)
        n_c = cc.chains
        n_s = -(-IMPORTANCE_DRAWS_PER_KEPT * cc.keep_draws // n_c)
        ext = 0
        while True:
            coef, sigma, theta, n_eff = model.importance(loglik, n_c * n_s, rng, bounds)
            if n_eff >= cc.ess_warn or ext >= cc.max_extensions:
                break
            # Too few effective draws: one more sweep of the sites and twice as many draws,
            # as a chain is lengthened.
            ext += 1
            n_s *= 2
            model.refine(loglik, rng, bounds, sweeps=1)
        if n_eff < cc.ess_warn:
            # Still too few: the year whose site the draws miss is widened (exact weights
            # still), which a longer run cannot do.
            coef, sigma, theta, n_eff = model.importance_widened(
                loglik, n_c * n_s, rng, bounds, (coef, sigma, theta, n_eff), cc.ess_warn)
        moved = None
        if 0 < n_eff < cc.ess_warn:
            # Still too few, every year's weights fine but not their product (inputs the
            # channels hardly tell apart, over many years): the weighted draws moved by a
            # Markov chain on the exact posterior until they forget their copies.
            per_chain = -(-cc.keep_draws // n_c)
            try:
                moved = rejuvenate(model, loglik, (coef, sigma, theta, n_eff),
                                   n_c * per_chain, rng, bounds, cc.ess_warn)
            except np.linalg.LinAlgError:
                # A trend whose precision is not positive definite at some chain's state
                # (sigma collapsed): the weighted draws stand, unconverged.
                moved = None
            if moved is not None and moved.ess > n_eff:
                coef, sigma, theta, n_eff = moved.coef, moved.sigma, moved.theta, moved.ess
                n_s = per_chain
            else:
                moved = None
        converged = n_eff >= cc.ess_warn
        pooled = np.ascontiguousarray(theta.transpose(1, 0, 2))              # [K, n, d]
        chains = pooled.reshape(K, n_c, n_s, d)
        rhat = split_rhat_many(np.moveaxis(chains, 3, 1))                     # [K, d]
        # Resampled draws repeat: their number overstates them, the weights' does not.
        n_eff_years = np.full((K, d), n_eff)
        fit = years_fit(surrogate, cfg, self.flows, total, pooled, ext, converged)
        noise = self.noise[:, 0] if self.noise.ndim == 2 else self.noise
        stats = draw_statistics(pooled, rhat, n_eff_years)
        return UnitPosterior(
            years=self.years, samples=pooled, acceptance=np.full((K, n_c), np.nan),
            noise_std=noise, noise_source=self.source, surrogate_var_ratio=ratio,
            fit=fit, trend=self._trend(starts, model, coef, sigma, n_c, n_s, n_eff, moved),
            var=pooled.var(axis=1), chain_end=chains[:, :, -1].copy(), **stats)

    def _trend(self, starts, model: ShapeMixture, coef: np.ndarray, sigma: np.ndarray,
               n_c: int, n_s: int, n_eff: float, moved=None) -> dict:
        """:data:`~twinmon.calibrate.trend.TREND_FIELDS` from the draws. Each segment's
        ``intercept`` and ``slope`` are the chord of the draw's trend over the segment's
        recorded years (its value at the first, its mean rate to the last; the line itself
        for a straight line); ``now`` is the trend at the last year, which the forecast
        extends. ``acceptance`` is NaN for weighted draws, the trend moves' acceptance for
        draws ``moved`` by :func:`~twinmon.calibrate.rejuvenate.rejuvenate`."""
        years = self.years.astype(float)
        code, m, now = model.decode(coef)
        n, K, d = m.shape
        S = max(len(s) for s in starts)
        start = np.full((S, d), -1, dtype=np.int64)
        a, b = np.full((n, S, d), np.nan), np.full((n, S, d), np.nan)
        for i in range(d):
            bounds = list(starts[i]) + [np.inf]
            for j in range(len(starts[i])):
                start[j, i] = starts[i][j]
                seg = np.flatnonzero((years >= bounds[j]) & (years < bounds[j + 1]))
                first, last = seg[0], seg[-1]
                span = years[last] - years[first]
                b[:, j, i] = ((m[:, last, i] - m[:, first, i]) / span if span > 0
                              else now[:, 1, i])
                a[:, j, i] = m[:, first, i] - b[:, j, i] * (years[first] - starts[i][j])
        last = [len(s) - 1 for s in starts]
        rhat = split_rhat_many(np.stack([
            np.stack([v.reshape(n_c, n_s) for v in (a[:, last[i], i], b[:, last[i], i],
                                                    sigma[:, i])]) for i in range(d)], axis=1))
        shapes = model.shapes
        shape = np.array([shapes[c].code for c in code], dtype=np.int64)
        return {"start": start, "intercept": a, "slope": b, "sigma": sigma,
                "sigma_scale": np.asarray(sigma_prior_scale(self.cfg), float),
                "rhat": rhat, "ess": np.full((3, d), n_eff),
                "acceptance": np.full(n_c, moved.acceptance["trend"] if moved else np.nan),
                "now": now, "now_year": np.int64(self.years[-1]),
                "shape": shape,
                "change_year": np.array([shapes[c].change_year for c in code], dtype=np.int64),
                "change_years": np.array([shapes[c].change_years for c in code],
                                         dtype=np.int64).reshape(n, d),
                "growth": np.array([shapes[c].growth for c in code]),
                "shape_prob": shape_probabilities(shape)}

    def result(self) -> UnitPosterior:
        return self._result


# ---------------------------------------------------------------------------------------
# The sampler: summaries of a group of units at once, then each unit's draws
# ---------------------------------------------------------------------------------------
def _group(surrogate, predict, runs: list) -> list:
    """The results of ``runs`` (LaplaceRun) from one batched summary of all their years:
    (posterior, found repairs) per run, in order."""
    bounds = runs[0].cfg.model.bounds
    summaries = summarise(surrogate, predict, [r.plan()[0] for r in runs], bounds)
    out = []
    for r, new in zip(runs, summaries):
        x, cov, total, ratio = r.sites(new)
        post = r.posterior(surrogate, predict, x, cov, total, ratio)
        # Recorded, so that an update summarises only the years added since.
        post.site = {"x": x, "cov": cov, "var": total, "ratio": ratio}
        out.append((post, list(r.found_repairs)))
    return out


def _work(runs: list) -> list:
    """One group of units in a worker process (its surrogate from the pool's initializer)."""
    from ..samplers.gpbatch import worker_predict
    from ..shared import worker
    return _group(worker["surrogate"], worker_predict(), runs)


class LaplaceSampler(Sampler):
    """The laplace method's sampler. ``vectorised`` (the default): the units are split into
    groups (:func:`~twinmon.calibrate.shared.unit_groups`); each group's unit-years are
    summarised in one batch and its units drawn, in a worker (``calibrate.workers``: 0 = one
    per core, 1 = in this process), through the surrogate's numpy form
    (:mod:`~twinmon.calibrate.samplers.gpbatch`). ``openturns``: the same, in this process,
    through OpenTURNS' own prediction (the reference the numpy form is checked against).
    A unit's result depends only on its own data and seed."""

    def __init__(self, name: str = "vectorised"):
        self.name = name

    def finish(self, work: Work) -> None:
        import os

        cfg, runs = work.cfg, work.runs
        pending = [u for u, r in runs.items() if not r.done]
        if not pending:
            return
        workers = min(cfg.calibrate.workers or len(os.sched_getaffinity(0)), len(pending))
        groups = unit_groups(pending, max(workers, 1), most=UNITS_PER_TASK)

        def take(group: list, results: list) -> None:
            for u, res in zip(group, results):
                runs[u].finish([res])
                work.finished(u)          # written to the file; its draws leave memory
            work.tick()

        if self.name == "openturns":
            for g in groups:
                take(g, _group(work.model, work.model.predict, [runs[u] for u in g]))
            return
        if workers <= 1 and not (cfg.calibrate.executor == "dask" and cfg.dask.address):
            from ..samplers.gpbatch import make_predictor
            predict = make_predictor(work.model)[0]
            for g in groups:
                take(g, _group(work.model, predict, [runs[u] for u in g]))
            return
        from concurrent.futures import wait

        from ...executors import InterruptGuard, open_pool
        pool = open_pool(cfg, "calibrate", max(workers, 1), *work.pool_args)
        with sampling_pool(pool, work.output), InterruptGuard() as guard:
            futures = [pool.submit(_work, [runs[u] for u in g]) for g in groups]
            # Taken in order as they complete (the file's layout does not depend on the
            # workers' timing), each dropped once taken. Polled, so that a Ctrl-C stops the
            # work within a fraction of a second.
            for i, g in enumerate(groups):
                while wait([futures[i]], timeout=0.2).not_done:
                    guard.check()
                guard.check()
                take(g, futures[i].result())
                futures[i] = None


class LaplaceMethod(Method):
    """The joint model on each year's Laplace approximation, drawn exactly
    (``calibrate.method: laplace``)."""

    name = "laplace"
    #: ``--update`` keeps the stored years' sites (each depends on its year alone) and
    #: summarises the years added since; every updated unit is drawn again whole.
    continues_years = True
    uses_events = True

    def can_continue(self, p: UnitPosterior) -> bool:
        return bool(p.site)

    @property
    def samplers(self):
        return {"vectorised": LaplaceSampler("vectorised"),
                "openturns": LaplaceSampler("openturns")}

    def start(self, model, cfg: Config, years, flows, noise, seed: int, source: str,
              events: Sequence = ()) -> LaplaceRun:
        return LaplaceRun(model, cfg, years, flows, noise, seed, source, events)
