"""Whether a unit's trend model could have predicted its own history, one year ahead.

A trend model that cannot follow a unit's history (wear that reverses or oscillates, two
separate steps, a repair no event records and the repair scan missed, a year whose estimate
is off) still gives a forecast with intervals that look sure. This check judges the model
*out of sample*, as a forecast is used: for each recorded year ``k`` whose trend segment has
at least :data:`MIN_YEARS` years before it, the model is fitted to the years before ``k`` and
predicts year ``k``'s site (:func:`predict_ahead`):

    x_k ~ sum_(s, p) w_sp N(H_s beta_sp, H_s P_sp^-1 H_s' + diag(sigma_p^2) + C_k)

over the posterior's shapes ``s`` (:mod:`twinmon.calibrate.shapes`, with the priors the
posterior was calibrated with; the straight line alone for a posterior without shapes) and a
fixed grid of the year-to-year sd ``sigma_p`` (:func:`sigma_grid`: under the fleet's prior of
it when the forecast pools sigma over the fleet, else calibration's half-Cauchy prior). At a
given sigma each shape is a linear Gaussian model: ``beta``'s posterior (mean, precision
``P_sp``) and the evidence that weighs it are closed form
(:func:`~twinmon.calibrate.gaussian_trend.linear_gaussian`, the shapes of one size on the
whole grid at once); ``H_s`` maps the coefficients to the trend one year on (the shape's ``now``
map extended, :func:`~twinmon.calibrate.shapes.extend`), ``C_k`` is the site's own covariance.
sigma is learnt from the years before ``k`` only, like the rest: the unit's posterior sigma,
fitted to the whole history, grows to swallow what the trend misses (a unit whose wear
reversed twice had sigma 2.0 N.m.s/rad against the fleet's median 0.24, and every year
inside its noise). The fleet's prior matters: under the half-Cauchy alone a few years leave
sigma so uncertain that a year 6 sd off lies 1.4 predictive sd off.

Each year's error is standardised by the Rosenblatt transform of its predictive mixture (the
conditional PIT of each input given the ones before it, through the normal quantile): under
the model the ``d`` values of a year, and the years' (one-step-ahead predictions of a
sequence, Dawid's prequential principle), are independent standard normals. Two views, each
at ``alpha / 2`` (Bonferroni): the sum of squares over the ``m`` years predicted, chi-square
with ``d m`` degrees of freedom (many moderate misses: oscillation, a reversal), and the worst
year's chi-square with ``d`` (one outlying year), times ``m`` (Bonferroni over the years).

The sites are the laplace method's (each year's likelihood summarised, ``UnitPosterior.site``);
for a posterior without them the yearly posterior means and covariances stand in
(:func:`unit_sites`).

A record whose every segment has :data:`MIN_YEARS` years or fewer leaves no year to predict:
nothing is checked, and a unit whose verdict is not healthy is then unreliable for that
reason (:func:`describe_unchecked`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..config import Config

#: Fewest years of the segment in force before a year predicted (a line through fewer
#: extrapolates its own noise).
MIN_YEARS = 3
#: Points of the year-to-year sd's grid (:func:`sigma_grid`) and their seed.
SIGMA_GRID = 64
SIGMA_SEED = 20240611
#: Mixture components weighing less than this share of the largest are dropped.
NEGLIGIBLE = 1e-9
#: A PIT closer than this to 0 or 1 is held there (its normal quantile stays finite: 37 sd).
PIT_FLOOR = 1e-300


@dataclass
class TrendFit:
    """The one-year-ahead check of a unit's trend model.

    Attributes
    ----------
    p_value : float
        Of the combined test (module docstring); 1 when no year could be predicted.
    years : ndarray of int, shape [m]
        The years predicted.
    z : ndarray, shape [m, d]
        Their standardised errors (Rosenblatt; independent N(0, 1) under the model).
    marginal : ndarray, shape [m, d]
        Each input's error over its predictive sd (the mixture's marginal moments), for
        the reason's words.
    year_p : ndarray, shape [m]
        Each year's p-value alone (chi-square with d dof of its ``z``).
    p_sum, p_worst : float
        The two views' p-values (sum of squares; worst year, Bonferroni over the years).
    shapes : tuple of str
        The shapes the model averaged (``line`` alone, or with ``accelerating``, ``change``).
    """

    p_value: float
    years: np.ndarray
    z: np.ndarray
    marginal: np.ndarray
    year_p: np.ndarray
    p_sum: float
    p_worst: float
    shapes: tuple

    def missed(self, alpha: float) -> np.ndarray:
        """Indices of the years to name: those significant alone at ``alpha``, else the
        (up to) two worst."""
        bad = np.flatnonzero(self.year_p < alpha)
        return bad if bad.size else np.sort(np.argsort(self.year_p)[:2])

    def as_dict(self, alpha: float) -> dict:
        """For ``--json`` and ``forecast.h5``."""
        return {"p_value": float(self.p_value), "years": [int(y) for y in self.years],
                "year_p_values": [float(f"{p:.3g}") for p in self.year_p],
                "missed_years": [int(self.years[k]) for k in self.missed(alpha)]
                if self.p_value < alpha else [],
                "shapes": list(self.shapes)}


def cut_indices(years: np.ndarray, starts: list, min_years: int = MIN_YEARS) -> np.ndarray:
    """Indices ``k`` of the years that can be predicted from the years before them: in every
    input's segment in force at year ``k`` (the last start at or before it) at least
    ``min_years`` recorded years come before ``k``.

    Parameters
    ----------
    years : ndarray of int, shape [K]
    starts : list of ndarray of int, one per input
        First year of each segment.
    """
    years = np.asarray(years)
    out = []
    for k in range(1, years.size):
        ok = True
        for s in starts:
            first = s[s <= years[k]].max()
            ok &= int(np.sum((years[:k] >= first))) >= min_years
        if ok:
            out.append(k)
    return np.array(out, dtype=int)


def sigma_grid(cfg: Config, fleet=None, n: int = SIGMA_GRID
               ) -> tuple[np.ndarray, np.ndarray]:
    """A fixed quasi-random grid of the year-to-year sd and its prior log weights.

    With ``fleet`` (:class:`~twinmon.calibrate.fleet.FleetPrior`: the fleet's log-normal
    prior of sigma, which the forecast pools a unit's draws to), ``log sigma_i`` spans its
    median +- 3 ``tau`` and is weighted by it, ``tau`` held at the prior's floor
    (:data:`~twinmon.calibrate.fleet.MIN_TAU`, the spread of a sound fleet's units): the
    question is whether the unit follows the trend with a sound unit's year-to-year
    variation, and a fitted spread above the floor is the fleet's misfitting units
    themselves (their sigma swallowed what the trend missed: a fleet of reversing wear had
    tau 1.5, which let a swing of 17 site sd pass as scatter). Otherwise calibration's
    half-Cauchy prior of scale ``A`` (:func:`~twinmon.calibrate.trend.sigma_prior_scale`)
    over ``[A / 100, 3 A]``.
    Scrambled Sobol points with a fixed seed, uniform in ``log sigma`` (hence the Jacobian
    ``log sigma`` in the half-Cauchy's weight).

    Returns
    -------
    sigma : ndarray, shape [n, d]
        Input units.
    log_prior : ndarray, shape [n]
    """
    from ..calibrate.shape_screen import sobol_points
    from ..calibrate.trend import sigma_prior_scale
    A = sigma_prior_scale(cfg)
    u = sobol_points(len(A), n, SIGMA_SEED)
    if fleet is not None:
        from ..calibrate.fleet import MIN_TAU
        mu = np.log(np.asarray(fleet.median, float))
        tau = np.minimum(np.asarray(fleet.tau, float), MIN_TAU)
        log_s = mu - 3 * tau + 6 * tau * u
        return np.exp(log_s), np.sum(-0.5 * ((log_s - mu) / tau) ** 2, axis=1)
    lo, hi = np.log(A / 100), np.log(3 * A)
    sigma = np.exp(lo + (hi - lo) * u)
    return sigma, np.sum(np.log(sigma) - np.log1p((sigma / A) ** 2), axis=1)


def _weight_tables(cov: np.ndarray, sigma: np.ndarray, A: np.ndarray, priors: dict) -> tuple:
    """:func:`~twinmon.calibrate.gaussian_trend.year_weight_table` at the grid's sigma
    ``sigma`` [P, d] and at the change screen's
    (:func:`~twinmon.calibrate.shape_screen.screen_grid` of sigma's prior scale ``A`` [d];
    None when the change shape has no prior weight: no screen)."""
    from ..calibrate.gaussian_trend import year_weight_table
    from ..calibrate.shape_screen import screen_grid
    return (year_weight_table(cov, sigma),
            year_weight_table(cov, screen_grid(A)[0]) if priors.get("change", 0) > 0 else None)


def predict_ahead(cfg: Config, years: np.ndarray, x: np.ndarray, cov: np.ndarray,
                  starts: list, priors: dict, k: int, grid: tuple,
                  tables: tuple | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trend model fitted to years ``[0, k)`` and its predictive of year ``k``'s site.

    The predictive is a mixture over the shapes and the sigma grid: per (shape, sigma) a
    linear Gaussian model whose coefficients' posterior and evidence are closed form;
    weights prior times evidence. The shapes' Zellner priors take the straight line's
    posterior mean of sigma on these years as their reference, as calibration does.

    Every shape is the line plus a set of extra columns
    (:func:`~twinmon.calibrate.shape_columns.shape_sets`), so its posterior is a block
    update of the line's at each sigma (:func:`~twinmon.calibrate.shape_screen.block_terms`,
    :func:`~twinmon.calibrate.shape_screen.set_loglik`): with ``V = P_e + F_ee`` the set's
    posterior precision given the line's and ``G = H_e - H_b Pb^-1 B_e``, the trend one year
    on has mean ``H_b mu_b + G V^-1 r_e`` and covariance ``H_b Pb^-1 H_b' + G V^-1 G'``
    (the block inverse of the whole precision), and the evidence gains the screen's term.
    The same numbers as a model per shape, at a few batched products per set size.

    Parameters
    ----------
    years : ndarray of int, shape [K]
    x, cov : ndarray, shapes [K, d], [K, d, d]
        The years' sites (input units).
    starts : list of ndarray of int
        Each input's segment starts; year ``k`` must lie in the segment in force at year
        ``k - 1`` (:func:`cut_indices`).
    priors : dict shape name -> float
        ``calibrate.shapes`` the posterior was drawn with.
    grid : (sigma [P, d], log_prior [P])
        :func:`sigma_grid`.
    tables : tuple, optional
        :func:`~twinmon.calibrate.gaussian_trend.year_weight_table` of ``cov`` at ``grid``'s
        sigma and at the change screen's
        (:func:`~twinmon.calibrate.shape_screen.screen_grid`; None without the change
        shape), when already computed (:func:`_weight_tables`: a unit's cuts share them).

    Returns
    -------
    w : ndarray, shape [n]
        The components' posterior weights (those below :data:`NEGLIGIBLE` of the largest
        dropped).
    mean : ndarray, shape [n, d]
    S : ndarray, shape [n, d, d]
        Each component's predictive mean and covariance of year ``k``'s site.
    """
    from ..calibrate.gaussian_trend import GaussianTrend, weights_of, year_weights
    from ..calibrate.methods.laplace import line_model
    from ..calibrate.shape_columns import OCCAM, line_now, shape_sets
    from ..calibrate.shape_screen import block_terms, set_loglik
    from ..calibrate.shapes import extend
    from ..calibrate.stacked import forward_solve
    from ..calibrate.trend import sigma_prior_scale
    sig, log_p0 = grid
    A = sigma_prior_scale(cfg)
    if tables is None:
        tables = _weight_tables(cov, sig, A, priors)
    yk = np.asarray(years[:k])
    xk, ck = x[:k], cov[:k]
    d = x.shape[1]
    st = [s[s <= yk[-1]] for s in starts]
    _, Mk, prec, mean0, slopes, _ = line_model(cfg, yk, st)
    line = GaussianTrend(xk, ck, Mk, prec, mean0, A)
    on_sig = weights_of(tables[0], k)
    # The line's posterior at the grid, on the weights the cuts share.
    Pb, _, mu, ll = line._conditional(sig, weights=on_sig)
    # The line's posterior mean of sigma on these years: the shapes' reference (as
    # calibration takes it from the line's sigma points).
    lw = log_p0 + ll
    w = np.exp(lw - lw.max())
    s_ref = (w / w.sum()) @ sig
    sets = shape_sets(line, yk, np.array([s[-1] for s in st]), priors, s_ref,
                      None if tables[1] is None else weights_of(tables[1], k))
    u = [float(years[k] - yk[-1])]
    # Each coefficient's map to the trend one year on (the ``now`` rows extended; extend()
    # is linear in them, so applied to each column's rows it gives the map's columns).
    Hb = extend(np.moveaxis(line_now(Mk, slopes), 2, 0), np.zeros(Mk.shape[2]), u)[:, 0].T
    He = extend(np.moveaxis(sets.now, 2, 0), sets.growth, u)[:, 0].T          # [d, n_x]
    # Occam's window, as calibration's mixture: a shape far less probable than the best at
    # the reference sigma could not hold weight, and is left out of the mixture.
    comps = ([((), sets.line_log_prior)] if np.isfinite(sets.line_log_prior) else []) + \
        [(cols, lp) for _, cols, lp, _ in sets.sets]
    groups = _by_size(comps)
    ok = np.ones(len(comps), bool)
    if sets.sets:
        # The block terms at the grid and at the reference sigma in one evaluation (the
        # reference the last point, with the line's posterior there), and each set's
        # log-likelihood at both in one call per size: a call per size and sigma costs
        # more than the grid rows of the sets the window drops (on 60 units of a fleet it
        # dropped none).
        ref_w = year_weights(ck, s_ref[None])
        Pr, _, mr, lr = line._conditional(s_ref[None], weights=ref_w)
        bt = block_terms(line, sets.E, np.vstack([sig, s_ref[None]]),
                         (np.concatenate([Pb, Pr]), np.concatenate([mu, mr]),
                          np.concatenate([ll, lr])),
                         tuple(np.concatenate(p) for p in zip(on_sig, ref_w)))
        terms = {size: set_loglik(bt, sets.S, np.array([comps[j][0] for j in of]))
                 for size, of in groups if size}
        quick = np.empty(len(comps))
        for size, of in groups:
            quick[of] = [comps[j][1] for j in of] + (
                terms[size][0][:, -1] if size else lr[0])
        ok = quick >= quick.max() + np.log(OCCAM)
        # G's line part, H_b Pb^-1 B, at every grid point [P, d, n_x].
        HPiB = np.einsum("da,pac->pdc", Hb, bt.PiB[:-1])
    line_mean = mu @ Hb.T                                                     # [P, d]
    line_cov = Hb @ np.linalg.solve(Pb, np.broadcast_to(Hb.T, Pb.shape[:2] + (d,)))
    eye = np.eye(d)
    noise = sig[:, :, None] ** 2 * eye + cov[k]                               # [P, d, d]
    logw, means, covs = [], [], []
    for size, of in groups:
        rows = [r for r, j in enumerate(of) if ok[j]]
        if not rows:
            continue
        lp = np.array([comps[of[r]][1] for r in rows])[:, None]
        if size == 0:
            logw.append((lp + log_p0 + ll).ravel())
            means.append(line_mean)
            covs.append(line_cov + noise)
            continue
        idx = np.array([comps[of[r]][0] for r in rows])                       # [G, n_e]
        lls, L, z = (a[rows, :-1] for a in terms[size])
        # G = H_e - H_b Pb^-1 B_e per set and sigma point, [G, P, d, n_e].
        Gm = He[:, idx].transpose(1, 0, 2)[:, None] - HPiB[:, :, idx].transpose(2, 0, 1, 3)
        # With V = L L': G V^-1 r_e = Y' z and G V^-1 G' = Y' Y, Y = L^-1 G'.
        Y = forward_solve(L, np.swapaxes(Gm, 2, 3))                          # [G, P, n_e, d]
        logw.append((lp + log_p0 + lls).ravel())
        means.append((line_mean + np.einsum("gped,gpe->gpd", Y, z)).reshape(-1, d))
        covs.append((line_cov + np.swapaxes(Y, 2, 3) @ Y + noise).reshape(-1, d, d))
    logw = np.concatenate(logw)
    keep = logw >= logw.max() + np.log(NEGLIGIBLE)
    w = np.exp(logw[keep] - logw.max())
    return w / w.sum(), np.concatenate(means)[keep], np.concatenate(covs)[keep]


def _by_size(comps: list) -> list:
    """The mixture's components ``(columns, log prior)`` grouped by their number of extra
    columns (a group's sets are evaluated together): ``(size, positions)`` by size."""
    sizes = sorted({len(c) for c, _ in comps})
    return [(n, [j for j, (c, _) in enumerate(comps) if len(c) == n]) for n in sizes]


def standardise(y: np.ndarray, w: np.ndarray, mean: np.ndarray, S: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """A site's error under a Gaussian mixture predictive.

    Parameters
    ----------
    y : ndarray, shape [d]
    w, mean, S : ndarray, shapes [n], [n, d], [n, d, d]

    Returns
    -------
    z : ndarray, shape [d]
        Rosenblatt transform: input ``i``'s PIT under the mixture conditional on inputs
        ``< i`` (the components reweighted by their density of those), through the normal
        quantile. Independent N(0, 1) when ``y`` is drawn from the mixture.
    marginal : ndarray, shape [d]
        ``(y - E y) / sd(y)`` per input under the mixture.
    """
    from scipy.special import ndtr, ndtri

    from ..calibrate.stacked import forward_solve, small_cholesky
    L = small_cholesky(S)                                                      # [n, d, d]
    e = forward_solve(L, (y - mean)[:, :, None])[:, :, 0]                      # [n, d]
    diag = np.einsum("nii->ni", L)
    d = y.size
    z = np.empty(d)
    logw = np.log(np.maximum(w, 1e-300))
    for i in range(d):
        # Components reweighted by their density of the inputs before i.
        lw = logw - 0.5 * np.sum(e[:, :i] ** 2, axis=1) - np.sum(np.log(diag[:, :i]), axis=1)
        c = np.exp(lw - lw.max())
        c /= c.sum()
        lower, upper = float(c @ ndtr(e[:, i])), float(c @ ndtr(-e[:, i]))
        # From the smaller tail, so that a far miss keeps its size.
        z[i] = (ndtri(max(lower, PIT_FLOOR)) if lower < upper
                else -ndtri(max(upper, PIT_FLOOR)))
    m = w @ mean
    var = np.einsum("n,nii->i", w, S) + w @ (mean - m) ** 2
    return z, (y - m) / np.sqrt(var)


def check_trend_fit(cfg: Config, years: np.ndarray, x: np.ndarray, cov: np.ndarray,
                    starts: list, priors: dict, fleet=None,
                    min_years: int = MIN_YEARS) -> Optional[TrendFit]:
    """The one-year-ahead check of a unit's trend model (module docstring).

    Parameters
    ----------
    years : ndarray of int, shape [K]
    x, cov : ndarray, shapes [K, d], [K, d, d]
        The years' sites (input units, squared).
    starts : list of ndarray of int, one per input
        Each input's segment starts (recorded events and repairs found).
    priors : dict shape name -> float
        The shapes and their prior probabilities (``{"line": 1}``: the line alone).
    fleet : FleetPrior, optional
        The fleet's prior of sigma (:func:`sigma_grid`); else calibration's.

    Returns
    -------
    TrendFit or None
        None when no year can be predicted (too few years in a segment).
    """
    from ..calibrate.trend import sigma_prior_scale
    from ..distributions import chi2_sf
    years = np.asarray(years)
    cuts = cut_indices(years, starts, min_years)
    if cuts.size == 0:
        return None
    d = x.shape[1]
    z = np.empty((cuts.size, d))
    marg = np.empty((cuts.size, d))
    grid = sigma_grid(cfg, fleet)
    tables = _weight_tables(cov, grid[0], sigma_prior_scale(cfg), priors)
    for j, k in enumerate(cuts):
        w, mean, S = predict_ahead(cfg, years, x, cov, starts, priors, int(k), grid, tables)
        z[j], marg[j] = standardise(x[k], w, mean, S)
    q = np.sum(z * z, axis=1)
    year_p = chi2_sf(q, d)
    p_sum = float(chi2_sf(q.sum(), d * cuts.size))
    p_worst = float(min(1.0, cuts.size * year_p.min()))
    used = tuple(n for n in ("line", "accelerating", "change") if priors.get(n, 0) > 0)
    return TrendFit(p_value=min(1.0, 2 * min(p_sum, p_worst)), years=years[cuts], z=z,
                    marginal=marg, year_p=year_p, p_sum=p_sum, p_worst=p_worst, shapes=used)


def unit_sites(cfg: Config, up, post_cov: np.ndarray, trend: dict, found=(),
               change_year=None) -> tuple[np.ndarray, np.ndarray, list]:
    """What :func:`check_trend_fit` reads of a unit's posterior.

    The sites are the laplace method's (``up.site``: each year's likelihood summarised);
    without them, the yearly posterior means and covariances stand in. The segments are the
    trend posterior's (``trend["start"]``), else the recorded events and the repairs
    ``found`` (:class:`~twinmon.repairs.FoundRepair`). A ``change_year`` (the posterior's
    change shape, :func:`change_year`: one year for every input, or a year or None per
    input) starts a segment too, as a repair does: a step is
    unpredictable the year it comes (its size has the change shape's prior, a few years'
    scatter); what is checked is that the years before and after it follow the trend.

    Parameters
    ----------
    up : UnitPosterior
    post_cov : ndarray, shape [K, d, d]
        Covariance of each year's posterior draws.
    trend : dict
        The trend posterior (``UnitPosterior.trend``), or empty.

    Returns
    -------
    x : ndarray, shape [K, d]
    cov : ndarray, shape [K, d, d]
    starts : list of ndarray of int
    """
    from ..calibrate.trend import segment_starts
    site = getattr(up, "site", None) or {}
    if site:
        x, cov = np.asarray(site["x"], float), np.asarray(site["cov"], float)
    else:
        x, cov = np.asarray(up.mean, float), np.asarray(post_cov, float)
    if trend and "start" in trend:
        st = np.asarray(trend["start"])
        starts = [st[:, i][st[:, i] >= 0] for i in range(st.shape[1])]
    else:
        events = [(e[0], e[1]) for e in getattr(up, "events", None) or ()]
        events += [(r.year, c) for r in found for c in r.components]
        starts = segment_starts(cfg, np.asarray(up.years), events)
    if change_year is not None:
        per = ([change_year] * len(starts) if np.ndim(change_year) == 0 else
               [-1 if y is None else y for y in change_year])
        starts = [np.union1d(s, [y]) if y > s[-1] else s for s, y in zip(starts, per)]
    return x, cov, starts


def change_year(shape: dict, priors: dict):
    """The posterior's most probable change year when the data favour a change: its
    posterior probability (:func:`~twinmon.calibrate.shapes.shape_summary`) at least its
    prior share of ``priors`` (a Bayes factor of at least 1 against the other shapes);
    else None. A summary with each input's year (``change_years``) gives that list (None
    for an input that does not change), else one year for every input. On the step
    fleets of benchmarks/prognosis.py (seed 11) half the single steps held less than half
    the posterior (a step of 3 site sd: change 0.34-0.44), and their step year,
    unpredictable one year ahead, failed the check."""
    total = sum(max(float(p), 0.0) for p in priors.values())
    if not shape or shape.get("change_year") is None or priors.get("change", 0) <= 0:
        return None
    if shape["change"] < priors.get("change", 0) / total:
        return None
    per = shape.get("change_years")
    return list(per) if per and any(y is not None for y in per) else \
        int(shape["change_year"])


def recorded_shapes(cfg: Config, posterior_path) -> dict:
    """``calibrate.shapes`` as the posterior at ``posterior_path`` recorded it (its
    provenance), else the config's: the one-year-ahead check must weigh the shapes the
    posterior weighed."""
    import yaml

    from ..artifacts import read_provenance
    from ..errors import ArtifactError
    try:
        text = read_provenance(posterior_path).get("config") or ""
        shapes = (yaml.safe_load(text) or {}).get("calibrate", {}).get("shapes")
    except (ArtifactError, OSError, yaml.YAMLError, AttributeError):
        shapes = None
    return dict(shapes) if isinstance(shapes, dict) else dict(cfg.calibrate.shapes)


def describe_latest(cfg: Config, fit: TrendFit, last_year: int, alpha: float) -> str:
    """The unit's status reason when its latest year alone was not what the trend of the
    years before expected (at ``alpha``, no correction over the years: the forecast starts
    from that year), or ``""``.

    Over the whole history such a year is one among several (:func:`describe_miss` corrects
    for their number), but the forecast extends from it: a pump coefficient stepping down
    0.5 in the last year, then flat, was read as wear starting to accelerate, and the unit
    told it fails three years later with probability 0.85. One year cannot tell a step, an
    estimate off, a repair or faster wear apart; the next year's transient will."""
    if fit is None or fit.years.size == 0 or int(fit.years[-1]) != int(last_year) or \
            not fit.year_p[-1] < alpha:
        return ""
    names = cfg.model.input_names
    i = int(np.argmax(np.abs(fit.marginal[-1])))
    v = float(fit.marginal[-1, i])
    return (f"prognosis unreliable: the latest year, {int(last_year)}, is not where the trend "
            f"of the years before put it (p = {fit.year_p[-1]:.2g}; {names[i]} lay "
            f"{abs(v):.1f} sd {'above' if v > 0 else 'below'} that forecast): the forecast "
            "starts from that one year, which cannot tell a step, an estimate off, a repair or "
            "faster wear apart; next year's transient will")


def describe_unchecked(years: np.ndarray, min_years: int = MIN_YEARS) -> str:
    """The unit's status reason when no year of its record could be predicted (a record,
    or every trend segment of it, of ``min_years`` years or fewer) and its verdict is not
    healthy: the trend its failure year and intervals extend was never checked.

    A line through three years' estimates follows their errors as readily as the wear
    (benchmarks/prognosis.py ``--family irregular``): on the pump's flow alone (seed 137)
    three of the five units with three recorded years and a fault or ambiguity named were
    told a failure in year 8 or 9 with P(unsafe) 0.75-0.85 that none of them reaches, their
    indicator's 90 % interval covering 0-2 of the 7 future years (a healthy unit among
    them, its third year's estimates far along the ridge of the two inputs); of the DC
    drive's twelve (seeds 79 and 131) three were told their failure year, three a year off,
    one two years late, and one failing in year 9 was told no failure."""
    years = np.asarray(years)
    return (f"prognosis unreliable: with {years.size} recorded year(s) (years "
            f"{int(years[0])}-{int(years[-1])}) no year could be predicted from the "
            f"{min_years} or more of its trend before it, so the trend its failure year and "
            "intervals extend was never checked against the unit's own history (a line "
            "through so few years follows their estimates' errors as readily as the wear); "
            "the next year's transient allows the check")


def describe_miss(cfg: Config, fit: TrendFit, alpha: float) -> str:
    """The unit's status reason when the check fails: the years missed, the p-value, the
    worst input and what to do."""
    names = cfg.model.input_names
    idx = fit.missed(alpha)
    yrs = ", ".join(str(int(fit.years[k])) for k in idx)
    worst = int(idx[np.argmin(fit.year_p[idx])])
    i = int(np.argmax(np.abs(fit.marginal[worst])))
    v = float(fit.marginal[worst, i])
    model = ("straight line" if fit.shapes == ("line",) else
             "trend (" + ", ".join({"line": "a straight line", "accelerating": "accelerating",
                                    "change": "one change of level and rate per input"}[s]
                                   for s in fit.shapes) + ")")
    return (f"prognosis unreliable: the trend missed year(s) {yrs} one year ahead "
            f"(p = {fit.p_value:.2g} over the {fit.years.size} years it predicted; in year "
            f"{int(fit.years[worst])} {names[i]} lay {abs(v):.1f} sd "
            f"{'above' if v > 0 else 'below'} the forecast): the unit's history does not "
            f"follow the {model} its forecast extends (wear that reverses or a part that steps "
            "more than once, a repair no event records, or a year's estimate off), so its "
            "failure year and intervals may be wrong; check its maintenance records (record a "
            "repair with 'twinmon events add') and those years' fit ('twinmon diagnose')")
