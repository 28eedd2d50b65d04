"""The fleet's prior of the joint method's year-to-year sd, and each unit's draws under it.

A jointly calibrated unit samples its trend with a year-to-year sd per input, which ten
years of one unit cannot tell from the years' estimation errors; the units of a fleet share
it. With ``forecast.pool_sigma`` and at least ``forecast.pool_min_units`` jointly
calibrated units, :func:`fleet_sigma_prior` fits a log-normal prior of that sd over the
fleet (:mod:`twinmon.calibrate.fleet`), and :func:`_pool_unit` resamples each unit's draws
to its posterior under that prior. It is the one thing a unit's forecast takes from the
rest of its fleet.
"""
from __future__ import annotations

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError, CalibrationError
from .streams import unit_rng

#: Below this effective number of posterior draws after pooling, forecast warns: the unit's
#: Monte Carlo rests on that many distinct trend states (the benchmark's seeds 11-16, 1000
#: kept draws: 31-72 at the fewest, 154-276 the median).
POOL_MIN_ESS = 30


def fleet_sigma_prior(cfg: Config, post):
    """The fleet's prior of the joint method's year-to-year sd (:mod:`twinmon.calibrate.fleet`),
    fitted on the posterior's jointly calibrated units; None when ``forecast.pool_sigma`` is
    off or fewer than ``forecast.pool_min_units`` units were calibrated jointly.

    Returns
    -------
    FleetPrior or None

    The units' ``sigma`` draws ([keep_draws, d] each) are read before the units stream
    through the forecast. A posterior written before the prior's scale was
    recorded (``trend/sigma_scale``) is taken to have been calibrated with this config's
    ``calibrate.prior_width``.
    """
    from ..calibrate.fleet import fit_fleet_prior
    from ..calibrate.trend import sigma_prior_scale
    if not cfg.forecast.pool_sigma:
        return None
    default = sigma_prior_scale(cfg)
    sigmas, bases = [], []
    d = default.size
    for unit, trend in _sigma_draws(post):
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


def _sigma_draws(post):
    """``(unit, {"sigma": [n, d][, "sigma_scale": [d]]})`` per jointly calibrated unit. From
    a file only those datasets are read, in one opening of it: a sequential posterior, which
    has no trend, costs a look at each unit's group."""
    units = post.units
    if not isinstance(units, artifacts.LazyUnits):
        for u in units:
            trend = getattr(units[u], "trend", None) or {}
            if trend:
                yield u, trend
        return
    with artifacts.open_artifact(units.path, "posterior") as f:
        for u in units:
            g = f["units"][u]
            if "trend" in g:
                yield u, {key: artifacts.get(g["trend"], key, units.path)
                          for key in ("sigma", "sigma_scale")
                          if key == "sigma" or key in g["trend"]}


def _pooling_dict(fleet, names: list) -> dict:
    """What the forecast pooled: the fleet's log-normal prior of the year-to-year sd (median,
    log-sd) and the calibration's half-Cauchy scale, per input."""
    if fleet is None:
        return {"pooled": False}
    return {"pooled": True, "units": fleet.n_units,
            "median": dict(zip(names, np.round(fleet.median, 6).tolist())),
            "log_sd": dict(zip(names, np.round(fleet.tau, 4).tolist())),
            "calibration_scale": dict(zip(names, np.round(fleet.base, 6).tolist()))}


def _pool_unit(cfg: Config, unit: str, trend: dict, samples: np.ndarray,
               fleet) -> tuple[dict, np.ndarray, float]:
    """A jointly calibrated unit's trend draws and years' draws [n_y, n, d] resampled to the
    fleet's prior of the year-to-year sd; returns them and the weights' effective number of
    draws."""
    from ..calibrate.trend import TREND_DRAWS
    idx, ess_frac = fleet.resample(np.asarray(trend["sigma"], float), unit_rng(cfg, unit, 5))
    pooled = {k: (np.asarray(v)[idx] if k in TREND_DRAWS else v) for k, v in trend.items()}
    # The artifact thins the years' and the trend's draws alike, so draw j is one chain
    # state in both; a posterior whose counts differ keeps its years' draws as they are.
    if samples.shape[1] == idx.size:
        samples = samples[:, idx, :]
    return pooled, samples, ess_frac * idx.size
