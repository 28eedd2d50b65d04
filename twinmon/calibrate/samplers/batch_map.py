"""The MAP point and Laplace approximation of many units' same-year posteriors at once, for
the vectorised sequential sampler.

:func:`batch_map` runs a projected Levenberg-Marquardt on every unit's standardised residuals
at once (the least squares :func:`~twinmon.calibrate.density.find_map` solves one unit at a
time), from the same start; the Laplace covariance is the same Gauss-Newton one.
:func:`laplace_logpdf` is the Gaussian that screens proposals in the delayed acceptance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Batch:
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


def batch_map(predict, batch: Batch, uniform: np.ndarray, max_iter: int = 60,
              start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """MAP point and Laplace covariance of every unit of a batch.

    The start is :func:`.density.find_map`'s (best point of a 21^d grid over the box for a
    uniform prior, the prior centre otherwise); then a projected Levenberg-Marquardt on the
    standardised residuals (plus the prior's), each unit on its own until its step is below
    1e-10 of the box or its cost stops falling. Covariance: the inverse Gauss-Newton
    Hessian ``J'J + prior precision + diag(1/range^2)`` at the MAP, as ``find_map``'s.

    Parameters
    ----------
    predict : callable, X [m, d] -> [m, n_out]
    batch : Batch
    uniform : ndarray of bool, shape [U]
        Units whose prior is uniform.
    start : ndarray, shape [U, d], optional
        Where to start instead (a MAP found before under a slightly different
        likelihood): no grid.

    Returns
    -------
    x_map : ndarray, shape [U, d]
    cov : ndarray, shape [U, d, d]
    """
    U, d = batch.centre.shape
    lo, hi = batch.lo, batch.hi
    span = hi - lo
    x = np.clip(batch.centre.copy() if start is None else np.asarray(start, float), lo, hi)
    if start is None and uniform.any():
        axes = [np.linspace(a, b, 21) for a, b in zip(lo, hi)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, d)
        # The grid's transients do not depend on the unit: predicted once. Per unit, the
        # same arithmetic as Batch.logpost (a uniform prior adds 0 inside the box).
        g_pred = predict(grid)
        for u in np.flatnonzero(uniform):
            r = batch.y[u] - g_pred
            lp = -0.5 * np.sum(r * r * batch.w[u], axis=1)
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


def laplace_logpdf(X: np.ndarray, m: np.ndarray, prec: np.ndarray, lo: np.ndarray,
                    hi: np.ndarray) -> np.ndarray:
    """Log-density (unnormalised) of the Laplace approximation, per row: ``-1/2 (x - m)'
    P (x - m)``, ``-inf`` outside the box. X, m [r, d]; prec [r, d, d]."""
    dx = X - m
    out = -0.5 * np.einsum("ri,rij,rj->r", dx, prec, dx)
    out[~np.all((X >= lo) & (X <= hi), axis=1)] = -np.inf
    return out
