"""Trend shapes of the laplace method: on each input's current segment, wear may follow a
straight line, a line that accelerates, or a line whose level and rate change in one year;
the posterior averages them by their evidence (Bayesian model averaging).

Real wear is rarely a straight line: it accelerates (the usual shape of fatigue and erosion),
or steps when something breaks or a process changes. A line through such a history forecasts
late or early with intervals that look sure. So besides ``line`` (the joint method's model),
the laplace method gives every unit two further shapes on the segment in force (the one the
forecast extends), each the line plus coefficients with a Gaussian prior:

* ``accelerating``: the line plus, per input, a quadratic term ``kappa ((t - c)^2 - v)``
  (``c`` and ``v`` the segment's mean year and the mean of ``(t - c)^2``, so that the line's
  level and slope keep their meaning), or an exponential term ``e exp(r (t - t_last))`` with
  its growth rate ``r`` one of :data:`GROWTH_RATES` (the field's exponential degradation
  model, whose rate a decade of yearly records pins down only roughly); the six forms share
  the shape's prior equally. A quadratic extended seven years falls short of exponential
  wear; the exponential forms carry that possibility into the forecast;
* ``change`` at year ``y`` (every recorded year with at least :data:`CHANGE_MIN_YEARS` years of
  the segment before it and from it): a jump of the level, ``1[t >= y]``, and of the rate,
  ``(t - y) 1[t >= y]``; the years are equally likely a priori and share the shape's prior.

Each extra coefficient block has Zellner's unit-information prior: zero mean, covariance
``K`` (the unit's years) times the inverse of the information the sites hold about the block
beyond the line, at the line's posterior mean of ``sigma`` -- the prior of one year's worth
of data, whose Bayes factors behave like BIC (Kass and Wasserman 1995), with no scale to tune
per model. The shapes share the line's flat levels, so their marginal likelihoods compare;
their prior probabilities are ``calibrate.shapes``.

Each shape is a :class:`~twinmon.calibrate.gaussian_trend.GaussianTrend`; the mixture draws
a shape per draw by its posterior probability on the sites, then from it, and is refined and
weighted to the exact likelihood as one model (:class:`ShapeMixture`). A shape whose
posterior probability on the sites is below :data:`OCCAM` of the best one's is dropped
before any draw (Occam's window, Madigan and Raftery 1994): it could not hold a draw.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .gaussian_trend import GaussianTrend, SiteModel, log_evidence_at

#: The shapes, in the order of their code in the posterior (``trend/shape``).
SHAPES = ("line", "accelerating", "change")
#: Fewest years of a segment on which acceleration is modelled (a quadratic on fewer is
#: the noise's).
ACCELERATING_MIN_YEARS = 5
#: Fewest years of the segment before a change and from it.
CHANGE_MIN_YEARS = 3
#: Shapes less probable than this share of the best one on the sites are dropped.
OCCAM = 1e-4
#: Growth rates (per year) of the accelerating shape's exponential forms, from a doubling
#: time of 7 years to one of 1.4 (slower growth is the quadratic's), spaced so that a
#: rate between two of them is still covered (tests/unit/test_calibrate_shapes.py).
GROWTH_RATES = (0.1, 0.2, 0.3, 0.4, 0.5)
#: Rows of a shape's map to the trend at the last year (``Shape.now``, ``trend/now``).
NOW_ROWS = ("level", "rate", "curvature", "growth_amplitude")


@dataclass
class Shape:
    """One trend shape of a unit.

    Attributes
    ----------
    code : int
        Index in :data:`SHAPES`.
    model : GaussianTrend
    log_prior : float
        Log prior probability of this shape (a change year: its share of ``change``'s).
    now : ndarray, shape [4, d, n_beta]
        Maps beta to the trend at the last recorded year (:data:`NOW_ROWS`): level, rate
        (per year), curvature and growth amplitude, per input; for a later year ``t``, with
        ``u = t - t_last``, the trend is ``level + rate u + curvature u^2 + amplitude
        (exp(growth u) - 1 - growth u)`` (:func:`extend`).
    change_year : int
        The year of a ``change`` shape, -1 for the others.
    growth : float
        The growth rate of an exponential form (per year), 0 for the others.
    """

    code: int
    model: GaussianTrend
    log_prior: float
    now: np.ndarray
    change_year: int = -1
    growth: float = 0.0


def build_shapes(years: np.ndarray, x: np.ndarray, cov: np.ndarray, Mk: np.ndarray,
                 prior_prec: np.ndarray, prior_mean: np.ndarray, A: np.ndarray,
                 slopes: np.ndarray, last_start: np.ndarray, priors: dict,
                 rng: Optional[np.random.Generator], sigma_ref: Optional[np.ndarray] = None
                 ) -> list[Shape]:
    """A unit's shapes on its sites.

    Parameters
    ----------
    years : ndarray of int, shape [K]
    x, cov : ndarray, shapes [K, d], [K, d, d]
        The years' sites.
    Mk : ndarray, shape [K, d, n_line]
        The line's design (segments' levels and slopes, :func:`~.trend.design_matrix`).
    prior_prec, prior_mean : ndarray, shape [n_line]
        The line's coefficient priors (levels flat).
    A : ndarray, shape [d]
        sigma's prior scale.
    slopes : ndarray of bool, shape [n_line]
        Which of the line's coefficients are slopes (each follows its segment's level).
    last_start : ndarray of int, shape [d]
        First year of each input's current segment.
    priors : dict shape name -> float
        Prior probabilities (``calibrate.shapes``; absent or 0: not fitted).
    rng : numpy Generator
        For the line's sigma points (the reference sigma of the other shapes' priors).
    sigma_ref : ndarray, shape [d], optional
        That reference sigma given (input units; ``rng`` then unused): the one-year-ahead
        check of :mod:`twinmon.forecast.trendfit` fixes sigma at the unit's posterior mean.

    Returns
    -------
    list of Shape
        ``line`` first; the others where the segment is long enough.
    """
    t = np.asarray(years, float)
    K, d = x.shape
    t_last = t[-1]
    seg = t[None, :] >= np.asarray(last_start, float)[:, None]              # [d, K]
    total = sum(max(float(p), 0.0) for p in priors.values())
    line = GaussianTrend(x, cov, Mk, prior_prec, prior_mean, A)
    # A line with prior 0 stays as the others' base, with no draws of its own.
    p_line = priors.get("line", 0.0) / total
    shapes = [Shape(0, line, np.log(p_line) if p_line > 0 else -np.inf, _line_now(Mk, slopes))]
    extras = []
    if priors.get("accelerating", 0.0) > 0:
        forms = []
        for r in (0.0,) + tuple(GROWTH_RATES):
            cols = []
            for i in range(d):
                if seg[i].sum() < ACCELERATING_MIN_YEARS:
                    continue
                ts = t[seg[i]]
                col = np.zeros((K, d))
                if r == 0.0:
                    c = ts.mean()
                    v = np.mean((ts - c) ** 2)
                    col[seg[i], i] = (ts - c) ** 2 - v
                    cols.append((col, i, ((t_last - c) ** 2 - v, 2.0 * (t_last - c), 1.0, 0.0)))
                else:
                    g = np.exp(r * (ts - t_last))
                    col[seg[i], i] = g - g.mean()
                    cols.append((col, i, (1.0 - g.mean(), r, 0.0, 1.0)))
            if cols:
                forms.append((r, cols))
        # The forms share the shape's prior equally (half on the quadratic, half shared by
        # the rates, measured worse on benchmarks/prognosis.py's accelerating fleets, seed 11:
        # quadratic coverage 0.79 against 0.83, exponential 0.89 against 0.94).
        for r, cols in forms:
            extras.append((1, cols, np.log(priors["accelerating"] / total / len(forms)), -1, r))
    if priors.get("change", 0.0) > 0:
        found = []
        for y in t:
            cols = []
            for i in range(d):
                before = (seg[i] & (t < y)).sum()
                after = (seg[i] & (t >= y)).sum()
                if before < CHANGE_MIN_YEARS or after < CHANGE_MIN_YEARS:
                    continue
                on = seg[i] & (t >= y)
                jump = np.zeros((K, d))
                jump[on, i] = 1.0
                rate = np.zeros((K, d))
                rate[on, i] = t[on] - y
                cols += [(jump, i, (1.0, 0.0, 0.0, 0.0)), (rate, i, (t_last - y, 1.0, 0.0, 0.0))]
            if cols:
                found.append((int(y), cols))
        for y, cols in found:
            extras.append((2, cols, np.log(priors["change"] / total / len(found)), y, 0.0))
    if not extras:
        return shapes
    if sigma_ref is None:
        sig, w = line.sigma_points(rng)[:2]
        s_ref = w @ sig                                                      # [d]
    else:
        s_ref = np.asarray(sigma_ref, float)
    # The years' weights at the reference sigma, the same for every extra block.
    W = np.linalg.inv(cov + np.diag(s_ref ** 2)[None])                       # [K, d, d]
    for code, cols, log_prior, year, growth in extras:
        E = np.stack([c for c, _, _ in cols], axis=2)                        # [K, d, n_e]
        P_e = _unit_information(W, Mk, E, prior_prec, K)
        M = np.concatenate([Mk, E], axis=2)
        n_l = Mk.shape[2]
        P = np.zeros((M.shape[2], M.shape[2]))
        P[:n_l, :n_l] = np.diag(prior_prec)
        P[n_l:, n_l:] = P_e
        now = np.concatenate([shapes[0].now, np.zeros((len(NOW_ROWS), d, len(cols)))],
                             axis=2)
        for j, (_, i, g) in enumerate(cols):
            now[:, i, n_l + j] = g
        model = GaussianTrend(x, cov, M, P, np.concatenate([prior_mean, np.zeros(len(cols))]),
                              A)
        shapes.append(Shape(code, model, log_prior, now, year, growth))
    return shapes


def _line_now(Mk: np.ndarray, slopes: np.ndarray) -> np.ndarray:
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


class ShapeMixture(SiteModel):
    """The unit's shapes as one model on shared sites: :meth:`draw` picks a shape per draw
    by its posterior probability on the sites (prior times evidence), then draws from it.

    Its draws' ``coef`` [n, 1 + K d + 4 d] is ``(shape index, trend at the years [K, d],
    trend at the last year [4, d])`` flattened (:meth:`decode`): the shapes' coefficients
    differ in number, their consequences do not."""

    def __init__(self, shapes: list[Shape]):
        self.shapes = shapes
        self.probs = np.full(len(shapes), np.nan)

    @property
    def x(self) -> np.ndarray:
        return self.shapes[0].model.x

    @x.setter
    def x(self, value: np.ndarray) -> None:
        for s in self.shapes:
            s.model.x = value

    @property
    def cov(self) -> np.ndarray:
        return self.shapes[0].model.cov

    @cov.setter
    def cov(self, value: np.ndarray) -> None:
        for s in self.shapes:
            s.model.cov = value

    def sigma_points(self, rng: np.random.Generator):
        """Each shape's sigma points (as ``GaussianTrend.sigma_points``; None for a shape
        outside Occam's window) and the shapes' posterior probabilities [n_shapes] on the
        sites; also kept as :attr:`probs`."""
        line = self.shapes[0].model.sigma_points(rng)
        points = [line] + [None] * (len(self.shapes) - 1)
        logp = np.full(len(self.shapes), -np.inf)
        logp[0] = self.shapes[0].log_prior + line[3]
        if len(self.shapes) > 1:
            # Occam's window from one evaluation per shape at the line's mean sigma: a
            # shape far less probable there is not worth its sigma points.
            s_ref = (line[1] @ line[0])[None]
            quick = np.array([s.log_prior for s in self.shapes]) + \
                log_evidence_at([s.model for s in self.shapes], s_ref)[:, 0]
            line_box = self.shapes[0].model.box
            kept = [j for j in range(1, len(self.shapes))
                    if quick[j] >= quick.max() + np.log(OCCAM)]
            # A shape's sigma sits near the line's: its first round is the line's last
            # points (sigma_points zooms or widens from there when they do not fit),
            # evaluated for every shape kept at once.
            first = log_evidence_at([self.shapes[j].model for j in kept], line[0]) \
                if kept else None
            for a, j in enumerate(kept):
                s = self.shapes[j]
                points[j] = s.model.sigma_points(rng, line_box, first=line[0],
                                                 first_ll=first[a])
                logp[j] = s.log_prior + points[j][3]
        p = np.exp(logp - logp.max())
        self.probs = p / p.sum()
        return points, self.probs

    def draw(self, n: int, rng: np.random.Generator, bounds: np.ndarray, points=None):
        """``n`` draws of the mixture: ``(coef, sigma, theta, sigma_ess)`` as
        ``GaussianTrend.draw``'s, ``coef`` as the class docstring says, in random order."""
        pts, probs = self.sigma_points(rng) if points is None else points
        counts = rng.multinomial(n, probs)
        K, d = self.x.shape
        r = len(NOW_ROWS)
        coef = np.empty((n, 1 + K * d + r * d))
        sigma, theta = np.empty((n, d)), np.empty((n, K, d))
        at, ess = 0, 0.0
        for j, (s, c) in enumerate(zip(self.shapes, counts)):
            if c == 0:
                continue
            beta, sg, th, e = s.model.draw(int(c), rng, bounds, pts[j])
            sl = slice(at, at + c)
            coef[sl, 0] = j
            coef[sl, 1:1 + K * d] = np.einsum("kia,na->nki", s.model.Mk, beta).reshape(c, -1)
            coef[sl, 1 + K * d:] = np.einsum("tia,na->nti", s.now, beta).reshape(c, -1)
            sigma[sl], theta[sl] = sg, th
            ess += probs[j] * e
            at += c
        order = rng.permutation(n)
        return coef[order], sigma[order], theta[order], ess

    def decode(self, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shape index [n], trend at the years [n, K, d], trend at the last year
        [n, len(NOW_ROWS), d] from :meth:`draw`'s ``coef``."""
        K, d = self.x.shape
        n = len(coef)
        return (coef[:, 0].astype(int), coef[:, 1:1 + K * d].reshape(n, K, d),
                coef[:, 1 + K * d:].reshape(n, len(NOW_ROWS), d))


def form_names() -> tuple:
    """The forms a draw's trend may take on its current segment, as the fleet's prior of the
    shapes (:mod:`.fleet_shapes`) tells them apart: the line, the quadratic, the
    exponential at each of :data:`GROWTH_RATES`, the change (its years together)."""
    return (("line", "quadratic") + tuple(f"exponential {r:g}" for r in GROWTH_RATES)
            + ("change",))


def form_of(code: np.ndarray, growth: np.ndarray) -> np.ndarray:
    """Each draw's form, the index in :func:`form_names` [n], from its shape code
    (``trend/shape``) [n] and growth rate (``trend/growth``, per year) [n]."""
    code = np.asarray(code, int)
    growth = np.asarray(growth, float)
    out = np.where(code == 0, 0, np.where(code == 2, len(GROWTH_RATES) + 2, 1))
    for j, r in enumerate(GROWTH_RATES):
        out = np.where((code == 1) & np.isclose(growth, r), 2 + j, out)
    return out


def form_priors(priors: dict) -> np.ndarray:
    """Prior probability of each of :func:`form_names` [F] as :func:`build_shapes` splits
    ``calibrate.shapes``: the accelerating shape's equally over its forms, the change's
    over its years (kept together here). Sums to 1."""
    p = {k: max(float(v), 0.0) for k, v in priors.items()}
    total = sum(p.values())
    acc = p.get("accelerating", 0.0) / (1 + len(GROWTH_RATES))
    return np.array([p.get("line", 0.0)] + [acc] * (1 + len(GROWTH_RATES))
                    + [p.get("change", 0.0)]) / total


def available_forms(segment_years: np.ndarray) -> np.ndarray:
    """Which of :func:`form_names` a unit's current segments allow [F] (bool), from each
    input's number of recorded years in its segment in force [d]: the line always, the
    accelerating forms when one input has :data:`ACCELERATING_MIN_YEARS`, the change when
    one has :data:`CHANGE_MIN_YEARS` before a year and from it."""
    n = np.asarray(segment_years, int)
    acc = bool(np.any(n >= ACCELERATING_MIN_YEARS))
    change = bool(np.any(n >= 2 * CHANGE_MIN_YEARS))
    return np.array([True] + [acc] * (1 + len(GROWTH_RATES)) + [change])


def shape_probabilities(codes: np.ndarray) -> np.ndarray:
    """Posterior probability of each of :data:`SHAPES` [3]: its share of the draws (weighted
    to the exact likelihood and resampled, so the share is the posterior's, not the
    sites')."""
    codes = np.asarray(codes, int)
    return np.bincount(codes, minlength=len(SHAPES))[:len(SHAPES)] / max(codes.size, 1)


def shape_summary(trend: dict) -> dict:
    """What a unit's trend draws say of its shape, for the forecast's verdict and report:
    ``{"line": p, "accelerating": p, "change": p, "change_year": y}`` (the draws' shares,
    ``change_year`` the most frequent among the change draws, or None); empty for a trend
    without shapes (the joint method's)."""
    if "shape" not in trend:
        return {}
    code = np.asarray(trend["shape"], int)
    p = shape_probabilities(code)
    out = {name: round(float(v), 3) for name, v in zip(SHAPES, p)}
    years = np.asarray(trend["change_year"], int)[code == 2]
    out["change_year"] = int(np.bincount(years - years.min()).argmax() + years.min()) \
        if years.size else None
    return out


def describe_shape(shape: dict) -> str:
    """One sentence on a shape other than the line that holds most of the posterior
    (:func:`shape_summary`), or ``""``."""
    if not shape:
        return ""
    if shape["accelerating"] >= 0.5:
        return (f"The wear accelerates (probability {shape['accelerating']:.2f}, a straight "
                f"line {shape['line']:.2f}): the forecast extends the curve.")
    if shape["change"] >= 0.5 and shape["change_year"] is not None:
        return (f"The trend changed in year {shape['change_year']} (probability "
                f"{shape['change']:.2f}, a straight line {shape['line']:.2f}): the forecast "
                "extends the rate since then.")
    return ""


def extend(now: np.ndarray, growth: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The trend ``u`` years after the last recorded year.

    Parameters
    ----------
    now : ndarray, shape [n, 4, d]
        Per draw, the trend at the last year (:data:`NOW_ROWS`).
    growth : ndarray, shape [n]
        Per draw, the exponential form's growth rate (per year; 0: none).
    u : ndarray, shape [h]
        Years after the last recorded year.

    Returns
    -------
    ndarray, shape [n, h, d]
    """
    u = np.asarray(u, float)[None, :, None]
    r = np.asarray(growth, float)[:, None, None]
    # exp(r u) - 1 - r u, the part of an exponential beyond its tangent (0 when r = 0).
    bend = np.expm1(r * u) - r * u
    return (now[:, None, 0, :] + now[:, None, 1, :] * u + now[:, None, 2, :] * u ** 2
            + now[:, None, 3, :] * bend)
