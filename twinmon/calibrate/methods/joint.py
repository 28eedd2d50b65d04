"""Joint calibration: a unit's whole history in one posterior, its degradation trend inside.

The paper's method (:mod:`.sequential`) estimates each year from the previous one and leaves
the trend to ``forecast``'s regression of the yearly means. Here the trend is part of the
model, so that the trend's uncertainty and the years' are estimated together.

Model (one unit; years ``t_1 < ... < t_K``; inputs ``i = 1..d``):

* ``y_k | theta_k``: the year's likelihood, as in the sequential method (surrogate, Gaussian
  noise + surrogate variance held at the year's maximum-likelihood point);
* ``theta_k,i = a_i,s + b_i,s * (t_k - c_i,s) + eta_k,i``, ``eta_k,i ~ N(0, sigma_i^2)``
  independent: a straight line per input and per *segment* ``s`` (centred on its mean
  recorded year ``c``). A maintenance event on the input's component starts a new segment
  (new level and slope) at the first recorded year on or after the event;
* the design box restricts ``theta`` in the joint density (``theta`` outside it has density
  0); it is not a normalised truncation per year, so the trend's implied prior is the one
  below times the probability that the years fall in the box (1 for a trend well inside);
* priors: flat on the levels; ``N(normal_rate_i, range_i^2)`` per year on the slopes
  (``range = high - low``): so weak that two years or more of a segment rule its slope,
  while a one-year segment still has a proper posterior; ``sigma_i ~ half-Cauchy(A_i)``,
  ``A_i = calibrate.prior_width * range_i``, the year-to-year scale the sequential method
  allows. The half-Cauchy (Gelman 2006) is flat near 0 and heavy-tailed: ten years of data,
  not the prior, set ``sigma`` (an inverse-gamma prior of that scale pulls sigma up to it).

Sampling: OpenTURNS' Gibbs sampler (``ot.Gibbs``) in the *non-centred* parametrisation
``theta_k = m_k(beta) + s * eps_k``, ``eps_k ~ N(0, I)``, ``s`` a signed scale whose absolute
value is ``sigma`` (Cauchy prior on the real line; ``(s, eps)`` and ``(-s, -eps)`` give the
same ``theta``, so ``s`` crosses 0 freely). State ``[eps_1 .. eps_K | beta | s]``; blocks:

* one ``RandomWalkMetropolisHastings`` per year moving ``eps_k`` (one surrogate evaluation);
  proposal ``N(0, 2.38^2/d * (I + S H_k S)^-1)``, ``H_k`` the year's Laplace precision at its
  maximum-likelihood point, ``S = diag(s0)`` a first guess of sigma;
* one ``RandomWalkMetropolisHastings`` moving the whole trend (every input's levels, slopes
  and ``s``) at once, ``calibrate.joint_trend_moves`` blocks per sweep (each move evaluates
  the K years in one surrogate call); proposal from the Gaussian approximation of its
  conditional given ``eps`` (the years' Laplace precisions pulled back through the design);

OpenTURNS adapts every block's proposal scale during the burn-in. All blocks share one
log-density, the joint's (:class:`_JointLogDensity`): OpenTURNS' Gibbs hands the current
log-posterior from one block to the next, recomputing it only where neighbouring blocks'
log-densities differ at the first state, which is exact only when they are the same function.
That is the reference (``calibrate.sampler: openturns``); the default runs the same blocks
and proposals for the chains of many units at once in numpy
(:mod:`~twinmon.calibrate.samplers.joint_vectorised`), about 6x faster per chain.

Why not the centred Gibbs (``theta_k`` by MH, levels and slopes from their Gaussian
conditional, ``sigma^2`` inverse-gamma): with the per-year posteriors much wider than sigma
(in the shipped fleet, a per-year sd of ~0.1 against a scatter of 0.01 for one input),
``theta`` and ``sigma`` lock each other (the hierarchical "funnel"): on the shipped fleet's
unit Park, 4 chains of 1500 draws gave a bulk ESS of 18-24 and R-hat 1.16. The non-centred
form mixes well in that regime; when the years' data are precise against sigma it slows
down, which R-hat/ESS report (and longer chains follow, ``calibrate.max_extensions``).

Output: the sequential method's :class:`UnitPosterior` (per year draws, statistics,
diagnostics, fit) plus ``trend`` (:data:`~twinmon.calibrate.trend.TREND_FIELDS`).
"""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from ...config import Config
from ...errors import CalibrationError
from ..base import Method
from ..density import Prior, find_map, make_log_density
from ..diagnostics import ess, split_rhat_many
from ..fit import years_fit
from ..posterior import UnitPosterior, draw_statistics
from ..samplers.gpbatch import make_predictor
from ..samplers.joint_vectorised import JointVectorisedSampler, run_joint_tasks
from ..samplers.openturns import OpenTurnsSampler
from ..shared import JointTask, initial_states, yearly_noise
from ..trend import (Layout, design_matrix, lines_at_start, segment_starts, sigma_prior_scale,
                     slope_prior, with_found_repairs)
from ..trend import theta as trend_theta

#: Random-walk MH on a Gaussian target in dimension p: 2.38^2/p times its covariance.
_RW_SCALE = 2.38 ** 2


# ---------------------------------------------------------------------------------------
# One chain
# ---------------------------------------------------------------------------------------
class _JointLogDensity:
    """The joint log-posterior as a function of the whole Gibbs state::

        sum_k loglik_k(theta_k) - 1/2 |eps|^2 - sum_i log(1 + s_i^2 / A_i^2)
            - 1/2 sum_i,seg (slope - normal_rate_i)^2 / range_i^2

    (``-inf`` when some ``theta_k`` leaves the box). The sampler calls it ~10^5 times per
    chain, so its overhead counts: the years whose ``theta_k`` equals the previous call's
    are not re-evaluated, a few recent values per year are cached (a rejected move comes
    back to the current state), and the years still to evaluate go through the surrogate in
    one call.
    """

    def __init__(self, surrogate, task: JointTask, lay: Layout):
        self.lay, self.surrogate = lay, surrogate
        lds = [make_log_density(surrogate, task.obs[k], task.noise_var[k],
                                Prior.uniform(task.bounds)) for k in range(lay.K)]
        # The years' likelihoods side by side, [K, n_t]: a missing sample weighs 0.
        n_t = len(lds[0].mask)
        self.y, self.w = np.zeros((lay.K, n_t)), np.zeros((lay.K, n_t))
        for k, ld in enumerate(lds):
            self.y[k, ld.mask], self.w[k, ld.mask] = ld.y, 1.0 / ld.var
        self.M = lay.mean_map(task.X)
        self.n_eps, self.n_beta = lay.n_eps, sum(lay.n_coef)
        self.lo, self.hi = task.bounds[:, 0], task.bounds[:, 1]
        self.slope, self.slope_mean, self.slope_prec = slope_prior(task, lay)
        self.A2 = np.asarray(task.cauchy_scale, float) ** 2
        self.cache: list[dict] = [{} for _ in range(lay.K)]
        self._prev = np.full((lay.K, lay.d), np.nan)
        self._ll = np.zeros(lay.K)
        self.evaluations = 0

    def _logliks(self, ks: np.ndarray, theta: np.ndarray) -> None:
        """Set ``self._ll[k]`` for the years ``ks`` at ``theta[k]``."""
        todo = []
        for k in ks:
            v = self.cache[k].get(theta[k].tobytes())
            if v is None:
                todo.append(k)
            else:
                self._ll[k] = v
        if not todo:
            return
        pred = self.surrogate.predict(theta[todo])
        self.evaluations += len(todo)
        r = self.y[todo] - pred
        ll = -0.5 * np.einsum("kt,kt->k", r * r, self.w[todo])
        self._ll[todo] = ll
        for k, v in zip(todo, ll):
            c = self.cache[k]
            if len(c) >= 4:          # current + a few candidates is all a block needs
                c.pop(next(iter(c)))
            c[theta[k].tobytes()] = v

    def __call__(self, z) -> list[float]:
        z = np.asarray(z, float)
        n_eps, K, d = self.n_eps, self.lay.K, self.lay.d
        eps, beta, s = z[:n_eps], z[n_eps:n_eps + self.n_beta], z[n_eps + self.n_beta:]
        theta = (self.M @ beta).reshape(K, d) + s * eps.reshape(K, d)
        if (theta < self.lo).any() or (theta > self.hi).any():
            return [-np.inf]
        b = beta[self.slope] - self.slope_mean
        lp = -0.5 * (float(eps @ eps) + float(b @ (b * self.slope_prec))) \
            - float(np.log1p(s * s / self.A2).sum())
        changed = np.flatnonzero((theta != self._prev).any(axis=1))
        if changed.size:
            self._logliks(changed, theta)
            self._prev = theta
        return [lp + float(self._ll.sum())]


def _gibbs(surrogate, task: JointTask):
    """The OpenTURNS Gibbs sampler of one chain (see the module docstring)."""
    import openturns as ot
    K, d = task.obs.shape[0], task.bounds.shape[0]
    lay = Layout(K, d, [X.shape[1] for X in task.X])
    D = lay.size
    ld = _JointLogDensity(surrogate, task, lay)
    target = ot.PythonFunction(D, 1, ld)
    # The box is enforced by the log-density (theta is a function of the whole state).
    support = ot.Interval([-1.0] * D, [1.0] * D, [False] * D, [False] * D)
    start = [float(v) for v in task.start]
    blocks = []
    for k in range(K):
        prop = ot.Normal([0.0] * d, ot.CovarianceMatrix(task.eps_cov[k].tolist()))
        blocks.append(ot.RandomWalkMetropolisHastings(target, support, start, prop,
                                                      lay.eps(k)))
    p = len(lay.trend)
    trend_prop = ot.Normal([0.0] * p, ot.CovarianceMatrix(task.trend_cov.tolist()))
    # Several moves of the trend per sweep: as many blocks (OpenTURNS 1.27's random-walk
    # sampler has no thinning of its own).
    blocks += [ot.RandomWalkMetropolisHastings(target, support, start, trend_prop, lay.trend)
               for _ in range(task.trend_moves)]
    for mh in blocks:
        # OpenTURNS adapts the proposal's scale during its burn-in only.
        mh.setBurnIn(task.burn_in)
    return ot.Gibbs(blocks), lay, ld


def run_joint_task(surrogate, task: JointTask) -> tuple[np.ndarray, np.ndarray, float]:
    """One Gibbs chain of one unit, burn-in removed.

    Returns
    -------
    draws : ndarray, shape [samples, D]
        Kept states (every ``thin``-th sweep after ``burn_in`` sweeps); layout of
        :class:`Layout`.
    acceptance : ndarray, shape [K]
        Fraction of sweeps after the burn-in in which year ``k``'s ``eps`` moved (its
        block's acceptance rate: one move per sweep).
    trend_acceptance : float
        Acceptance rate of the trend's moves after the burn-in.
    """
    import openturns as ot
    ot.RandomGenerator.SetSeed(int(task.seed) % (2 ** 31))
    gibbs, lay, _ = _gibbs(surrogate, task)
    n_burn, n_all = task.burn_in, task.burn_in + task.samples * task.thin
    trend_blocks = range(lay.K, lay.K + task.trend_moves)

    def trend_rate() -> float:
        mh = gibbs.getMetropolisHastingsCollection()
        return float(np.mean([mh[j].getAcceptanceRate() for j in trend_blocks]))

    if n_burn:
        gibbs.getSample(n_burn)
    early = trend_rate() if n_burn else 0.0
    z = np.asarray(gibbs.getSample(n_all - n_burn))
    # OpenTURNS counts acceptances from the start: take the burn-in's out.
    trend_acc = (trend_rate() * n_all - early * n_burn) / (n_all - n_burn)
    # A continuous proposal never repeats a point: an unchanged block is a rejection.
    moved = np.diff(z, axis=0) != 0
    acceptance = moved[:, :lay.n_eps].reshape(-1, lay.K, lay.d).any(axis=2).mean(axis=0)
    return z[task.thin - 1::task.thin], acceptance, float(trend_acc)


# ---------------------------------------------------------------------------------------
# One unit
# ---------------------------------------------------------------------------------------
class JointRun:
    """One unit's joint calibration, with :class:`~twinmon.calibrate.base.UnitRun`'s interface.

    :meth:`plan` returns one task per chain (all of the unit's years in each);
    :meth:`finish` takes their results and either accepts them or asks for longer chains
    (poor R-hat or ESS for some year or for a slope, up to ``calibrate.max_extensions``
    times). ``k`` counts the years done (0, then all of them).
    """

    def __init__(self, surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                 noise_source: str, events: Sequence = ()):
        self.surrogate, self.cfg, self.seed, self.source = surrogate, cfg, rng_seed, noise_source
        self.years = np.asarray(years, dtype=np.int64)
        self.flows = np.atleast_2d(np.asarray(flows, float))
        n_y = len(self.years)
        self.noise = yearly_noise(surrogate, noise_std, n_y)
        self.events = list(events)
        #: Repairs no event records, found in the years' estimates (:meth:`_prepare`).
        self.found_repairs: list = []
        self._design(segment_starts(cfg, self.years, self.events))
        self.k = 0
        self.ext = 0
        self._setup: Optional[dict] = None
        self._result: Optional[UnitPosterior] = None

    def _design(self, starts: list) -> None:
        """The trend's segments (``starts`` per input), design matrices and state layout."""
        self.starts = starts
        designs = [design_matrix(self.years, s) for s in self.starts]
        self.X = [x for x, _ in designs]
        self.centres = [c for _, c in designs]
        self.lay = Layout(len(self.years), len(self.cfg.model.input_names),
                          [x.shape[1] for x in self.X])
        self.M = self.lay.mean_map(self.X)

    def _restart_at_repairs(self, x_ml: np.ndarray, cov: np.ndarray) -> None:
        """Start a segment where the years' maximum-likelihood points fall back towards
        nominal with no event recorded, each year's Laplace covariance as its error
        (:func:`~twinmon.calibrate.trend.with_found_repairs`)."""
        starts, self.found_repairs = with_found_repairs(self.cfg, self.years, self.events,
                                                        self.starts, x_ml, cov)
        if self.found_repairs:
            self._design(starts)

    @property
    def done(self) -> bool:
        return self._result is not None

    def resume(self, p: UnitPosterior) -> None:
        """``calibrate --update`` keeps earlier years as they were; a joint posterior
        changes every year when one is added, so it is sampled again whole."""
        raise CalibrationError("calibrate --update continues the sequential method only: the "
                               "joint method samples every year again when one is added; "
                               "run without --update")

    def _noise_var(self, k: int) -> np.ndarray:
        if self.noise.ndim == 2:   # per channel: each channel's noise over its own steps
            return self.surrogate.noise_var(self.noise[k])
        return np.asarray(self.noise[k] ** 2)

    def _prepare(self) -> dict:
        """Per year: likelihood variance, maximum-likelihood point and Laplace precision;
        the priors' scales; the proposals. Computed once (extensions reuse it)."""
        cfg, sur, lay = self.cfg, self.surrogate, self.lay
        bounds = cfg.model.bounds
        K, d = lay.K, lay.d
        span = np.diff(bounds, axis=1).ravel()
        uniform = Prior.uniform(bounds)
        total, x_ml, cov, ratio = [], np.empty((K, d)), np.empty((K, d, d)), np.empty(K)
        for k in range(K):
            # The surrogate variance is held at the year's maximum-likelihood point (the
            # sequential method holds it at its prior's centre): ~1e-3 of the noise.
            noise_var = self._noise_var(k)
            x0, _ = find_map(make_log_density(sur, self.flows[k], noise_var, uniform))
            s_var = sur.predict_with_var(x0[None, :])[1][0]
            total.append(noise_var + s_var)
            ratio[k] = float(np.mean(s_var / noise_var))
            x_ml[k], cov[k] = find_map(make_log_density(sur, self.flows[k], total[k], uniform))
        self._restart_at_repairs(x_ml, cov)
        lay = self.lay
        H = np.linalg.inv(cov)                                          # [K, d, d]
        A = sigma_prior_scale(cfg)
        slope_mean = np.array([s.normal_rate for s in cfg.model.inputs.values()], float)
        # A first guess of sigma: the scatter of the years' maximum-likelihood points about
        # their least-squares lines, less their own variance, at least a tenth of A.
        s0 = np.empty(d)
        for i in range(d):
            X = self.X[i]
            coef = np.linalg.lstsq(X, x_ml[:, i], rcond=None)[0]
            dof = K - np.linalg.matrix_rank(X)
            scatter = float(np.sum((x_ml[:, i] - X @ coef) ** 2)) / dof if dof > 0 else 0.0
            s0[i] = np.sqrt(max(scatter - np.mean(cov[:, i, i]), (0.1 * A[i]) ** 2))
        S = np.diag(s0)
        eps_cov = np.array([_RW_SCALE / d * np.linalg.inv(np.eye(d) + S @ H[k] @ S)
                            for k in range(K)])
        # The trend's conditional given eps, the years' likelihoods taken as Gaussian:
        # precision sum_k J_k' H_k J_k with J_k = d theta_k / d(beta, s) = [M_k, diag(eps_k)]
        # (E eps = 0, E eps^2 = 1), plus the priors' curvature.
        Mk = self.M.reshape(K, d, -1)
        n_beta = Mk.shape[2]
        P = np.zeros((n_beta + d, n_beta + d))
        for k in range(K):
            P[:n_beta, :n_beta] += Mk[k].T @ H[k] @ Mk[k]
            P[n_beta:, n_beta:] += np.diag(np.diag(H[k]))
        slope_sd = span.copy()
        for i in range(d):
            for j in self.lay.beta(i)[1::2]:
                P[j - lay.n_eps, j - lay.n_eps] += slope_sd[i] ** -2.0
        P[n_beta:, n_beta:] += np.diag(2.0 / A ** 2)
        trend_cov = _RW_SCALE / (n_beta + d) * np.linalg.inv(P)
        return dict(total=np.array(total), x_ml=x_ml, cov=cov, ratio=ratio, A=A,
                    slope_mean=slope_mean, slope_sd=slope_sd, s0=s0, eps_cov=eps_cov,
                    trend_cov=0.5 * (trend_cov + trend_cov.T))

    def _starts(self, s: dict, chains: int, seed: int) -> np.ndarray:
        """Dispersed starting states [chains, D]: each year's theta drawn around its
        maximum-likelihood point (:func:`~twinmon.calibrate.shared.initial_states`), the
        trend fitted to them by least squares, ``s`` spread over a factor e^2 around its first
        guess, and ``eps`` what makes up each theta."""
        lay = self.lay
        rng = np.random.default_rng(seed)
        prior = Prior.uniform(self.cfg.model.bounds)
        theta = np.stack([initial_states(rng, s["x_ml"][k], s["cov"][k], prior, chains)
                          for k in range(lay.K)], axis=1)              # [chains, K, d]
        out = np.empty((chains, lay.size))
        for c in range(chains):
            z = out[c]
            for i in range(lay.d):
                z[lay.beta(i)] = np.linalg.lstsq(self.X[i], theta[c, :, i], rcond=None)[0]
            sc = s["s0"] * np.exp(rng.uniform(-1.0, 1.0, lay.d))
            z[lay.s] = sc
            m = (self.M @ z[lay.n_eps:lay.size - lay.d]).reshape(lay.K, lay.d)
            z[:lay.n_eps] = ((theta[c] - m) / sc).ravel()
        return out

    def plan(self) -> list[JointTask]:
        cc = self.cfg.calibrate
        if self._setup is None:
            self._setup = self._prepare()
        s = self._setup
        # A unit sampled again runs 2^ext times longer, thinned to the same number of kept
        # draws, from fresh seeds (the sequential method's rule, for the whole unit).
        seed = self.seed + 7919 * self.ext
        starts = self._starts(s, cc.chains, seed)
        thin, burn = 2 ** self.ext, cc.burn_in * 2 ** self.ext
        return [JointTask(self.cfg.model.bounds, self.flows, s["total"], self.X,
                           s["slope_mean"], s["slope_sd"], s["A"], starts[c], s["eps_cov"],
                           s["trend_cov"], cc.joint_trend_moves, cc.samples, burn,
                           seed + 1 + c, thin)
                for c in range(cc.chains)]

    def finish(self, results: list) -> None:
        cc, lay = self.cfg.calibrate, self.lay
        z = np.array([r[0] for r in results])                  # [chains, samples, D]
        K, d = lay.K, lay.d
        n_c, n_s = z.shape[:2]
        theta = trend_theta(z, lay, self.M)                     # [chains, samples, K, d]
        rhat = split_rhat_many(np.moveaxis(theta, (2, 3), (0, 1)))              # [K, d]
        n_eff = np.array([[ess(theta[:, :, k, j], rank_normalize=True) for j in range(d)]
                          for k in range(K)])
        trend = self._trend(z, [r[2] for r in results])
        ok_year = np.all(rhat <= cc.rhat_warn, axis=1) & np.all(n_eff >= cc.ess_warn, axis=1)
        # The slope is what forecast extrapolates: it must have converged too.
        ok_slope = bool(np.all(trend["rhat"][1] <= cc.rhat_warn)
                        and np.all(trend["ess"][1] >= cc.ess_warn))
        if not (ok_year.all() and ok_slope) and self.ext < cc.max_extensions:
            self.ext += 1          # sample the unit again, longer (plan() sees ext)
            return
        s = self._setup
        pooled = theta.reshape(n_c * n_s, K, d).transpose(1, 0, 2)     # [K, draws, d]
        stats = draw_statistics(pooled, rhat, n_eff)
        fit = years_fit(self.surrogate, self.cfg, self.flows, s["total"], pooled, self.ext,
                        ok_year)
        acc = np.array([r[1] for r in results]).T                        # [K, chains]
        noise = self.noise[:, 0] if self.noise.ndim == 2 else self.noise
        self._result = UnitPosterior(
            years=self.years, samples=np.ascontiguousarray(pooled), acceptance=acc,
            noise_std=noise, noise_source=self.source, surrogate_var_ratio=s["ratio"],
            fit=fit, trend=trend, var=pooled.var(axis=1),
            chain_end=theta[:, -1].transpose(1, 0, 2).copy(), **stats)
        self.k = K

    def _trend(self, z: np.ndarray, acceptance: list) -> dict:
        """The trend's draws and diagnostics (:data:`~twinmon.calibrate.trend.TREND_FIELDS`)
        from the chains' states ``z`` [chains, samples, D]."""
        lay = self.lay
        n_c, n_s = z.shape[:2]
        d = lay.d
        S = max(len(s) for s in self.starts)
        start = np.full((S, d), -1, dtype=np.int64)
        a = np.full((n_c, n_s, S, d), np.nan)
        b = np.full((n_c, n_s, S, d), np.nan)
        for i in range(d):
            n = len(self.starts[i])
            start[:n, i] = self.starts[i]
            a[:, :, :n, i], b[:, :, :n, i] = lines_at_start(z[:, :, lay.beta(i)],
                                                            self.starts[i], self.centres[i])
        sigma = np.abs(z[:, :, lay.s])
        last = [len(st) - 1 for st in self.starts]
        ends = np.stack([np.stack([a[:, :, last[i], i], b[:, :, last[i], i], sigma[:, :, i]])
                         for i in range(d)], axis=1)  # [3, d, m, n]
        rhat = split_rhat_many(ends)
        n_eff = np.array([[ess(x, rank_normalize=True) for x in row] for row in ends])
        flat = n_c * n_s
        return {"start": start, "intercept": a.reshape(flat, S, d),
                "slope": b.reshape(flat, S, d), "sigma": sigma.reshape(flat, d),
                "sigma_scale": np.asarray(self._setup["A"], float), "rhat": rhat,
                "ess": n_eff, "acceptance": np.asarray(acceptance, float)}

    def result(self) -> UnitPosterior:
        return self._result


def calibrate_unit_joint(surrogate, cfg: Config, years, flows, noise_std, rng_seed: int,
                         noise_source: str = "file", events: Sequence = ()) -> UnitPosterior:
    """Joint posterior of one unit's inputs over all its years and of their trend
    (in-process; see the module docstring).

    Parameters
    ----------
    surrogate : Surrogate
    cfg : Config
        Uses ``model`` (box, components, normal rates) and ``calibrate`` (chains, samples,
        burn-in, prior width, trend moves, R-hat/ESS marks, extensions; ``sampler``:
        ``vectorised`` runs the chains batched in numpy
        (:mod:`~twinmon.calibrate.samplers.joint_vectorised`),
        ``openturns`` with OpenTURNS' Gibbs, one after the other).
    years : array of int, shape [n_y]
    flows : ndarray, shape [n_y, n_t]
        Measured output (its units) on the surrogate's time grid; NaN = missing.
    noise_std : float or ndarray, shape [n_y]
        Output noise standard deviation (output units).
    rng_seed : int
        Seed of this unit's draws (chain ``c`` uses ``rng_seed + 1 + c``).
    noise_source : str
        Recorded with the result.
    events : sequence of (year, component)
        Maintenance events (see :func:`~twinmon.calibrate.trend.segment_starts`).

    Returns
    -------
    UnitPosterior
        With ``trend`` (:data:`~twinmon.calibrate.trend.TREND_FIELDS`).
    """
    run = JointRun(surrogate, cfg, years, flows, noise_std, rng_seed, noise_source, events)
    if cfg.calibrate.sampler == "vectorised":
        predict = make_predictor(surrogate)[0]

        def chains(tasks):
            return run_joint_tasks(predict, tasks)
    else:
        def chains(tasks):
            return [run_joint_task(surrogate, t) for t in tasks]
    while not run.done:
        run.finish(chains(run.plan()))
    return run.result()


class JointMethod(Method):
    """Each unit's whole history in one posterior with its degradation trend
    (``calibrate.method: joint``)."""

    name = "joint"
    continues_years = False
    uses_events = True

    @property
    def samplers(self):
        return {"vectorised": JointVectorisedSampler(),
                "openturns": OpenTurnsSampler(run_joint_task)}

    def start(self, model, cfg: Config, years, flows, noise, seed: int, source: str,
              events: Sequence = ()) -> JointRun:
        return JointRun(model, cfg, years, flows, noise, seed, source, events)
