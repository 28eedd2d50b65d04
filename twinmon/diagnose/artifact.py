"""The artifact of ``diagnose``: ``gap.h5`` (``twinmon.gap/1``), written by :func:`write_gap` and
read back by :func:`read_gap` into :class:`~twinmon.diagnose.result.UnitGap` records.

What is stored per unit is driven by two tables: ``_ARRAYS`` (datasets with their units and
description) and ``_ATTRS`` / ``_JSON_ATTRS`` (scalar and JSON attributes).
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
               "separation_scores", "candidates", "effect_onsets")


def write_gap(path, results: dict, cfg: Config, time: np.ndarray, inputs) -> None:
    """Write ``gap.h5`` (``twinmon.gap/1``)::

        /time                          [n_t]  s
        /windows/names [n_w], /windows/bounds [n_w, 2] s
        attrs input_names (JSON)
        /units/<U>/<array>             see _ARRAYS (per year, [year, time], [year, window],
                                       [year, input] or [candidate] in ranking order)
        /units/<U>.attrs verdict, onset (-1: none), rms_before, rms_after, closed_percent,
                         delta_bic_final, separating_channel, absorbed_share, p_gap,
                         noise_std, failure_year_before/after (-1: none within the horizon),
                         and JSON: effects, group, where_windows, where_years, estimate
                         ({name: [mean, q05, q95]}), separation_scores, candidates,
                         effect_onsets ({name: onset year})
        /units/<U>/cache/              per-year records for diagnose --update
                                       (:mod:`.update`; gzip; absent in files written before
                                       them, which read_gap still reads):
            digest     [n_y]           SHA-256 of the year's whitened observations + noise
            base_u     [n_y, d]        normalised inputs of the base fit
            base_rows  [n_y, m]        its whitened residual (m = channels x n_t; NaN missing)
            base_jac   [n_y, m, d]     its Jacobian w.r.t. the normalised inputs
            base_lev   [n_y, m]        its leverages
            screen_gains [n_c, n_v, n_y]  initial screening's chi-square gains (attrs
                                       candidates, grid_sizes: JSON; NaN past a grid)
    """
    wins = cfg.diagnose_windows()
    with artifacts.write_artifact(path, "gap", config=cfg.section_yaml(*SECTIONS),
                                  inputs=inputs, seed=cfg.seed, compact=True) as f:
        # compact: ~30 small datasets per unit, whose B-trees were most of the file (30 pump
        # units x 10 years: 1.3 MB with the --update records; 2.6 MB without them, 3.6 MB
        # with them, in the older format).
        artifacts.put(f, "time", np.asarray(time), "s", "sample times")
        artifacts.put(f, "windows/names", list(wins), "", "time windows of the transient")
        artifacts.put(f, "windows/bounds", np.array([[w.start, w.stop] for w in wins.values()]),
                      "s", "start and stop of each window")
        f.attrs["input_names"] = json.dumps(cfg.model.input_names)
        for unit, g in results.items():
            grp = f.create_group(f"units/{unit}")
            for name, (units, desc) in _ARRAYS.items():
                units = cfg.model.output.units if units == "output units" else units
                data = np.asarray(getattr(g, name))
                if data.dtype == bool:
                    data = data.astype(np.int8)
                artifacts.put(grp, name, data, units, desc)
            for name in _ATTRS:
                v = getattr(g, name)
                grp.attrs[name] = -1 if v is None else v
            for name in _JSON_ATTRS:
                grp.attrs[name] = artifacts.json_attr(getattr(g, name))
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
            kw = {n: artifacts.get(g, n, path) for n in _ARRAYS}
            kw["significant_years"] = kw["significant_years"].astype(bool)
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
                kw[n] = json.loads(g.attrs[n])
            kw["estimate"] = {k: tuple(v) for k, v in kw["estimate"].items()}
            kw["cache"] = read_cache(g, path) if cache else None
            units[unit] = UnitGap(unit=unit, **kw)
        return GapFile(time, names, bounds, json.loads(f.attrs["input_names"]), units)
