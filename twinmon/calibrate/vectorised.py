"""The fast path: random-walk Metropolis over every chain of every unit's year at once, in numpy.

The model is the paper's sequential one (:mod:`.sequential`: the same priors, likelihood,
MAP and Laplace-shaped proposal, R-hat/ESS diagnostics and goodness of fit); what changes is
how it is sampled:

* **Batched surrogate.** :class:`GPBatch` evaluates the Karhunen-Loeve + Gaussian-process
  surrogate as array arithmetic (kernel to the training points, times the stored kriging
  weights, lifted by the basis), one call per Metropolis step for all chains of all units
  of a batch, instead of one OpenTURNS call per point. It is the same prediction: it
  checks itself against the OpenTURNS metamodel when built (agreement ~1e-9 relative; the
  kriging sum cancels terms ~10^7 times larger than its value, so neither side is exact to
  the last bit) and falls back to ``surrogate.predict`` when it cannot reproduce it.
* **Batched MAP.** :func:`batch_map` runs a projected Levenberg-Marquardt on every unit's
  standardised residuals at once (the least squares :func:`.density.find_map` solves one
  unit at a time), from the same start (the 21^d grid's best point for a uniform prior, the
  prior centre otherwise); the Laplace covariance is the same Gauss-Newton one.
* **Delayed acceptance** (Christen & Fox 2005). A proposal is screened by the Laplace
  approximation (no surrogate call) and only one it accepts goes through the surrogate,
  accepted with the ratio of the exact to the approximate Metropolis ratios: the chain
  targets the exact posterior, and the surrogate sees ~40 % of the proposals (the ESS per
  step drops by ~15 %; the CPU per unit-year by ~25 %).
* **Adaptive length.** After the burn-in, a unit-year stops as soon as its rank-normalised
  split R-hat <= ``calibrate.rhat_warn`` and bulk ESS >= ``calibrate.ess_warn`` for every
  input (first look after :func:`first_look` steps, then extensions sized by the ESS, see
  :func:`_more_steps`), or at the longest run the OpenTURNS path may make (``samples *
  2^max_extensions``, twice that for a uniform prior); not converged there, it is
  "unconverged" as on the OpenTURNS path. ``fit/extensions`` counts the extensions.
* **Warm start.** A year after the first starts its chains where the previous year's chains
  ended, moved by the shift of the MAP (``end_c + MAP_k - mean_{k-1}``: the previous
  posterior's spread, centred on this year's mode), so a short burn-in (a fifth) suffices;
  a start outside the box falls back to the MAP. The first year (and any year without
  stored chain ends) starts as :func:`.sequential.plan_chains` does: MAP + 2 Laplace sd.

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

import math
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ..config import Config
from .posterior import (FIT_FIELDS, STATUS_OK, STATUS_UNCONVERGED, UnitPosterior, thin_indices,
                        year_fit)
from .sequential import _initial_states, year_prior

#: Rows per block of the batched prediction: its [rows, modes, training points] scratch
#: arrays (a few hundred kB each) stay in the processor's cache.
BLOCK_ROWS = 64
#: Warm-started years burn in for this fraction of ``calibrate.burn_in``.
WARM_BURN_FRACTION = 0.2
#: During the burn-in each chain's proposal scale is adapted every this many steps, as
#: OpenTURNS' random walk does (its defaults: period 30, range [0.117, 0.468], x1.2 / x0.8).
ADAPT_PERIOD, ADAPT_RANGE, ADAPT_UP, ADAPT_DOWN = 30, (0.117, 0.468), 1.2, 0.8
#: Screen proposals with the Laplace approximation first (delayed acceptance, see _sample_year).
DELAYED = True
#: Relative agreement with OpenTURNS' prediction required of :class:`GPBatch`.
SELF_CHECK_RTOL = 1e-6


# ---------------------------------------------------------------------------------------
# The surrogate as array arithmetic
# ---------------------------------------------------------------------------------------
def _matern52(t: np.ndarray, w: np.ndarray, w3: np.ndarray, e: np.ndarray,
              out: np.ndarray) -> np.ndarray:
    """``w (1 + t + t^2/3) exp(-t)`` in place (``w3 = w / 3``); ``e`` is scratch."""
    np.negative(t, out=e)
    np.exp(e, out=e)
    np.multiply(t, w3, out=out)
    out += w
    out *= t
    out += w
    out *= e
    return out


def _matern32(t, w, w3, e, out):
    """``w (1 + t) exp(-t)``."""
    np.negative(t, out=e)
    np.exp(e, out=e)
    np.multiply(t, w, out=out)
    out += w
    out *= e
    return out


def _sq_exp(t, w, w3, e, out):
    """``w exp(-t^2 / 2)``."""
    np.multiply(t, t, out=out)
    out *= -0.5
    np.exp(out, out=out)
    out *= w
    return out


def _abs_exp(t, w, w3, e, out):
    """``w exp(-t)``, t the L1 distance (OpenTURNS' AbsoluteExponential)."""
    np.negative(t, out=out)
    np.exp(out, out=out)
    out *= w
    return out


#: Kernel name -> (factor on the scaled distance, kernel of the scaled distance t, whether t
#: is the L1 distance).
_KERNELS = {"matern52": (math.sqrt(5.0), _matern52, False),
            "matern32": (math.sqrt(3.0), _matern32, False),
            "squared_exponential": (1.0, _sq_exp, False), "exponential": (1.0, _abs_exp, True)}


def _trend_features(U: np.ndarray, trend: str) -> np.ndarray:
    """OpenTURNS' constant / linear / quadratic basis at U [m, d] -> [m, p] (its order:
    1, x_i, then x_i x_j for j = 0..d-1, i <= j)."""
    ones = np.ones((len(U), 1))
    if trend == "constant":
        return ones
    if trend == "linear":
        return np.hstack([ones, U])
    i, j = np.array([(i, j) for j in range(U.shape[1]) for i in range(j + 1)]).T
    return np.hstack([ones, U, U[:, i] * U[:, j]])


class GPBatch:
    """A :class:`~twinmon.reduce.Surrogate`'s ``predict`` as numpy arithmetic.

    Per mode ``k``: ``xi_k(u) = trend_k(u) + sum_i w_ki k_k(u, u_i)`` with ``u`` the input
    scaled to the unit box, ``u_i`` the training points and ``w_k`` OpenTURNS' kriging
    weights (``getCovarianceCoefficients``) times the kernel amplitude squared; the
    transient is ``mean + xi @ basis`` (exponentiated for the log transform).

    Parameters
    ----------
    surrogate : Surrogate

    Raises
    ------
    ValueError
        A kernel or trend it does not know, or a prediction unlike OpenTURNS' (self-check).
    """

    def __init__(self, surrogate):
        s = surrogate
        if s.kernel not in _KERNELS or s.trend not in ("constant", "linear", "quadratic"):
            raise ValueError(f"no batched form of kernel {s.kernel!r} / trend {s.trend!r}")
        self.kernel, self.trend, self.transform = s.kernel, s.trend, s.transform
        self.lo = s.bounds[:, 0].astype(float)
        self.width = (s.bounds[:, 1] - s.bounds[:, 0]).astype(float)
        factor = _KERNELS[s.kernel][0]
        self.inv_scale = factor / np.asarray(s.scales, float)          # [K, d]
        K, (n, d) = s.n_modes, s.X_train.shape
        self.K, self.n, self.d = K, n, d
        # Scaled training coordinates per input, [K, n] each: a block of rows minus them is
        # one broadcast [rows, K, n] per input.
        self.xs = [s.X_train[None, :, j] * self.inv_scale[:, j, None] for j in range(d)]
        gamma = np.column_stack([np.asarray(r.getCovarianceCoefficients()).ravel()
                                 for r in s._results]).T                # [K, n]
        self.w = np.asarray(s.amplitudes, float)[:, None] ** 2 * gamma             # [K, n]
        self.w3 = self.w / 3.0
        self.trend_matrix = np.array([np.asarray(c, float) for c in s.trend_coefs])  # [K, p]
        self._buffers: dict = {}
        self.mean, self.basis = np.asarray(s.mean, float), np.asarray(s.basis, float)
        self._self_check(s)

    def _self_check(self, s) -> None:
        rng = np.random.default_rng(0)
        X = np.vstack([s.bounds[:, 0] + s.X_train[:8] * self.width,
                       s.bounds[:, 0] + rng.random((8, self.d)) * self.width])
        ref, mine = s.predict(X), self(X)
        err = np.max(np.abs(mine - ref) / np.maximum(np.abs(ref), 1e-300))
        if not err <= SELF_CHECK_RTOL:
            raise ValueError(f"batched prediction differs from OpenTURNS' by {err:.2g}")

    def coefficients(self, X: np.ndarray) -> np.ndarray:
        """Mode coefficients, shape [m, K], for inputs [m, d] (input units)."""
        X = np.atleast_2d(np.asarray(X, float))
        out = np.empty((len(X), self.K))
        for start in range(0, len(X), BLOCK_ROWS):
            out[start:start + BLOCK_ROWS] = self._block(X[start:start + BLOCK_ROWS])
        return out

    def _block(self, X: np.ndarray) -> np.ndarray:
        m, K, n = len(X), self.K, self.n
        U = (X - self.lo) / self.width
        buf = self._buffers.get(m)
        if buf is None:   # scratch reused from call to call (the sampler repeats sizes)
            buf = self._buffers[m] = np.empty((3, m, K, n))
        t, tmp, out = buf
        _, kernel, l1 = _KERNELS[self.kernel]
        # Scaled distance to every training point of every mode: [m, K, n].
        for j in range(self.d):
            uj = U[:, j, None] * self.inv_scale[None, :, j]                     # [m, K]
            dst = t if j == 0 else tmp
            np.subtract(uj[:, :, None], self.xs[j], out=dst)
            if l1:
                np.abs(dst, out=dst)
            else:
                np.multiply(dst, dst, out=dst)
            if j:
                t += tmp
        if not l1:
            np.sqrt(t, out=t)
        xi = kernel(t, self.w, self.w3, tmp, out).sum(axis=2)    # per-row sums, [m, K]
        # einsum's own loops (not BLAS): the same sum order whatever the number of rows
        xi += np.einsum("mp,kp->mk", _trend_features(U, self.trend), self.trend_matrix)
        return xi

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Predicted transients, shape [m, n_t], for inputs [m, d] (input units)."""
        z = np.einsum("mk,kt->mt", self.coefficients(X), self.basis)   # not BLAS, as above
        z += self.mean
        return np.exp(z, out=z) if self.transform == "log" else z


def make_predictor(surrogate) -> tuple[Callable[[np.ndarray], np.ndarray], bool]:
    """A batch predictor ``X [m, d] -> [m, n_out]`` for the surrogate, and whether it is the
    numpy form (:class:`GPBatch`; a stacked view with ``parts`` gets one per part, side by
    side) or the surrogate's own ``predict``."""
    from ..reduce import Surrogate
    parts = getattr(surrogate, "parts", None)
    try:
        if isinstance(surrogate, Surrogate):
            return GPBatch(surrogate), True
        if parts and all(isinstance(p, Surrogate) for p in parts.values()):
            gps = [GPBatch(p) for p in parts.values()]
            return (lambda X: np.hstack([g(X) for g in gps])), True
    except ValueError:
        pass
    return surrogate.predict, False


# ---------------------------------------------------------------------------------------
# Log-posterior of many units at once
# ---------------------------------------------------------------------------------------
@dataclass
class _Batch:
    """Per-unit arrays of one year's batch (unit axis first)."""

    y: np.ndarray          # [U, n_out] observation, NaN -> 0
    w: np.ndarray          # [U, n_out] 1 / total variance, 0 where missing
    centre: np.ndarray     # [U, d] prior centre (box centre for a uniform prior)
    inv_std: np.ndarray    # [U, d] 1 / prior sd (0 for a uniform prior)
    lo: np.ndarray         # [d]
    hi: np.ndarray         # [d]

    def residuals(self, predict, X: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Standardised residuals [m, n_out] of points X [m, d] of units idx [m]."""
        return (self.y[idx] - predict(X)) * np.sqrt(self.w[idx])

    def logpost(self, predict, X: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Unnormalised log-posterior [m] of points X [m, d] of units idx [m]; -inf outside
        the box (the surrogate is not called there)."""
        out = np.full(len(X), -np.inf)
        ok = np.all((X >= self.lo) & (X <= self.hi), axis=1)
        if ok.any():
            Xo, io = X[ok], idx[ok]
            r = self.y[io] - predict(Xo)
            lp = -0.5 * np.sum(r * r * self.w[io], axis=1)
            z = (Xo - self.centre[io]) * self.inv_std[io]
            out[ok] = lp - 0.5 * np.sum(z * z, axis=1)
        return out


def batch_map(predict, batch: _Batch, uniform: np.ndarray, max_iter: int = 60
              ) -> tuple[np.ndarray, np.ndarray]:
    """MAP point and Laplace covariance of every unit of a batch.

    The start is :func:`.density.find_map`'s (best point of a 21^d grid over the box for a
    uniform prior, the prior centre otherwise); then a projected Levenberg-Marquardt on the
    standardised residuals (plus the prior's), each unit on its own until its step is below
    1e-10 of the box or its cost stops falling. Covariance: the inverse Gauss-Newton
    Hessian ``J'J + prior precision + diag(1/range^2)`` at the MAP, as ``find_map``'s.

    Parameters
    ----------
    predict : callable, X [m, d] -> [m, n_out]
    batch : _Batch
    uniform : ndarray of bool, shape [U]
        Units whose prior is uniform.

    Returns
    -------
    x_map : ndarray, shape [U, d]
    cov : ndarray, shape [U, d, d]
    """
    U, d = batch.centre.shape
    lo, hi = batch.lo, batch.hi
    span = hi - lo
    x = np.clip(batch.centre.copy(), lo, hi)
    if uniform.any():
        axes = [np.linspace(a, b, 21) for a, b in zip(lo, hi)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, d)
        for u in np.flatnonzero(uniform):
            lp = batch.logpost(predict, grid, np.full(len(grid), u))
            x[u] = grid[int(np.argmax(lp))]
    x = np.clip(x, lo + 1e-9 * span, hi - 1e-9 * span)
    h = 1e-4 * span
    eye_h = np.diag(h)
    all_units = np.arange(U)

    def resid(X, idx):
        r = batch.residuals(predict, X, idx)
        return np.hstack([r, (X - batch.centre[idx]) * batch.inv_std[idx]])

    def jac(X, idx):
        # central differences, one call for every unit and direction: [m, n_out, d]
        m = len(X)
        pts = np.concatenate([X[:, None, :] + eye_h, X[:, None, :] - eye_h], axis=1)
        pred = predict(pts.reshape(-1, d)).reshape(m, 2 * d, -1) * \
            np.sqrt(batch.w[idx])[:, None, :]
        return -((pred[:, :d] - pred[:, d:]) / (2 * h[None, :, None])).transpose(0, 2, 1)

    r = resid(x, all_units)
    cost = 0.5 * np.sum(r * r, axis=1)
    J = jac(x, all_units)
    prior_prec = batch.inv_std ** 2                     # [U, d]
    mu = np.full(U, 1e-3)
    active = np.ones(U, bool)
    for _ in range(max_iter):
        a = np.flatnonzero(active)
        if a.size == 0:
            break
        Ja = J[a]
        rd = r[a, :-d]
        g = np.einsum("uti,ut->ui", Ja, rd) + batch.inv_std[a] * r[a, -d:]
        H = np.einsum("uti,utj->uij", Ja, Ja) + prior_prec[a][:, :, None] * np.eye(d)
        diag = np.einsum("uii->ui", H)
        A = H + (mu[a][:, None] * np.maximum(diag, 1e-300))[:, :, None] * np.eye(d)
        step = -np.linalg.solve(A, g[:, :, None])[:, :, 0]
        x_new = np.clip(x[a] + step, lo, hi)
        r_new = resid(x_new, a)
        c_new = 0.5 * np.sum(r_new * r_new, axis=1)
        better = c_new < cost[a]
        moved = np.max(np.abs(x_new - x[a]) / span, axis=1)
        small = (moved < 1e-10) | (better & (cost[a] - c_new <= 1e-12 * np.maximum(cost[a],
                                                                              1e-300)))
        ok = a[better]
        x[ok], r[ok], cost[ok] = x_new[better], r_new[better], c_new[better]
        if ok.size:
            J[ok] = jac(x[ok], ok)
        mu[ok] = np.maximum(mu[ok] / 3.0, 1e-12)
        worse = a[~better]
        mu[worse] *= 4.0
        done = small | (mu[a] > 1e12)
        active[a[done]] = False
    J = jac(x, all_units)
    H = np.einsum("uti,utj->uij", J, J) + prior_prec[:, :, None] * np.eye(d) + \
        np.diag(1.0 / span ** 2)
    return x, np.linalg.inv(H)


# ---------------------------------------------------------------------------------------
# Convergence diagnostics of many unit-years at once (for the stopping rule)
# ---------------------------------------------------------------------------------------
def first_look(cfg: Config) -> int:
    """Steps per chain after the burn-in before convergence is first checked: enough for an
    ESS of ``ess_warn`` at half a draw's worth per step (random-walk Metropolis in low
    dimension rarely does better), at least 100, at most ``calibrate.samples``."""
    cc = cfg.calibrate
    return int(min(cc.samples, max(100, math.ceil(2 * cc.ess_warn / cc.chains))))


def chunk_steps(cfg: Config) -> int:
    """Steps per chain added at each look after the first (half the first look)."""
    return max(50, first_look(cfg) // 2)


def longest_run(cfg: Config, uniform: bool) -> int:
    """Cap on the steps per chain after the burn-in: the OpenTURNS path's longest run."""
    cc = cfg.calibrate
    return cc.samples * 2 ** cc.max_extensions * (2 if uniform else 1)


def _laplace_logpdf(X: np.ndarray, m: np.ndarray, prec: np.ndarray, lo: np.ndarray,
                    hi: np.ndarray) -> np.ndarray:
    """Log-density (unnormalised) of the Laplace approximation, per row: ``-1/2 (x - m)'
    P (x - m)``, ``-inf`` outside the box. X, m [r, d]; prec [r, d, d]."""
    dx = X - m
    out = -0.5 * np.einsum("ri,rij,rj->r", dx, prec, dx)
    out[~np.all((X >= lo) & (X <= hi), axis=1)] = -np.inf
    return out


def _more_steps(cfg: Config, n: int, rhat: np.ndarray, n_eff: np.ndarray, cap: int) -> int:
    """Steps to add to chains of ``n`` steps that missed the marks: as many as the ESS,
    growing in proportion to the length, should need (plus a tenth), at least
    :func:`chunk_steps`, at most ``n`` (an ESS from short chains that have not mixed yet is
    far too low: extrapolated, it would ask for ten times too many steps), and only up to
    ``cap``."""
    cc = cfg.calibrate
    worst = float(np.nanmin(n_eff)) if np.isfinite(n_eff).any() else 0.0
    want = chunk_steps(cfg)
    if 0 < worst < cc.ess_warn:
        want = max(want, min(n, math.ceil(n * (1.1 * cc.ess_warn / worst - 1.0))))
    return int(max(1, min(want, cap - n)))


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of all values of ``x`` (ties get their average rank), shape of ``x``: what
    ``scipy.stats.rankdata(method="average")`` gives, from one stable sort (a chain repeats
    every rejected draw, so ties are the rule)."""
    flat = x.ravel()
    order = np.argsort(flat, kind="stable")
    srt = flat[order]
    new = np.empty(srt.size, bool)
    new[0] = True
    np.not_equal(srt[1:], srt[:-1], out=new[1:])
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], srt.size)
    ranks = np.empty(srt.size)
    ranks[order] = ((starts + ends + 1) / 2.0)[np.cumsum(new) - 1]
    return ranks.reshape(x.shape)


def _z_scale(x: np.ndarray) -> np.ndarray:
    """:func:`.diagnostics._z_scale` with :func:`_average_ranks`."""
    from scipy.special import ndtri
    return ndtri((_average_ranks(x) - 0.375) / (x.size + 0.25))


def _ess_z(x: np.ndarray) -> float:
    """:func:`.diagnostics.ess` of already split, rank-normalised chains [m, n], with
    Geyer's initial positive and monotone sequences as array operations (the same values,
    summed in the same order, as the reference's loop over lags)."""
    from .diagnostics import _autocov
    m, n = x.shape
    if np.ptp(x) == 0 or n < 4:
        return float("nan")
    acov = _autocov(x)
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n
    if m > 1:
        var_plus += np.var(x.mean(axis=1), ddof=1)
    # np.mean over each column, as the reference's np.mean(acov[:, t]) sums it
    rho_all = 1.0 - (mean_var - np.mean(np.ascontiguousarray(acov.T), axis=1)) / var_plus
    # Pair j = (rho[2j], rho[2j+1]); pair 0 is (1, rho[1]). The reference's first loop
    # reads pairs 1, 2, ... while the last pair read had a positive sum and t = 2j - 1 <
    # n - 3; j_last is the last pair it reads.
    n_read = len(range(1, n - 3, 2))
    even = rho_all[2:2 * n_read + 1:2]
    odd = rho_all[3:2 * n_read + 2:2]
    pair = np.concatenate([[1.0 + rho_all[1]], even + odd])             # [n_read + 1]
    stop = np.flatnonzero(pair <= 0.0)
    j_last = int(min(stop[0], n_read)) if stop.size else n_read
    rho = np.zeros(n)
    rho[0], rho[1] = 1.0, rho_all[1]
    if j_last >= 1:
        # pairs 1 .. j_last - 1 are stored; pair j_last only if its sum is >= 0
        upto = j_last if pair[j_last] < 0 else j_last + 1
        rho[2:2 * upto] = rho_all[2:2 * upto]
    max_t = 2 * j_last - 1
    rho_even = 1.0 if j_last == 0 else rho_all[2 * j_last]
    if rho_even > 0:
        rho[max_t + 1] = rho_even
    # Monotone: pairs 1 .. j_last - 1 may not exceed the pair before (as modified).
    if j_last >= 2:
        sums = rho[0:2 * j_last:2] + rho[1:2 * j_last:2]                 # pairs 0 .. j_last-1
        capped = np.minimum.accumulate(sums)
        lower = np.flatnonzero(sums[1:] > capped[:-1]) + 1
        rho[2 * lower] = capped[lower - 1] / 2.0
        rho[2 * lower + 1] = capped[lower - 1] / 2.0
    total = m * n
    tau = -1.0 + 2.0 * np.sum(rho[:max_t + 1]) + np.sum(rho[max_t + 1:max_t + 2])
    tau = max(tau, 1.0 / np.log10(total))
    return float(total / tau)


def _diagnostics(draws: np.ndarray, need_rhat: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Rank-normalised split R-hat and bulk ESS per input of one unit-year's chains
    [C, N, d]: the values of :func:`.diagnostics.split_rhat` and
    :func:`.diagnostics.ess` (``rank_normalize=True``), sharing the ranks they both take.
    Without ``need_rhat`` the R-hat is NaN (not computed)."""
    from .diagnostics import _rhat, _split
    d = draws.shape[2]
    rhat, n_eff = np.full(d, np.nan), np.full(d, np.nan)
    for j in range(d):
        x = draws[:, :, j]
        if np.ptp(x) == 0:
            continue
        z = _z_scale(_split(x))
        n_eff[j] = _ess_z(z)
        if need_rhat:
            bulk = _rhat(z)
            folded = np.abs(x - np.median(x))
            rhat[j] = max(bulk, _rhat(_z_scale(_split(folded)))) if np.ptp(folded) > 0 \
                else bulk
    return rhat, n_eff


def _converged(draws: np.ndarray, cfg: Config) -> tuple[bool, np.ndarray, np.ndarray]:
    """R-hat and bulk ESS per input of one unit-year's chains [C, N, d] (see
    :func:`_diagnostics`), and whether they meet the config's marks. The R-hat is only
    computed once the ESS is met (until then the chains run on anyway)."""
    cc = cfg.calibrate
    _, n_eff = _diagnostics(draws, need_rhat=False)
    if not np.all(n_eff >= cc.ess_warn):
        return False, np.full(len(n_eff), np.nan), n_eff
    rhat, n_eff = _diagnostics(draws)
    return bool(np.all(rhat <= cc.rhat_warn)), rhat, n_eff


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
    """One unit's results, filled a year at a time by :func:`_sample_years`."""

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
    :class:`.sequential._UnitRun` computes them)."""
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
    batch = _Batch(np.where(miss, 0.0, Y), W, centre, inv_std, lo, hi)
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
            starts[u] = _initial_states(rng, x_map[u], cov[u], priors[u], C)
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
    lq = _laplace_logpdf(x, x_map[unit_of], prec[unit_of], lo, hi)
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
            lq_prop = _laplace_logpdf(prop, mr, pr, lo, hi)
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
            conv, rhat, n_eff = _converged(chains, cfg)
            if conv or kept[u] >= cap[u]:
                result[u] = (chains, conv, rhat, n_eff)
                active[u] = False
                zbuf[u] = lubuf[u] = None
            else:
                looks[u] += 1
                start_segment(u, _more_steps(cfg, kept[u], rhat, n_eff, cap[u]))

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
def _groups(units: list, workers: int) -> list[list]:
    """Units split into tasks: at least one per worker, up to four per worker when there are
    enough units for batches of ~64 (a batch of a few hundred chains keeps the numpy calls
    large; several tasks per worker keep the workers evenly busy)."""
    n = max(workers, min(4 * workers, math.ceil(len(units) / 64)), 1)
    size = math.ceil(len(units) / n)
    return [units[i:i + size] for i in range(0, len(units), size)]


def _work(cfg: Config, units: list[UnitData]) -> dict[str, UnitPosterior]:
    from . import _worker   # the surrogate set up once per worker by calibrate's initializer
    if "predict" not in _worker:
        _worker["predict"] = make_predictor(_worker["surrogate"])[0]
    return calibrate_units(_worker["surrogate"], cfg, units, predict=_worker["predict"])


def run_vectorised(cfg: Config, surrogate, runs: dict, resume: dict, output,
                   progress: Optional[Callable[[int, int], None]], pool_args: tuple) -> None:
    """Calibrate every unit of ``runs`` (``calibrate()``'s :class:`.sequential._UnitRun`
    table: years, observations, noise, seed) with the vectorised sampler, replacing each
    entry by its finished result (a :class:`.update.Kept`).

    ``resume``: unit -> stored posterior to continue after (``--update``; units with nothing
    new are already ``Kept``). ``pool_args``:
    ``(initializer, initargs)`` of calibrate's worker processes (``calibrate.workers``:
    0 = one per core, 1 = in this process; the units are split into batches, each run by
    one worker through all its years). Results do not depend on the split.
    """
    import os

    from .update import Kept
    total = sum(len(r.years) for r in runs.values())
    done = [sum(len(p.years) for p in resume.values())]
    results = {u: r.result() for u, r in runs.items() if r.done}
    pending = [UnitData(u, r.years, r.flows, r.noise, r.seed, r.source, resume.get(u))
               for u, r in runs.items() if not r.done]

    def tick(n: int) -> None:
        done[0] += n
        if progress:
            progress(done[0], total)

    workers = min(cfg.calibrate.workers or len(os.sched_getaffinity(0)), len(pending))
    dask_cluster = cfg.calibrate.executor == "dask" and cfg.dask.address
    if pending and workers <= 1 and not dask_cluster:
        results.update(calibrate_units(surrogate, cfg, pending, tick,
                                       predict=make_predictor(surrogate)[0]))
    elif pending:
        from concurrent.futures import FIRST_COMPLETED, wait
        # Imported once here, not in every forked worker (scipy.stats is not needed: the
        # goodness-of-fit p-values come from scipy.special, see diagnose.stats).
        import scipy.special  # noqa: F401

        from ..executors import InterruptGuard, open_pool
        from . import sampling_pool
        pool = open_pool(cfg, "calibrate", max(workers, 1), *pool_args)
        with sampling_pool(pool, output), InterruptGuard() as guard:
            futures = {pool.submit(_work, cfg, g): g for g in _groups(pending, workers)}
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
