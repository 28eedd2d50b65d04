"""The artifact of ``diagnose``: ``gap.h5`` (``twinmon.gap/2``), written by :func:`write_gap` and
read back by :func:`read_gap` into :class:`~twinmon.diagnose.result.UnitGap` records.

What is stored per unit is driven by two tables: ``_ARRAYS`` (the fields of the unit's
per-year and per-candidate records, with their units and description) and ``_ATTRS`` /
``_JSON_ATTRS`` (the values of its JSON ``result`` attribute).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError
from .result import UnitGap
from .update import read_cache, write_cache

#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "diagnose", "safety")

_ARRAYS = {
    # name: (units, description)
    "years": ("year", "year of service"),
    "residual_before": ("1", "standardised output residual of the base twin [year, time]"),
    "residual_after": ("1", "standardised output residual of the twin with the effect(s) "
                       "[year, time]"),
    "chi2_before": ("1", "chi-square of the whitened residual, base twin [year]"),
    "chi2_after": ("1", "chi-square of the whitened residual, final twin [year]"),
    "dof": ("1", "degrees of freedom of the per-year chi-square [year]"),
    "p_chi2_before": ("1", "p-value of the per-year chi-square, base twin [year]"),
    "p_ljung_box_before": ("1", "Ljung-Box p-value of the output residual, base twin [year]"),
    "p_chi2_after": ("1", "p-value of the per-year chi-square, final twin [year]"),
    "significant_years": ("1", "1 where the year's gap is significant (Bonferroni) [year]"),
    "window_rms_before": ("1", "RMS of the standardised output residual [year, window], base"),
    "window_rms_after": ("1", "RMS of the standardised output residual [year, window], final"),
    "observed": ("output units", "observed output [year, time]"),
    "predicted_before": ("output units", "output of the base twin [year, time]"),
    "predicted_after": ("output units", "output of the final twin [year, time]"),
    "inputs_before": ("input units", "degradation inputs, base twin [year, input]"),
    "inputs_after": ("input units", "degradation inputs, final twin [year, input]"),
    "inputs_sd_before": ("input units", "linearised standard deviation [year, input], base"),
    "inputs_sd_after": ("input units", "linearised standard deviation [year, input], final"),
    "screen_score": ("1", "screening chi-square reduction [candidate] (ranking order)"),
    "screen_onset": ("year", "onset year found by screening [candidate]"),
    "fit_onset": ("year", "onset year of the confirmed fit [candidate]"),
    "fit_value": ("effect units", "fitted effect value [candidate]"),
    "fit_sd": ("effect units", "linearised standard deviation of the effect [candidate]"),
    "delta_bic": ("1", "BIC(base) - BIC(base + candidate) [candidate]; > bic_gain accepted"),
}
_ATTRS = ("verdict", "onset", "rms_before", "rms_after", "closed_percent", "delta_bic_final",
          "separating_channel", "absorbed_share", "p_gap", "noise_std", "failure_year_before",
          "failure_year_after", "fmu_runs", "wall_time")
_JSON_ATTRS = ("effects", "group", "where_windows", "where_years", "estimate",
               "separation_scores", "candidates", "effect_onsets", "groups", "hidden",
               "noise_dof")
#: Values a file written before them lacks, and what they are then.
_OPTIONAL = {"groups": [], "hidden": {}, "noise_dof": None}


#: Arrays of ``_ARRAYS`` indexed by candidate (ranking order); the others by year.
_CANDIDATE_ARRAYS = ("screen_score", "screen_onset", "fit_onset", "fit_value", "fit_sd",
                     "delta_bic")
_YEAR_ARRAYS = tuple(n for n in _ARRAYS if n not in _CANDIDATE_ARRAYS)


def _packed(g: UnitGap, names: tuple, n: int, unit: str) -> np.ndarray:
    """The arrays ``names`` of ``g`` (each [n, ...]) side by side as one structured array [n]
    (booleans as int8)."""
    cols = {}
    for name in names:
        data = np.asarray(getattr(g, name))
        cols[name] = data.astype(np.int8) if data.dtype == bool else data
        if data.shape[:1] != (n,):
            raise ValueError(f"unit {unit}: {name} has shape {data.shape}, expected ({n}, ...)")
    rec = np.zeros(n, [(k, v.dtype.str, v.shape[1:]) for k, v in cols.items()])
    for k, v in cols.items():
        rec[k] = v
    return rec


def write_gap(path, results: dict, cfg: Config, time: np.ndarray, inputs) -> None:
    """Write ``gap.h5`` (``twinmon.gap/2``)::

        /time                          [n_t]  s
        /windows/names [n_w], /windows/bounds [n_w, 2] s
        attrs input_names (JSON); array_fields (JSON {name: [units, description]}: every
              field of the records below)
        /units/<U>/record              compound [n_y]: per year, the _ARRAYS indexed by year
                                       (years, residuals and predictions [n_t], windows'
                                       RMS [n_w], inputs and their sd [d], chi-squares,
                                       p-values, significant_years)
        /units/<U>/candidates          compound [n_c]: the _ARRAYS indexed by candidate, in
                                       ranking order (screen_score, screen_onset, fit_onset,
                                       fit_value, fit_sd, delta_bic)
        /units/<U>.attrs result        JSON: verdict, onset (null: none), rms_before,
                                       rms_after, closed_percent, delta_bic_final,
                                       separating_channel, absorbed_share, p_gap, noise_std,
                                       failure_year_before/after (null: none within the
                                       horizon), fmu_runs, wall_time, effects, group,
                                       where_windows, where_years, estimate ({name: [mean,
                                       q05, q95]}), separation_scores, candidates,
                                       effect_onsets ({name: onset year}), groups (one per
                                       effect of the final twin: its members with weight,
                                       value, q05, q95, delta_bic, together_with,
                                       closed_percent, failure_year; failure_year_range,
                                       failure_year_spread, separating_channel,
                                       separation_scores; absent in files written before
                                       it: read as []), hidden ({effect: {value, gap,
                                       visible, channel, channel_score}}: candidates the
                                       degradation inputs take up on the recorded
                                       channels; absent in older files: read as {}),
                                       noise_dof (the output's noise level's degrees of
                                       freedom where diagnose estimated it, else null;
                                       absent in older files: read as null)
        /units/<U>/cache               compound [n_y], gzip: per-year records for diagnose
                                       --update (:func:`.update.write_cache`): digest,
                                       base_u [d], base_rows [m], base_jac [m, d], base_lev [m]
        /units/<U>/cache_gains         [n_c, n_v, n_y], gzip: initial screening's gains (attr
                                       grid: JSON candidates and grid sizes)

    A unit is four datasets and one attribute (``twinmon.gap/1`` had ~30 datasets and ~80
    attributes per unit, 22 ms of writing each); ``read_gap`` reads both layouts.
    """
    wins = cfg.diagnose_windows()
    with artifacts.write_artifact(path, "gap", config=cfg.section_yaml(*SECTIONS),
                                  inputs=inputs, seed=cfg.seed, compact=True) as f:
        artifacts.put(f, "time", np.asarray(time), "s", "sample times")
        artifacts.put(f, "windows/names", list(wins), "", "time windows of the transient")
        artifacts.put(f, "windows/bounds", np.array([[w.start, w.stop] for w in wins.values()]),
                      "s", "start and stop of each window")
        f.attrs["input_names"] = json.dumps(cfg.model.input_names)
        f.attrs["array_fields"] = json.dumps(
            {k: [cfg.model.output.units if u == "output units" else u, desc]
             for k, (u, desc) in _ARRAYS.items()})
        units = f.create_group("units")
        for unit, g in results.items():
            grp = units.create_group(unit)
            n_y = len(np.asarray(g.years))
            # fletcher32: flipped bytes are found on reading (artifacts.put's rule).
            grp.create_dataset("record", data=_packed(g, _YEAR_ARRAYS, n_y, unit),
                               fletcher32=bool(n_y))
            n_c = len(np.asarray(g.screen_score))
            grp.create_dataset("candidates", data=_packed(g, _CANDIDATE_ARRAYS, n_c, unit),
                               fletcher32=bool(n_c))
            result = {n: getattr(g, n) for n in _ATTRS + _JSON_ATTRS}
            grp.attrs["result"] = artifacts.json_attr(result)
            if g.cache is not None:
                write_cache(grp, g.cache)


@dataclass
class GapFile:
    """A loaded ``gap.h5``: time [n_t], window names and bounds [n_w, 2], units {name: UnitGap}."""

    time: np.ndarray
    windows: list
    window_bounds: np.ndarray
    input_names: list
    units: dict = field(default_factory=dict)


def read_gap(path: str | os.PathLike, cache: bool = False) -> GapFile:
    """Load ``gap.h5`` (schema checked) into :class:`UnitGap` records; with ``cache``, their
    per-year records for ``--update`` too (``UnitGap.cache``, None in a file written before
    them)."""
    path = Path(path)
    with artifacts.open_artifact(path, "gap") as f:
        time = artifacts.get(f, "time", path)
        names = list(artifacts.get(f, "windows/names", path))
        bounds = artifacts.get(f, "windows/bounds", path)
        units = {}
        if "units" not in f:
            raise ArtifactError(f"{path}: group /units is missing")
        for unit, g in f["units"].items():
            kw = _read_unit(g, unit, path) if "record" in g else _read_unit_v1(g, unit, path)
            kw["significant_years"] = kw["significant_years"].astype(bool)
            kw["estimate"] = {k: tuple(v) for k, v in kw["estimate"].items()}
            kw["cache"] = read_cache(g, path) if cache else None
            units[unit] = UnitGap(unit=unit, **kw)
        return GapFile(time, names, bounds, json.loads(f.attrs["input_names"]), units)


def _read_unit(g, unit: str, path) -> dict:
    """A unit of a ``twinmon.gap/2`` file: UnitGap's fields but ``unit`` and ``cache``."""
    kw = {}
    for name, names in (("record", _YEAR_ARRAYS), ("candidates", _CANDIDATE_ARRAYS)):
        rec = artifacts.get(g, name, path)
        missing = [n for n in names if n not in (rec.dtype.names or ())]
        if missing:
            raise ArtifactError(f"{path}: /units/{unit}/{name} lacks the field {missing[0]!r}")
        kw.update({n: np.ascontiguousarray(rec[n]) for n in names})
    if "result" not in g.attrs:
        raise ArtifactError(f"{path}: attribute /units/{unit}.result is missing")
    result = json.loads(g.attrs["result"])
    for n, default in _OPTIONAL.items():
        result.setdefault(n, default)
    missing = [n for n in _ATTRS + _JSON_ATTRS if n not in result]
    if missing:
        raise ArtifactError(f"{path}: attribute /units/{unit}.result lacks {missing[0]!r}")
    kw.update(result)
    return kw


def _read_unit_v1(g, unit: str, path) -> dict:
    """A unit of a ``twinmon.gap/1`` file (a dataset per array, an attribute per value)."""
    kw = {n: artifacts.get(g, n, path) for n in _ARRAYS}
    for n in _ATTRS:
        if n not in g.attrs:
            raise ArtifactError(f"{path}: attribute /units/{unit}.{n} is missing")
        v = g.attrs[n]
        v = v.decode() if isinstance(v, bytes) else v
        v = v.item() if isinstance(v, np.generic) else v
        if n in ("onset", "failure_year_before", "failure_year_after") and v == -1:
            v = None
        kw[n] = v
    for n in _JSON_ATTRS:
        kw[n] = json.loads(g.attrs[n]) if n in g.attrs else _OPTIONAL[n]
    return kw


#: What a diagnosis records of its own cost (an update's differ from a full run's).
COST_FIELDS = ("fmu_runs", "wall_time")


def gap_differences(a_path, b_path) -> list:
    """What differs between two ``gap.h5`` files, unit by unit (every field of every unit,
    bit for bit with NaN equal to NaN, the per-year records included), the units' own cost
    (:data:`COST_FIELDS`) left out: empty when ``diagnose --update`` gave what a full run
    gives. Also the config and schema of the two files."""
    from dataclasses import fields
    out = []
    pa, pb = artifacts.read_provenance(a_path), artifacts.read_provenance(b_path)
    out += [f".{k}" for k in ("schema", "config", "seed") if pa.get(k) != pb.get(k)]
    a, b = read_gap(a_path, cache=True), read_gap(b_path, cache=True)
    if list(a.units) != list(b.units):
        return out + [f"units {sorted(set(a.units) ^ set(b.units))}"]

    def same(x, y) -> bool:
        if isinstance(x, dict) and isinstance(y, dict):
            return x.keys() == y.keys() and all(same(x[k], y[k]) for k in x)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            x, y = np.asarray(x), np.asarray(y)
            return x.shape == y.shape and x.dtype == y.dtype and np.array_equal(
                x, y, equal_nan=x.dtype.kind == "f")
        if isinstance(x, float) and isinstance(y, float) and np.isnan(x) and np.isnan(y):
            return True
        return x == y
    for unit in a.units:
        x, y = a.units[unit], b.units[unit]
        for f in fields(x):
            if f.name in COST_FIELDS:
                continue
            u, v = getattr(x, f.name), getattr(y, f.name)
            if f.name == "cache" and u is not None and v is not None:
                u, v = vars(u), vars(v)
            if not same(u, v):
                out.append(f"/units/{unit}: {f.name}")
    return out
