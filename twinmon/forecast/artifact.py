"""The forecast artifact ``forecast.h5`` (``twinmon.forecast/1``): writer and reader.

The stage opens it with :func:`_open_forecast` (the fleet-wide attributes: inputs,
directions, indicator, levels) and adds each unit's group as it comes back
(:func:`_write_unit`); the Monte Carlo arrays are stored one compressed chunk per year
(:func:`_put_per_year`). :func:`read_forecast` opens it lazily: a unit is read when it is
looked up (:func:`_read_unit`), with or without its Monte Carlo arrays. The layout is in
``docs/forecast.md``.
"""
from __future__ import annotations

import json
import os
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError
from .attribution import Attribution
from .detection import IndicatorDrift
from .judge import STATUS_OK
from .trend import Trend
from .unit import UnitForecast

#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "forecast", "safety", "seed")


@contextmanager
def _open_forecast(path, cfg: Config, names: list, directions: dict, box_ok: bool, *,
                   seed: int, inputs: list):
    """The forecast artifact being written, its fleet-wide attributes set; yields the open
    (temporary) file for :func:`_write_unit`, renamed into place when the block ends well."""
    from ..safety import Indicator
    ind = Indicator.from_config(cfg)
    section = cfg.section_yaml(*SECTIONS)
    with artifacts.write_artifact(path, "forecast", config=section, inputs=inputs,
                                  seed=seed, compact=True) as f:
        f.attrs["input_names"] = artifacts.json_attr(names)
        f.attrs["input_units"] = artifacts.json_attr([cfg.model.inputs[n].units for n in names])
        f.attrs["directions"] = artifacts.json_attr({n: d.sign for n, d in directions.items()})
        f.attrs["direction_sources"] = artifacts.json_attr(
            {n: {"source": d.source, "effect": d.effect, "noise": d.noise, "note": d.note}
             for n, d in directions.items()})
        f.attrs["confidence"] = cfg.forecast.confidence
        f.attrs["alpha"] = cfg.forecast.alpha
        f.attrs["indicator"] = artifacts.json_attr(
            {"name": ind.name, "label": ind.label, "units": ind.units, "limit": ind.limit,
             "sense": ind.sense, "variable": ind.variable, "kind": ind.spec.kind})
        f.attrs["failure_probability"] = cfg.safety.failure_probability
        f.attrs["box_physical"] = box_ok
        yield f


def _write_unit(f, cfg: Config, unit: str, u: UnitForecast, names: list) -> None:
    """One unit's group of the forecast artifact."""
    from ..safety import Indicator
    put = artifacts.put
    ind = Indicator.from_config(cfg)
    g = f.create_group(f"units/{unit}")
    at = {"status": u.status, "status_reason": u.status_reason, "forced": u.forced,
          "root_cause": u.root_cause}
    if u.drift is not None:
        at["detection"] = artifacts.json_attr(_drift_state(u.drift))
    if u.attribution is not None:
        a = u.attribution
        at["attribution"] = artifacts.json_attr(
            {"verdict": a.verdict, "probabilities": a.probabilities, "sets": a.sets,
             "separating_channel": a.separating_channel,
             "channel_scores": a.channel_scores, "named": list(a.named)})
    at.update(failure_year=-1 if u.failure_year is None else u.failure_year, plan=u.plan,
              fmu_fraction=u.fmu_fraction, model_fraction=u.model_fraction,
              fmu_failures=u.fmu_failures)
    put(g, "years_observed", u.years_observed.astype(np.int64), "year",
        "observed years (1 = first year of service)")
    put(g, "years_future", u.years_future.astype(np.int64), "year", "forecast years")
    for i, name in enumerate(names):
        t, un = u.trends[name], cfg.model.inputs[name].units
        tg = g.create_group(f"trends/{name}")
        ta = {key: float(getattr(t, key)) for key in (
            "intercept", "slope", "slope_se", "residual_std", "x_mean", "sxx", "normal_rate",
            "tolerance", "p_value")}
        ta.update(n=t.n, direction=t.direction, slope_ci90=np.array(t.slope_ci, float),
                  test=t.test, rejects=t.rejects, component=t.component)
        artifacts.set_attrs(tg, ta)
        put(tg, "estimate", u.estimates[name], un,
            f"posterior mean of {name} per observed year (regression data)")
        put(tg, "pred_mean", u.pred_mean[name], un, f"trend line of {name}, future years")
        c = f"{100 * cfg.forecast.confidence:g} %"
        put(tg, "pred_lo", u.pred_lo[name], un,
            f"lower {c} prediction bound (Student t, new observation)")
        put(tg, "pred_hi", u.pred_hi[name], un,
            f"upper {c} prediction bound (Student t, new observation)")
    # The Monte Carlo arrays: one compressed chunk per year (see _put_per_year), packed
    # already when a worker sent the unit.
    mc = u._packed if u._packed is not None else _mc_arrays(u)
    _put_per_year(g, "samples", mc["samples"], "input units",
                  "Monte Carlo input samples [future year, sample, input]")
    _put_per_year(g, "indicator", mc["indicator"], ind.units, f"{ind.name} per future "
                  "year and sample; inf = level never reached, NaN = FMU run failed; the "
                  "limit-state model's estimate where source is 3")
    _put_per_year(g, "nonphysical", mc["nonphysical"], "1",
                  "1 where the FMU reported the non-physical mode")
    _put_per_year(g, "source", mc["source"], "1", "0 surrogate, 1 FMU (outside the box), "
                  "2 FMU run failed (counted unsafe), 3 limit-state model (outside the box, "
                  "surely unsafe)")
    put(g, "p_unsafe", u.p_unsafe, "1", "probability of being unsafe per future year")
    _put_per_year(g, "indicator_observed", mc["indicator_observed"], ind.units,
                  f"{ind.name} of posterior samples per observed year [year, sample]")
    put(g, "p_unsafe_observed", u.p_unsafe_observed, "1",
        "probability of being unsafe per observed year (posterior samples)")
    if np.isfinite(u.pool_ess):
        at["pool_ess"] = u.pool_ess
    if u.repairs:
        at["unrecorded_repairs"] = artifacts.json_attr(u.repairs)
    if u.shape:
        at["trend_shape"] = artifacts.json_attr(u.shape)
    if u.trend_fit:
        at["trend_fit"] = artifacts.json_attr(u.trend_fit)
    if u.level_cause:
        at["level_cause"] = artifacts.json_attr(u.level_cause)
    if u.unsafe_at_nominal is not None:
        at["unsafe_at_nominal"] = float(u.unsafe_at_nominal)
    if u.unsafe_since is not None:
        at["unsafe_since"] = int(u.unsafe_since)
    if u.watch:
        at["watch"] = artifacts.json_attr(u.watch)
    if u.has_truth:
        at["true_failure_year"] = -1 if u.true_failure_year is None else u.true_failure_year
        at["truth_source"] = u.truth_source
    artifacts.set_attrs(g, at)
    if u.has_truth:
        put(g, "truth/indicator", u.true_indicator, ind.units,
            f"{ind.name} of the true future inputs ({u.truth_source}), future years (FMU)")
        put(g, "truth/unsafe", u.true_unsafe.astype(np.int8), "1",
            "1 where the true unit is unsafe, future years")
        for name in names:
            put(g, f"truth/inputs/{name}", u.true_inputs[name],
                cfg.model.inputs[name].units,
                f"true {name} over the future years ({u.truth_source})")


#: The per-year gzip level of the Monte Carlo arrays (HDF5's deflate filter, its level).
GZIP_LEVEL = 4


@dataclass
class PackedArray:
    """A [year, sample, ...] array already through the filters :func:`_put_per_year` stores
    it with (byte shuffle, then zlib at ``GZIP_LEVEL``): one compressed chunk per year.

    The workers pack their units' Monte Carlo arrays (:func:`pack_unit`), so the one process
    that writes ``forecast.h5`` only copies bytes: compressing ~0.4 MB a unit there took 19
    of its 44 ms a unit (60 units). On two cores the fleet's wall time is the same either way
    (docs/forecast.md); with more workers, the one writer would otherwise set the pace."""

    dtype: str
    shape: tuple
    chunks: list


def pack_per_year(data: np.ndarray) -> PackedArray:
    """The chunks HDF5's shuffle + deflate filters would store for ``data`` [year, ...], one
    per year (the shuffle puts each element's first bytes together, then its second ...)."""
    import zlib
    data = np.ascontiguousarray(data)
    size = data.dtype.itemsize
    chunks = [zlib.compress(np.ascontiguousarray(row).view(np.uint8).reshape(-1, size)
                            .T.tobytes(), GZIP_LEVEL) for row in data]
    return PackedArray(data.dtype.str, data.shape, chunks)


def _mc_arrays(u: UnitForecast) -> dict:
    """The unit's per-sample arrays as they are stored (flags as int8)."""
    return {"samples": u.samples, "indicator": u.indicator,
            "nonphysical": np.asarray(u.nonphysical).astype(np.int8), "source": u.source,
            "indicator_observed": u.indicator_observed}


def pack_unit(u: UnitForecast) -> UnitForecast:
    """The unit without its Monte Carlo arrays (:meth:`UnitForecast.slim`), carrying them
    packed for :func:`_write_unit` instead: what a worker sends back."""
    packed = {k: pack_per_year(v) if np.ndim(v) >= 2 and np.size(v) else v
              for k, v in _mc_arrays(u).items()}
    out = u.slim()
    out._packed = packed
    return out


def _put_per_year(g, name: str, data, units: str, description: str) -> None:
    """A [year, sample, ...] array as one chunk per year, shuffled and gzip-compressed
    (flags and failed-run codes are mostly zeros; draws lose about a fifth), so that a
    fleet's forecast stays small and a unit-year is read alone. ``data`` may come packed
    (:class:`PackedArray`); an array is packed here, so the bytes are the same either way.
    No Fletcher-32 checksum on these: each chunk's zlib stream carries its own (Adler-32),
    which finds flipped bytes as well."""
    if not isinstance(data, PackedArray):
        data = np.asarray(data)
        if data.ndim < 2 or not data.size:
            artifacts.put(g, name, data, units, description)
            return
        data = pack_per_year(data)
    ds = g.create_dataset(name, shape=data.shape, dtype=np.dtype(data.dtype),
                          chunks=(1,) + tuple(data.shape[1:]), compression="gzip",
                          compression_opts=GZIP_LEVEL, shuffle=True)
    zeros = (0,) * (len(data.shape) - 1)
    for year, chunk in enumerate(data.chunks):
        ds.id.write_direct_chunk((year,) + zeros, chunk, 0)
    artifacts.set_attrs(ds, {"units": units, "description": description})


def _drift_state(dr: IndicatorDrift) -> dict:
    """The detection as JSON-able values (for the artifact)."""
    return {"years": [int(y) for y in dr.years], "values": [float(v) for v in dr.values],
            "slope": dr.slope, "slope_se": dr.slope_se, "dof": dr.dof,
            "normal_slope": dr.normal_slope,
            "normal_halfwidth": [float(v) for v in dr.normal_halfwidth],
            "gradient": [float(v) for v in dr.gradient], "sense": dr.sense,
            "p_value": dr.p_value, "abnormal": bool(dr.abnormal), "p_inputs": dr.p_inputs,
            "p_history": dr.p_history, "p_inputs_rate": dr.p_inputs_rate,
            "detectable": [float(v) for v in dr.detectable]}


def _drift_from(d: dict) -> IndicatorDrift:
    return IndicatorDrift(**{k: (np.asarray(v) if isinstance(v, list) else v)
                             for k, v in d.items()})


@dataclass
class Forecast:
    """A loaded ``forecast.h5``: ``units`` maps unit -> :class:`UnitForecast`.

    Read from a file, ``units`` is an :class:`~twinmon.artifacts.LazyUnits` mapping: a unit
    is read when it is looked up, so a fleet's forecast never sits in memory whole."""

    path: Path
    input_names: list
    confidence: float
    units: Mapping
    directions: dict = field(default_factory=dict)
    #: The health indicator the forecast was made with (name, label, units, limit, sense,
    #: variable, kind); empty for files written before it was recorded.
    indicator: dict = field(default_factory=dict)
    #: The fleet's prior of the joint method's year-to-year sd (:func:`~.pooling._pooling_dict`).
    sigma_pooling: dict = field(default_factory=lambda: {"pooled": False})
    #: The fleet's prior of the trend forms (:func:`~.pooling._shapes_dict`).
    shape_pooling: dict = field(default_factory=lambda: {"pooled": False})
    #: The posterior's units left out for too few calibrated years: unit -> its years.
    too_few_years: dict = field(default_factory=dict)


def read_forecast(path: str | os.PathLike, arrays: bool = True) -> Forecast:
    """Open a forecast artifact (schema checked); its units are read when looked up.

    ``arrays=False`` leaves each unit's Monte Carlo arrays (samples, indicator and flags,
    ~0.4 MB a unit) on disk: the unit is then as :meth:`UnitForecast.slim` makes it, for a
    fleet's summaries.

    Raises
    ------
    ArtifactError
        Missing file, wrong schema, no ``/units``; on access: a unit's missing datasets or
        damaged bytes (naming the file and the dataset).
    """
    path = Path(path)
    with artifacts.open_artifact(path, "forecast") as f:
        names = json.loads(f.attrs["input_names"])
        if "units" not in f:
            raise ArtifactError(f"{path}: group /units is missing")
        unit_names = list(f["units"])
        out = Forecast(path, names, float(f.attrs["confidence"]), {},
                       json.loads(f.attrs["directions"]),
                       json.loads(f.attrs["indicator"]) if "indicator" in f.attrs else {},
                       json.loads(f.attrs.get("sigma_pooling", '{"pooled": false}')),
                       json.loads(f.attrs.get("shape_pooling", '{"pooled": false}')),
                       json.loads(f.attrs.get("too_few_years", "{}")))
    out.units = artifacts.LazyUnits(path, "forecast", unit_names,
                                    lambda f, unit, p: _read_unit(f, unit, p, names, arrays))
    return out


#: The per-sample datasets of a unit (what ``read_forecast(arrays=False)`` leaves on disk).
_MC_ARRAYS = ("samples", "indicator", "nonphysical", "source", "indicator_observed")


def _n_samples(g, path: Path) -> int:
    if "indicator" not in g:
        raise ArtifactError(f"{path}: dataset {g.name}/indicator is missing")
    return int(g["indicator"].shape[1])


def _read_unit(f, unit: str, path: Path, names: list, arrays: bool = True) -> UnitForecast:
    """Read one unit of an open forecast artifact (without its Monte Carlo arrays unless
    ``arrays``)."""
    def get(g, n):
        if not arrays and n in _MC_ARRAYS:
            return None
        return artifacts.get(g, n, path)
    if f"units/{unit}" not in f:
        raise ArtifactError(f"{path}: group /units/{unit} is missing")
    g = f["units"][unit]
    trends, est, pm, plo, phi = {}, {}, {}, {}, {}
    for name in names:
        if f"trends/{name}" not in g:
            raise ArtifactError(f"{path}: group /units/{unit}/trends/{name} is missing")
        tg = g[f"trends/{name}"]
        a = tg.attrs
        trends[name] = Trend(
            intercept=float(a["intercept"]), slope=float(a["slope"]),
            slope_se=float(a["slope_se"]), slope_ci=tuple(map(float, a["slope_ci90"])),
            residual_std=float(a["residual_std"]), n=int(a["n"]),
            x_mean=float(a["x_mean"]), sxx=float(a["sxx"]),
            normal_rate=float(a["normal_rate"]), tolerance=float(a["tolerance"]),
            direction=int(a["direction"]), p_value=float(a["p_value"]),
            test=str(a["test"]), rejects=bool(a["rejects"]),
            component=str(a["component"]))
        est[name], pm[name] = get(tg, "estimate"), get(tg, "pred_mean")
        plo[name], phi[name] = get(tg, "pred_lo"), get(tg, "pred_hi")
    fy = int(g.attrs["failure_year"])
    has_truth = "true_failure_year" in g.attrs
    tfy = int(g.attrs["true_failure_year"]) if has_truth else -1
    return UnitForecast(
        years_observed=get(g, "years_observed"), estimates=est,
        years_future=get(g, "years_future"), trends=trends, pred_mean=pm,
        pred_lo=plo, pred_hi=phi, samples=get(g, "samples"), indicator=get(g, "indicator"),
        nonphysical=get(g, "nonphysical").astype(bool) if arrays else None,
        source=get(g, "source"),
        p_unsafe=get(g, "p_unsafe"), indicator_observed=get(g, "indicator_observed"),
        p_unsafe_observed=get(g, "p_unsafe_observed"),
        failure_year=None if fy < 0 else fy, root_cause=str(g.attrs["root_cause"]),
        plan=str(g.attrs["plan"]), fmu_failures=int(g.attrs["fmu_failures"]),
        status=str(g.attrs.get("status", STATUS_OK)),
        status_reason=str(g.attrs.get("status_reason", "")),
        forced=bool(g.attrs.get("forced", False)),
        pool_ess=float(g.attrs.get("pool_ess", np.nan)),
        repairs=json.loads(g.attrs["unrecorded_repairs"]) if "unrecorded_repairs" in g.attrs
        else [],
        shape=json.loads(g.attrs["trend_shape"]) if "trend_shape" in g.attrs else {},
        trend_fit=json.loads(g.attrs["trend_fit"]) if "trend_fit" in g.attrs else {},
        level_cause=json.loads(g.attrs["level_cause"]) if "level_cause" in g.attrs else {},
        unsafe_at_nominal=(float(g.attrs["unsafe_at_nominal"]) if "unsafe_at_nominal" in g.attrs
                           else None),
        unsafe_since=int(g.attrs["unsafe_since"]) if "unsafe_since" in g.attrs else None,
        watch=json.loads(g.attrs["watch"]) if "watch" in g.attrs else {},
        drift=_drift_from(json.loads(g.attrs["detection"])) if "detection" in g.attrs else None,
        attribution=(Attribution(**json.loads(g.attrs["attribution"]))
                     if "attribution" in g.attrs else None),
        has_truth=has_truth, true_failure_year=None if tfy < 0 else tfy,
        truth_source=str(g.attrs.get("truth_source", "trend line" if has_truth else "")),
        true_indicator=get(g, "truth/indicator") if has_truth else None,
        true_unsafe=get(g, "truth/unsafe").astype(bool) if has_truth else None,
        true_inputs={n: get(g, f"truth/inputs/{n}") for n in names} if has_truth
        else None,
        _slim=None if arrays else {"fmu_fraction": float(g.attrs["fmu_fraction"]),
                                   "model_fraction": float(g.attrs.get("model_fraction", 0.0)),
                                   "quantiles": {}, "n_samples": _n_samples(g, path)})
