"""Forecast a chunk of units: every unit's Monte Carlo points go through the twin in one batch.

For each unit of the chunk, :func:`_plan_unit` fits the trends and their tests and draws the
Monte Carlo points (future states, posterior draws of the observed years, the probes of the
indicator's gradient); the chunk's points then run through the twin at once
(:func:`~.twin.evaluate_twin`); :func:`_finish_unit` takes each unit's slice back:
probabilities of being unsafe, failure year, judgement, maintenance plan and prognosis
status. With a truth file, :func:`_add_truth` adds the true future and failure year.
:func:`_check_unit` refuses, before any work is sent out, a posterior that cannot be
forecast. The same code runs in this process or in a pool worker (:mod:`.workers`), on the
:class:`_TwinState` it was given.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from ..calibrate.shapes import describe_shape, shape_probabilities, shape_summary
from ..config import Config
from ..errors import ArtifactError, CalibrationError
from ..repairs import FoundRepair, find_repairs
from ..safety import trailing_run
from .attribution import HEALTHY, SEVERAL
from .covariance import estimate_error_covariance, filter_attenuation
from .detection import gradient_from, gradient_points, mid_state
from .judge import (MIN_LINE_DRAWS, MIN_TREND_YEARS, STATUS_OK, STATUS_UNRELIABLE,
                    STATUS_WITHHELD, describe_bend, describe_blind, describe_lag, describe_restart,
                    history_slope_draws, judge, prognosis_status, recent_restarts)
from .plan import (accelerating, level_cause, level_plan, maintenance_plan, nominal_plan,
                   restore_points, unconfirmed)
from .pooling import ShapePriors, _pool_unit, drift_probability, sigma_weights
from .predictive import (residual_correlation, sample_predictive, sample_state,
                         state_interval, state_predictive)
from .streams import unit_rng
from .trend import (posterior_slope_test, repair_years, segment_trend, shape_gate,
                    slope_test)
from .trendfit import (change_year, check_trend_fit, describe_latest, describe_miss,
                       describe_unchecked, unit_sites)
from .twin import SOURCE_FAILED, TwinResult, evaluate_twin
from .unit import UnitForecast


class _TwinState:
    """What forecasting a chunk needs once per process: the config, the surrogate and its
    numpy form (:func:`~twinmon.calibrate.samplers.gpbatch.make_predictor`: GPBatch, checked
    against OpenTURNS when built, tabulated where the table passes its own check), the FMU
    spec, the executor of the FMU runs and the limit-state model of the points outside the
    box (:class:`~.limitstate.LimitState`, or None)."""

    def __init__(self, cfg: Config, sur, spec, executor, limit_state=None):
        from ..calibrate.samplers.gpbatch import make_predictor
        self.cfg, self.sur, self.spec, self.executor = cfg, sur, spec, executor
        self.predict = make_predictor(sur)[0]
        self.limit_state = limit_state


def _check_unit(cfg: Config, posterior_path, unit: str, up) -> None:
    """A unit's posterior must allow a forecast (raised before any work is sent out)."""
    years = np.asarray(up.years, int)
    mean = np.asarray(up.mean, float)
    d = len(cfg.model.input_names)
    if years.size < MIN_TREND_YEARS:
        raise CalibrationError(f"{posterior_path}: unit {unit} has {years.size} year(s); a "
                               f"trend with prediction intervals needs at least "
                               f"{MIN_TREND_YEARS}")
    if mean.shape != (years.size, d) or not np.all(np.isfinite(mean)):
        raise ArtifactError(f"{posterior_path}: /units/{unit}/mean must be finite with "
                            f"shape ({years.size}, {d}), got shape {mean.shape}")
    _check_plausible(posterior_path, unit, np.asarray(up.samples, float), cfg)


def _truth_of(truth, truth_path, unit: str):
    """The unit's (years, inputs, future years, future inputs) of the truth file (the last
    two None when it has no future), or None without one."""
    if truth is None:
        return None
    if unit not in truth.inputs:
        raise ArtifactError(f"{truth_path}: unit {unit} is missing from the truth file")
    return (np.asarray(truth.years[unit], float), truth.inputs[unit],
            truth.future_years.get(unit), truth.future_inputs.get(unit))


def _forecast_chunk(state: _TwinState, units: list, *, directions: dict, box_ok: bool,
                    fit_windows: list, truth_path, fleet=None, shapes=None,
                    shape_priors: Optional[dict] = None,
                    input_range: Optional[np.ndarray] = None) -> list:
    """Forecast a chunk of units: their Monte Carlo points go through the twin in one batch.

    Parameters
    ----------
    state : _TwinState
    units : list of (unit, UnitPosterior, truth or None)
    input_range : ndarray, shape [d, 2], optional
        The range the FMU declares for each input (:func:`~twinmon.simulate.declared_range`):
        future draws beyond it are held at its bound.

    Returns
    -------
    list of (unit, UnitForecast)
    """
    cfg = state.cfg
    if not units:
        return []
    plans, points = [], []
    for unit, up, _ in units:
        p, pts = _plan_unit(cfg, unit, up, directions, fleet, shape_priors, shapes,
                            input_range)
        plans.append(p)
        points += pts
    twin = evaluate_twin(cfg, state.sur, np.concatenate(points), state.executor,
                         fmu_everywhere=not box_ok, predict=state.predict, spec=state.spec,
                         limit_state=state.limit_state)
    unsafe_all = twin.unsafe(cfg.safety)
    out, offsets, offset = [], [], 0
    for (unit, up, tr), p in zip(units, plans):
        offsets.append(offset)
        uf, offset = _finish_unit(cfg, unit, up, p, twin, unsafe_all, offset, directions,
                                  fit_windows)
        out.append(uf)
    # Units unsafe now with no drift to blame: which part's level puts them there, from the
    # twin at their last state with each input set back to nominal (a few points, for the
    # few units that need them; the others' results do not move).
    limit = cfg.safety.failure_probability
    need = [j for j, uf in enumerate(out) if uf.root_cause == HEALTHY
            and np.size(uf.p_unsafe_observed) and uf.p_unsafe_observed[-1] > limit]
    if need:
        d = len(cfg.model.input_names)
        last = [plans[j]["mean"][-1] for j in need]
        back = evaluate_twin(cfg, state.sur, np.concatenate([restore_points(cfg, x)
                                                             for x in last]),
                             state.executor, fmu_everywhere=not box_ok, predict=state.predict,
                             spec=state.spec, limit_state=state.limit_state)
        bad = back.unsafe(cfg.safety)
        for a, j in enumerate(need):
            rows = slice(a * (d + 1), (a + 1) * (d + 1))
            levels = level_cause(cfg, last[a], bad[rows], back.value[rows],
                                 float(np.nanmedian(out[j].indicator_observed[-1])))
            if levels:
                unit, up, _ = units[j]
                out[j] = _finish_unit(cfg, unit, up, plans[j], twin, unsafe_all, offsets[j],
                                      directions, fit_windows, levels)[0]
            elif bad[rows][-1]:
                # A new unit is past the limit too: the limit, not a part, is at fault.
                out[j].unsafe_at_nominal = float(back.value[rows][-1])
                out[j].plan = nominal_plan(cfg, float(back.value[rows][-1]),
                                           float(out[j].p_unsafe_observed[-1]),
                                           int(out[j].years_observed[-1]))
    for (unit, _, tr), uf in zip(units, out):
        if tr is not None:
            _add_truth(cfg, uf, unit, tr, truth_path, state.spec, state.executor)
    return list(zip([u for u, _, _ in units], out))


def _plan_unit(cfg: Config, unit: str, up, directions: dict, fleet=None,
               shape_priors: Optional[dict] = None, shapes=None,
               input_range: Optional[np.ndarray] = None) -> tuple[dict, list]:
    """A unit's trends, tests and Monte Carlo points (future states, posterior draws of the
    observed years, the probes of the indicator's gradient) before the twin runs.

    With ``fleet`` (:func:`~.pooling.fleet_sigma_prior`), a jointly calibrated unit's draws -- the
    years' and the trend's, which are the same chain states -- are first resampled to its
    posterior under the fleet's prior of the year-to-year sd; its yearly estimates are then
    those draws' means. With ``shapes`` (:func:`~.pooling.fleet_shape_prior`), the same
    resampling also takes a laplace posterior's future draws to the fleet's prior of the
    trend forms: :class:`~.pooling.ShapePriors`' by whether an input's slope drifts beyond
    normal ageing (its test rejects). ``shape_priors``: ``calibrate.shapes`` as the
    posterior recorded it (:func:`~.trendfit.recorded_shapes`; default the config's).
    ``input_range`` [d, 2]: the FMU's declared range of each input; a future draw beyond it
    (a trend extended to a negative damping, say) is held at the bound, the nearest state
    the model can be in."""
    fc = cfg.forecast
    shape_priors = dict(cfg.calibrate.shapes) if shape_priors is None else shape_priors
    names = cfg.model.input_names
    d = len(names)
    years = np.asarray(up.years, int)
    mean = np.asarray(up.mean, float)
    samples_post = np.asarray(up.samples, float)
    trend_post = getattr(up, "trend", None) or {}
    pool_ess = float("nan")
    # The trend's future is drawn under the fleet's prior of the shapes as well; the
    # verdict (detection, attribution: the wear over the record) reads the draws under the
    # calibration's prior of the shapes, so that the fleet's idea of where wear goes does
    # not move the judgement of how fast it went (resampled to the fleet's shapes, the
    # faults of one part were named "both" 17 times in 224 against 10 in 256:
    # benchmarks/prognosis.py, seeds 11-12, docs/forecast.md).
    calibrated, calibrated_samples = trend_post, samples_post
    future = trend_post
    if fleet is not None and trend_post:
        trend_post, pooled, pool_ess = _pool_unit(cfg, unit, trend_post, samples_post, fleet)
        future = trend_post
        if pooled is not samples_post:
            samples_post, mean = pooled, pooled.mean(axis=1)
    post_cov = np.array([np.cov(samples_post[k], rowvar=False).reshape(d, d)
                         for k in range(years.size)])
    since = repair_years(cfg, up, years)
    if trend_post:
        # The joint method looked for unrecorded repairs itself, in the years' likelihoods,
        # and its trend restarts there (since includes them).
        repairs = [FoundRepair(**r) for r in getattr(up, "found_repairs", None) or ()]
    else:
        # Yearly estimates are refitted here: the component's trend restarts at the jump,
        # as for a recorded event.
        repairs = find_repairs(cfg, years, mean, since,
                               {n: d.sign for n, d in directions.items()}, post_cov)
        since = repair_years(cfg, up, years, repairs)
    trends = {}
    slope_draws = history_draws = rate_draws = None
    changed = 0.0
    if trend_post:
        from ..calibrate.trend import last_segment
        slope_draws = last_segment(trend_post, "slope")         # [n, d]
        history_draws = history_slope_draws(trend_post)
        if "now" in trend_post and "shape" in trend_post:
            # The laplace method's trend shapes: the rate at the last year [n, d] and the
            # posterior's weight on wear that changed or accelerated (judge's detection).
            rate_draws = np.asarray(trend_post["now"], float)[:, 1, :]
            changed = 1.0 - float(shape_probabilities(trend_post["shape"])[0])
    for i, name in enumerate(names):
        spec = cfg.model.inputs[name]
        t = segment_trend(years, mean[:, i], since[name], spec)
        t.component = spec.component
        args = (spec.normal_rate, spec.normal_rate_tolerance, directions[name].sign, fc.alpha)
        trends[name] = (t if t.test else
                        posterior_slope_test(t, slope_draws[:, i], *args) if trend_post
                        else slope_test(t, *args))
    applied = None
    if shapes is not None and "shape" in calibrated:
        # The fleet's prior of the shapes by what the unit's slopes show (ShapePriors): a
        # unit that surely drifts beyond normal ageing (a slope test rejects) takes the one
        # learnt from the fleet's wear; another, the two averaged by its posterior
        # probability of drifting, so that a unit whose record shows no wear takes the
        # prior of the units like it.
        applied = shapes
        if isinstance(shapes, ShapePriors):
            # The calibrated draws with their weights to the fleet's sigma (slope_draws are
            # those draws resampled: the weights are not theirs).
            from ..calibrate.trend import last_segment
            p = 1.0 if any(t.rejects for t in trends.values()) else drift_probability(
                cfg, last_segment(calibrated, "slope"), sigma_weights(calibrated, fleet),
                directions)
            applied = shapes.blend(p)
        future, _, ess = _pool_unit(cfg, unit, calibrated, calibrated_samples, fleet, applied,
                                    stream=6)
        pool_ess = min(ess, pool_ess) if np.isfinite(pool_ess) else ess
    # The inputs' residuals on the years every trend covers (after the latest repair).
    common = years >= max(since.values())
    resid = np.column_stack([mean[common, i] - (trends[n].intercept + trends[n].slope *
                                                years[common]) for i, n in enumerate(names)])
    corr = (residual_correlation(resid) if fc.correlate and common.sum() >= 3
            else np.eye(d))
    # Probe points of the indicator's gradient at the unit's mid-history state (the
    # detection's normal-ageing band), evaluated with every other point.
    probe, step = gradient_points(cfg, mid_state(trends, names))
    fut = years[-1] + np.arange(1, fc.horizon + 1)
    state = future_line = None
    err_cov = estimate_error_covariance(cfg, post_cov, sequential=not trend_post)
    # How much of a drift the sequential estimates show (their prior lags it where the data
    # are weak); a joint posterior's trend is sampled with its years and does not lag.
    attenuation = None if trend_post else filter_attenuation(
        cfg, years, post_cov, np.array([since[n] for n in names]))
    if trend_post:
        # The joint method sampled the trend itself: draw the future from its posterior
        # predictive (levels, slopes and year-to-year sd), not from lines refitted to
        # the yearly means.
        from ..calibrate.trend import trend_predictive
        rng = unit_rng(cfg, unit, 0)
        draws = trend_predictive(new_parts_as_before(future, since, years, names), fut,
                                 rng)                          # [n, h, d]
        take = rng.integers(0, draws.shape[0], fc.samples)
        X = draws[take].transpose(1, 0, 2)
        state = "trend"
        if "shape" in future:
            # Which future draws extend a straight line (describe_bend: a failure year that
            # only the bent draws reach).
            future_line = np.asarray(future["shape"])[take] == 0
    elif fc.predictive == "state" and common.sum() >= MIN_TREND_YEARS:
        # (A part replaced in the last years: its line has no spread of its own to take
        # the state's uncertainty from; each trend's own predictive below carries the
        # whole history's scatter, as segment_trend's normal ageing does.)
        state = state_predictive([trends[n] for n in names], years[common], resid,
                                 post_cov[common], fut)
        X = sample_state(state, fc.samples, unit_rng(cfg, unit, 0))
    else:
        X = sample_predictive([trends[n] for n in names], fut, corr, fc.samples,
                              unit_rng(cfg, unit, 0))
    if input_range is not None:
        X = np.clip(X, input_range[:, 0], input_range[:, 1])
    n_o = min(fc.observed_samples, samples_post.shape[1])
    pick = np.sort(unit_rng(cfg, unit, 1).choice(samples_post.shape[1], n_o, replace=False))
    Xo = samples_post[:, pick, :]
    trend_fit = None
    if fc.trend_fit_alpha > 0:
        # The posterior's own trend model, judged one year ahead over the unit's history.
        priors = shape_priors if "shape" in trend_post else {"line": 1.0}
        # The draws' share of the change against the prior they were drawn under: the
        # fleet's when it was pooled.
        drawn = applied.shape_priors() if applied is not None else priors
        x, cov, starts = unit_sites(cfg, up, post_cov, trend_post, repairs,
                                    change_year(shape_summary(future), drawn))
        trend_fit = check_trend_fit(cfg, years, x, cov, starts, priors,
                                    fleet if trend_post else None)
    plan = dict(years=years, mean=mean, trends=trends, fut=fut, X=X, Xo=Xo, corr=corr,
                resid=resid, step=step, since=max(since.values()), since_by_input=since,
                repairs=repairs, post_cov=post_cov,
                err_cov=err_cov, state=state, slope_draws=slope_draws,
                history_draws=history_draws, rate_draws=rate_draws, changed=changed,
                pool_ess=pool_ess,
                shapes="now" in trend_post and cfg.calibrate.shapes.get("accelerating", 0) > 0,
                shape=shape_summary(future), trend_fit=trend_fit, attenuation=attenuation,
                future_line=future_line)
    return plan, [X.reshape(-1, d), Xo.reshape(-1, d), probe]


def new_parts_as_before(trend: dict, since: dict, years: np.ndarray, names: list) -> dict:
    """``trend`` with each input whose part is newer than :data:`MIN_TREND_YEARS` recorded
    years extended at the rate its earlier parts wore (:func:`~.judge.history_slope_draws`,
    each draw's), as a straight line from the new part's level.

    A segment of one or two years holds no rate of its own: its slope's posterior is its
    weak prior, and extended seven years it spreads the new part over half the box (a bearing
    replaced in the last year was told P(unsafe) 0.35 the next year, "inspect now"). The
    part usually wears as the one it replaced (same duty, same kind of part), as detection
    assumes when it pools the segments' rates; the unit's status says the rate is not its
    own (:func:`~.judge.describe_restart`). Unchanged when no input is that new.

    Parameters
    ----------
    trend : dict
        ``UnitPosterior.trend`` (:data:`~twinmon.calibrate.trend.TREND_FIELDS`): the laplace
        method's ``now`` [n, 4, d] (level, rate, curvature, growth amplitude at the last
        year), or the joint method's segments.
    since : dict input name -> int
        First year of each input's current part.
    years : ndarray of int, shape [n_y]
    names : list of str
        The inputs, in the trend's order.
    """
    late = recent_restarts(since, years)
    new = [i for i, n in enumerate(names) if n in late]
    hist = history_slope_draws(trend) if new and "start" in trend else None
    if hist is None:
        return trend
    out = dict(trend)
    if "now" in trend:
        now = np.array(trend["now"], float)
        now[:, 1, new] = hist[:, new]
        now[:, 2:, new] = 0.0
        out["now"] = now
    else:
        start = np.asarray(trend["start"])
        last = (start >= 0).sum(axis=0) - 1
        slope = np.array(trend["slope"], float)
        for i in new:
            slope[:, last[i], i] = hist[:, i]
        out["slope"] = slope
    return out


def _finish_unit(cfg: Config, unit: str, up, p: dict, twin: TwinResult,
                 unsafe_all: np.ndarray, offset: int, directions: dict,
                 fit_windows: list, levels: Optional[dict] = None
                 ) -> tuple[UnitForecast, int]:
    """A unit's forecast from its plan and its slice of the chunk's twin results (starting at
    ``offset``): probabilities, failure year, verdict, plan, status. Returns it and the
    offset of the next unit. ``levels``: the inputs whose level puts a unit with no drift
    past its limit (:func:`~.plan.level_cause`): they are its root cause and its plan."""
    from ..safety import failure_year as first_failure
    fc = cfg.forecast
    names = cfg.model.input_names
    d = len(names)
    h, n_s = p["X"].shape[:2]
    n_y, n_o = p["Xo"].shape[:2]
    sl = slice(offset, offset + h * n_s)
    so = slice(sl.stop, sl.stop + n_y * n_o)
    sg = slice(so.stop, so.stop + 2 * d)
    value = twin.value[sl].reshape(h, n_s)
    p_unsafe = unsafe_all[sl].reshape(h, n_s).mean(axis=1)
    p_obs = unsafe_all[so].reshape(n_y, n_o).mean(axis=1)
    fyear = first_failure(p["fut"], p_unsafe, cfg.safety)
    trends = p["trends"]
    ind_obs = twin.value[so].reshape(n_y, n_o)
    drift, attribution = judge(cfg, unit, p, ind_obs, gradient_from(twin.value[sg], p["step"]),
                               directions, set(getattr(up, "channels", None) or ()))
    pm, plo, phi = {}, {}, {}
    for i, (name, t) in enumerate(trends.items()):
        if isinstance(p["state"], str):      # the joint method's trend draws
            q = np.quantile(p["X"][:, :, i], [0.5, (1 - fc.confidence) / 2,
                                              (1 + fc.confidence) / 2], axis=1)
            pm[name], plo[name], phi[name] = q
        elif p["state"] is not None:
            pm[name], plo[name], phi[name] = state_interval(p["state"], i, fc.confidence)
        else:
            pm[name], plo[name], phi[name], _ = t.predict(p["fut"], fc.confidence)
    uf = UnitForecast(
        years_observed=p["years"], estimates={n: p["mean"][:, i] for i, n in enumerate(names)},
        years_future=p["fut"], trends=trends, pred_mean=pm, pred_lo=plo, pred_hi=phi,
        samples=p["X"], indicator=value, nonphysical=twin.nonphysical[sl].reshape(h, n_s),
        source=twin.source[sl].reshape(h, n_s), p_unsafe=p_unsafe,
        indicator_observed=ind_obs, p_unsafe_observed=p_obs,
        failure_year=fyear, root_cause=attribution.verdict,
        fmu_failures=int(np.sum(twin.source[sl] == SOURCE_FAILED)),
        drift=drift, attribution=attribution, pool_ess=p["pool_ess"],
        unsafe_since=trailing_run(p["years"], p_obs > cfg.safety.failure_probability))
    uf.plan = maintenance_plan(trends, p["fut"], p_unsafe, fyear,
                               int(p["years"][-1]), float(p_obs[-1]), cfg.safety,
                               drift=drift, attribution=attribution, cfg=cfg)
    # The straight-line trends may not follow the wear: accelerating wear makes the line's
    # failure year late with intervals that look sure (a posterior that averaged the
    # accelerating shape in, calibrate.shapes, has weighed it already).
    shape, accel = ("", None) if p["shapes"] else shape_gate(
        cfg, p["since_by_input"], p["years"], p["mean"], trends,
        every=uf.root_cause == HEALTHY and not levels)
    if levels:
        comps = list(dict.fromkeys(cfg.model.inputs[n].component or n for n in levels))
        uf.root_cause = comps[0] if len(comps) == 1 else SEVERAL
        uf.level_cause = levels
        uf.plan = level_plan(cfg, levels, float(p_obs[-1]), int(p["years"][-1]))
    elif uf.root_cause == HEALTHY and accel:
        # No fault found, but a part's wear speeds up: that part is the one to look at,
        # not "no action".
        uf.watch, uf.plan = accelerating(cfg, accel, fyear, p["fut"], p_unsafe, uf.plan)
    elif uf.root_cause == HEALTHY:
        lone = unconfirmed(cfg, trends, drift, fyear, p["fut"], p_unsafe)
        if lone:
            uf.watch, uf.plan = lone[0], lone[1] + ("" if fyear is None else f" {uf.plan}")
    uf.repairs = [r.as_dict() for r in p["repairs"]]
    uf.shape = p["shape"]
    told = describe_shape(uf.shape) if uf.root_cause != HEALTHY else ""
    if told:
        uf.plan = f"{uf.plan} {told}"
    found = "; ".join(r.describe(cfg, unit) for r in p["repairs"])
    if found:
        uf.plan = f"{found[0].upper()}{found[1:]}; its trend restarts there. {uf.plan}"
    uf.status, uf.status_reason = prognosis_status(up, cfg, fit_windows)
    if uf.status == STATUS_OK and shape:
        uf.status, uf.status_reason = STATUS_UNRELIABLE, shape
    if uf.status == STATUS_OK and p.get("attenuation") is not None:
        lag = describe_lag(names, p["attenuation"])
        if lag:
            uf.status, uf.status_reason = STATUS_UNRELIABLE, lag
    fit = p["trend_fit"]
    if fit is not None:
        uf.trend_fit = fit.as_dict(fc.trend_fit_alpha)
        if uf.status == STATUS_OK and fit.p_value < fc.trend_fit_alpha:
            # The twin fits each year, but the trend it extends could not have predicted
            # them: a failure year and intervals from it would look surer than they are.
            uf.status, uf.status_reason = STATUS_UNRELIABLE, describe_miss(
                cfg, fit, fc.trend_fit_alpha)
        if uf.status == STATUS_OK:
            latest = describe_latest(cfg, fit, int(p["years"][-1]), fc.trend_fit_alpha)
            if latest:
                uf.status, uf.status_reason = STATUS_UNRELIABLE, latest
    elif uf.status == STATUS_OK and fc.trend_fit_alpha > 0 and uf.root_cause != HEALTHY:
        # No year could be predicted from the years before it: the fault is seen (the drift
        # test needs no trend shape) but the trend its prognosis extends is unchecked.
        uf.status, uf.status_reason = STATUS_UNRELIABLE, describe_unchecked(p["years"])
    if uf.status == STATUS_OK:
        # No fault found, but a failure year from the trend's bend alone.
        line = p["future_line"]
        p_line = (unsafe_all[sl].reshape(h, n_s)[:, line].mean(axis=1)
                  if line is not None and line.sum() >= MIN_LINE_DRAWS else None)
        bend = describe_bend(cfg, uf.shape, p["fut"], p_unsafe, fyear, p_line,
                             uf.root_cause == HEALTHY)
        if bend:
            uf.status, uf.status_reason = STATUS_UNRELIABLE, bend
    if uf.status == STATUS_OK:
        # A part replaced lately (a recorded event, or a repair found): its trend restarted
        # too few years ago to show the new part's rate. (After the trend-fit gate: a
        # one-year spike whose fall back reads as a repair is named as the spike.)
        fresh = describe_restart(p["since_by_input"], p["years"])
        if fresh:
            uf.status, uf.status_reason = STATUS_UNRELIABLE, fresh
    if uf.status == STATUS_OK and uf.root_cause == HEALTHY:
        # No fault seen, but a short or gappy record may not have been able to see one.
        blind = describe_blind(cfg, drift, p["years"])
        if blind:
            uf.status, uf.status_reason = STATUS_UNRELIABLE, blind
    if uf.status == STATUS_WITHHELD:
        if fc.force_prognosis:
            uf.forced = True
            uf.plan = f"FORCED despite: {uf.status_reason}. {uf.plan}"
        else:
            # A twin that misses the data predicts nothing about the plant.
            uf.failure_year, uf.root_cause, uf.plan = None, STATUS_WITHHELD, \
                uf.status_reason[0].upper() + uf.status_reason[1:] + "."
            uf.watch = {}
    elif uf.status == STATUS_UNRELIABLE:
        uf.plan = f"{uf.plan} ({uf.status_reason}.)"
    return uf, sg.stop


def _check_plausible(path, unit: str, samples: np.ndarray, cfg: Config) -> None:
    """Posterior draws must be finite and inside the design box widened by the fit margin
    (calibration's prior never leaves the box): anything else is a damaged or foreign file,
    and a forecast from it would be garbage with exit 0."""
    box = cfg.model.bounds
    pad = cfg.diagnose.fit_margin * (box[:, 1] - box[:, 0])
    lo, hi = box[:, 0] - pad, box[:, 1] + pad
    bad = ~np.isfinite(samples) | (samples < lo) | (samples > hi)
    if bad.any():
        k, j, i = np.argwhere(bad)[0]
        name = cfg.model.input_names[i]
        raise ArtifactError(f"{path}: /units/{unit}/samples[{k}, {j}, {i}] ({name}) is "
                            f"{float(samples[k, j, i]):g}, outside the design box "
                            f"[{box[i, 0]:g}, {box[i, 1]:g}] widened by the fit margin: "
                            "a damaged or foreign posterior; re-run calibrate")


def _add_truth(cfg: Config, uf: UnitForecast, unit: str, truth_unit, truth_path, spec,
               executor) -> None:
    """True future inputs, indicator and failure year, run through the FMU.

    ``truth_unit``: the unit's years [n_y], inputs {name: [n_y]}, and the truth file's
    future years [h] and inputs {name: [h]} or None. The future is the truth file's where it
    covers the forecast's years -- its recorded years (a forecast made from the first years
    of the record, as a backtest makes it) and its recorded future: what the unit will
    really be, year-to-year jitter included; otherwise (truth files written before the
    future was recorded, a longer horizon) each true trajectory's fitted line extended.
    ``uf.truth_source`` says which. The true failure year is the first future year the true
    unit is unsafe; for a unit truly unsafe at the forecast's last recorded year already, the
    first of the years it has been unsafe in a row up to it (as ``unsafe_since`` reads the
    forecast's own)."""
    ty, inputs, fy, finputs = truth_unit
    names = cfg.model.input_names
    for name in names:
        if name not in inputs:
            raise ArtifactError(f"{truth_path}: /units/{unit}/inputs/{name} is missing")
    # Every true year the file holds, recorded then future (the future after the record).
    years = np.asarray(ty)
    values = {n: np.asarray(inputs[n], float) for n in names}
    if fy is not None and all(n in finputs for n in names):
        later = np.asarray(fy) > years.max()
        years = np.concatenate([years, np.asarray(fy)[later]])
        values = {n: np.concatenate([values[n], np.asarray(finputs[n], float)[later]])
                  for n in names}
    pos = np.minimum(np.searchsorted(years, uf.years_future), years.size - 1)
    realised = bool(np.array_equal(years[pos], uf.years_future))
    Xt = np.empty((uf.years_future.size, len(names)))
    for i, name in enumerate(names):
        if realised:
            Xt[:, i] = values[name][pos]
        else:
            slope, icpt = np.polyfit(ty, np.asarray(inputs[name], float), 1)
            Xt[:, i] = icpt + slope * uf.years_future
    uf.truth_source = "recorded future" if realised else "trend line"
    # The true state of the forecast's last recorded year too, run with the future: a unit
    # truly unsafe there failed before the forecast's years (its true failure year is the
    # first of that trailing run, found from the years before it only then).
    h = uf.years_future.size
    last = int(uf.years_observed[-1])
    past = np.flatnonzero(years <= last)
    seen = past.size and int(years[past[-1]]) == last
    Xp = (np.column_stack([values[n][past] for n in names]) if seen
          else np.empty((0, len(names))))
    value, bad = _true_unsafe(cfg, spec, executor, np.vstack([Xt, Xp[-1:]]))
    uf.has_truth = True
    uf.true_indicator = value[:h]
    uf.true_unsafe = bad[:h]
    uf.true_inputs = {n: Xt[:, i] for i, n in enumerate(cfg.model.input_names)}
    uf.true_failure_year = int(uf.years_future[np.argmax(bad[:h])]) if bad[:h].any() else None
    if seen and bad[h]:
        flags = _true_unsafe(cfg, spec, executor, Xp[:-1])[1]
        uf.true_failure_year = trailing_run(years[past], np.append(flags, True))


def _true_unsafe(cfg: Config, spec, executor, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The health indicator [m] and whether each state is unsafe [m] (a failed run is), of
    true states ``X`` [m, d], through the FMU."""
    from ..safety import Indicator, is_unsafe
    from ..simulate import as_parameters, run_batch
    if not len(X):
        return np.empty(0), np.empty(0, bool)
    batch = run_batch(spec, as_parameters(cfg, X), executor)
    ind = Indicator.from_config(cfg)
    value = np.where(batch.ok, ind(spec.times, batch.outputs[ind.variable]), np.nan)
    nph = (batch.outputs[cfg.model.nonphysical][:, -1] > 0.5) if cfg.model.nonphysical else None
    return value, is_unsafe(value, cfg.safety, nph) | ~batch.ok
