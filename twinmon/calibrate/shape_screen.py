"""The evidence screen of the trend shapes' extra columns (:mod:`.shapes`): the log
evidence of the line plus each of many sets of extra columns, integrated over sigma on a
grid, by block updates of the line's posterior instead of one model per set.

The change shape's combinations (each input's change in a year of its own: 25 for two inputs
with five candidate years each) are weighed here before any model is built, so that only
those worth their sigma points and draws are (:func:`~.shape_columns._change_selection`).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .gaussian_trend import GaussianTrend, linear_gaussian, year_weights
from .stacked import forward_solve, small_cholesky

#: Sigma points (and the seed of their quasi-random set) on which the change's
#: combinations are screened (:func:`screen_grid`).
SCREEN_POINTS = 64
SCREEN_SEED = 20


def screen(line: GaussianTrend, E: np.ndarray, S: np.ndarray, grid: tuple,
           weights: tuple | None = None):
    """The log evidence of the line plus sets of extra columns, integrated over sigma on a
    grid, without building the models: at each sigma point the line's posterior is
    computed once, and a set's columns add a block-update of its marginal likelihood,

        log p(x | line + e) - log p(x | line) = 0.5 log|P_e| - 0.5 log|P_e + F| +
                                               0.5 r' (P_e + F)^-1 r,

    with ``F`` the columns' information given the line's coefficients, ``r`` their score at
    the line's posterior mean and ``P_e`` their prior precision (the same as the models'
    :func:`~.gaussian_trend.linear_gaussian`, checked in tests/unit/test_calibrate_shapes.py).

    Parameters
    ----------
    line : GaussianTrend
    E : ndarray, shape [K, d, n_x]
        Every extra column.
    S : ndarray, shape [n_x, n_x]
        Their prior precision (a set's is its rows and columns).
    grid : (sigma [P, d], log_weight [P])
        :func:`screen_grid`.
    weights : (Wf [P, K d d], logdet_v [P]), optional
        :func:`~.gaussian_trend.year_weights` of the line's sites at ``grid``'s sigma, when
        already computed.

    Returns
    -------
    callable, list of column-index lists, all of one length -> ndarray [n_sets]
        Each set's log evidence up to a constant shared by every set (the empty set: the
        line's).
    """
    sigma, log_w = grid
    bt = block_terms(line, E, sigma, weights=weights)
    ll = bt.ll + log_w

    def evidence(sets: list) -> np.ndarray:
        idx = np.array(sets, dtype=int).reshape(len(sets), -1)               # [G, n_e]
        out = ll[None] if idx.shape[1] == 0 else set_loglik(bt, S, idx, ll)[0]
        top = out.max(axis=1, keepdims=True)
        return top[:, 0] + np.log(np.exp(out - top).sum(axis=1))

    return evidence


@dataclass
class BlockTerms:
    """The line's posterior at sigma points and what extra columns add to it (:func:`block_terms`).

    Attributes
    ----------
    Pb : ndarray, shape [P, n_l, n_l]
        The line's coefficients' posterior precision at each sigma point.
    mu : ndarray, shape [P, n_l]
        Their posterior mean.
    ll : ndarray, shape [P]
        The line's log marginal likelihood (:func:`~.gaussian_trend.linear_gaussian`'s).
    F : ndarray, shape [P, n_x, n_x]
        The columns' information given the line's coefficients.
    r : ndarray, shape [P, n_x]
        Their score at the line's posterior mean.
    PiB : ndarray, shape [P, n_l, n_x]
        ``Pb^-1 B``, ``B`` the cross information of the line's coefficients and the columns:
        a set ``e`` of columns moves the line's mean by ``-PiB[:, e] mu_e``.
    """

    Pb: np.ndarray
    mu: np.ndarray
    ll: np.ndarray
    F: np.ndarray
    r: np.ndarray
    PiB: np.ndarray


def block_terms(line: GaussianTrend, E: np.ndarray, sigma: np.ndarray,
                post: tuple | None = None, weights: tuple | None = None) -> BlockTerms:
    """The line's posterior at sigma points ``sigma`` [P, d] and the block-update terms of
    extra columns ``E`` [K, d, n_x] (:func:`screen`'s formula): with a set ``e`` of them
    and its prior precision ``P_e``, ``V = P_e + F_ee`` is the set's posterior precision
    given the line's, ``V^-1 r_e`` its mean. ``post``: the line's ``(Pb, mu, ll)`` at
    ``sigma`` when already computed (``line._conditional(sigma)``'s); ``weights``: the
    years' ``(Wf, logdet_v)`` at ``sigma`` when already computed
    (:func:`~.gaussian_trend.year_weights`'s)."""
    Wf, logdet_v = year_weights(line.cov, sigma) if weights is None else weights
    K, d, n_l = line.Mk.shape
    if post is None:
        Pb, _, mu, ll = linear_gaussian(Wf, logdet_v, line.Mk[None], line.x,
                                        line.prior_P[None],
                                        np.asarray(line.prior_mean, float)[None],
                                        np.array([line._log_norm]))
        post = Pb[0], mu[0], ll[0]                                           # [P, ...]
    Pb, mu, ll = post
    P, n_x = len(sigma), E.shape[2]
    # Sums over (year, input) as matrix products of the flattened arrays.
    WE = np.matmul(Wf.reshape(P, K, d, d), E).reshape(P, K * d, n_x)        # [P, K d, n_x]
    D = np.matmul(E.reshape(K * d, n_x).T, WE)
    B = np.matmul(line.Mk.reshape(K * d, n_l).T, WE)                         # [P, n_l, n_x]
    PiB = np.linalg.solve(Pb, B)
    F = D - np.matmul(np.swapaxes(B, 1, 2), PiB)
    resid = (line.x[None] - np.einsum("kia,pa->pki", line.Mk, mu)).reshape(P, 1, K * d)
    r = np.matmul(resid, WE)[:, 0]                                           # [P, n_x]
    return BlockTerms(Pb, mu, ll, F, r, PiB)


def set_loglik(bt: BlockTerms, S: np.ndarray, idx: np.ndarray,
               base: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The log marginal likelihood of the line plus each set of columns ``idx`` [G, n_e]
    (n_e >= 1) at the sigma points of ``bt`` (P of them), a set's prior precision the rows
    and columns of ``S`` (:func:`screen`'s formula).

    Returns
    -------
    ll : ndarray, shape [G, P]
        ``base`` [P] (default the line's, ``bt.ll``) plus each set's block update: what
        :func:`~.gaussian_trend.linear_gaussian` gives the set's model of its own.
    L : ndarray, shape [G, P, n_e, n_e]
        Cholesky factor of the sets' posterior precision given the line's coefficients,
        ``V = L L'``.
    z : ndarray, shape [G, P, n_e]
        ``L^-1 r_e``, ``r_e`` the sets' scores at the line's posterior mean (``L'^-1 z``:
        their posterior mean).
    """
    base = bt.ll if base is None else base
    P_e = S[idx[:, :, None], idx[:, None, :]]                                # [G, n_e, n_e]
    V = P_e[:, None] + np.swapaxes(bt.F[:, idx[:, :, None], idx[:, None, :]], 0, 1)
    r_e = np.swapaxes(bt.r[:, idx], 0, 1)
    L = small_cholesky(V)                                                    # [G, P, n_e, n_e]
    z = forward_solve(L, r_e[..., None])[..., 0]
    ll = base[None] + 0.5 * (np.linalg.slogdet(P_e)[1][:, None]
                             - 2.0 * np.log(np.einsum("gpii->gpi", L)).sum(axis=2)
                             + np.sum(z * z, axis=2))
    return ll, L, z


def screen_grid(A: np.ndarray, n: int = SCREEN_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Sigma points of the change's screen [n, d] (input units), quasi-random and
    log-uniform from ``A / 100`` to ``3 A`` per input (``A`` [d], sigma's prior scale), and
    their log weights [n]: the half-Cauchy prior's density in log sigma, so that a model's
    ``logsumexp(log-likelihood + weight)`` is its log evidence up to a constant shared by
    the models screened together."""
    u = sobol_points(len(A), n, SCREEN_SEED)
    A = np.asarray(A, float)
    lo, hi = np.log(A / 100), np.log(3 * A)
    sigma = np.exp(lo + (hi - lo) * u)
    return sigma, np.sum(np.log(sigma) - np.log1p((sigma / A) ** 2), axis=1)


@lru_cache(maxsize=8)
def sobol_points(d: int, n: int, seed: int) -> np.ndarray:
    """Scrambled Sobol points in the unit cube [n, d], read-only: a grid that is the same
    for every unit is built once per process (scrambling costs about a millisecond)."""
    from scipy.stats import qmc
    u = qmc.Sobol(d, scramble=True, seed=seed).random(n)
    u.flags.writeable = False
    return u
