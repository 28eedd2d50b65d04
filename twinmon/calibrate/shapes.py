"""Trend shapes of the laplace method: on each input's current segment, wear may follow a
straight line, a line that accelerates, or a line whose level and rate change, each input's
in a year of its own; the posterior averages them by their evidence (Bayesian model
averaging).

Real wear is rarely a straight line: it accelerates (the usual shape of fatigue and erosion),
or steps when something breaks or a process changes. A line through such a history forecasts
late or early with intervals that look sure. So besides ``line`` (the joint method's model),
the laplace method gives every unit two further shapes on the segment in force (the one the
forecast extends), each the line plus coefficients with a Gaussian prior:

* ``accelerating``: the line plus, per input, a quadratic term ``kappa ((t - c)^2 - v)``
  (``c`` and ``v`` the segment's mean year and the mean of ``(t - c)^2``, so that the line's
  level and slope keep their meaning), or an exponential term ``e exp(r (t - t_last))`` with
  its growth rate ``r`` one of :data:`GROWTH_RATES` (the field's exponential degradation
  model, whose rate a decade of yearly records pins down only roughly), or a power law
  ``c a^b``, ``a`` the years since the segment's first, with ``b`` one of
  :data:`POWER_EXPONENTS` (the field's other standard degradation model: wear whose rate
  grows ever more slowly); the nine forms share the shape's prior equally. A quadratic
  extended seven years falls short of exponential wear and runs ahead of power-law wear
  (its curvature is the record's mean, the power law's falls): the other forms carry those
  futures into the forecast;
* ``change``: a jump of an input's level, ``1[t >= y]``, and of its rate, ``(t - y)
  1[t >= y]``, in a year ``y`` with at least :data:`CHANGE_MIN_YEARS` years of its segment
  before it and from it. Each input changes or not, in a year of its own: a priori each
  input changes with probability 1/2, in a year uniform over its candidates, independently
  of the others, given that one changes (so the sets of inputs that change are equally
  likely; two inputs changing in the same year is one of their combinations). Two parts
  need not break in the same year: with one year shared by the inputs, the later step was
  read as a rate and extended.

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

The change's combinations (25 for two inputs with five candidate years each, against the
shared year's 5) are screened once, before any model is built: each one's evidence
integrated over sigma on a coarse grid (:func:`~.shape_screen.screen_grid`; at the line's
mean sigma alone, inflated by the steps a line cannot follow, a second step did not pay for
its coefficients), by a block update of the line's (:func:`~.shape_screen.screen`: the
combinations cost a few batched products, not a model each). Kept are those in Occam's
window of the best shape that also pass the window's second rule among the combinations,
Occam's razor: a combination is dropped when one without one of its inputs' changes is more
probable (that change does not pay for its two coefficients; its years, each a sliver of the
same draws, would each cost the mixture sigma points and draws). A change is always weighed
against the line and the accelerating forms.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .gaussian_trend import GaussianTrend, SiteModel, draw_years, log_evidence_at
from .shape_columns import (ACCELERATING_GROWTHS, ACCELERATING_MIN_YEARS, CHANGE_MIN_YEARS,
                            GROWTH_RATES, NOW_ROWS, OCCAM, POWER_EXPONENTS,
                            _accelerating_forms, _change_candidates, _change_columns,
                            _change_selection, _reference_weights, _unit_information,
                            line_now)

#: The shapes, in the order of their code in the posterior (``trend/shape``).
SHAPES = ("line", "accelerating", "change")


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
    change_years : tuple of int, length d
        A ``change`` shape's year per input, -1 for an input that does not change (and for
        every input of the other shapes).
    growth : float
        The growth rate of an exponential form (per year), 0 for the others.
    """

    code: int
    model: GaussianTrend
    log_prior: float
    now: np.ndarray
    change_years: tuple = ()
    growth: float = 0.0

    @property
    def change_year(self) -> int:
        """The first year in which a ``change`` shape's inputs change, -1 for the others."""
        on = [y for y in self.change_years if y >= 0]
        return min(on) if on else -1


def build_shapes(years: np.ndarray, x: np.ndarray, cov: np.ndarray, Mk: np.ndarray,
                 prior_prec: np.ndarray, prior_mean: np.ndarray, A: np.ndarray,
                 slopes: np.ndarray, last_start: np.ndarray, priors: dict,
                 rng: np.random.Generator) -> list[Shape]:
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
        For the line's sigma points (their mean: the reference sigma of the other shapes'
        priors; :func:`~.shape_columns.shape_sets` takes it given instead).

    Returns
    -------
    list of Shape
        ``line`` first; the others where the segment is long enough.
    """
    t = np.asarray(years, float)
    K, d = x.shape
    seg = t[None, :] >= np.asarray(last_start, float)[:, None]              # [d, K]
    total = sum(max(float(p), 0.0) for p in priors.values())
    line = GaussianTrend(x, cov, Mk, prior_prec, prior_mean, A)
    # A line with prior 0 stays as the others' base, with no draws of its own.
    p_line = priors.get("line", 0.0) / total
    shapes = [Shape(0, line, np.log(p_line) if p_line > 0 else -np.inf, line_now(Mk, slopes),
                    (-1,) * d)]
    extras = _accelerating_forms(t, seg, priors, total)
    p_change = priors.get("change", 0.0) / total
    cand = _change_candidates(t, seg, p_change)
    if not extras and not any(cand):
        return shapes
    sig, w = line.sigma_points(rng)[:2]
    W = _reference_weights(cov, w @ sig)
    for code, cols, log_prior, growth in extras:
        shapes.append(_extended(shapes[0], code, cols, log_prior, W, prior_prec, prior_mean,
                                A, (-1,) * d, growth))
    if any(cand):
        shapes += _change_shapes(shapes[0], [(cols, lp) for _, cols, lp, _ in extras], cand,
                                 t, seg, np.log(p_change), W, prior_prec, prior_mean, A)
    return shapes


def _extended(line: Shape, code: int, cols: list, log_prior: float, W: np.ndarray,
              prior_prec: np.ndarray, prior_mean: np.ndarray, A: np.ndarray,
              change_years: tuple, growth: float) -> Shape:
    """The line plus the columns ``cols``, each ``(column [K, d], input, its map to the trend
    at the last year [4])``, under Zellner's unit-information prior at the year weights
    ``W`` [K, d, d] (:func:`_unit_information`)."""
    Mk = line.model.Mk
    K, d, n_l = Mk.shape
    E = np.stack([c for c, _, _ in cols], axis=2)                            # [K, d, n_e]
    M = np.concatenate([Mk, E], axis=2)
    P = np.zeros((M.shape[2], M.shape[2]))
    P[:n_l, :n_l] = np.diag(prior_prec)
    P[n_l:, n_l:] = _unit_information(W, Mk, E, prior_prec, K)
    now = np.concatenate([line.now, np.zeros((len(NOW_ROWS), d, len(cols)))], axis=2)
    for j, (_, i, g) in enumerate(cols):
        now[:, i, n_l + j] = g
    model = GaussianTrend(line.model.x, line.model.cov, M, P,
                          np.concatenate([prior_mean, np.zeros(len(cols))]), A)
    return Shape(code, model, log_prior, now, tuple(change_years), growth)


def _change_shapes(line: Shape, forms: list, cand: list, t: np.ndarray, seg: np.ndarray,
                   log_p: float, W: np.ndarray, prior_prec: np.ndarray,
                   prior_mean: np.ndarray, A: np.ndarray) -> list:
    """The ``change`` shape's combinations worth weighing (:func:`_change_selection`), each
    as a model.

    Returns
    -------
    list of Shape
        One per combination kept: every input with candidate years either changes, in one
        of them, or does not; at least one changes.
    """
    _, _, _, cols, kept = _change_selection(line.model, line.log_prior, forms, cand, t, seg,
                                            log_p, W, prior_prec, A)
    return [_extended(line, 2, [e for b in combo for e in cols[b]], log_prior, W,
                      prior_prec, prior_mean, A, when, 0.0) for combo, log_prior, when in kept]


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
        sigma = np.empty((n, d))
        at, ess = 0, 0.0
        for j, (s, c) in enumerate(zip(self.shapes, counts)):
            if c == 0:
                continue
            beta, sigma[at:at + c], e = s.model.draw_trend(int(c), rng, pts[j])
            sl = slice(at, at + c)
            coef[sl, 0] = j
            coef[sl, 1:1 + K * d] = np.einsum("kia,na->nki", s.model.Mk, beta).reshape(c, -1)
            coef[sl, 1 + K * d:] = np.einsum("tia,na->nti", s.now, beta).reshape(c, -1)
            ess += probs[j] * e
            at += c
        # The years given each draw's trend, every shape's draws at once (the shapes share
        # their sites).
        theta = draw_years(self.x, self.cov, coef[:, 1:1 + K * d].reshape(n, K, d), sigma,
                           rng, bounds)
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
    exponential at each of :data:`GROWTH_RATES`, the power law at each of
    :data:`POWER_EXPONENTS`, the change (its years together)."""
    return (("line", "quadratic") + tuple(f"exponential {r:g}" for r in GROWTH_RATES)
            + tuple(f"power {b:g}" for b in POWER_EXPONENTS) + ("change",))


def form_of(code: np.ndarray, growth: np.ndarray) -> np.ndarray:
    """Each draw's form, the index in :func:`form_names` [n], from its shape code
    (``trend/shape``) [n] and growth (``trend/growth``: an exponential's rate per year,
    minus a power law's exponent) [n]."""
    code = np.asarray(code, int)
    growth = np.asarray(growth, float)
    out = np.where(code == 0, 0, np.where(code == 2, len(ACCELERATING_GROWTHS) + 1, 1))
    for j, r in enumerate(ACCELERATING_GROWTHS[1:]):
        out = np.where((code == 1) & np.isclose(growth, r), 2 + j, out)
    return out


def form_priors(priors: dict) -> np.ndarray:
    """Prior probability of each of :func:`form_names` [F] as :func:`build_shapes` splits
    ``calibrate.shapes``: the accelerating shape's equally over its forms, the change's
    over its years (kept together here). Sums to 1."""
    p = {k: max(float(v), 0.0) for k, v in priors.items()}
    total = sum(p.values())
    n_acc = len(ACCELERATING_GROWTHS)
    acc = p.get("accelerating", 0.0) / n_acc
    return np.array([p.get("line", 0.0)] + [acc] * n_acc + [p.get("change", 0.0)]) / total


def available_forms(segment_years: np.ndarray) -> np.ndarray:
    """Which of :func:`form_names` a unit's current segments allow [F] (bool), from each
    input's number of recorded years in its segment in force [d]: the line always, the
    accelerating forms when one input has :data:`ACCELERATING_MIN_YEARS`, the change when
    one has :data:`CHANGE_MIN_YEARS` before a year and from it."""
    n = np.asarray(segment_years, int)
    acc = bool(np.any(n >= ACCELERATING_MIN_YEARS))
    change = bool(np.any(n >= 2 * CHANGE_MIN_YEARS))
    return np.array([True] + [acc] * len(ACCELERATING_GROWTHS) + [change])


def shape_probabilities(codes: np.ndarray) -> np.ndarray:
    """Posterior probability of each of :data:`SHAPES` [3]: its share of the draws (weighted
    to the exact likelihood and resampled, so the share is the posterior's, not the
    sites')."""
    codes = np.asarray(codes, int)
    return np.bincount(codes, minlength=len(SHAPES))[:len(SHAPES)] / max(codes.size, 1)


def shape_summary(trend: dict) -> dict:
    """What a unit's trend draws say of its shape, for the forecast's verdict and report:
    ``{"line": p, "accelerating": p, "change": p, "change_year": y, "change_years": [y_i]}``
    (the draws' shares; ``change_year`` the most frequent first year of a change among the
    change draws, or None; ``change_years``, when the draws record them, per input the most
    frequent year of its change among the change draws, None for an input that changes in
    fewer than half of them); empty for a trend without shapes (the joint method's)."""
    if "shape" not in trend:
        return {}
    code = np.asarray(trend["shape"], int)
    p = shape_probabilities(code)
    out = {name: round(float(v), 3) for name, v in zip(SHAPES, p)}
    out["change_year"] = _mode(np.asarray(trend["change_year"], int)[code == 2])
    if "change_years" in trend:
        per = np.asarray(trend["change_years"], int)[code == 2]             # [n_c, d]
        # No change draws (a unit whose change shape holds none): every input None.
        out["change_years"] = [_mode(per[per[:, i] >= 0, i])
                               if len(per) and np.mean(per[:, i] >= 0) >= 0.5 else None
                               for i in range(per.shape[1])]
    return out


def _mode(years: np.ndarray) -> Optional[int]:
    """The most frequent of ``years`` (ints), the earliest of ties; None when empty."""
    if not years.size:
        return None
    return int(np.bincount(years - years.min()).argmax() + years.min())


def describe_shape(shape: dict) -> str:
    """One sentence on a shape other than the line that holds most of the posterior
    (:func:`shape_summary`), or ``""``."""
    if not shape:
        return ""
    if shape["accelerating"] >= 0.5:
        return (f"The wear accelerates (probability {shape['accelerating']:.2f}, a straight "
                f"line {shape['line']:.2f}): the forecast extends the curve.")
    if shape["change"] >= 0.5 and shape["change_year"] is not None:
        years = sorted({y for y in shape.get("change_years") or () if y is not None}) \
            or [shape["change_year"]]
        when = (f"year {years[0]}" if len(years) == 1 else
                "years " + ", ".join(map(str, years[:-1])) + f" and {years[-1]}")
        return (f"The trend changed in {when} (probability "
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
        Per draw, the exponential form's growth rate (per year; 0 or negative, a power
        law's: none).
    u : ndarray, shape [h]
        Years after the last recorded year.

    Returns
    -------
    ndarray, shape [n, h, d]
    """
    u = np.asarray(u, float)[None, :, None]
    # A power law's growth (minus its exponent) has no exponential part: its amplitude row
    # is 0 and its bend is in the curvature row.
    r = np.maximum(np.asarray(growth, float), 0.0)[:, None, None]
    # exp(r u) - 1 - r u, the part of an exponential beyond its tangent (0 when r = 0).
    bend = np.expm1(r * u) - r * u
    return (now[:, None, 0, :] + now[:, None, 1, :] * u + now[:, None, 2, :] * u ** 2
            + now[:, None, 3, :] * bend)
