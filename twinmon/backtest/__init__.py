"""``twinmon backtest``: how good the forecasts have been on the user's own history.

No truth file is needed. For each cut year ``k`` (from the ``backtest.min_years``-th year of a
unit to its last but one), the forecast is made from the years up to ``k`` only and scored
against what was later observed: the health indicator of each later year, i.e. the median
of the indicator over that year's posterior draws (the calibrated twin's reading of that
year's recording), and the first year whose recording was unsafe (P(unsafe) of that year's
posterior above ``safety.failure_probability``).

Scores (Saxena et al., "Metrics for offline evaluation of prognostic performance", 2010; the
metrics NASA's ProgPy implements):

* **coverage**: share of (unit, cut, later year) whose observed indicator lies inside the
  forecast's ``forecast.confidence`` interval of the indicator;
* **indicator error**: median absolute error of the forecast's median indicator;
* **time to failure**, for units whose history reaches unsafe in year ``F`` (end of life),
  with RUL ``F - k`` at cut ``k``:

  - **alpha-lambda accuracy**: at the cut ``k_lambda = k_0 + lambda (F - k_0)`` (the nearest
    cut; ``k_0`` the first cut), is the predicted RUL within ``+- alpha`` times the true RUL?
    (``backtest.alpha`` 0.2, ``backtest.lambda`` 0.5);
  - **relative accuracy** at that cut: ``1 - |RUL - RUL_pred| / RUL``;
  - **prognostic horizon**: ``F - k*``, with ``k*`` the first cut from which every
    prediction stays within the alpha cone.

  A forecast that sees no failure within its horizon predicts RUL = horizon + 1 (censored).

The per-cut posteriors are the stored yearly posteriors truncated at the cut: exact for the
sequential method (each year's posterior uses only earlier years). A joint posterior's years
were calibrated knowing the later years, so with the joint method each cut's history is
calibrated again from the observations (``observations_path``; the config's calibrate
settings, one calibration per cut year). Without the observations the joint posterior is
truncated instead: the back-test is then optimistic, and says so (``warnings``).
"""
from __future__ import annotations

import dataclasses
import os
import tempfile
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from .. import artifacts, lineage
from ..config import Config
from ..errors import ArtifactError
from ..plausibility import check_observations
from .artifact import SECTIONS, read_backtest, write_backtest
from .scores import (BacktestSummary, TTFScore, UnitBacktest, coverage_by_record,
                     coverage_verdict, ttf_scores, wilson_interval)

__all__ = ["BacktestSummary", "SECTIONS", "TTFScore", "UnitBacktest", "backtest",
           "calibrate_cut", "check_calibrated_from", "coverage_by_record", "coverage_verdict",
           "read_backtest", "truncate", "ttf_scores", "wilson_interval", "write_backtest"]

def truncate(up, last_year: int):
    """A unit's posterior restricted to the years up to ``last_year`` (trend draws dropped:
    they were fitted on the whole history)."""
    keep = np.asarray(up.years) <= last_year
    n_y = len(up.years)
    out = {}
    for f in dataclasses.fields(up):
        v = getattr(up, f.name)
        if f.name == "fit":
            v = {k: np.asarray(a)[keep] for k, a in v.items()}
        elif f.name == "trend":
            v = {}
        elif isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == n_y:
            v = v[keep]
        out[f.name] = v
    return type(up)(**out)


def check_calibrated_from(cfg: Config, posterior_path, observations_path, units: list):
    """The observations must be those the posterior was calibrated from: its provenance
    lists their hash (a posterior written before provenance recorded it: the units must
    be there).

    Returns
    -------
    Observations
        The file's content, read once for every cut (:func:`calibrate_cut`).

    Raises
    ------
    ArtifactError
        A missing or other file, or one without some unit of the posterior.
    """
    from ..observations import read_observations
    if not Path(observations_path).is_file():
        raise ArtifactError(f"{observations_path}: file not found (expected the observations "
                            f"{posterior_path} was calibrated from)")
    made_from = {r.get("sha256") for r in artifacts.read_provenance(posterior_path)
                 .get("inputs", [])}
    digest = artifacts.file_sha256(observations_path)
    if made_from and digest not in made_from:
        raise ArtifactError(f"{observations_path}: not the observations {posterior_path} was "
                            f"calibrated from (sha256 {digest[:12]} is not among its inputs)")
    obs = read_observations(observations_path, cfg.model.output.name)
    check_observations(cfg, obs)
    missing = [u for u in units if u not in obs.units]
    if missing:
        raise ArtifactError(f"{observations_path}: no unit {missing[0]!r} of {posterior_path}")
    return obs


def calibrate_cut(cfg: Config, surrogate_path, obs, units: list, last_year: int,
                  workdir, method: str = "joint") -> dict:
    """Posteriors of ``units`` calibrated from their records up to ``last_year`` only.

    Parameters
    ----------
    cfg : Config
        Its ``calibrate`` section (sampler, seed) as for the full history.
    surrogate_path : path-like
    obs : Observations
        The unit's whole records (``read_observations``).
    units : list of str
    last_year : int
    workdir : path-like
        Where the cut's observations and posterior are written.
    method : str
        The method of the full history's posterior, one whose years know the later ones
        (``joint`` or ``laplace``; only those posteriors' cuts are calibrated again).

    Returns
    -------
    dict unit -> UnitPosterior
    """
    from ..calibrate import calibrate, read_posterior
    from ..observations import write_observations
    # The cut's units are fewer than the fleet's: ``calibrate.method: auto`` would pick by
    # their count, where the cut must be calibrated as the full history was.
    cfg = dataclasses.replace(cfg, calibrate=dataclasses.replace(cfg.calibrate, method=method))
    workdir = Path(workdir)
    cut_obs = workdir / f"observations_to_{last_year}.h5"
    write_observations(cut_obs, obs.up_to(last_year, units))
    out = workdir / f"posterior_to_{last_year}.h5"
    calibrate(cfg, surrogate_path, cut_obs, out)
    return dict(read_posterior(out).units)


@artifacts.locks_output("output", "twinmon backtest")
def backtest(cfg: Config, posterior_path: str | os.PathLike, surrogate_path: str | os.PathLike,
             output: str | os.PathLike | None = None, executor=None,
             progress: Optional[Callable[[int, int], None]] = None,
             observations_path: str | os.PathLike | None = None) -> BacktestSummary:
    """Back-test the forecasts on the history in a posterior (see the module docstring).

    ``observations_path``: the observations the posterior was calibrated from; with a joint
    posterior, each cut's history is calibrated again from them (without: truncated, and
    the summary warns that the scores are optimistic). Not used for a sequential posterior.

    Raises
    ------
    ArtifactError
        Unusable inputs (as ``forecast``), or no unit with enough years for one cut.
    """
    from ..calibrate import Posterior, read_posterior
    from ..forecast import (box_is_physical, degrading_directions, forecast_limit_state,
                           forecast_units)
    from ..reduce import check_made_for, read_surrogate
    from ..safety import Indicator
    posterior_path, surrogate_path = Path(posterior_path), Path(surrogate_path)
    bt = cfg.backtest
    post = read_posterior(posterior_path)
    sur = read_surrogate(surrogate_path)
    check_made_for(cfg, surrogate_path, sur.input_names, sur.time, sur.bounds,
                   "simulate and reduce")
    # (The observations a joint posterior is calibrated again from are checked with the
    # cuts, by check_calibrated_from.)
    lineage.check_chain({"posterior": posterior_path, "surrogate": surrogate_path})
    if list(post.input_names) != cfg.model.input_names:
        raise ArtifactError(f"{posterior_path}: posterior inputs {list(post.input_names)} "
                            f"differ from the config's inputs {cfg.model.input_names}")
    directions = degrading_directions(cfg, sur)
    box_ok = box_is_physical(cfg)
    # Built once for every cut: it depends on the config and the FMU, not on the units.
    limit_state = forecast_limit_state(cfg, directions, box_ok)[0]
    h = cfg.forecast.horizon
    c = cfg.forecast.confidence
    q = [(1 - c) / 2, 0.5, (1 + c) / 2]

    # The whole history once: the observed indicator and unsafe years.
    full, _, _ = forecast_units(cfg, post, sur, posterior_path=posterior_path,
                                executor=executor, directions=directions, box_ok=box_ok,
                                limit_state=limit_state)
    units = {}
    years_of = {u: np.asarray(post.units[u].years, int) for u in post.units}
    cuts_of = {u: y[bt.min_years - 1:-1] for u, y in years_of.items()}
    all_cuts = sorted({int(k) for v in cuts_of.values() for k in v})
    if not all_cuts:
        raise ArtifactError(f"{posterior_path}: no unit has more than backtest.min_years = "
                            f"{bt.min_years} years: nothing to back-test")
    joint = any(getattr(p, "trend", None) for p in post.units.values())
    # The method that drew the trend (a posterior written before it was recorded: joint).
    method = artifacts.read_provenance(posterior_path).get("method") or "joint"
    method = method if method in ("joint", "laplace") else "joint"
    recalibrate = joint and observations_path is not None
    if recalibrate:
        obs = check_calibrated_from(cfg, posterior_path, observations_path, list(post.units))
    warnings = []
    if joint and not recalibrate:
        warnings.append(f"{posterior_path}: joint posterior truncated at each cut, its years "
                        "calibrated knowing the later ones: the scores are optimistic; pass "
                        "the observations (--observations) to calibrate each cut again")
    preds = {u: {} for u in post.units}
    with tempfile.TemporaryDirectory(prefix="twinmon-backtest-") as tmp:
        for n, k in enumerate(all_cuts):
            at = [u for u in post.units if k in cuts_of[u]]
            sub = (calibrate_cut(cfg, surrogate_path, obs, at, k, tmp, method)
                   if recalibrate else {u: truncate(post.units[u], k) for u in at})
            cut_post = Posterior(post.input_names, sub, post.path, post.fit_windows)
            res, _, _ = forecast_units(cfg, cut_post, sur, posterior_path=posterior_path,
                                       executor=executor, directions=directions, box_ok=box_ok,
                                       limit_state=limit_state)
            for u, uf in res.items():
                preds[u][k] = (uf.indicator_quantiles(q),
                               -1 if uf.failure_year is None else int(uf.failure_year))
            if progress:
                progress(n + 1, len(all_cuts))

    ind = Indicator.from_config(cfg)
    limit = cfg.safety.failure_probability
    pairs_in, errs, ttf = [], [], {}
    for u, uf in full.items():
        yrs = years_of[u]
        v = np.where(np.isnan(uf.indicator_observed), np.inf, uf.indicator_observed)
        obs = np.quantile(v, 0.5, axis=1, method="inverted_cdf")
        unsafe = uf.p_unsafe_observed > limit
        eol = int(yrs[np.argmax(unsafe)]) if unsafe.any() else None
        cuts = np.array(sorted(preds[u]), int)
        lo = np.array([preds[u][k][0][0] for k in cuts]).reshape(-1, h)
        med = np.array([preds[u][k][0][1] for k in cuts]).reshape(-1, h)
        hi = np.array([preds[u][k][0][2] for k in cuts]).reshape(-1, h)
        fp = np.array([preds[u][k][1] for k in cuts], int)
        b = UnitBacktest(yrs, obs, unsafe, cuts, lo, med, hi, fp, eol, h,
                         tuple(sorted({int(e[0]) for e in
                                       getattr(post.units[u], "events", None) or ()})))
        units[u] = b
        pairs_in += [inside for _, inside in b.scored()]
        for ci, j, y in b.pairs():
            o = obs[np.flatnonzero(yrs == y)[0]]
            if np.isfinite(o) and np.isfinite(med[ci, j]):
                errs.append(abs(med[ci, j] - o))
        if eol is not None and cuts.size:
            s = ttf_scores(cuts, fp, eol, h, bt.alpha, bt.lambda_value)
            if s is not None:
                ttf[u] = s
    coverage = float(np.mean(pairs_in)) if pairs_in else float("nan")
    in_band, message = coverage_verdict(coverage, len(pairs_in), c, bt.coverage_band)
    if not in_band:
        warnings.append(message)
    by_record, more = coverage_by_record(units, c, bt.coverage_band)
    warnings += more
    summary = BacktestSummary(units, coverage,
                              len(pairs_in), float(np.median(errs)) if errs else float("nan"),
                              ttf, str(output or ""), c, warnings,
                              "recalibrated" if recalibrate else "truncated",
                              coverage_in_band=in_band,
                              coverage_band=(c - bt.coverage_band, c + bt.coverage_band),
                              by_record=by_record)
    if output is not None:
        write_backtest(output, cfg, summary, ind, [posterior_path, surrogate_path] +
                       ([observations_path] if recalibrate else []))
    return summary
