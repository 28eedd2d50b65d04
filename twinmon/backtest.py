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
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import artifacts, lineage
from .plausibility import check_observations
from .config import Config
from .errors import ArtifactError

#: Config sections recorded in the artifact.
SECTIONS = ("model", "forecast", "safety", "seed", "backtest")


@dataclass
class UnitBacktest:
    """One unit's back-test.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    observed : ndarray, shape [n_y]
        Observed indicator per year (posterior median; inf = level not reached).
    observed_unsafe : ndarray of bool, shape [n_y]
    cuts : ndarray of int, shape [n_c]
    pred_lo, pred_med, pred_hi : ndarray, shape [n_c, h]
        Forecast interval and median of the indicator for cut + 1 .. cut + h.
    failure_pred : ndarray of int, shape [n_c]
        Predicted failure year per cut (-1: none within the horizon).
    end_of_life : int or None
        First observed unsafe year.
    """

    years: np.ndarray
    observed: np.ndarray
    observed_unsafe: np.ndarray
    cuts: np.ndarray
    pred_lo: np.ndarray
    pred_med: np.ndarray
    pred_hi: np.ndarray
    failure_pred: np.ndarray
    end_of_life: Optional[int]
    horizon: int

    def pairs(self):
        """(cut index, future index, year) of every forecast year that was later observed
        (and not past the end of life, after which the unit would have been repaired)."""
        last = self.end_of_life if self.end_of_life is not None else int(self.years[-1])
        for c, k in enumerate(self.cuts):
            for j in range(self.horizon):
                y = int(k) + 1 + j
                if y <= last and y in self.years:
                    yield c, j, y

    def scored(self):
        """(years recorded up to the cut, observation inside the interval) of every pair of
        :meth:`pairs`."""
        for c, j, y in self.pairs():
            o = self.observed[np.flatnonzero(self.years == y)[0]]
            yield (int(np.sum(self.years <= self.cuts[c])),
                   bool(self.pred_lo[c, j] <= o <= self.pred_hi[c, j]))


@dataclass
class TTFScore:
    """Time-to-failure scores of one unit that reached unsafe (see module docstring)."""

    end_of_life: int
    rul_true: np.ndarray
    rul_pred: np.ndarray
    cut_lambda: int
    alpha_lambda: bool
    relative_accuracy: float
    prognostic_horizon: float


def ttf_scores(cuts: np.ndarray, failure_pred: np.ndarray, end_of_life: int, horizon: int,
               alpha: float = 0.2, lam: float = 0.5) -> Optional[TTFScore]:
    """alpha-lambda accuracy, relative accuracy and prognostic horizon of one unit.

    Parameters
    ----------
    cuts : ndarray of int, shape [n_c]
    failure_pred : ndarray of int, shape [n_c]
        Predicted failure year per cut; -1 = none within ``horizon`` (censored at
        ``cut + horizon + 1``).
    end_of_life : int
        True (or observed) failure year.

    Returns
    -------
    TTFScore or None
        None when no cut precedes the end of life.
    """
    cuts = np.asarray(cuts, int)
    before = cuts < end_of_life
    if not before.any():
        return None
    k = cuts[before]
    fp = np.asarray(failure_pred, int)[before]
    fp = np.where(fp < 0, k + horizon + 1, fp)
    rul, pred = end_of_life - k, fp - k
    ok = np.abs(pred - rul) <= alpha * rul
    k_lam = k[0] + lam * (end_of_life - k[0])
    i = int(np.argmin(np.abs(k - k_lam)))
    ra = float(1 - abs(rul[i] - pred[i]) / rul[i])
    # Prognostic horizon: from the first cut after which every prediction stays in the cone.
    ph = 0.0
    for j in range(len(k)):
        if ok[j:].all():
            ph = float(end_of_life - k[j])
            break
    return TTFScore(end_of_life, rul, pred, int(k[i]), bool(ok[i]), ra, ph)


@dataclass
class BacktestSummary:
    units: dict
    coverage: float
    n_pairs: int
    indicator_mae: float
    ttf: dict = field(default_factory=dict)
    output: str = ""
    confidence: float = 0.9
    #: Caveats of the scores (a joint posterior truncated instead of calibrated again).
    warnings: list = field(default_factory=list)
    #: ``truncated`` (the stored posterior cut at each cut year) or ``recalibrated``.
    cut_posteriors: str = "truncated"
    #: False when the coverage is outside ``coverage_band`` beyond its sampling error
    #: (:func:`coverage_verdict`; the warning is among ``warnings``).
    coverage_in_band: bool = True
    coverage_band: tuple = (float("nan"), float("nan"))
    #: The coverage of the forecasts made from each number of recorded years (at the cut):
    #: ``{n: {"coverage", "pairs", "in_band"}}`` (:func:`coverage_by_record`). Wear whose shape
    #: a short record cannot show misses there while the pooled coverage may still hold.
    by_record: dict = field(default_factory=dict)

    @property
    def unsafe_before_cuts(self) -> dict:
        """Units unsafe already at or before their first cut: ``{unit: first unsafe year}``.
        No forecast was made from before their end of life, so they have no time-to-failure
        score and their years past it no coverage pair (the unit would have been repaired)."""
        return {u: int(b.end_of_life) for u, b in self.units.items()
                if b.end_of_life is not None and u not in self.ttf}

    @property
    def all_in_band(self) -> bool:
        """The pooled coverage and that of every record length in their band."""
        return self.coverage_in_band and all(v["in_band"] for v in self.by_record.values())

    @property
    def alpha_lambda(self) -> float:
        return float(np.mean([s.alpha_lambda for s in self.ttf.values()])) if self.ttf \
            else float("nan")

    def as_dict(self) -> dict:
        f = (lambda v: None if v is None or not np.isfinite(v) else round(float(v), 4))
        return {
            "coverage": f(self.coverage), "confidence": self.confidence,
            "coverage_in_band": self.coverage_in_band,
            "coverage_band": [f(b) for b in self.coverage_band],
            "pairs": self.n_pairs, "indicator_mae": f(self.indicator_mae),
            "coverage_by_record": {str(n): {"coverage": f(v["coverage"]), "pairs": v["pairs"],
                                            "in_band": v["in_band"]}
                                   for n, v in self.by_record.items()},
            "alpha_lambda_accuracy": f(self.alpha_lambda),
            "units_reaching_unsafe": len(self.ttf),
            "units_unsafe_before_cuts": self.unsafe_before_cuts,
            "ttf": {u: {"end_of_life": s.end_of_life, "cut_lambda": s.cut_lambda,
                        "alpha_lambda": s.alpha_lambda,
                        "relative_accuracy": f(s.relative_accuracy),
                        "prognostic_horizon": f(s.prognostic_horizon)}
                    for u, s in self.ttf.items()},
            "units": {u: {"cuts": b.cuts.tolist(), "failure_pred": b.failure_pred.tolist(),
                          "end_of_life": b.end_of_life} for u, b in self.units.items()},
            "cut_posteriors": self.cut_posteriors, "warnings": list(self.warnings),
            "output": self.output,
        }


def wilson_interval(share: float, n: int, z: float = 1.645) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``share`` of ``n`` trials (90 % for the
    default ``z``); NaNs when ``n`` is 0."""
    if n == 0:
        return float("nan"), float("nan")
    centre = (share + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(share * (1 - share) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(centre - half), float(centre + half)


def coverage_verdict(coverage: float, n_pairs: int, confidence: float,
                     band: float) -> tuple[bool, str]:
    """Whether a back-test's coverage is consistent with its intervals' confidence.

    Parameters
    ----------
    coverage : float
        Share of the ``n_pairs`` later observations inside the forecast intervals.
    confidence : float
        The intervals' nominal confidence (``forecast.confidence``).
    band : float
        Tolerated departure (``backtest.coverage_band``): coverage in
        ``[confidence - band, confidence + band]`` is in the band.

    Returns
    -------
    in_band : bool
        False when the coverage's 90 % Wilson interval lies wholly outside the band: with
        few pairs a coverage outside the band may be chance, and is not flagged.
    message : str
        The warning, naming the coverage, the pairs and what it means; ``""`` when in band.
    """
    lo_band, hi_band = confidence - band, confidence + band
    if n_pairs == 0 or not np.isfinite(coverage):
        return True, ""
    lo, hi = wilson_interval(coverage, n_pairs)
    if hi < lo_band:
        return False, (f"back-test coverage {coverage:.2f} of {n_pairs} later observations "
                       f"(90 % interval {lo:.2f}-{hi:.2f}) is below {lo_band:.2f}-{hi_band:.2f}: "
                       f"the {100 * confidence:.0f} % forecast intervals were too narrow on "
                       "this history (wear that is not a straight line, an unrecorded repair, "
                       "a record too short); do not rely on the forecast's failure years")
    if lo > hi_band:
        return False, (f"back-test coverage {coverage:.2f} of {n_pairs} later observations "
                       f"(90 % interval {lo:.2f}-{hi:.2f}) is above {lo_band:.2f}-{hi_band:.2f}: "
                       f"the {100 * confidence:.0f} % forecast intervals were wider than this "
                       "history needed; failure years come early")
    return True, ""


def coverage_by_record(units: dict, confidence: float, band: float) -> tuple[dict, list]:
    """The coverage of the forecasts made from each number of recorded years.

    Forecasts from five or six years of accelerating wear cover far less than those from
    ten (the record cannot show the shape yet), and a pooled coverage can hide it: each
    record length is judged against the band on its own (:func:`coverage_verdict`).

    Parameters
    ----------
    units : dict unit -> UnitBacktest
    confidence, band : float
        As :func:`coverage_verdict`'s.

    Returns
    -------
    by_record : dict int -> dict
        ``{"coverage", "pairs", "in_band"}`` per number of years recorded up to the cut.
    warnings : list of str
        One per record length outside the band.
    """
    groups: dict = {}
    for b in units.values():
        for n, inside in b.scored():
            groups.setdefault(n, []).append(inside)
    out, warnings = {}, []
    for n in sorted(groups):
        cov, m = float(np.mean(groups[n])), len(groups[n])
        in_band = coverage_verdict(cov, m, confidence, band)[0]
        out[n] = {"coverage": cov, "pairs": m, "in_band": in_band}
        if not in_band:
            lo, hi = wilson_interval(cov, m)
            low = cov < confidence
            warnings.append(
                f"back-test: the forecasts made from {n} recorded year(s) covered {cov:.2f} of "
                f"{m} later observations (90 % interval {lo:.2f}-{hi:.2f}), "
                f"{'below' if low else 'above'} {confidence - band:.2f}-{confidence + band:.2f}: "
                + ("from so few years the intervals were too narrow on this history (a shape "
                   "of wear the record could not show yet); trust a forecast from a record "
                   "that short less" if low else
                   "from so few years the intervals were wider than this history needed"))
    return out, warnings


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
    from .observations import read_observations
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
    from .calibrate import calibrate, read_posterior
    from .observations import write_observations
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
    from .calibrate import Posterior, read_posterior
    from .forecast import (box_is_physical, degrading_directions, forecast_limit_state,
                           forecast_units)
    from .reduce import check_made_for, read_surrogate
    from .safety import Indicator
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
        b = UnitBacktest(yrs, obs, unsafe, cuts, lo, med, hi, fp, eol, h)
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
                             int(g.attrs["horizon"]))
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
