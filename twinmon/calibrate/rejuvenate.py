"""Resample-move: the laplace method's weighted draws moved by a Markov chain on the exact
posterior, for a unit whose weights stay too uneven.

The laplace method weights draws of a Gaussian model (each year's site, refined by
expectation propagation) to the exact likelihood. Where the recorded channels hardly tell
the inputs apart, each year's likelihood is a long curved ridge cut by the design box; no
Gaussian follows it, and over ten years of three inputs the small mismatches of every year
multiply: on a water heater recorded by its water temperature alone, units kept 34-372
effective draws of 8000, every year's own weights fine (thousands) and their product not.
More draws (Pareto shape above 0.7: the weights' variance is infinite) and wider sites do
not help.

The weighted draws are still a fair start: the posterior up to the few draws that carry it.
Resample-move (Gilks and Berzuini, JRSS B 63, 2001) keeps them and moves each by a Markov
chain that leaves the exact posterior unchanged, until the copies of one draw have
forgotten that they were copies. The state of a chain is the model's: the shape ``s``, its
coefficients ``beta``, the year-to-year sd ``sigma`` [d] and the years ``theta`` [K, d].
Each sweep, every chain at once:

1. **Shape and coefficients given the years** (Gibbs): with the years known exactly, each
   shape is a linear Gaussian model in ``beta``; ``s`` is drawn from its evidence times its
   prior (the shapes the Gaussian model kept), then ``beta`` from its conditional.
2. **sigma given the rest** (independence Metropolis-Hastings): proposed from the
   inverse-gamma that a flat prior would give, accepted by the half-Cauchy prior's ratio.
3. **Each year given the trend** (independence Metropolis-Hastings, every year at once):
   proposed from the Gaussian model's conditional (site times trend), accepted by the
   year's exact likelihood over its site, as the importance weights are; outside the box
   rejected.
4. **sigma with the years** (non-centred): ``sigma`` scaled at random and the years'
   departures from the trend with it, accepted by the exact likelihood: the funnel between
   ``sigma`` and the years, which the centred steps cross slowly, crossed in one move.
5. **The trend with the years** (non-centred, :data:`TREND_MOVES` per sweep): ``beta``
   moved by a random walk shaped by its Gaussian-model covariance, the years shifted with
   it, accepted by the exact likelihood: a slide along the ridge that the years cannot
   make one at a time.

Every other sweep runs the steps in reverse order, so that two sweeps make a reversible
chain. The chains are judged as a cluster sample: the draws that started as copies of one
weighted draw form a group, whose members stay correlated by the chain's autocorrelation
at twice the sweeps run. The sweeps go on, in blocks of :data:`BLOCK`, until Kish's design
effect of the groups at that correlation (:func:`resampled_ess`: the largest over every
year's inputs, the sds and the trend's level and rate at the last year) leaves the mark's
effective number, or :data:`MAX_SWEEPS` are run.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .stacked import inv_chol

#: Sweeps between two looks at the effective number, and at most this many in all.
BLOCK = 10
MAX_SWEEPS = 80
#: Non-centred moves of the trend per sweep, and their random walk's scale: Roberts and
#: Rosenthal's 2.38 / sqrt(dimension) times the Gaussian model's covariance of beta.
TREND_MOVES = 2
TREND_SCALE = 2.38
#: Sd of the non-centred move of log sigma.
SCALE_STEP = 0.3


@dataclass
class Moved:
    """What :func:`rejuvenate` returns.

    Attributes
    ----------
    coef, sigma, theta : ndarray
        The chains' last states, as :meth:`ShapeMixture.draw` gives them: ``coef`` [n, 1 +
        K d + 4 d], ``sigma`` [n, d], ``theta`` [n, K, d].
    ess : float
        Effective number of the draws (the module docstring).
    sweeps : int
    acceptance : dict str -> float
        Mean acceptance of each Metropolis-Hastings step.
    """

    coef: np.ndarray
    sigma: np.ndarray
    theta: np.ndarray
    ess: float
    sweeps: int
    acceptance: dict


def _log_half_cauchy(s: np.ndarray, A: np.ndarray) -> np.ndarray:
    return -np.log1p((s / A) ** 2)


class _Chains:
    """The chains' state and the model's pieces the steps share."""

    def __init__(self, model, loglik, bounds: np.ndarray, sigma: np.ndarray,
                 theta: np.ndarray, code: np.ndarray):
        self.model, self.loglik, self.bounds = model, loglik, bounds
        self.x, self.H = model.x, np.linalg.inv(model.cov)
        self.A = np.asarray(model.shapes[0].model.A, float)
        self.allowed = [j for j in range(len(model.shapes))
                        if np.isfinite(model.probs[j]) and model.probs[j] > 0]
        self.sigma, self.theta, self.code = sigma.copy(), theta.copy(), code.copy()
        nb = max(model.shapes[j].model.Mk.shape[2] for j in self.allowed)
        self.beta = np.zeros((len(theta), nb))
        self.m = np.zeros_like(theta)
        self.ll = loglik(theta)                                            # [n, K]
        self.moves = {"sigma": [], "years": [], "scale": [], "trend": []}
        self._walks = self._trend_walks()

    def _over_site(self, theta: np.ndarray, ll: np.ndarray) -> np.ndarray:
        """Each year's exact log-likelihood over its site (the importance weights' factor)."""
        dx = theta - self.x
        return ll + 0.5 * np.einsum("nki,kij,nkj->nk", dx, self.H, dx)

    def _inside(self, theta: np.ndarray, axis) -> np.ndarray:
        return np.all((theta >= self.bounds[:, 0]) & (theta <= self.bounds[:, 1]), axis=axis)

    def _trend_walks(self) -> dict:
        """Per shape, the Cholesky factor of the trend move's covariance: the Gaussian
        model's posterior covariance of beta at the chains' median sigma, scaled."""
        d = self.x.shape[1]
        W = np.linalg.inv(self.model.cov + np.eye(d) * np.median(self.sigma, axis=0) ** 2)
        out = {}
        for j in self.allowed:
            m = self.model.shapes[j].model
            P = m.prior_P + np.einsum("kia,kij,kjb->ab", m.Mk, W, m.Mk)
            C = np.linalg.inv(P)
            C = 0.5 * (C + C.T) + 1e-12 * np.trace(C) * np.eye(len(C))
            out[j] = np.linalg.cholesky(C) * TREND_SCALE / np.sqrt(len(C))
        return out

    def shape_and_trend(self, rng: np.random.Generator) -> None:
        """Step 1: ``s`` from its evidence given the years, then ``beta`` given ``s``."""
        theta, n, K = self.theta, len(self.theta), self.theta.shape[1]
        w = 1.0 / self.sigma ** 2                                          # [n, d]
        quad = np.einsum("ni,nki->n", w, theta ** 2)
        logdet_v = -K * np.log(w).sum(axis=1)
        lp, parts = [], []
        for j in self.allowed:
            m = self.model.shapes[j].model
            # With the years exact, the years' weights are diag(1/sigma^2): the sums over
            # years are per-input Gram matrices, weighted per chain.
            P = m.prior_P[None] + np.einsum("ni,kia,kib->nab", w, m.Mk, m.Mk)
            b = (m.prior_P @ np.asarray(m.prior_mean, float))[None] + \
                np.einsum("ni,kia,nki->na", w, m.Mk, theta)
            L = np.linalg.cholesky(P)
            y = np.linalg.solve(L, b[..., None])[..., 0]
            logdet_b = 2.0 * np.log(np.einsum("nii->ni", L)).sum(axis=1)
            # linear_gaussian's log marginal likelihood, the sites' covariance 0.
            ll = -0.5 * (logdet_v + quad - np.einsum("na,na->n", y, y) + logdet_b) + \
                m._log_norm
            lp.append(self.model.shapes[j].log_prior + ll)
            parts.append((L, y))
        lp = np.array(lp)
        p = np.exp(lp - lp.max(axis=0))
        p /= p.sum(axis=0)
        pick = np.minimum((np.cumsum(p, axis=0) < rng.random(n)).sum(axis=0),
                          len(self.allowed) - 1)
        z = rng.standard_normal(self.beta.shape)
        self.beta[:] = 0.0
        for a, j in enumerate(self.allowed):
            sel = np.flatnonzero(pick == a)
            if not sel.size:
                continue
            L, y = parts[a]
            nb = y.shape[1]
            # beta = L^-T (y + z): mean L^-T y = P^-1 b, covariance P^-1.
            b = np.linalg.solve(np.swapaxes(L[sel], 1, 2),
                                (y[sel] + z[sel, :nb])[..., None])[..., 0]
            self.beta[sel, :nb] = b
            self.m[sel] = np.einsum("kia,na->nki", self.model.shapes[j].model.Mk, b)
            self.code[sel] = j

    def sigma_given_rest(self, rng: np.random.Generator) -> None:
        """Step 2: ``sigma^2`` proposed from inverse-gamma((K - 1) / 2, SS / 2), the
        conditional under a flat prior; accepted by the half-Cauchy's ratio."""
        K = self.theta.shape[1]
        ss = ((self.theta - self.m) ** 2).sum(axis=1)                       # [n, d]
        new = np.sqrt(0.5 * ss / rng.gamma(0.5 * (K - 1), size=ss.shape))
        ok = np.log(rng.random(ss.shape)) < \
            _log_half_cauchy(new, self.A) - _log_half_cauchy(self.sigma, self.A)
        self.sigma = np.where(ok, new, self.sigma)
        self.moves["sigma"].append(ok.mean())

    def years(self, rng: np.random.Generator) -> None:
        """Step 3: every year proposed from site times trend, accepted by its exact
        likelihood over its site."""
        d = self.x.shape[1]
        s_inv = 1.0 / self.sigma ** 2
        G, Lg = inv_chol(self.H[None] + s_inv[:, None, :, None] * np.eye(d))
        hx = np.einsum("kij,kj->ki", self.H, self.x)
        mu = np.einsum("nkij,nkj->nki", G, hx[None] + s_inv[:, None, :] * self.m)
        prop = mu + np.einsum("nkij,nkj->nki", Lg, rng.standard_normal(mu.shape))
        ll = self.loglik(prop)
        gain = self._over_site(prop, ll) - self._over_site(self.theta, self.ll)
        ok = self._inside(prop, 2) & (np.log(rng.random(gain.shape)) < gain)
        self.theta = np.where(ok[..., None], prop, self.theta)
        self.ll = np.where(ok, ll, self.ll)
        self.moves["years"].append(ok.mean())

    def scale(self, rng: np.random.Generator) -> None:
        """Step 4: ``sigma`` times ``exp(SCALE_STEP z)`` and the years' departures from the
        trend with it. The years' Gaussian factor and the map's Jacobian cancel; the random
        walk on log sigma adds ``sigma' / sigma``."""
        new = self.sigma * np.exp(SCALE_STEP * rng.standard_normal(self.sigma.shape))
        prop = self.m + (new / self.sigma)[:, None, :] * (self.theta - self.m)
        ll = self.loglik(prop)
        gain = (_log_half_cauchy(new, self.A) - _log_half_cauchy(self.sigma, self.A)
                + np.log(new / self.sigma)).sum(axis=1) + (ll - self.ll).sum(axis=1)
        ok = self._inside(prop, (1, 2)) & (np.log(rng.random(len(gain))) < gain)
        self.sigma = np.where(ok[:, None], new, self.sigma)
        self.theta = np.where(ok[:, None, None], prop, self.theta)
        self.ll = np.where(ok[:, None], ll, self.ll)
        self.moves["scale"].append(ok.mean())

    def slide(self, rng: np.random.Generator) -> None:
        """Step 5: ``beta`` by a random walk (its shape kept), the years shifted with the
        trend; the prior of beta and the exact likelihood decide."""
        took = 0
        for j in self.allowed:
            sel = np.flatnonzero(self.code == j)
            if not sel.size:
                continue
            m = self.model.shapes[j].model
            nb = m.Mk.shape[2]
            b = self.beta[sel, :nb]
            step = rng.standard_normal((sel.size, nb)) @ self._walks[j].T
            shift = np.einsum("kia,na->nki", m.Mk, step)
            prop = self.theta[sel] + shift
            ll = self.loglik(prop)
            m0 = np.asarray(m.prior_mean, float)
            prior = -0.5 * (np.einsum("na,ab,nb->n", b + step - m0, m.prior_P, b + step - m0)
                            - np.einsum("na,ab,nb->n", b - m0, m.prior_P, b - m0))
            gain = prior + (ll - self.ll[sel]).sum(axis=1)
            ok = self._inside(prop, (1, 2)) & (np.log(rng.random(sel.size)) < gain)
            a = sel[ok]
            self.beta[a, :nb] = b[ok] + step[ok]
            self.theta[a], self.m[a] = prop[ok], self.m[a] + shift[ok]
            self.ll[a] = ll[ok]
            took += ok.sum()
        self.moves["trend"].append(took / len(self.theta))

    def coef(self) -> np.ndarray:
        """The states as :meth:`ShapeMixture.draw`'s ``coef``."""
        n, K, d = self.theta.shape
        now = np.empty((n,) + self.model.shapes[0].now.shape[:2])
        for j in self.allowed:
            sel = np.flatnonzero(self.code == j)
            s = self.model.shapes[j]
            nb = s.model.Mk.shape[2]
            now[sel] = np.einsum("tia,na->nti", s.now, self.beta[sel, :nb])
        return np.column_stack([self.code.astype(float), self.m.reshape(n, -1),
                                now.reshape(n, -1)])


def moved_by_chain(acceptance, trend_acceptance) -> bool:
    """Whether a unit's draws are weighted draws this module's chain moved: no acceptance
    per year (``UnitPosterior.acceptance`` [K, chains] all NaN: draws without a chain per
    year, the laplace method's) and its trend moves' acceptance recorded
    (``trend/acceptance``; None or absent: a trend read without it, or none)."""
    if trend_acceptance is None or np.isfinite(np.asarray(acceptance, float)).any():
        return False
    return bool(np.isfinite(np.asarray(trend_acceptance, float)).any())


def resampled_ess(groups: np.ndarray, before: np.ndarray, after: np.ndarray,
                  sweeps: int, lag: int) -> float:
    """Effective number of ``n`` chains that started in groups of copies, after ``sweeps``.

    Two chains of a reversible kernel that started as copies of one draw of the posterior
    are correlated, after ``t`` sweeps, by the chain's autocorrelation at lag ``2 t``
    (``Var E[f(X_t) | X_0] = <f, P^2t f>``); Kish's design effect of the groups is then
    ``1 + (m - 1) rho``, ``m = sum(m_g^2) / n`` the groups' mean size as a draw sees it.
    The autocorrelation is measured at ``lag`` from every chain's states ``lag`` sweeps
    apart (``before``, ``after`` [n, q], about the pooled mean: copies not yet apart raise
    it) and extended geometrically, ``rho(lag)^(2 sweeps / lag)``, as a Markov chain's
    decays; the largest over the ``q`` columns counts. Estimated from the ``n`` pairs, not
    from the groups: the groups' own intraclass correlation is too noisy to read with a few
    hundred groups of very unequal sizes (independent draws in the groups of a resample
    with 18 effective weights read as 157-286 effective of 1000 over 36 columns).

    Parameters
    ----------
    groups : ndarray of int, shape [n]
        Each chain's group (the draw it started as a copy of), 0 .. G - 1.
    before, after : ndarray, shape [n, q]
    sweeps, lag : int
    """
    n = len(groups)
    size = np.bincount(groups).astype(float)
    both = np.vstack([before, after])
    mu, var = both.mean(axis=0), both.var(axis=0)
    live = var > 0
    rho = np.mean((before - mu) * (after - mu), axis=0)[live] / var[live]
    worst = float(np.clip(rho.max(), 0.0, 1.0)) if rho.size else 0.0
    icc = worst ** (2.0 * sweeps / lag)
    return n / (1.0 + ((size ** 2).sum() / n - 1.0) * icc)


def rejuvenate(model, loglik, start: tuple, n: int, rng: np.random.Generator,
               bounds: np.ndarray, mark: float, max_sweeps: int = MAX_SWEEPS) -> Moved:
    """``n`` chains from ``start``'s draws, swept until their effective number reaches
    ``mark`` (checked every :data:`BLOCK` sweeps) or ``max_sweeps`` are run.

    Parameters
    ----------
    model : ShapeMixture
        The unit's Gaussian model, after its sigma points (``probs``: the shapes kept).
    loglik : callable, theta [m, K, d] -> [m, K]
        Each year's exact log-likelihood.
    start : tuple
        :meth:`~.gaussian_trend.SiteModel.importance`'s result ``(coef, sigma, theta,
        ess)``: resampled draws, every one inside the box.
    n : int
        Chains (and draws returned).
    bounds : ndarray, shape [d, 2]
    mark : float
        The effective number wanted (``calibrate.ess_warn``).
    """
    coef, sigma, theta = start[:3]
    pick = rng.integers(len(theta), size=n)
    K, d = theta.shape[1:]
    # Copies of one weighted draw are one group, wherever they sit in the resampled array.
    _, groups = np.unique(theta[pick].reshape(n, -1), axis=0, return_inverse=True)
    groups = groups.ravel()
    c = _Chains(model, loglik, bounds, sigma[pick], theta[pick],
                coef[pick, 0].astype(int))

    def watched(out: np.ndarray) -> np.ndarray:
        # Every year's inputs, the sds (log), the trend's level and rate at the last year.
        now = out[:, 1 + K * d:].reshape(n, -1, d)[:, :2].reshape(n, -1)
        return np.hstack([c.theta.reshape(n, -1), np.log(c.sigma), now])

    steps = [c.shape_and_trend, c.sigma_given_rest, c.years, c.scale] + \
        [c.slide] * TREND_MOVES
    sweeps, ess, out = 0, 0.0, coef[pick]
    before = watched(out)
    while sweeps < max_sweeps:
        for i in range(BLOCK):
            # Every other sweep in reverse: two sweeps make a palindrome of reversible
            # steps, a reversible chain (what resampled_ess reads its decay by).
            for step in (steps if i % 2 == 0 else steps[::-1]):
                step(rng)
        sweeps += BLOCK
        out = c.coef()
        after = watched(out)
        ess = resampled_ess(groups, before, after, sweeps, BLOCK)
        if ess >= mark:
            break
        before = after
    return Moved(out, c.sigma, c.theta, ess, sweeps,
                 {k: float(np.mean(v)) for k, v in c.moves.items()})
