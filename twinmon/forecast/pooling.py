"""The fleet's priors of a trend posterior -- its year-to-year sd and its trend shapes --
and each unit's draws under them.

A jointly calibrated unit samples its trend with a year-to-year sd per input, which ten
years of one unit cannot tell from the years' estimation errors; the units of a fleet share
it. With ``forecast.pool_sigma`` and at least ``forecast.pool_min_units`` jointly
calibrated units, :func:`fleet_sigma_prior` fits a log-normal prior of that sd over the
fleet (:mod:`twinmon.calibrate.fleet`). A laplace posterior's units also weighed trend
shapes (a line, accelerating forms, a change) whose forms ten years of one unit cannot tell
apart; with ``forecast.pool_shapes`` :func:`fleet_shape_prior` fits the fleet's prior
probabilities of those forms (:mod:`twinmon.calibrate.fleet_shapes`). :func:`_pool_unit`
resamples each unit's draws to its posterior under both. They are the one thing a unit's
forecast takes from the rest of its fleet.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Optional

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError, CalibrationError
from .streams import unit_rng

if TYPE_CHECKING:
    from ..calibrate.fleet_shapes import FleetShapes

#: Below this effective number of posterior draws after pooling, forecast warns: the unit's
#: Monte Carlo rests on that many distinct trend states (the benchmark's seeds 11-16, 1000
#: kept draws: 31-72 at the fewest, 154-276 the median).
POOL_MIN_ESS = 30


@dataclass(frozen=True)
class ShapePriors:
    """The fleet's priors of the trend forms, by what a unit's slopes show.

    ``drifting``, fitted on every unit, is the prior of a unit with an input whose slope
    drifts beyond normal ageing; ``steady``, fitted on the units none of whose slopes does
    when there are at least ``forecast.pool_min_units`` of them (else None: they take
    ``drifting``), the prior of those units.
    Wear, not normal ageing, is what accelerates: given the whole fleet's prior, the healthy
    units of a fleet of exponential wear were extended as exponentials, and 26 of 36 were
    told a failure year within the horizon (none true; benchmarks/prognosis.py, flow, seeds
    43, 47, 53)."""

    drifting: FleetShapes
    steady: Optional[FleetShapes] = None

    def blend(self, p_drifting: float) -> FleetShapes:
        """The prior a unit's future is drawn under when it drifts with probability
        ``p_drifting`` (:func:`drift_probability`): ``p drifting + (1 - p) steady``, the two
        priors averaged by the unit's own evidence of drifting. A slope test at
        ``forecast.alpha`` alone decides it too often for the steady prior: a pump whose
        coefficient fell 3.73 -> 3.01 with its yearly fall growing from 0.01 to 0.15 (its
        slope -0.080 +- 0.017 against normal ageing's -0.02 +- 0.03, p = 0.038) took the
        sound units' prior, its forecast held the line at 0.87 and missed from the second
        year on (benchmarks/RESULTS.md, *The fleet's prior of the shapes by a unit's
        evidence of drifting*)."""
        if self.steady is None or p_drifting >= 1.0:
            return self.drifting
        if p_drifting <= 0.0:
            return self.steady
        return replace(self.drifting, proportions=p_drifting * self.drifting.proportions
                       + (1.0 - p_drifting) * self.steady.proportions)


def fleet_priors(cfg: Config, post, shape_priors: dict, directions: dict | None = None) -> tuple:
    """Both of the fleet's priors, :func:`fleet_sigma_prior`'s and
    :func:`fleet_shape_prior`'s, from one pass over the posterior's trend draws, read before
    the first unit's forecast can start (1000 units: 2.2 s, against 3.4 s in two passes).

    ``directions`` (input -> :class:`~.directions.Direction`): with them, the units whose
    slopes stay within normal ageing (:func:`_drifts`) get a prior of their own
    (:class:`ShapePriors`).

    Returns
    -------
    (FleetPrior or None, ShapePriors or None)
    """
    shapes_wanted = _pools_shapes(cfg, shape_priors)
    if not cfg.forecast.pool_sigma and not shapes_wanted:
        return None, None
    keys = ("sigma", "sigma_scale") + (("shape", "growth", "start", "slope")
                                       if shapes_wanted else ())
    draws = list(_trend_draws(post, keys, years=shapes_wanted))
    fleet = fleet_sigma_prior(cfg, post, draws)
    every = fleet_shape_prior(cfg, post, shape_priors, fleet, draws)
    if every is None:
        return fleet, None
    steady = None
    if directions is not None:
        still = [(u, t) for u, t in draws if "slope" in t
                 and not _drifts(cfg, t, directions, fleet)]
        steady = fleet_shape_prior(cfg, post, shape_priors, fleet, still)
    return fleet, ShapePriors(every, steady)


def sigma_weights(trend: dict, fleet=None) -> np.ndarray:
    """Weights [n] (summing to 1) that take a unit's trend draws to the fleet's prior of the
    year-to-year sd (``fleet``, a FleetPrior, as :func:`_pool_unit` resamples them); equal
    without one."""
    sigma = np.asarray(trend["sigma"], float)
    return fleet.weights(sigma) if fleet is not None else np.full(len(sigma), 1.0 / len(sigma))


def drift_probability(cfg: Config, slopes: np.ndarray, weights: np.ndarray,
                      directions: dict) -> float:
    """The posterior probability that some input of a unit wears beyond normal ageing: the
    weighted share of its slope draws ``slopes`` [n, d] (``weights`` [n], summing to 1) in
    which some input's slope lies past ``normal_rate +- normal_rate_tolerance`` on its
    degrading side (either side for an input whose direction is unknown). From the joint
    draws, so that inputs whose estimates trade off count once."""
    names = cfg.model.input_names
    rate = np.array([cfg.model.inputs[n].normal_rate for n in names])
    tol = np.array([cfg.model.inputs[n].normal_rate_tolerance for n in names])
    sign = np.array([directions[n].sign for n in names])
    s = np.asarray(slopes, float)
    up, down = s > rate + tol, s < rate - tol
    beyond = np.where(sign > 0, up, np.where(sign < 0, down, up | down))
    return float(np.clip(np.asarray(weights, float) @ np.any(beyond, axis=1), 0.0, 1.0))


def _drifts(cfg: Config, trend: dict, directions: dict, fleet=None) -> bool:
    """Whether some input's slope in its last segment drifts beyond normal ageing: the
    forecast's per-input test (:func:`~.trend.posterior_slope_test`'s: the posterior's
    slope draws, normal, at ``forecast.alpha``), the draws weighted to the fleet's sigma as
    :func:`_pool_unit` resamples them."""
    from ..calibrate.trend import last_segment
    from .trend import POSTERIOR_DOF, slope_p_value
    slope = last_segment(trend, "slope")                                  # [n, d]
    w = sigma_weights(trend, fleet)
    b = w @ slope
    se = np.sqrt(np.maximum(w @ (slope - b) ** 2, 0.0))
    return any(slope_p_value(b[i], se[i], POSTERIOR_DOF, cfg.model.inputs[name].normal_rate,
                             cfg.model.inputs[name].normal_rate_tolerance,
                             directions[name].sign) < cfg.forecast.alpha
               for i, name in enumerate(cfg.model.input_names))


def fleet_sigma_prior(cfg: Config, post, draws: list | None = None):
    """The fleet's prior of the joint method's year-to-year sd (:mod:`twinmon.calibrate.fleet`),
    fitted on the posterior's jointly calibrated units; None when ``forecast.pool_sigma`` is
    off or fewer than ``forecast.pool_min_units`` units were calibrated jointly.

    Returns
    -------
    FleetPrior or None

    The units' ``sigma`` draws ([keep_draws, d] each) are read before the units stream
    through the forecast (``draws``: :func:`_trend_draws`' units, already read). A posterior
    written before the prior's scale was recorded (``trend/sigma_scale``) is taken to have
    been calibrated with this config's ``calibrate.prior_width``.
    """
    from ..calibrate.fleet import fit_fleet_prior
    from ..calibrate.trend import sigma_prior_scale
    if not cfg.forecast.pool_sigma:
        return None
    default = sigma_prior_scale(cfg)
    sigmas, bases = [], []
    d = default.size
    for unit, trend in (draws if draws is not None
                        else _trend_draws(post, ("sigma", "sigma_scale"))):
        sigma = np.asarray(trend["sigma"], float)
        base = np.asarray(trend.get("sigma_scale", default), float)
        where = f"{post.path}: /units/{unit}/trend/sigma"
        if sigma.ndim != 2 or sigma.shape[1] != d or not sigma.size:
            raise ArtifactError(f"{where} must have shape (draws, {d}), got {sigma.shape}")
        bad = ~(np.isfinite(sigma) & (sigma >= 0))
        if bad.any():
            j, i = np.argwhere(bad)[0]
            raise ArtifactError(f"{where} must hold finite values >= 0, got {sigma[j, i]} "
                                f"at draw {j}, input {i}")
        if base.shape != (d,) or not np.all(np.isfinite(base) & (base > 0)):
            raise ArtifactError(f"{post.path}: /units/{unit}/trend/sigma_scale must hold "
                                f"{d} finite values > 0, got {base.tolist()}")
        sigmas.append(sigma)
        bases.append(base)
    if len(sigmas) < cfg.forecast.pool_min_units:
        return None
    if not np.allclose(bases, bases[0], rtol=1e-9):
        raise CalibrationError(
            f"{post.path}: the jointly calibrated units were calibrated with different "
            "priors of their year-to-year sd (calibrate.prior_width); pooling them needs one "
            "(re-run calibrate, or set forecast.pool_sigma: false)")
    return fit_fleet_prior(sigmas, bases[0])


def _trend_draws(post, keys: tuple, years: bool = False):
    """``(unit, {key: array})`` per jointly calibrated unit, the trend fields ``keys`` it
    has (``sigma`` always) and, with ``years``, its recorded ``years``. From a file only
    those datasets are read, in one opening of it: a sequential posterior, which has no
    trend, costs a look at each unit's group."""
    units = post.units
    if not isinstance(units, artifacts.LazyUnits):
        for u in units:
            trend = getattr(units[u], "trend", None) or {}
            if trend:
                out = {k: trend[k] for k in keys if k in trend}
                if years:
                    out["years"] = np.asarray(units[u].years)
                yield u, out
        return
    with artifacts.open_artifact(units.path, "posterior") as f:
        for u in units:
            g = f["units"][u]
            if "trend" in g:
                t = g["trend"]
                there = set(t)
                out = {key: artifacts.get(t, key, units.path)
                       for key in keys if key == "sigma" or key in there}
                if years:
                    out["years"] = g["record"].fields("year")[()]
                yield u, out


def fleet_shape_prior(cfg: Config, post, shape_priors: dict, fleet=None,
                      draws: list | None = None):
    """The fleet's prior of the trend forms (:mod:`twinmon.calibrate.fleet_shapes`), fitted
    on the posterior's units that weighed shapes (a laplace posterior's); None when
    ``forecast.pool_shapes`` is off, the posterior weighed the line alone, or fewer than
    ``forecast.pool_min_units`` units weighed shapes on segments long enough for a shape
    other than the line.

    Parameters
    ----------
    shape_priors : dict
        ``calibrate.shapes`` as the posterior recorded it
        (:func:`~.trendfit.recorded_shapes`): the prior the units' draws follow.
    fleet : FleetPrior, optional
        The fleet's prior of sigma (:func:`fleet_sigma_prior`): each unit's shares of the
        forms are then those of its draws weighted to it, as :func:`_pool_unit` will.
    draws : list, optional
        :func:`_trend_draws`' units with ``sigma``, ``shape``, ``growth``, ``start`` and
        ``years``, already read.

    Returns
    -------
    FleetShapes or None
    """
    from ..calibrate.fleet_shapes import fit_fleet_shapes
    from ..calibrate.shapes import available_forms, form_of, form_priors
    if not _pools_shapes(cfg, shape_priors):
        return None
    base = form_priors(shape_priors)
    shares, avail = [], []
    for unit, trend in (draws if draws is not None else
                        _trend_draws(post, ("sigma", "shape", "growth", "start"), years=True)):
        if "shape" not in trend:
            continue
        forms = form_of(trend["shape"], trend["growth"])
        w = sigma_weights(trend, fleet)
        shares.append(np.bincount(forms, weights=w, minlength=base.size)[:base.size])
        start = np.asarray(trend["start"])
        last = start[(start >= 0).sum(axis=0) - 1, np.arange(start.shape[1])]   # [d]
        yrs = np.asarray(trend["years"])
        span = (yrs[None, :] >= last[:, None]).sum(axis=1)                      # [d]
        # A segment shorter than pool_shapes_min_years says nothing of the fleet's shapes
        # (its evidence leans on the line whatever the wear): the line alone is available.
        avail.append(available_forms(span) if span.max() >= cfg.forecast.pool_shapes_min_years
                     else available_forms(np.zeros_like(span)))
    if len(shares) < cfg.forecast.pool_min_units:
        return None
    fit = fit_fleet_shapes(np.array(shares), np.array(avail), base)
    # Units whose segments allow the line alone say nothing of the shapes.
    return fit if fit.n_units >= cfg.forecast.pool_min_units else None


def _pools_shapes(cfg: Config, shape_priors: dict) -> bool:
    """Whether the forecast fits the fleet's prior of the trend forms: ``forecast.pool_shapes``
    on and the posterior weighed more than one form."""
    from ..calibrate.shapes import form_priors
    return bool(cfg.forecast.pool_shapes
                and np.count_nonzero(form_priors(shape_priors)) >= 2)


def _pooling_dict(fleet, names: list) -> dict:
    """What the forecast pooled: the fleet's log-normal prior of the year-to-year sd (median,
    log-sd) and the calibration's half-Cauchy scale, per input."""
    if fleet is None:
        return {"pooled": False}
    return {"pooled": True, "units": fleet.n_units,
            "median": dict(zip(names, np.round(fleet.median, 6).tolist())),
            "log_sd": dict(zip(names, np.round(fleet.tau, 4).tolist())),
            "calibration_scale": dict(zip(names, np.round(fleet.base, 6).tolist()))}


def _shapes_dict(shapes) -> dict:
    """What the forecast pooled of the trend shapes: the fleet's prior of each form and the
    calibration's; ``steady``, the prior of the units whose slopes stay within normal
    ageing (``{"pooled": false}`` when they take the fleet's)."""
    if shapes is None:
        return {"pooled": False}
    from ..calibrate.shapes import form_names
    one = (lambda f: {"pooled": True, "units": f.n_units, "prior_units": f.prior_units,
                      "fleet": dict(zip(form_names(), np.round(f.proportions, 4).tolist())),
                      "calibration": dict(zip(form_names(), np.round(f.base, 4).tolist()))})
    if not isinstance(shapes, ShapePriors):
        return one(shapes)
    return {**one(shapes.drifting),
            "steady": one(shapes.steady) if shapes.steady is not None else {"pooled": False}}


def _pool_unit(cfg: Config, unit: str, trend: dict, samples: np.ndarray,
               fleet=None, shapes=None, stream: int = 5) -> tuple[dict, np.ndarray, float]:
    """A jointly calibrated unit's trend draws and years' draws [n_y, n, d] resampled to the
    fleet's prior of the year-to-year sd (``fleet``, a FleetPrior) and of the trend forms
    (``shapes``, a FleetShapes; used when the unit's draws have shapes), one systematic
    resampling by the product of the two weights (its uniform from the unit's ``stream``,
    :mod:`.streams`); returns them and the weights' effective number of draws."""
    from ..calibrate.fleet import systematic_resample
    from ..calibrate.shapes import form_of
    from ..calibrate.trend import TREND_DRAWS
    w = sigma_weights(trend, fleet)
    if shapes is not None and "shape" in trend:
        w = w * np.exp(shapes.log_weights(form_of(trend["shape"], trend["growth"])))
        w /= w.sum()
    idx, ess_frac = systematic_resample(w, unit_rng(cfg, unit, stream))
    pooled = {k: (np.asarray(v)[idx] if k in TREND_DRAWS else v) for k, v in trend.items()}
    # The artifact thins the years' and the trend's draws alike, so draw j is one chain
    # state in both; a posterior whose counts differ keeps its years' draws as they are.
    if samples.shape[1] == idx.size:
        samples = samples[:, idx, :]
    return pooled, samples, ess_frac * idx.size
