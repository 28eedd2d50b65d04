"""Stage ``forecast``: trends of the calibrated inputs, failure probability, root cause, plan.

For every unit the yearly posterior means of each degradation input are regressed on the year
(OpenTURNS ``LinearModelAlgorithm``, ordinary least squares, as in the paper). The fitted lines
are extended over ``forecast.horizon`` years past the last observation with prediction
intervals (Student t with ``n - 2`` degrees of freedom, not normal quantiles).

Monte Carlo samples of the inputs drawn from the predictive distribution of the unit's
future state are propagated through the twin: points inside the surrogate's training box
through the Gaussian process surrogate (vectorised), points outside it through the FMU
itself, so a Gaussian process is never extrapolated. A sample is unsafe when its health
indicator passes ``safety.unsafe_if``, when the FMU reports the non-physical mode, or when
the FMU run fails. The failure year is the first future year whose probability of being
unsafe exceeds ``safety.failure_probability``.

Detection and root cause (:func:`~.judge.judge`): the trend of the unit's health indicator
(its posterior draws per observed year through the twin) is tested against the drift
normal ageing of every input produces, and the inputs' slopes jointly against the
normal-ageing box, each at ``forecast.alpha`` / 2. A drifting unit's components get
probabilities of ageing faster than normal; the verdict names those at or above
``forecast.attribution_confidence``, or says ``ambiguous`` with the probabilities and the
unrecorded channel that would tell them apart. Each input keeps its one-sided t test of the
slope against ``normal_rate`` +- ``normal_rate_tolerance`` in its degrading direction (the
paper's test, reported per trend).

Units stream through in chunks over ``simulate.executor``'s workers
(:func:`~.workers.iter_forecast`) and are written as they come back, so memory does not grow
with the fleet.

See ``docs/forecast.md`` for the choices (OLS on the estimates, correlated draws) and the
artifact layout.

Layout: one concern per file; each imports only those above it in this table.

=================  ==========================================================================
``streams.py``     :func:`~.streams.unit_rng`: each unit's random streams, keyed by its name
``trend.py``       :class:`Trend`, :func:`fit_trend`, repairs, the per-input slope tests
``covariance.py``  the yearly estimates' error covariance, the slopes' covariance, ``cover``
``detection.py``   :class:`IndicatorDrift`: the indicator's drift and the inputs' box test
``attribution.py`` :class:`Attribution`: probabilities of each abnormal component, the
                   channel that would separate an ambiguous verdict
``judge.py``       :func:`judge` (detection, then attribution), :func:`verdict`,
                   :func:`prognosis_status` and the ``STATUS_*`` values
``limitstate.py``  :func:`~.limitstate.build_limit_state`: outside the box, a model of
                   the margin to the safety limit learnt from FMU runs
``twin.py``        :func:`evaluate_twin` (surrogate in the box; outside, the limit-state
                   model where it is sure, else the FMU), :class:`TwinResult`,
                   :func:`box_is_physical`, the ``SOURCE_*`` values
``directions.py``  :class:`Direction`, :func:`degrading_directions`
``predictive.py``  the future inputs' distribution and its draws (``forecast.predictive``)
``plan.py``        :func:`maintenance_plan`
``pooling.py``     :func:`fleet_sigma_prior`: the fleet's prior of the joint method's
                   year-to-year sd, each unit's draws resampled to it
``trendfit.py``    :func:`~.trendfit.check_trend_fit`: the trend-fit gate, the posterior's
                   trend model judged one year ahead over the unit's history
``unit.py``        :class:`UnitForecast`, :class:`ForecastSummary`
``artifact.py``    ``forecast.h5``: the writer, :func:`read_forecast`, :class:`Forecast`
``chunk.py``       a chunk of units: plan each, one batch through the twin, finish each
``workers.py``     :func:`iter_forecast`: the chunks here or on a process / Dask pool
``__init__``       the stage :func:`forecast` (writes ``forecast.h5``) and
                   :func:`forecast_units` (in memory, for ``backtest``)
=================  ==========================================================================
"""
from __future__ import annotations

import os
import time as _time
from pathlib import Path
from typing import Callable, Optional

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError, CalibrationError
from .artifact import SECTIONS, Forecast, _open_forecast, _write_unit, read_forecast
from .attribution import AMBIGUOUS, HEALTHY, SEVERAL, Attribution, attribute
from .covariance import estimate_error_covariance, filter_error_covariance, slope_covariance
from .detection import IndicatorDrift, box_test_uniform, indicator_drift
from .directions import Direction, degrading_directions, indicator_noise
from .judge import (MIN_TREND_YEARS, STATUS_OK, STATUS_UNRELIABLE, STATUS_WITHHELD, judge,
                    prognosis_status, verdict)
from .plan import maintenance_plan
from .pooling import (POOL_MIN_ESS, _pooling_dict, _shapes_dict, fleet_priors,
                      fleet_sigma_prior)
from .predictive import (StatePredictive, residual_correlation, sample_predictive,
                         sample_state, state_interval, state_predictive)
from .streams import SEED_OFFSET
from .trend import (POSTERIOR_DOF, SLOPE_CI, Trend, fit_trend, posterior_slope_test,
                    repair_years, segment_trend, slope_test)
from .limitstate import LimitState, build_limit_state, forecast_limit_state
from .trendfit import recorded_shapes
from .twin import (SOURCE_FAILED, SOURCE_FMU, SOURCE_MODEL, SOURCE_SURROGATE, TwinResult,
                   box_is_physical, evaluate_twin)
from .unit import ForecastSummary, UnitForecast
from .workers import iter_forecast

__all__ = ["forecast", "forecast_units", "iter_forecast", "read_forecast", "Forecast",
           "ForecastSummary", "UnitForecast", "SECTIONS", "SEED_OFFSET", "POOL_MIN_ESS",
           "STATUS_OK", "STATUS_WITHHELD", "STATUS_UNRELIABLE", "SOURCE_SURROGATE",
           "SOURCE_FMU", "SOURCE_FAILED", "SOURCE_MODEL", "LimitState", "build_limit_state",
           "forecast_limit_state", "SLOPE_CI", "POSTERIOR_DOF", "Trend", "fit_trend",
           "repair_years", "segment_trend", "slope_test", "posterior_slope_test", "verdict",
           "judge", "prognosis_status", "Direction", "degrading_directions",
           "indicator_noise", "TwinResult", "evaluate_twin", "box_is_physical",
           "residual_correlation", "sample_predictive", "StatePredictive",
           "state_predictive", "sample_state", "state_interval", "maintenance_plan",
           "fleet_sigma_prior", "estimate_error_covariance", "filter_error_covariance",
           "slope_covariance", "IndicatorDrift", "indicator_drift", "box_test_uniform",
           "Attribution", "attribute", "AMBIGUOUS", "HEALTHY", "SEVERAL"]


@artifacts.locks_output("output", "twinmon forecast")
def forecast(cfg: Config, posterior_path: str | os.PathLike, surrogate_path: str | os.PathLike,
             output: str | os.PathLike, truth_path: str | os.PathLike | None = None,
             executor=None, workers: Optional[int] = None,
             progress: Optional[Callable[[int, int], None]] = None) -> ForecastSummary:
    """Forecast every unit of a posterior and write ``forecast.h5``.

    Units stream through: read from the posterior one chunk at a time, forecast on the pool
    of :func:`iter_forecast`, written and dropped (the summary keeps each unit's figures, not
    its Monte Carlo arrays), so memory does not grow with the fleet.

    Parameters
    ----------
    cfg : Config
    posterior_path : path-like
        Posterior artifact of ``calibrate`` (per unit and year: samples and mean).
    surrogate_path : path-like
        Surrogate artifact of ``reduce``.
    output : path-like
        The forecast artifact to write.
    truth_path : path-like, optional
        Truth file of ``fabricate``: adds each unit's true failure year.
    executor : Executor, optional
        For the FMU runs when the units are forecast in this process (one unit, or one
        worker); defaults to ``cfg.simulate.executor`` with ``cfg.simulate.workers``.
    workers : int, optional
        Processes over units (default ``cfg.simulate.workers``; 0 = one per core).
    progress : callable, optional
        ``progress(done, total)`` over the units.

    Raises
    ------
    ArtifactError
        An input artifact is missing, of the wrong kind, or made for other inputs.
    CalibrationError
        Every unit has fewer than 3 years (no prediction interval is possible); a fleet's
        units with fewer are left out (``too_few_years``), the others forecast.
    """
    from ..calibrate import read_posterior
    from ..executors import check_workers
    from ..lineage import check_chain
    from ..reduce import check_made_for, read_surrogate

    start = _time.perf_counter()
    check_workers(cfg.simulate.workers if workers is None else workers)
    posterior_path, surrogate_path = Path(posterior_path), Path(surrogate_path)
    # A posterior of another surrogate or another fleet's chain: refused naming both files.
    check_chain({"posterior": posterior_path, "surrogate": surrogate_path})
    names = cfg.model.input_names
    post = read_posterior(posterior_path)
    if list(post.input_names) != names:
        raise ArtifactError(f"{posterior_path}: posterior inputs {list(post.input_names)} "
                            f"differ from the config's inputs {names}")
    sur = read_surrogate(surrogate_path)
    check_made_for(cfg, surrogate_path, sur.input_names, sur.time, sur.bounds,
                   "simulate and reduce")
    if not post.units:
        raise ArtifactError(f"{posterior_path}: no units in the posterior")
    made_with = artifacts.read_provenance(posterior_path).get("surrogate_id", "")
    if made_with and made_with != sur.fingerprint():
        raise ArtifactError(f"{posterior_path}: calibrated through another surrogate than "
                            f"{surrogate_path} (their fingerprints differ); re-run calibrate, "
                            "or pass the surrogate it was made with")
    truth = None
    if truth_path is not None:
        from ..fabricate import read_truth
        truth = read_truth(truth_path)
    directions = degrading_directions(cfg, sur)
    box_ok = box_is_physical(cfg)
    fleet, shapes = fleet_priors(cfg, post, recorded_shapes(cfg, posterior_path), directions)
    limit_state, why = forecast_limit_state(cfg, directions, box_ok)
    units, short = {}, {}
    with _open_forecast(output, cfg, names, directions, box_ok, seed=cfg.seed + SEED_OFFSET,
                        inputs=[posterior_path, surrogate_path] +
                        ([truth_path] if truth_path else [])) as f:
        f.attrs["sigma_pooling"] = artifacts.json_attr(_pooling_dict(fleet, names))
        f.attrs["limit_state"] = artifacts.json_attr(_limit_state_dict(limit_state, why))
        f.attrs["shape_pooling"] = artifacts.json_attr(_shapes_dict(shapes))
        for unit, uf in iter_forecast(cfg, post, sur, posterior_path=posterior_path,
                                      truth=truth, truth_path=truth_path, executor=executor,
                                      workers=workers, progress=progress,
                                      directions=directions, box_ok=box_ok, fleet=fleet,
                                      limit_state=limit_state, shapes=shapes, pack=True,
                                      skipped=short):
            _write_unit(f, cfg, unit, uf, names)
            units[unit] = uf.slim()
        if not units:
            # Nothing to forecast (the artifact being written is dropped).
            u, k = next(iter(short.items()))
            raise CalibrationError(f"{posterior_path}: unit {u} has {k} year(s); a trend with "
                                   f"prediction intervals needs at least {MIN_TREND_YEARS}"
                                   + (" (and so has every other unit)" if len(short) > 1
                                      else ""))
        f.attrs["too_few_years"] = artifacts.json_attr(short)
    warnings = [d.note for d in directions.values() if d.note]
    if short:
        warnings.append(
            f"{len(short)} unit(s) with fewer than {MIN_TREND_YEARS} calibrated years, too "
            "few for a trend, are not forecast: "
            + ", ".join(f"{u} ({k})" for u, k in short.items())
            + "; each is once its record has them")
    if why:
        warnings.append(f"{why}: every Monte Carlo point outside the design box ran through "
                        "the FMU")
    fell = [u + " (" + ", ".join(f"{' or '.join(r['components'])} year {r['year']}"
                                 for r in uf.repairs) + ")"
            for u, uf in units.items() if uf.repairs]
    if fell:
        warnings.append(f"{len(fell)} unit(s) fell back towards nominal as after a repair no "
                        f"event records: {', '.join(fell)}; their plans say how to record it")
    longest = max(len(uf.years_observed) for uf in units.values())
    if cfg.forecast.horizon > longest:
        # The trends' shapes (a curvature, a change) are fitted on the record: extended
        # beyond its length they reach values no part takes (a horizon of 30 on 10 years
        # put 1 % of a winding's draws past 70 000 Ohm, and ran 250 times the FMU work).
        warnings.append(
            f"forecast.horizon {cfg.forecast.horizon} years is longer than the longest "
            f"record ({longest} calibrated years): the trends are extrapolated beyond what "
            "they were fitted on, and the far years' intervals and FMU runs grow with it")
    few = {u: uf.pool_ess for u, uf in units.items() if uf.pool_ess < POOL_MIN_ESS}
    if few:
        worst = min(few, key=few.get)
        warnings.append(
            f"{len(few)} unit(s) keep fewer than {POOL_MIN_ESS} effective posterior draws "
            f"once their year-to-year sd is pooled over the fleet (fewest: {worst}, "
            f"{few[worst]:.0f}): their forecast rests on few trend draws; a larger "
            "calibrate.keep_draws keeps more")
    return ForecastSummary(units, str(output), _time.perf_counter() - start, box_ok,
                           warnings, _pooling_dict(fleet, names), _shapes_dict(shapes),
                           _limit_state_dict(limit_state, why), short)


def _limit_state_dict(model: Optional[LimitState], why: str) -> dict:
    """What ``--json`` and ``forecast.h5`` say of the limit-state model (``used`` false with
    the reason when it was asked for and not used)."""
    if model is None:
        return {"used": False, "reason": why}
    return {"used": True, **model.as_dict()}


def forecast_units(cfg: Config, post, sur, *, posterior_path="<memory>", truth=None,
                   truth_path=None, executor=None, workers: Optional[int] = None,
                   progress=None, directions=None, box_ok=None,
                   pool_over=None, limit_state=False) -> tuple[dict, dict, bool]:
    """The forecast of every unit of a loaded posterior, in memory (no file written).

    ``backtest`` (which calls it on truncated histories) and the benchmarks use it; the
    arguments are those of :func:`iter_forecast`. ``pool_over``: the posterior whose units
    the fleet's priors are fitted on (default ``post``), so that a few units are forecast
    as their whole fleet's forecast would forecast them. ``limit_state``: the model of the
    points outside the box (None: every one through the FMU); by default built here as
    :func:`forecast` builds it (a caller forecasting several times builds it once).

    Returns
    -------
    units : dict unit -> UnitForecast
        Every unit with at least ``MIN_TREND_YEARS`` calibrated years.
    directions : dict input -> Direction
    box_ok : bool
    """
    if directions is None:
        directions = degrading_directions(cfg, sur)
    if box_ok is None:
        box_ok = box_is_physical(cfg)
    if limit_state is False:
        limit_state = forecast_limit_state(cfg, directions, box_ok)[0]
    pool_over = post if pool_over is None else pool_over
    fleet, shapes = fleet_priors(cfg, pool_over, recorded_shapes(cfg, posterior_path),
                                 directions)
    # Units with too few years for a trend are left out, as forecast() leaves them.
    units = dict(iter_forecast(cfg, post, sur, posterior_path=posterior_path, truth=truth,
                               truth_path=truth_path, executor=executor, workers=workers,
                               progress=progress, directions=directions, box_ok=box_ok,
                               fleet=fleet, shapes=shapes, limit_state=limit_state,
                               skipped={}))
    return units, directions, box_ok
