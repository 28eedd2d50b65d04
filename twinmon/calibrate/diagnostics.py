"""Convergence diagnostics (Vehtari, Gelman, Simpson, Carpenter, Buerkner 2021), and the runs
of years their warnings name."""
from __future__ import annotations

import numpy as np


def _split(chains: np.ndarray) -> np.ndarray:
    """[..., m, n] -> [..., 2m, n//2]: each chain cut in halves, so drifts within a chain
    show."""
    chains = np.atleast_2d(np.asarray(chains, float))
    n = chains.shape[-1]
    half = n // 2
    return np.concatenate([chains[..., :half], chains[..., n - half:]], axis=-2)


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of all values of ``x`` (ties get their average rank), shape of ``x``: what
    ``scipy.stats.rankdata(method="average")`` gives, bit for bit (the averages are halves,
    exact in floating point), from one stable sort and about three times faster: a chain
    repeats every rejected draw and importance resampling repeats draws, so ties are the
    rule."""
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
    """Rank-normalisation: ranks over all draws mapped to normal scores."""
    from scipy.special import ndtri
    return ndtri((_average_ranks(x) - 0.375) / (x.size + 0.25))


def _rhat(chains: np.ndarray) -> float:
    m, n = chains.shape
    within = np.mean(np.var(chains, axis=1, ddof=1))
    between = n * np.var(np.mean(chains, axis=1), ddof=1)
    if within <= 0:
        return float("nan")
    return float(np.sqrt((between / within + n - 1) / n))


def split_rhat(chains: np.ndarray, rank_normalize: bool = True) -> float:
    """Split R-hat of one scalar quantity.

    Parameters
    ----------
    chains : ndarray, shape [m, n]
        ``m`` chains of ``n`` post-burn-in draws.
    rank_normalize : bool
        True: the rank-normalised R-hat of Vehtari et al. (2021), the larger of the bulk
        (ranks) and tail (ranks of ``|x - median|``) values; False: the classic split R-hat.

    Returns
    -------
    float
        Near 1 when the chains agree; > 1.01-1.05 signals poor mixing.
    """
    chains = np.atleast_2d(np.asarray(chains, float))
    if not rank_normalize:
        return float("nan") if np.ptp(chains) == 0 else _rhat(_split(chains))
    return float(split_rhat_many(chains[None])[0])


def _z_scale_rows(x: np.ndarray) -> np.ndarray:
    """:func:`_z_scale` of each ``x[b]`` [B, ...] on its own, in one sort: the same values,
    bit for bit (the ranks are found within each row as :func:`_average_ranks` finds them)."""
    from scipy.special import ndtri
    B = x.shape[0]
    flat = x.reshape(B, -1)
    N = flat.shape[1]
    # Ties share their group's average rank whatever their order within it, so an
    # unstable sort (twice as fast as a stable one here) gives the same ranks.
    order = np.argsort(flat, axis=1)
    srt = np.take_along_axis(flat, order, axis=1)
    new = np.empty((B, N), bool)
    new[:, 0] = True
    np.not_equal(srt[:, 1:], srt[:, :-1], out=new[:, 1:])
    # Groups of ties over the rows laid end to end: a row's first value always opens one.
    starts = np.flatnonzero(new.ravel())
    ends = np.append(starts[1:], B * N)
    offset = (starts // N) * N
    avg = ((starts - offset) + (ends - offset) + 1) / 2.0
    # Normal scores per group of ties, then spread to its members (resampled draws repeat).
    score = ndtri((avg - 0.375) / (N + 0.25))
    z = np.empty((B, N))
    np.put_along_axis(z, order, score[np.cumsum(new.ravel()) - 1].reshape(B, N), axis=1)
    return z.reshape(x.shape)


def _rhat_rows(chains: np.ndarray) -> np.ndarray:
    """:func:`_rhat` of each ``chains[b]`` [B, m, n]: [B] (NaN where the within-chain
    variance is 0)."""
    n = chains.shape[2]
    within = np.mean(np.var(chains, axis=2, ddof=1), axis=1)
    between = n * np.var(np.mean(chains, axis=2), axis=1, ddof=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt((between / within + n - 1) / n)
    return np.where(within > 0, r, np.nan)


def split_rhat_many(chains: np.ndarray) -> np.ndarray:
    """:func:`split_rhat` (rank-normalised) of many scalar quantities at once: the larger of
    the bulk and tail R-hats of each, NaN for a constant one. A unit's years and inputs are
    dozens of quantities, and a call each cost more than the arithmetic.

    Parameters
    ----------
    chains : ndarray, shape [..., m, n]
        ``m`` chains of ``n`` draws of each quantity.

    Returns
    -------
    ndarray, shape [...]
    """
    x = np.asarray(chains, float)
    lead, (m, n) = x.shape[:-2], x.shape[-2:]
    x = x.reshape(-1, m, n)
    out = np.full(len(x), np.nan)
    live = np.ptp(x.reshape(len(x), -1), axis=1) != 0
    if not live.any():
        return out.reshape(lead)
    x = x[live]
    bulk = _rhat_rows(_z_scale_rows(_split(x)))
    folded = np.abs(x - np.median(x.reshape(len(x), -1), axis=1)[:, None, None])
    spread = np.ptp(folded.reshape(len(x), -1), axis=1) > 0
    tail = bulk.copy()
    if spread.any():
        tail[spread] = _rhat_rows(_z_scale_rows(_split(folded[spread])))
    # max() of two floats as split_rhat takes it: a NaN bulk gives NaN, a NaN tail the bulk.
    out[live] = np.where(np.isnan(bulk) | ~(tail > bulk), bulk, tail)
    return out.reshape(lead)


def _autocov(x: np.ndarray) -> np.ndarray:
    """Biased autocovariance of each row, shape [m, n], by FFT."""
    m, n = x.shape
    xc = x - x.mean(axis=1, keepdims=True)
    size = 1 << (2 * n - 1).bit_length()
    f = np.fft.rfft(xc, size, axis=1)
    return np.fft.irfft(f * np.conj(f), size, axis=1)[:, :n] / n


def ess(chains: np.ndarray, rank_normalize: bool = False) -> float:
    """Effective sample size of one scalar quantity over all chains.

    Autocorrelations combine the chains as in Stan/ArviZ and are summed with Geyer's initial
    monotone sequence. ``rank_normalize=True`` gives the bulk ESS of Vehtari et al. (2021)
    (split chains, ranks); False the plain ESS of the values (use it for the Monte Carlo
    standard error of the mean: ``sd / sqrt(ess)``).

    Parameters
    ----------
    chains : ndarray, shape [m, n]

    Returns
    -------
    float
        Between ~0 and ``m * n`` (more for antithetic chains).
    """
    x = np.atleast_2d(np.asarray(chains, float))
    if rank_normalize:
        x = _z_scale(_split(x))
    m, n = x.shape
    if np.ptp(x) == 0 or n < 4:
        return float("nan")
    acov = _autocov(x)
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n
    if m > 1:
        var_plus += np.var(x.mean(axis=1), ddof=1)
    rho = np.zeros(n)
    rho_even = 1.0
    rho[0] = rho_even
    rho_odd = 1.0 - (mean_var - np.mean(acov[:, 1])) / var_plus
    rho[1] = rho_odd
    # Geyer's initial positive sequence: sum pairs while their sum stays positive.
    t = 1
    while t < n - 3 and rho_even + rho_odd > 0.0:
        rho_even = 1.0 - (mean_var - np.mean(acov[:, t + 1])) / var_plus
        rho_odd = 1.0 - (mean_var - np.mean(acov[:, t + 2])) / var_plus
        if rho_even + rho_odd >= 0:
            rho[t + 1] = rho_even
            rho[t + 2] = rho_odd
        t += 2
    max_t = t - 2
    if rho_even > 0:
        rho[max_t + 1] = rho_even
    # Geyer's initial monotone sequence: pair sums may not increase.
    t = 1
    while t <= max_t - 2:
        if rho[t + 1] + rho[t + 2] > rho[t - 1] + rho[t]:
            rho[t + 1] = (rho[t - 1] + rho[t]) / 2.0
            rho[t + 2] = rho[t + 1]
        t += 2
    total = m * n
    tau = -1.0 + 2.0 * np.sum(rho[:max_t + 1]) + np.sum(rho[max_t + 1:max_t + 2])
    tau = max(tau, 1.0 / np.log10(total))
    return float(total / tau)


def year_ranges(years) -> str:
    """Years as runs: ``[1, 2, 3, 5, 7, 8]`` -> ``"1-3, 5, 7-8"``."""
    out, run = [], []
    for y in (int(v) for v in years):
        if run and y != run[-1] + 1:
            out.append(run)
            run = []
        run.append(y)
    if run:
        out.append(run)
    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in out)
