"""``backtest.h5`` (``twinmon.backtest/1``): writing and reading the back-test artifact."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError
from .scores import BacktestSummary, UnitBacktest, coverage_by_record, ttf_scores

#: Config sections recorded in the artifact.
SECTIONS = ("model", "forecast", "safety", "seed", "backtest")


def write_backtest(path, cfg: Config, s: BacktestSummary, ind, inputs) -> None:
    """``backtest.h5`` (``twinmon.backtest/1``): per unit the cuts, the forecast interval of
    the indicator per cut and future year, the observed indicator and the failure years."""
    put = artifacts.put
    # Cuts calibrated again depend on the calibrate section too.
    sections = SECTIONS + (("calibrate",) if s.cut_posteriors == "recalibrated" else ())
    with artifacts.write_artifact(path, "backtest", config=cfg.section_yaml(*sections),
                                  inputs=inputs, seed=cfg.seed) as f:
        f.attrs["coverage"] = s.coverage
        f.attrs["coverage_in_band"] = s.coverage_in_band
        f.attrs["coverage_band"] = np.asarray(s.coverage_band, float)
        f.attrs["cut_posteriors"] = s.cut_posteriors
        f.attrs["warnings"] = artifacts.json_attr(list(s.warnings))
        f.attrs["confidence"] = s.confidence
        f.attrs["indicator_mae"] = s.indicator_mae
        f.attrs["alpha_lambda"] = s.alpha_lambda
        f.attrs["alpha"] = cfg.backtest.alpha
        f.attrs["lambda_value"] = cfg.backtest.lambda_value
        f.attrs["indicator"] = artifacts.json_attr({"name": ind.name, "units": ind.units,
                                                    "limit": ind.limit})
        for u, b in s.units.items():
            g = f.create_group(f"units/{u}")
            put(g, "years", b.years, "year", "observed years")
            put(g, "observed", b.observed, ind.units, f"observed {ind.name} (posterior median)")
            put(g, "observed_unsafe", b.observed_unsafe.astype(np.int8), "1",
                "1 where the year's recording was unsafe")
            put(g, "cuts", b.cuts, "year", "last year each back-test forecast saw")
            for name in ("pred_lo", "pred_med", "pred_hi"):
                put(g, name, getattr(b, name), ind.units,
                    f"forecast {name[5:]} of {ind.name} [cut, future year]")
            put(g, "failure_pred", b.failure_pred, "year", "predicted failure year per cut "
                "(-1: none within the horizon)")
            g.attrs["end_of_life"] = -1 if b.end_of_life is None else b.end_of_life
            g.attrs["horizon"] = b.horizon
            g.attrs["repair_years"] = np.asarray(b.repairs, np.int64)


def read_backtest(path: str | os.PathLike) -> BacktestSummary:
    """Load ``backtest.h5`` (the TTF scores are recomputed from the stored arrays)."""
    path = Path(path)
    units, ttf = {}, {}
    with artifacts.open_artifact(path, "backtest") as f:
        if "units" not in f:
            raise ArtifactError(f"{path}: group /units is missing")
        alpha, lam = float(f.attrs["alpha"]), float(f.attrs["lambda_value"])
        for u, g in f["units"].items():
            get = (lambda n: artifacts.get(g, n, path))
            eol = int(g.attrs["end_of_life"])
            b = UnitBacktest(get("years"), get("observed"), get("observed_unsafe").astype(bool),
                             get("cuts"), get("pred_lo"), get("pred_med"), get("pred_hi"),
                             get("failure_pred"), None if eol < 0 else eol,
                             int(g.attrs["horizon"]),
                             tuple(int(y) for y in g.attrs.get("repair_years", ())))
            units[u] = b
            if b.end_of_life is not None and b.cuts.size:
                sc = ttf_scores(b.cuts, b.failure_pred, b.end_of_life, b.horizon, alpha, lam)
                if sc is not None:
                    ttf[u] = sc
        warnings = json.loads(f.attrs["warnings"]) if "warnings" in f.attrs else []
        band = tuple(float(b) for b in f.attrs.get("coverage_band", (np.nan, np.nan)))
        confidence = float(f.attrs["confidence"])
        # Recomputed from the stored intervals and observations (the same numbers).
        by_record = (coverage_by_record(units, confidence, 0.5 * (band[1] - band[0]))[0]
                     if np.all(np.isfinite(band)) else {})
        n_pairs = sum(1 for b in units.values() for _ in b.pairs())
        return BacktestSummary(units, float(f.attrs["coverage"]), n_pairs,
                               float(f.attrs["indicator_mae"]), ttf, str(path),
                               float(f.attrs["confidence"]), warnings,
                               str(f.attrs.get("cut_posteriors", "truncated")),
                               coverage_in_band=bool(f.attrs.get("coverage_in_band", True)),
                               coverage_band=band, by_record=by_record)
