"""A unit's trend on Gaussian summaries of its years: the joint method's model with each
year's likelihood replaced by a Gaussian *site*, its posterior in closed form but for
sigma, the sites refined by expectation propagation, and the draws weighted back to the exact
likelihood (used by :mod:`.methods.laplace`, whose docstring gives the model)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .stacked import chol_solve, inv_chol, inv_logdet

#: Quasi-random sigma points per round, and the effective number of them the weights must
#: reach before the zooming stops (at most :data:`SIGMA_ROUNDS` rounds).
SIGMA_POINTS = 512
SIGMA_ESS = 100.0
SIGMA_ROUNDS = 5
#: Points with a weight below this share of the largest do not hold the next round's box;
#: one within a spacing of an inner face of a reused box with more than ``SIGMA_EDGE`` of
#: it means the box cuts the mass off.
SIGMA_KEEP = 1e-4
SIGMA_EDGE = 1e-3
#: A year's draw outside the design box is drawn again this many times, then clipped.
BOX_TRIES = 20
#: Expectation propagation of the years' sites (GaussianTrend.refine): sweeps, draws of the
#: model per sweep, likelihood points per year, and the fewest effective points an update
#: rests on.
EP_SWEEPS = 3
EP_DRAWS = 1000
EP_POINTS = 300
EP_MIN_ESS = 30.0
#: The last resort of the importance weights (SiteModel.importance_widened): factors on the
#: covariance of the sites whose own weights are the unevenest, tried in turn, and how
#: uneven that is (a year's effective number below this fraction of the best year's).
WIDEN_FACTORS = (4.0, 16.0)
WIDEN_BELOW = 0.5
#: No box: the Gaussian model's own draws (the box enters through the weights).
WIDE_BOX = np.tile([-np.inf, np.inf], (64, 1))


def year_weight_table(cov: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each year's weight ``(C_k + diag(sigma^2))^-1`` and the log-determinant of its
    covariance, at sigma points ``sigma`` [P, d], for the sites' covariances ``cov``
    [K, d, d]: [P, K, d, d] and [P, K]. The years before a cut are a slice of it (the
    forecast's trend-fit check shares one table between its cuts)."""
    P, (K, d) = len(sigma), cov.shape[:2]
    if d == 2:
        # inv_logdet's closed form written straight into the output, without the
        # [P, K, 2, 2] sums and stacks (the same values, bit for bit): this is called some
        # ninety times a unit.
        s2 = sigma ** 2
        a = cov[None, :, 0, 0] + s2[:, None, 0]
        c = cov[None, :, 1, 1] + s2[:, None, 1]
        b = cov[:, 0, 1]
        det = a * c - b * b
        W = np.empty((P, K, 2, 2))
        W[..., 0, 0] = c / det
        W[..., 0, 1] = W[..., 1, 0] = -b / det
        W[..., 1, 1] = a / det
        return W, np.log(det)
    return inv_logdet(cov[None] + (sigma ** 2)[:, None, :, None] * np.eye(d))


def year_weights(cov: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each year's weight ``(C_k + diag(sigma^2))^-1`` at sigma points ``sigma`` [P, d], the
    sites' covariances ``cov`` [K, d, d]: flattened, [P, K d d], and the log-determinant of
    the years' covariances summed, [P] (:func:`year_weight_table`, summed over the years)."""
    return weights_of(year_weight_table(cov, sigma))


def weights_of(table: tuple, k: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`year_weights` of the years ``[0, k)`` (all: None) from their
    :func:`year_weight_table` ``(W [P, K, d, d], logdet [P, K])``: ``(Wf [P, k d d],
    logdet_v [P])``."""
    W, logdet = table
    return W[:, :k].reshape(len(W), -1), logdet[:, :k].sum(axis=1)


def linear_gaussian(Wf: np.ndarray, logdet_v: np.ndarray, Mk: np.ndarray, x: np.ndarray,
                    prior_P: np.ndarray, prior_mean: np.ndarray, log_norm: np.ndarray,
                    want_mean: bool = True):
    """The trend coefficients' Gaussian conditional and the sites' log marginal likelihood,
    for ``G`` trend designs of one size at ``P`` sigma points at once (the models'
    :meth:`GaussianTrend._conditional`).

    Parameters
    ----------
    Wf, logdet_v : ndarray, shapes [P, K d d], [P]
        :func:`year_weights`.
    Mk : ndarray, shape [G, K, d, nb]
    x : ndarray, shape [K, d]
    prior_P, prior_mean : ndarray, shapes [G, nb, nb], [G, nb]
    log_norm : ndarray, shape [G]
        The proper part of each prior's log normalisation.
    want_mean : bool
        False: ``mean`` is None (the log marginal likelihood alone: what the evidence and
        sigma's points need).

    Returns
    -------
    Pb, Lb : ndarray, shape [G, P, nb, nb]
        Precision and its Cholesky factor.
    mean : ndarray, shape [G, P, nb], or None
    ll : ndarray, shape [G, P]
    """
    G, K, d, nb = Mk.shape
    P = len(Wf)
    if d <= 2:
        # Every sum over (year, input, input) is one matrix product with W flattened:
        # sum_kij W[p,k,i,j] f[k,i,j,...] (far faster than stacked small products).
        MM = np.einsum("gkia,gkjb->kijgab", Mk, Mk).reshape(K * d * d, G * nb * nb)
        Pb = np.swapaxes((Wf @ MM).reshape(P, G, nb, nb), 0, 1) + prior_P[:, None]
        Mx = np.einsum("gkia,kj->kijga", Mk, x).reshape(K * d * d, G * nb)
        b = np.swapaxes((Wf @ Mx).reshape(P, G, nb), 0, 1)
    else:
        # That product grows as d^2 nb^2 (a 3-input mixture: 40 ms a unit for the
        # trend-fit gate): W M per sigma point and year first, then M' (W M) per design.
        W = Wf.reshape(P, K, d, d)
        M = np.moveaxis(Mk, 0, 2).reshape(K, d, G * nb)
        WM = np.matmul(W, M[None]).reshape(P, K * d, G, nb)
        Mt = np.swapaxes(Mk.reshape(G, K * d, nb), 1, 2)                    # [G, nb, Kd]
        Pb = np.matmul(Mt[:, None], np.moveaxis(WM, 2, 0)) + prior_P[:, None]
        Wx = np.einsum("pkij,kj->pki", W, x).reshape(P, K * d)
        b = np.einsum("gca,pc->gpa", Mk.reshape(G, K * d, nb), Wx)
    b = b + np.einsum("gab,gb->ga", prior_P, prior_mean)[:, None]
    quad = Wf @ np.einsum("ki,kj->kij", x, x).ravel()
    Lb = np.linalg.cholesky(Pb)
    y, mean = chol_solve(Pb, Lb, b, want_mean)
    fit = np.einsum("gpa,gpa->gp", b, mean) if y is None else np.einsum("gpa,gpa->gp", y, y)
    logdet_b = 2.0 * np.log(np.einsum("gpii->gpi", Lb)).sum(axis=2)
    ll = -0.5 * (logdet_v + quad - fit + logdet_b) + log_norm[:, None]
    return Pb, Lb, mean, ll


def log_evidence_at(models: list, sigma: np.ndarray) -> np.ndarray:
    """Each model's log marginal likelihood of the sites at sigma points ``sigma`` [P, d]
    (:meth:`GaussianTrend._conditional`'s), the models of one size evaluated together (one
    batched product each: a unit's dozens of shapes cost a few calls) [len(models), P].
    The models share their sites."""
    cov, x = models[0].cov, models[0].x
    Wf, logdet_v = year_weights(cov, sigma)
    out = np.empty((len(models), len(sigma)))
    groups: dict = {}
    for j, m in enumerate(models):
        groups.setdefault(m.Mk.shape[2], []).append(j)
    for idx in groups.values():
        ms = [models[j] for j in idx]
        out[idx] = linear_gaussian(Wf, logdet_v, np.stack([m.Mk for m in ms]), x,
                                   np.stack([m.prior_P for m in ms]),
                                   np.stack([np.asarray(m.prior_mean, float) for m in ms]),
                                   np.array([m._log_norm for m in ms]), want_mean=False)[3]
    return out


class SiteModel:
    """What a Gaussian model on the years' sites does with the exact likelihood, whatever
    its trend (:class:`GaussianTrend`, or a mixture of shapes,
    :class:`~twinmon.calibrate.shapes.ShapeMixture`): refine the sites by expectation
    propagation, and weight its draws to the exact posterior. A subclass has the sites
    ``x`` [K, d] and ``cov`` [K, d, d], ``sigma_points(rng)`` and ``draw(n, rng, bounds,
    points)`` returning ``(coef, sigma, theta, sigma_ess)``, ``coef`` [n, ...] the draws'
    trend coefficients in whatever form the subclass documents."""

    def refine(self, loglik, rng: np.random.Generator, bounds: np.ndarray,
               sweeps: int = EP_SWEEPS) -> None:
        """Move each year's Gaussian site towards the year's exact likelihood where the
        trend puts the year (expectation propagation, damped by half).

        Per sweep: each year's current posterior marginal ``q_k`` (moments of
        :data:`EP_DRAWS` draws) less its site is the *cavity*; the *tilted* distribution,
        cavity times the exact likelihood in the box, has its moments estimated from
        :data:`EP_POINTS` points of ``q_k`` weighted by likelihood / site; the new site is
        tilted / cavity. A year whose cavity or new site is not positive definite, or whose
        weights are too few (effective number < :data:`EP_MIN_ESS`), keeps its site.

        Parameters
        ----------
        loglik : callable, theta [m, K, d] -> [m, K]
            Each year's exact log-likelihood at its own points.
        """
        K, d = self.x.shape
        lo, hi = bounds[:, 0], bounds[:, 1]
        eye = np.eye(d)
        # sigma's posterior moves little with the sites: its points are found once here
        # (the final weights correct what is left).
        points = self.sigma_points(rng)
        for _ in range(sweeps):
            theta = self.draw(EP_DRAWS, rng, WIDE_BOX[:d], points)[2]          # [n, K, d]
            mu = theta.mean(axis=0)
            dev = theta - mu
            S = np.einsum("nki,nkj->kij", dev, dev) / (len(theta) - 1) + 1e-12 * eye
            S_inv = np.linalg.inv(S)
            H = np.linalg.inv(self.cov)
            lam_c = S_inv - H
            eta_c = np.einsum("kij,kj->ki", S_inv, mu) - np.einsum("kij,kj->ki", H, self.x)
            z = mu + np.einsum("kij,mkj->mki", np.linalg.cholesky(S),
                               rng.standard_normal((EP_POINTS, K, d)))
            dz = z - self.x
            lw = loglik(z) + 0.5 * np.einsum("mki,kij,mkj->mk", dz, H, dz)
            lw[~np.all((z >= lo) & (z <= hi), axis=2)] = -np.inf
            new_x, new_cov = self.x.copy(), self.cov.copy()
            for k in range(K):
                if not np.isfinite(lw[:, k]).any() or \
                        np.linalg.eigvalsh(lam_c[k]).min() <= 0:
                    continue
                w = np.exp(lw[:, k] - lw[:, k].max())
                w /= w.sum()
                if 1.0 / float(w @ w) < EP_MIN_ESS:
                    continue
                m = w @ z[:, k]
                e = z[:, k] - m
                St_inv = np.linalg.inv(e.T @ (e * w[:, None]))
                H_new = 0.5 * (St_inv - lam_c[k]) + 0.5 * H[k]
                if np.linalg.eigvalsh(H_new).min() <= 0:
                    continue
                eta = 0.5 * (St_inv @ m - eta_c[k]) + 0.5 * H[k] @ self.x[k]
                new_cov[k] = np.linalg.inv(H_new)
                new_x[k] = new_cov[k] @ eta
            self.x, self.cov = new_x, 0.5 * (new_cov + np.swapaxes(new_cov, 1, 2))
    def importance(self, loglik, n: int, rng: np.random.Generator, bounds: np.ndarray):
        """Draws of the exact joint posterior: ``n`` draws of this Gaussian model weighted
        by each year's exact likelihood over its site (0 outside the box), then ``n``
        resampled by their weights (systematic resampling).

        Returns
        -------
        beta, sigma, theta
            As :meth:`draw`'s, resampled.
        ess : float
            Effective number of the weighted draws (Kish); 0 when every draw left the box
            (the draws are then the Gaussian model's, held in the box).

        Each year's own effective number (its factor of the weights alone, over the draws
        in the box) is kept as :attr:`year_ess` [K], which tells the year whose site the
        draws miss (:meth:`importance_widened`).
        """
        d = self.x.shape[1]
        beta, sigma, theta, _ = self.draw(n, rng, WIDE_BOX[:d])
        dx = theta - self.x
        H = np.linalg.inv(self.cov)
        lw_k = loglik(theta) + 0.5 * np.einsum("nki,kij,nkj->nk", dx, H, dx)   # [n, K]
        inside = np.all((theta >= bounds[:, 0]) & (theta <= bounds[:, 1]), axis=(1, 2))
        self.year_ess = _kish(lw_k[inside]) if inside.any() else np.zeros(len(self.x))
        lw = np.sum(lw_k, axis=1)
        lw[~inside] = -np.inf
        if not np.isfinite(lw).any():
            # Every draw leaves the box (a unit whose inputs lie beyond it): the Gaussian
            # model's draws held in the box, with no weight behind them (effective number
            # 0: the caller marks the years unconverged).
            beta, sigma, theta, _ = self.draw(n, rng, bounds)
            return beta, sigma, theta, 0.0
        lw, _ = pareto_smooth(lw)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        # Systematic resampling, then a shuffle: the kept draws carry no order.
        idx = np.minimum(np.searchsorted(np.cumsum(w), (rng.random() + np.arange(n)) / n),
                         n - 1)
        idx = rng.permutation(idx)
        return beta[idx], sigma[idx], theta[idx], 1.0 / float(w @ w)

    def importance_widened(self, loglik, n: int, rng: np.random.Generator,
                           bounds: np.ndarray, first: tuple, mark: float) -> tuple:
        """:meth:`importance` again with the sites the draws miss widened, for a model whose
        weights stay too uneven (``first``, :meth:`importance`'s result, has fewer than
        ``mark`` effective draws).

        A year whose site sits off its likelihood's mass (at one end of a flat ridge
        between two inputs, where the Laplace point and expectation propagation can leave
        it) gives the draws a factor of the weights far more uneven than the other years'.
        Those years (their own effective number below :data:`WIDEN_BELOW` of the best
        year's, :attr:`year_ess`) get their site covariance multiplied by each of
        :data:`WIDEN_FACTORS` in turn, until ``mark`` is met. The weights stay those of
        the exact likelihood over the site in use, so the result is the same posterior,
        from a proposal that reaches the mass. The sites are left as they were.

        Returns
        -------
        tuple
            :meth:`importance`'s result with the most effective draws, ``first`` when no
            widening gives more.
        """
        best, cov = first, self.cov
        ye = getattr(self, "year_ess", None)
        if ye is None or not np.isfinite(ye).all() or ye.max() <= 0:
            return best
        off = ye < WIDEN_BELOW * ye.max()
        if not off.any():
            return best
        try:
            for f in WIDEN_FACTORS:
                wide = cov.copy()
                wide[off] *= f
                self.cov = wide
                got = self.importance(loglik, n, rng, bounds)
                if got[3] > best[3]:
                    best = got
                if best[3] >= mark:
                    break
        finally:
            self.cov = cov
            self.year_ess = ye
        return best


def _kish(lw: np.ndarray) -> np.ndarray:
    """Effective number (Kish) of each column's weights, given as their logs [n, K] -> [K]."""
    w = np.exp(lw - lw.max(axis=0))
    return w.sum(axis=0) ** 2 / np.sum(w * w, axis=0)


def pareto_smooth(lw: np.ndarray) -> tuple[np.ndarray, float]:
    """Pareto-smoothed importance weights (Vehtari, Simpson, Gelman, Yao and Gabry 2024):
    the largest ``min(n / 5, 3 sqrt(n))`` of the log-weights ``lw`` [n] (-inf allowed)
    replaced by the expected order statistics of a generalised Pareto fitted to them
    (Zhang and Stephens 2009, with their weak prior on the shape). A proposal whose tails
    are lighter than the target's (a year's likelihood along a flat ridge, beyond its
    Gaussian site) gives weights of infinite variance: their effective number is then set
    by the one or two largest, a lottery from one seed to the next. Smoothed, the tail
    keeps its mass without one draw taking it. Returns the smoothed log-weights and the
    fitted shape ``k`` (above 0.7 the estimate is not to be trusted; inf when the tail is
    too short to fit)."""
    lw = np.array(lw, float)
    fin = np.isfinite(lw)
    n = int(fin.sum())
    m = int(np.ceil(min(0.2 * n, 3.0 * np.sqrt(n))))
    if n < 10 or m < 5:
        return lw, np.inf
    top = lw.max()
    lw = lw - top
    order = np.argsort(np.where(fin, lw, -np.inf))
    # The cutoff floored where exp() still holds it (ArviZ's psislw does the same): a tail
    # 800 nats below the top is not one to fit. The tail is what lies above it (ties at the
    # cutoff are body, not zeros in the fit).
    cut = max(float(lw[order[-m - 1]]), float(np.log(np.finfo(float).tiny)))
    tail_idx = np.flatnonzero(fin & (lw > cut))
    if tail_idx.size <= 4:
        return lw + top, np.inf
    tail_idx = tail_idx[np.argsort(lw[tail_idx])]                            # ascending
    x = np.exp(lw[tail_idx]) - np.exp(cut)
    k, sigma = _gpd_fit(x)
    if np.isfinite(k) and np.isfinite(sigma) and sigma > 0:
        p = (np.arange(tail_idx.size) + 0.5) / tail_idx.size
        q = sigma * (-np.log1p(-p) if abs(k) < 1e-12 else np.expm1(-k * np.log1p(-p)) / k)
        lw[tail_idx] = np.minimum(np.log(q + np.exp(cut)), 0.0)
    return lw + top, float(k)


def _gpd_fit(x: np.ndarray) -> tuple[float, float]:
    """Shape and scale of a generalised Pareto fitted to ``x`` (ascending, > 0) by Zhang and
    Stephens' (2009) empirical Bayes estimate, the shape shrunk towards 0.5 (PSIS's prior)."""
    n = len(x)
    n_b = 30 + int(np.sqrt(n))
    b = 1.0 - np.sqrt(n_b / (np.arange(1, n_b + 1) - 0.5))
    b = b / (3.0 * x[int(n / 4 + 0.5) - 1]) + 1.0 / x[-1]
    k = np.log1p(-b[:, None] * x).mean(axis=1)
    ll = n * (np.log(-b / k) - k - 1.0)
    w = 1.0 / np.exp(ll - ll[:, None]).sum(axis=1)
    keep = w >= 10 * np.finfo(float).eps
    w, b = w[keep] / w[keep].sum(), b[keep]
    b_post = float(np.sum(b * w))
    if not np.isfinite(b_post) or b_post == 0:
        return np.inf, np.nan               # no fit: the caller keeps the raw weights
    k_post = float(np.log1p(-b_post * x).mean())
    sigma = -k_post / b_post
    k_post = (n * k_post + 10 * 0.5) / (n + 10)
    return k_post, sigma


@dataclass
class GaussianTrend(SiteModel):
    """One unit's trend model on its years' summaries.

    Attributes
    ----------
    x : ndarray, shape [K, d]
        The years' maximum-likelihood points (input units).
    cov : ndarray, shape [K, d, d]
        Their Laplace covariances.
    Mk : ndarray, shape [K, d, n_beta]
        The trend's design per year (``theta_k = Mk[k] @ beta``).
    prior_prec : ndarray, shape [n_beta] or [n_beta, n_beta]
        Gaussian prior precision of beta: per coefficient (0: flat, the levels), or a whole
        matrix (a shape's extra coefficients, :mod:`.shapes`); zero rows are flat.
    prior_mean : ndarray, shape [n_beta]
    A : ndarray, shape [d]
        Scale of sigma's half-Cauchy prior (input units).
    """

    x: np.ndarray
    cov: np.ndarray
    Mk: np.ndarray
    prior_prec: np.ndarray
    prior_mean: np.ndarray
    A: np.ndarray

    def __post_init__(self):
        P0 = np.asarray(self.prior_prec, float)
        self.prior_P = P0 if P0.ndim == 2 else np.diag(P0)
        # The proper part's normalisation, so that the marginal likelihoods of models that
        # share their flat coefficients compare (:meth:`sigma_points`' log evidence).
        proper = np.diag(self.prior_P) > 0
        m0 = np.asarray(self.prior_mean, float)
        self._log_norm = 0.5 * (np.linalg.slogdet(self.prior_P[np.ix_(proper, proper)])[1]
                                - m0 @ self.prior_P @ m0)

    def _conditional(self, sigma: np.ndarray, want_mean: bool = True,
                     weights: tuple | None = None):
        """beta's Gaussian conditional and sigma's log marginal likelihood at sigma points
        ``sigma`` [P, d]: (precision [P, nb, nb], its Cholesky factor, mean [P, nb] or None,
        log-likelihood [P]) (:func:`linear_gaussian`). ``weights``: the years'
        :func:`year_weights` at ``sigma`` when already computed."""
        Wf, logdet_v = year_weights(self.cov, sigma) if weights is None else weights
        out = linear_gaussian(Wf, logdet_v, self.Mk[None], self.x, self.prior_P[None],
                              np.asarray(self.prior_mean, float)[None],
                              np.array([self._log_norm]), want_mean)
        return tuple(None if a is None else a[0] for a in out)

    def _sigma(self, u: np.ndarray) -> np.ndarray:
        return self.A * np.tan(0.5 * np.pi * u)

    def sigma_points(self, rng: np.random.Generator, start=None, first=None, first_ll=None
                     ) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Weighted sigma points of sigma's posterior (the module docstring): points [P, d],
        normalised weights [P], their effective number, and the log evidence: the log
        marginal likelihood of the sites under this model, up to a constant shared by
        models with the same flat coefficients (sigma's prior is uniform in ``u``, so it
        is the volume of the last round's box times the mean likelihood there).

        The rounds start from ``start`` (a box ``(lo, hi)`` in ``u``), else from this model's
        last box (:attr:`box`, kept between calls: the sites move little from one call to
        the next), else from the whole prior; a start box that cuts off weight (a point
        within a spacing of an inner face holding more than ``SIGMA_EDGE`` of the largest
        weight) is dropped for the whole prior. ``first``: the first round's sigma points
        [P, d], spread evenly over ``start`` (another model's last round: models whose sigma
        agree then cost one evaluation of them); ``first_ll``: this model's log-likelihood
        at them [P], when already evaluated (:func:`log_evidence_at`, with other models)."""
        from scipy.stats import qmc
        d = self.x.shape[1]
        whole = (np.zeros(d), np.ones(d))
        lo, hi = start if start is not None else getattr(self, "box", whole)
        for r in range(SIGMA_ROUNDS):
            if r == 0 and first is not None:
                sigma = first
                u = 2.0 / np.pi * np.arctan(sigma / self.A)
            else:
                seed = int(rng.integers(2 ** 31))
                u = lo + (hi - lo) * qmc.Sobol(d, scramble=True, seed=seed).random(SIGMA_POINTS)
                u = np.minimum(u, 1.0 - 1e-12)
                sigma = self._sigma(u)
            ll = (first_ll if r == 0 and first is not None and first_ll is not None
                  else self._conditional(sigma, want_mean=False)[3])
            w = np.exp(ll - ll.max())
            log_z = float(ll.max() + np.log(w.mean()) + np.log(np.prod(hi - lo)))
            w /= w.sum()
            n_eff = 1.0 / float(np.sum(w * w))
            pad = (hi - lo) * SIGMA_POINTS ** (-1.0 / d)
            near = ((u - lo < pad) & (lo > 0)) | ((hi - u < pad) & (hi < 1))
            near = near.any(axis=1)
            if near.any() and w[near].max() > SIGMA_EDGE * w.max():
                # The box cuts the mass off: start again from the whole prior.
                lo, hi = whole
                continue
            # Another model's points are taken at half the mark: they were zoomed to its
            # mass, which lies close (their weights are still exact importance weights).
            if n_eff >= (SIGMA_ESS / 2 if r == 0 and first is not None else SIGMA_ESS):
                break
            # Zoom in on the mass: the box of the points that carry weight, one point
            # spacing wider on each side (the prior is uniform in u, so each round is
            # importance sampling on its own box).
            keep = u[w >= SIGMA_KEEP * w.max()]
            lo = np.maximum(keep.min(axis=0) - pad, 0.0)
            hi = np.minimum(keep.max(axis=0) + pad, 1.0)
        self.box = (lo, hi)
        return sigma, w, n_eff, log_z

    def draw(self, n: int, rng: np.random.Generator, bounds: np.ndarray, points=None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``n`` independent posterior draws (sigma from ``points``, an earlier
        :meth:`sigma_points`' result, when given).

        Returns
        -------
        beta : ndarray, shape [n, n_beta]
        sigma : ndarray, shape [n, d]
        theta : ndarray, shape [n, K, d]
            The years' inputs, inside ``bounds`` (module docstring).
        sigma_ess : float
            Effective number of the sigma points behind the draws.
        """
        beta, sigma, n_eff = self.draw_trend(n, rng, points)
        m = np.einsum("kia,na->nki", self.Mk, beta)                           # [n, K, d]
        return beta, sigma, draw_years(self.x, self.cov, m, sigma, rng, bounds), n_eff

    def draw_trend(self, n: int, rng: np.random.Generator, points=None
                   ) -> tuple[np.ndarray, np.ndarray, float]:
        """The trend part of :meth:`draw`: ``beta`` [n, n_beta], ``sigma`` [n, d] and the
        sigma points' effective number (the years: :func:`draw_years`)."""
        pts, w, n_eff = (self.sigma_points(rng) if points is None else points)[:3]
        pick = rng.choice(len(w), size=n, p=w)
        uniq, inv = np.unique(pick, return_inverse=True)
        sigma_u = pts[uniq]
        Pb, Lb, mean, _ = self._conditional(sigma_u)
        # beta = mean + Lb^-T z: covariance Pb^-1. Lb is inverted once per distinct sigma
        # point (a few hundred), not solved once per draw (thousands).
        z = rng.standard_normal((n, mean.shape[1]))
        beta = mean[inv] + np.einsum("nba,nb->na", np.linalg.inv(Lb)[inv], z)
        return beta, sigma_u[inv], n_eff


def draw_years(x: np.ndarray, cov: np.ndarray, m: np.ndarray, sigma: np.ndarray,
               rng: np.random.Generator, bounds: np.ndarray) -> np.ndarray:
    """The years' inputs given the trend: per draw and year, the site ``N(x_k; theta_k,
    C_k)`` times ``N(theta_k; m_k, diag(sigma^2))``, held in ``bounds`` [d, 2] (a draw
    outside is drawn again :data:`BOX_TRIES` times, then clipped).

    Parameters
    ----------
    x, cov : ndarray, shapes [K, d], [K, d, d]
        The sites.
    m : ndarray, shape [n, K, d]
        Each draw's trend at the years.
    sigma : ndarray, shape [n, d]

    Returns
    -------
    ndarray, shape [n, K, d]
    """
    d = x.shape[1]
    H = np.linalg.inv(cov)                                                    # [K, d, d]
    S_inv = 1.0 / sigma ** 2                                                  # [n, d]
    G, Lg = inv_chol(H[None] + S_inv[:, None, :, None] * np.eye(d))          # [n, K, d, d]
    hx = np.einsum("kij,kj->ki", H, x)
    mu = np.einsum("nkij,nkj->nki", G, hx[None] + S_inv[:, None, :] * m)
    lo, hi = bounds[:, 0], bounds[:, 1]
    theta = np.empty_like(mu)
    todo = np.ones(mu.shape[:2], bool)
    for _ in range(BOX_TRIES):
        e = rng.standard_normal(mu.shape)
        t = mu + np.einsum("nkij,nkj->nki", Lg, e)
        take = todo & np.all((t >= lo) & (t <= hi), axis=2)
        theta[take] = t[take]
        todo &= ~take
        if not todo.any():
            break
    if todo.any():
        theta[todo] = np.clip(t[todo], lo, hi)
    return theta
