"""The trend shapes' extra columns on a unit's line (:mod:`.shapes`): the accelerating
forms, the change's candidate years and the combinations its evidence screen keeps
(:func:`~.shape_screen.screen`), each block's Zellner unit-information prior, and the shapes
as sets of columns (:func:`shape_sets`) for a caller that weighs them by block updates of
the line's posterior instead of a model each (the one-year-ahead check of
:mod:`twinmon.forecast.trendfit`). :func:`~.shapes.build_shapes` builds a model per shape
from the same pieces.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations, product

import numpy as np

from .gaussian_trend import GaussianTrend
from .shape_screen import screen, screen_grid

#: Fewest years of a segment on which acceleration is modelled (a quadratic on fewer is
#: the noise's).
ACCELERATING_MIN_YEARS = 5
#: Fewest years of the segment before a change and from it.
CHANGE_MIN_YEARS = 3
#: Shapes less probable than this share of the best one on the sites are dropped.
OCCAM = 1e-4
#: Most combinations of the inputs' change years weighed in full; beyond (three inputs or
#: more), each input keeps its ``CHANGE_SCREEN`` most probable years (its change alone).
CHANGE_COMBOS = 64
CHANGE_SCREEN = 2
#: Growth rates (per year) of the accelerating shape's exponential forms, from a doubling
#: time of 7 years to one of 1.4 (slower growth is the quadratic's), spaced so that a
#: rate between two of them is still covered (tests/unit/test_calibrate_shapes.py).
GROWTH_RATES = (0.1, 0.2, 0.3, 0.4, 0.5)
#: Exponents of the accelerating shape's power-law forms ``c a^b``, ``a`` the age from the
#: segment's first year: wear that accelerates less than a quadratic, whose curvature a
#: decade shows falling (a quadratic fitted to it keeps the record's mean curvature and
#: runs ahead of it in the forecast).
POWER_EXPONENTS = (1.25, 1.5, 1.75)
#: The accelerating shape's forms, in their order, by their growth (``trend/growth``): the
#: quadratic 0, each exponential its rate, each power law minus its exponent.
ACCELERATING_GROWTHS = (0.0,) + GROWTH_RATES + tuple(-b for b in POWER_EXPONENTS)
#: Rows of a shape's map to the trend at the last year (``Shape.now``, ``trend/now``).
NOW_ROWS = ("level", "rate", "curvature", "growth_amplitude")


@dataclass
class ShapeSets:
    """A unit's shapes as sets of extra columns on its line, without a model each: what
    :func:`build_shapes` would build, for a caller that weighs them by block updates of the
    line's posterior (the one-year-ahead check of :mod:`twinmon.forecast.trendfit`).

    Attributes
    ----------
    E : ndarray, shape [K, d, n_x]
        Every extra column: the accelerating forms' first, then two per change block.
    now : ndarray, shape [4, d, n_x]
        Each column's map to the trend at the last year (:data:`NOW_ROWS`).
    growth : ndarray, shape [n_x]
        Each column's growth rate (an exponential form's, else 0), for :func:`extend`.
        A power form's column is 0 here: its map extends it by its quadratic at the last
        year.
    S : ndarray, shape [n_x, n_x]
        The columns' Zellner prior precision at the reference sigma; a set's prior is its
        rows and columns (the Schur complement of the line's information restricted to a
        set is the restriction of the whole one's).
    line_log_prior : float
        -inf when the line has prior 0 (it is then only the others' base).
    sets : list of (code, columns, log_prior, change_years)
        The other shapes: their code (:data:`SHAPES`), column indices into ``E``, log prior
        and, for a change, each input's year (-1: none).
    """

    E: np.ndarray
    now: np.ndarray
    growth: np.ndarray
    S: np.ndarray
    line_log_prior: float
    sets: list


def shape_sets(line: GaussianTrend, years: np.ndarray, last_start: np.ndarray, priors: dict,
               sigma_ref: np.ndarray, screen_weights: tuple | None = None) -> ShapeSets:
    """:func:`~.shapes.build_shapes`' shapes on ``line`` (its sites, design and priors), as sets of
    columns (:class:`ShapeSets`): the same accelerating forms, change candidates and
    screened combinations, at the reference sigma ``sigma_ref`` [d]. ``screen_weights``:
    the sites' :func:`~.gaussian_trend.year_weights` at the change screen's sigma points
    (:func:`~.shape_screen.screen_grid` of ``line.A``) when already computed."""
    t = np.asarray(years, float)
    K, d, _ = line.Mk.shape
    seg = t[None, :] >= np.asarray(last_start, float)[:, None]
    total = sum(max(float(p), 0.0) for p in priors.values())
    p_line = priors.get("line", 0.0) / total
    lp_line = float(np.log(p_line)) if p_line > 0 else -np.inf
    extras = _accelerating_forms(t, seg, priors, total)
    p_change = priors.get("change", 0.0) / total
    cand = _change_candidates(t, seg, p_change)
    cols = [c for _, f, _, _ in extras for c in f]
    sets, at = [], 0
    for code, f, log_prior, _ in extras:
        sets.append((code, tuple(range(at, at + len(f))), log_prior, (-1,) * d))
        at += len(f)
    growth = [max(r, 0.0) for _, f, _, r in extras for _ in f]
    prior_prec = np.diag(line.prior_P)
    if cols or any(cand):
        W = _reference_weights(line.cov, sigma_ref)
    if any(cand):
        E, S, blocks, bcols, kept = _change_selection(
            line, lp_line, [(f, lp) for _, f, lp, _ in extras], cand, t, seg,
            np.log(p_change), W, prior_prec, line.A, screen_weights)
        cols += [c for pair in bcols for c in pair]
        growth += [0.0] * (2 * len(blocks))
        for combo, log_prior, when in kept:
            sets.append((2, tuple(at + 2 * b + c for b in combo for c in (0, 1)), log_prior,
                         when))
    elif cols:
        E = np.stack([c for c, _, _ in cols], axis=2)
        S = _unit_information(W, line.Mk, E, prior_prec, K)
    else:
        E, S = np.zeros((K, d, 0)), np.zeros((0, 0))
    now = np.zeros((len(NOW_ROWS), d, len(cols)))
    for j, (_, i, g) in enumerate(cols):
        now[:, i, j] = g
    return ShapeSets(E, now, np.array(growth, float), S, lp_line, sets)


def _accelerating_forms(t: np.ndarray, seg: np.ndarray, priors: dict, total: float) -> list:
    """The accelerating shape's forms on the inputs' current segments ``seg`` [d, K]: per
    form ``(1, columns, log prior, growth)``, the columns as :func:`~.shapes._extended`
    takes them: the quadratic first (growth 0), then the exponentials of
    :data:`GROWTH_RATES` (growth their rate), then the power laws of
    :data:`POWER_EXPONENTS` (growth minus their exponent, which tells them apart in
    ``trend/growth``).

    A power form's column is ``a^b`` (``a`` the years since the segment's first year), less
    its mean; its map to the trend at the last year is its value, rate and half its second
    derivative there (``A^b``, ``b A^(b-1)``, ``b (b-1) A^(b-2) / 2`` at the last year's
    age ``A``), so the forecast extends it by that quadratic. The cubic term left out is
    ``b (b-1) (b-2) A^(b-3) u^3 / 6``, negative for ``1 < b < 2``: 1-2 % of the rise over
    seven years from a decade of record (A = 9), on the pessimistic side."""
    if priors.get("accelerating", 0.0) <= 0:
        return []
    d, K = seg.shape
    t_last = t[-1]
    rates = ACCELERATING_GROWTHS
    n_exp = len(GROWTH_RATES)
    able = [i for i in range(d) if seg[i].sum() >= ACCELERATING_MIN_YEARS]
    # Every form's column of every input in one array (a view each), the exponentials of
    # all rates at once: the forms are rebuilt for each of a unit's cut years.
    col = np.zeros((len(rates), d, K, d))
    per = {}
    b = np.array(POWER_EXPONENTS)[:, None]
    for i in able:
        ts = t[seg[i]]
        c = ts.mean()
        v = np.mean((ts - c) ** 2)
        col[0, i, seg[i], i] = (ts - c) ** 2 - v
        g = np.exp(np.array(GROWTH_RATES)[:, None] * (ts - t_last))          # [R, n]
        g_mean = g.mean(axis=1)
        col[1:1 + n_exp, i, seg[i], i] = g - g_mean[:, None]
        age = ts - ts[0]
        pw = age[None, :] ** b                                               # [P, n]
        pw_mean = pw.mean(axis=1)
        col[1 + n_exp:, i, seg[i], i] = pw - pw_mean[:, None]
        A = t_last - ts[0]
        per[i] = [((t_last - c) ** 2 - v, 2.0 * (t_last - c), 1.0, 0.0)] + \
            [(1.0 - g_mean[j], r, 0.0, 1.0) for j, r in enumerate(GROWTH_RATES)] + \
            [(A ** e - pw_mean[j], e * A ** (e - 1), 0.5 * e * (e - 1) * A ** (e - 2), 0.0)
             for j, e in enumerate(POWER_EXPONENTS)]
    forms = [(r, [(col[j, i], i, per[i][j]) for i in able]) for j, r in enumerate(rates)
             if able]
    # The forms share the shape's prior equally (half on the quadratic, half shared by the
    # rates, measured worse on benchmarks/prognosis.py's accelerating fleets, seed 11:
    # quadratic coverage 0.79 against 0.83, exponential 0.89 against 0.94).
    return [(1, cols, np.log(priors["accelerating"] / total / len(forms)), r)
            for r, cols in forms]


def _change_candidates(t: np.ndarray, seg: np.ndarray, p_change: float) -> list:
    """Each input's years of a change: :data:`CHANGE_MIN_YEARS` of its segment before and
    from it (none when the change has prior 0)."""
    if p_change <= 0:
        return [[] for _ in range(len(seg))]
    # Years of each segment before each candidate year and from it, [d, K], every input
    # and year at once.
    on = seg.astype(float)
    before = on @ (t[None, :] < t[:, None]).T.astype(float)
    after = on @ (t[None, :] >= t[:, None]).T.astype(float)
    ok = (before >= CHANGE_MIN_YEARS) & (after >= CHANGE_MIN_YEARS)
    return [[int(y) for y in t[ok[i]]] for i in range(len(seg))]


def _reference_weights(cov: np.ndarray, s_ref: np.ndarray) -> np.ndarray:
    """The years' weights ``(C_k + diag(s_ref^2))^-1`` [K, d, d] at the reference sigma
    ``s_ref`` [d] (the line's posterior mean of it), the same for every extra block."""
    return np.linalg.inv(cov + np.diag(np.asarray(s_ref, float) ** 2)[None])


def _change_columns(t: np.ndarray, seg: np.ndarray, i: int, d: int, y: int) -> list:
    """Input ``i``'s change in year ``y`` on its segment ``seg`` [K] (bool): a jump of its
    level, ``1[t >= y]``, and of its rate, ``(t - y) 1[t >= y]``; two ``(column [K, d],
    input, map to the trend at the last year)`` entries."""
    on = seg & (t >= y)
    jump = np.zeros((len(t), d))
    jump[on, i] = 1.0
    rate = np.zeros((len(t), d))
    rate[on, i] = t[on] - y
    return [(jump, i, (1.0, 0.0, 0.0, 0.0)), (rate, i, (t[-1] - y, 1.0, 0.0, 0.0))]


def _change_block_columns(t: np.ndarray, seg: np.ndarray, d: int, blocks: list) -> tuple:
    """:func:`_change_columns` of every block ``(input, year)`` at once: their entries (views
    of one array) and the columns themselves [K, d, 2 n_blocks], each block's jump then
    rate."""
    K, n = len(t), len(blocks)
    ins = np.array([i for i, _ in blocks], dtype=int)
    ys = np.array([y for _, y in blocks], float)
    on = seg[ins] & (t[None, :] >= ys[:, None])                              # [n, K]
    E = np.zeros((n, 2, K, d))
    E[np.arange(n), 0, :, ins] = on
    E[np.arange(n), 1, :, ins] = np.where(on, t[None, :] - ys[:, None], 0.0)
    cols = [[(E[b, 0], i, (1.0, 0.0, 0.0, 0.0)), (E[b, 1], i, (t[-1] - y, 1.0, 0.0, 0.0))]
            for b, (i, y) in enumerate(blocks)]
    return cols, np.moveaxis(E.reshape(2 * n, K, d), 0, 2)


def _change_selection(line: GaussianTrend, line_log_prior: float, forms: list, cand: list,
                      t: np.ndarray, seg: np.ndarray, log_p: float, W: np.ndarray,
                      prior_prec: np.ndarray, A: np.ndarray,
                      screen_weights: tuple | None = None) -> tuple:
    """The ``change`` shape's combinations worth weighing (the module docstring): those in
    Occam's window of the best shape and past the razor, on their evidence integrated over
    sigma on the screen's grid (:func:`~.shape_screen.screen_grid`).

    Parameters
    ----------
    line : GaussianTrend
    line_log_prior : float
    forms : list of (cols, log_prior)
        The accelerating forms (their columns as :func:`_extended` takes them): the
        window's best may be one of them.
    cand : list of list of int
        Each input's candidate years (empty: it cannot change).
    t : ndarray, shape [K]
    seg : ndarray of bool, shape [d, K]
        Each input's current segment.
    log_p : float
        Log prior probability of the change shape.
    W : ndarray, shape [K, d, d]
        The years' weights at the reference sigma (:func:`_unit_information`).
    A : ndarray, shape [d]
        sigma's prior scale.
    screen_weights : (Wf, logdet_v), optional
        The sites' :func:`~.gaussian_trend.year_weights` at ``screen_grid(A)``'s sigma,
        when already computed.

    Returns
    -------
    E : ndarray, shape [K, d, n_x]
        Every extra column: the forms' (first), then two per change block.
    S : ndarray, shape [n_x, n_x]
        Their Zellner prior precision.
    blocks : list of (input, year)
    cols : list
        Each block's two columns (:func:`_change_columns`).
    kept : list of (combination, log_prior, change_years)
        A combination is a tuple of indices into ``blocks``; ``change_years`` gives each
        input's year (-1: it does not change).
    """
    Mk = line.Mk
    K, d, n_l = Mk.shape
    able = [i for i in range(d) if cand[i]]
    # Each input changes with probability 1/2, in a year uniform over its candidates,
    # given that one does: the sets of inputs that change are equally likely.
    log_norm = log_p - np.log1p(-0.5 ** len(able)) + len(able) * np.log(0.5)
    blocks = [(i, y) for i in able for y in cand[i]]
    cols, E_change = _change_block_columns(t, seg, d, blocks)
    # Every extra column at once: the forms' (first), then two per change block.
    E = np.concatenate([np.stack([c for f, _ in forms for c, _, _ in f], axis=2)
                        if forms else np.zeros((K, d, 0)), E_change], axis=2)  # [K, d, n_x]
    at = np.cumsum([0] + [len(f) for f, _ in forms])
    base = at[-1]
    S = _unit_information(W, Mk, E, prior_prec, K)
    evidence = screen(line, E, S, screen_grid(A), screen_weights)
    # Each block's log number of candidate years (its input's): a combination's prior
    # takes one per block.
    log_n = np.log([len(cand[i]) for i, _ in blocks])

    def prior(combos: list) -> np.ndarray:
        return log_norm - log_n[np.array(combos, dtype=int)].sum(axis=1)

    def score(combos: list) -> np.ndarray:
        # A combination's columns: its blocks' two each, in the blocks' order.
        idx = (base + 2 * np.array(combos, dtype=int)[:, :, None] + np.arange(2)).reshape(
            len(combos), -1)
        return prior(combos) + evidence(idx)

    years = [[b for b in range(len(blocks)) if blocks[b][0] == i] for i in range(d)]
    if np.prod([len(cand[i]) + 1 for i in able]) - 1 > CHANGE_COMBOS:
        # Too many combinations to weigh them all: each input keeps its CHANGE_SCREEN
        # most probable years (its change alone) (three inputs or more; two weigh every
        # pair).
        q1 = score([(b,) for b in range(len(blocks))])
        years = [sorted(sorted(bs, key=lambda b: -q1[b])[:CHANGE_SCREEN]) for bs in years]
    combos = [c for k in range(1, len(able) + 1) for S_ in combinations(able, k)
              for c in product(*(years[i] for i in S_))]
    q = np.empty(len(combos))
    for k in range(1, len(able) + 1):
        of = [j for j, c in enumerate(combos) if len(c) == k]
        if of:
            q[of] = score([combos[j] for j in of])
    others = [line_log_prior + evidence([[]])[0]]
    if forms:
        others += list(np.array([lp for _, lp in forms])
                       + evidence([list(range(at[j], at[j + 1])) for j in range(len(forms))]))
    best = max(q.max(), max(others))
    index = {c: j for j, c in enumerate(combos)}
    kept = []
    for j, c in enumerate(combos):
        if q[j] < best + np.log(OCCAM):
            continue
        # Occam's razor within the change (Madigan and Raftery 1994): an input's change
        # that the combination without it explains better is not weighed.
        if any(q[index[c[:m] + c[m + 1:]]] > q[j] for m in range(len(c)) if len(c) > 1):
            continue
        when = [-1] * d
        for b in c:
            when[blocks[b][0]] = blocks[b][1]
        kept.append((c, float(prior([c])[0]), tuple(when)))
    return E, S, blocks, cols, kept


def line_now(Mk: np.ndarray, slopes: np.ndarray) -> np.ndarray:
    """The line's map to the trend at the last year [4, d, n_line]: the last year's design
    row gives the level; the rate is the slope of the segment in force (the slope column
    beside the level column that is 1 in the last year)."""
    K, d, n = Mk.shape
    now = np.zeros((len(NOW_ROWS), d, n))
    now[0] = Mk[-1]
    for i in range(d):
        level = np.flatnonzero((Mk[-1, i] == 1.0) & ~slopes)[0]
        now[1, i, level + 1] = 1.0
    return now


def _unit_information(W: np.ndarray, Mk: np.ndarray, E: np.ndarray,
                      prior_prec: np.ndarray, n: int) -> np.ndarray:
    """Zellner's unit-information prior precision of the extra coefficients ``E`` beyond the
    line ``Mk``: their information given the line's, over ``n`` (the module docstring).
    ``W`` [K, d, d]: each year's weight, ``(C_k + diag(sigma^2))^-1`` at the reference
    sigma."""
    M = np.concatenate([Mk, E], axis=2)
    info = np.einsum("kia,kij,kjb->ab", M, W, M)
    n_l = Mk.shape[2]
    I_bb = info[:n_l, :n_l] + np.diag(prior_prec)
    I_eb = info[n_l:, :n_l]
    schur = info[n_l:, n_l:] - I_eb @ np.linalg.solve(I_bb, I_eb.T)
    return 0.5 * (schur + schur.T) / n
