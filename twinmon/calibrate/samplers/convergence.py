"""The vectorised sequential sampler's stopping rule: when to look at a unit-year's chains,
how many steps to add when they missed the marks, and their rank-normalised split R-hat and
bulk ESS computed as array operations (the values of :mod:`~twinmon.calibrate.diagnostics`).
"""
from __future__ import annotations

import math

import numpy as np

from ...config import Config
from ..diagnostics import _z_scale


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


def more_steps(cfg: Config, n: int, rhat: np.ndarray, n_eff: np.ndarray, cap: int) -> int:
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


def _ess_z(x: np.ndarray) -> float:
    """:func:`.diagnostics.ess` of already split, rank-normalised chains [m, n], with
    Geyer's initial positive and monotone sequences as array operations (the same values,
    summed in the same order, as the reference's loop over lags)."""
    from ..diagnostics import _autocov
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


def diagnostics(draws: np.ndarray, need_rhat: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Rank-normalised split R-hat and bulk ESS per input of one unit-year's chains
    [C, N, d]: the values of :func:`.diagnostics.split_rhat` and
    :func:`.diagnostics.ess` (``rank_normalize=True``), sharing the ranks they both take.
    Without ``need_rhat`` the R-hat is NaN (not computed)."""
    from ..diagnostics import _rhat, _split
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


def converged(draws: np.ndarray, cfg: Config) -> tuple[bool, np.ndarray, np.ndarray]:
    """R-hat and bulk ESS per input of one unit-year's chains [C, N, d] (see
    :func:`diagnostics`), and whether they meet the config's marks. The R-hat is only
    computed once the ESS is met (until then the chains run on anyway)."""
    cc = cfg.calibrate
    _, n_eff = diagnostics(draws, need_rhat=False)
    if not np.all(n_eff >= cc.ess_warn):
        return False, np.full(len(n_eff), np.nan), n_eff
    rhat, n_eff = diagnostics(draws)
    return bool(np.all(rhat <= cc.rhat_warn)), rhat, n_eff
