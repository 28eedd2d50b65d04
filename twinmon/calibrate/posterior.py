"""Per-unit posteriors, per-year goodness of fit, and reading the ``posterior.h5`` artifact
(written by :mod:`.posterior_writer`)."""
from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from .. import artifacts
from ..errors import ArtifactError
from .fit import FIT_FIELDS, STATUS_OK
from .trend import TREND_DRAWS, TREND_FIELDS, TREND_OPTIONAL

#: Config sections recorded as the posterior's provenance (and compared by ``twinmon run``).
SECTIONS = ("model", "calibrate", "seed")
#: Added to ``cfg.seed`` so that calibrate's random streams differ from other stages'.
SEED_OFFSET = 3000
#: Stored type of the draws (the years' and the trend's), read back as float64. Single
#: precision keeps 7 significant digits, a million times finer than a posterior's Monte
#: Carlo error (its sd / sqrt(ESS)), at half the bytes, where gzip cannot shrink float64's
#: random mantissas (a 60-unit fleet's posterior: 13.3 -> 6.7 MB).
DRAW_DTYPE = np.float32


@dataclass
class UnitPosterior:
    """Posterior of one unit's inputs, year by year.

    Attributes
    ----------
    years : ndarray of int, shape [n_y]
    samples : ndarray, shape [n_y, n_s, d]
        Pooled post-burn-in draws of all chains (chain-major), input units.
    mean, median, q05, q95 : ndarray, shape [n_y, d]
    rhat, ess : ndarray, shape [n_y, d]
        Rank-normalised split R-hat and bulk effective sample size per input.
    acceptance : ndarray, shape [n_y, chains]
    noise_std : ndarray, shape [n_y]
        Output noise standard deviation used in the likelihood (output units).
    noise_source : str
        ``"file"``, ``"config"``, ``"estimated"`` or ``"differences"`` (estimated from the
        residuals' second differences, the residuals holding more than noise).
    surrogate_var_ratio : ndarray, shape [n_y]
        Mean over time steps of surrogate predictive variance / noise variance.
    """

    years: np.ndarray
    samples: np.ndarray
    mean: np.ndarray
    median: np.ndarray
    q05: np.ndarray
    q95: np.ndarray
    rhat: np.ndarray
    ess: np.ndarray
    acceptance: np.ndarray
    noise_std: np.ndarray
    noise_source: str
    surrogate_var_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: Goodness of fit per year (see :func:`year_fit`); empty for posteriors written before.
    fit: dict = field(default_factory=dict)
    #: Trend posterior of the joint method (``trend.TREND_FIELDS``); empty for sequential.
    trend: dict = field(default_factory=dict)
    #: Channels in the likelihood when there were several: name -> {"std", "source"} (the
    #: output first); empty when the output alone was used. ``fit["channel_rms"]`` [year,
    #: channel] then holds each channel's residual RMS, in its noise sd.
    channels: dict = field(default_factory=dict)
    #: Maintenance events of the unit, (year, component, action), from the observations.
    events: list = field(default_factory=list)
    #: Repairs no event records that calibration found in the years' estimates and started
    #: a trend segment at (the joint method): ``FoundRepair.as_dict()`` each.
    found_repairs: list = field(default_factory=list)
    #: Posterior variance of all the draws [year, input] and each chain's last state [year,
    #: chain, input]: what ``calibrate --update`` continues from (the next year's prior and
    #: the vectorised sampler's warm start); empty in posteriors written before.
    var: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    chain_end: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    #: Per year, a SHA-256 of the observation row and noise the year was calibrated on:
    #: ``--update`` keeps a year only if its data are unchanged.
    digest: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=str))
    #: Index of the first year whose draws ``samples`` holds ([n_y - samples_from, n_s, d]):
    #: 0 but for ``calibrate --update``, which leaves the draws of the years it keeps in the
    #: posterior it continues (read with ``draws=False``) and writes only the new ones.
    samples_from: int = 0
    #: The laplace method's Gaussian site of each year (what ``calibrate --update`` keeps of
    #: the stored years, :data:`SITE_FIELDS`): ``x`` [n_y, d], ``cov`` [n_y, d, d], ``var``
    #: [n_y, n_out], ``ratio`` [n_y]; empty for the other methods and for posteriors
    #: written before.
    site: dict = field(default_factory=dict)

    @property
    def chains(self) -> int:
        return self.acceptance.shape[1]

    @property
    def status(self) -> np.ndarray:
        """Per year: ``ok``, ``misfit`` (the twin misses the plant), ``edge`` (the posterior
        sits on the design box's edge) or ``unconverged``; all ``ok`` when not recorded."""
        st = self.fit.get("status")
        return np.asarray(st) if st is not None else np.full(len(self.years), STATUS_OK)


@dataclass
class Posterior:
    """A loaded ``posterior.h5``: ``input_names`` and per unit a :class:`UnitPosterior`.

    Read from a file, ``units`` is an :class:`~twinmon.artifacts.LazyUnits` mapping: a unit
    is read (and checked) when it is looked up, so a fleet's posterior never sits in memory
    whole."""

    input_names: list[str]
    units: Mapping[str, UnitPosterior]
    path: Path = Path("<memory>")
    #: Names of the windows ``fit/window`` indexes.
    fit_windows: list = field(default_factory=list)


_DATASETS = {
    # name: (units, description); "in" = input units (listed per input in the attrs)
    "years": ("year", "year of service of each calibration"),
    "samples": ("input units", "post-burn-in MCMC draws, evenly thinned over the chain-major "
                "pooled draws to calibrate.keep_draws [year, draw, input]"),
    "mean": ("input units", "posterior mean [year, input]"),
    "median": ("input units", "posterior median [year, input]"),
    "q05": ("input units", "posterior 5 % quantile [year, input]"),
    "q95": ("input units", "posterior 95 % quantile [year, input]"),
    "rhat": ("1", "rank-normalised split R-hat [year, input]"),
    "ess": ("1", "bulk effective sample size [year, input]"),
    "acceptance": ("1", "Metropolis-Hastings acceptance rate after burn-in [year, chain]"),
    "noise_std": ("output units", "output noise standard deviation used in the likelihood "
                  "[year]"),
    "surrogate_var_ratio": ("1", "mean surrogate predictive variance / noise variance [year]"),
}


def draw_statistics(draws: np.ndarray, rhat: np.ndarray, ess: np.ndarray) -> dict:
    """:class:`UnitPosterior`'s summary fields of draws [K, n_s, d] (``mean``, ``median``,
    ``q05``, ``q95`` [K, d]) with the diagnostics ``rhat`` and ``ess`` [K, d]."""
    return {"mean": draws.mean(axis=1), "median": np.median(draws, axis=1),
            "q05": np.quantile(draws, 0.05, axis=1), "q95": np.quantile(draws, 0.95, axis=1),
            "rhat": rhat, "ess": ess}


#: Optional per-unit datasets (absent from posteriors written before ``--update`` existed).
_CONTINUATION = {
    "var": ("input units squared", "posterior variance of all the draws [year, input]"),
    "chain_end": ("input units", "last state of each chain [year, chain, input]"),
    "digest": ("1", "SHA-256 of the observation row and noise each year was calibrated on "
               "[year]"),
}


#: The laplace method's site of a year (``UnitPosterior.site``), stored as the record's
#: ``site_<key>`` fields: key -> (units, description).
SITE_FIELDS = {
    "x": ("input units", "laplace: the year's maximum-likelihood point (its site's centre) "
          "[year, input]"),
    "cov": ("input units squared", "laplace: the site's Laplace covariance [year, input, "
            "input]"),
    "var": ("output units squared", "laplace: the likelihood's variance per sample, noise + "
            "surrogate variance at the site [year, sample]"),
    "ratio": ("1", "laplace: mean surrogate-to-noise variance ratio of the site [year]"),
}


def thin_indices(n_draws: int, keep: int) -> np.ndarray:
    """Indices of ``keep`` draws evenly spaced over ``n_draws`` pooled draws (all of them
    when ``keep >= n_draws``).

    The pooled draws are chain-major (chain after chain, each the same length), so every
    chain gives ``keep / chains`` draws (within one), evenly spaced along it: the kept set
    spans every chain from start to end and the thinning cuts the autocorrelation between
    neighbouring kept draws.
    """
    if keep >= n_draws:
        return np.arange(n_draws)
    return np.floor((np.arange(keep) + 0.5) * (n_draws / keep)).astype(np.int64)


def record_dtype(d: int, chains: int, n_channels: int = 0, fit: bool = True,
                 continuation: bool = True, n_site: int = 0) -> np.dtype:
    """The compound dtype of ``/units/<U>/record``: one row per year (:data:`RECORD_FIELDS`).

    Parameters
    ----------
    d, chains : int
        Inputs and chains (the shapes of the subarray fields).
    n_channels : int
        Channels of ``fit_channel_rms`` (0: no such field).
    fit, continuation : bool
        Whether the ``fit_*`` fields and ``var``/``chain_end``/``digest`` are present (a
        posterior without them, e.g. built in memory by a test, stores none).
    n_site : int
        Samples of the likelihood's variance in the ``site_*`` fields (the laplace method's
        sites, :data:`SITE_FIELDS`); 0: no such fields.
    """
    fields = [("year", "<i8")] + [(k, "<f8", (d,)) for k in
                                  ("mean", "median", "q05", "q95", "rhat", "ess")]
    fields += [("acceptance", "<f8", (chains,)), ("noise_std", "<f8"),
               ("surrogate_var_ratio", "<f8")]
    if continuation:
        fields += [("var", "<f8", (d,)), ("chain_end", "<f8", (chains, d)), ("digest", "S64")]
    if fit:
        fields += [("fit_rms", "<f8"), ("fit_p_chi2", "<f8"), ("fit_p_ljung_box", "<f8"),
                   ("fit_window", "<i8"), ("fit_window_rms", "<f8"),
                   ("fit_edge_share", "<f8", (d,)), ("fit_extensions", "<i8"),
                   ("fit_converged", "i1"), ("fit_status", "S16")]
        if n_channels:
            fields.append(("fit_channel_rms", "<f8", (n_channels,)))
    if n_site:
        fields += [("site_x", "<f8", (d,)), ("site_cov", "<f8", (d, d)),
                   ("site_var", "<f8", (n_site,)), ("site_ratio", "<f8")]
    return np.dtype(fields)


#: What each field of ``/units/<U>/record`` holds: (units, description). Recorded once, as
#: the root attribute ``record_fields``, not on every unit's dataset (attributes cost as
#: much to write as a small dataset).
RECORD_FIELDS = {
    "year": _DATASETS["years"],
    **{k: _DATASETS[k] for k in ("mean", "median", "q05", "q95", "rhat", "ess", "acceptance",
                                 "noise_std", "surrogate_var_ratio")},
    **_CONTINUATION,
    **{f"fit_{k}": v for k, v in FIT_FIELDS.items()},
    "fit_channel_rms": ("1", "residual RMS per channel (order of the unit's channels "
                        "attribute), in its noise sd [year, channel]"),
    **{f"site_{k}": v for k, v in SITE_FIELDS.items()},
}


def slim(p: UnitPosterior) -> UnitPosterior:
    """``p`` without its draws (the years' and the trend's), which calibrate has written:
    what its summary keeps of a unit (statistics, fit, sites, a few kB) while the fleet's
    draws go to the file."""
    from dataclasses import replace
    n_y, _, d = np.shape(p.samples) if np.ndim(p.samples) == 3 else (len(p.years), 0, 0)
    return replace(p, samples=np.zeros((n_y, 0, d)),
                   trend={k: v for k, v in p.trend.items() if k not in TREND_DRAWS})


def _get_trend(g: h5py.Group, path: Path) -> dict:
    """The trend posterior of one unit; empty when it has none (the sequential method).
    The fields of ``trend.TREND_OPTIONAL`` may be absent."""
    if "trend" not in g:
        return {}
    t = g["trend"]
    there = set(t)
    out = {key: artifacts.get(t, key, path) for key in TREND_FIELDS
           if key not in TREND_OPTIONAL or key in there}
    return {key: v.astype(float) if v.dtype.kind == "f" else v for key, v in out.items()}


def read_posterior(path: str | os.PathLike, draws: bool = True,
                   trend: bool = True) -> Posterior:
    """Open ``posterior.h5`` (schema checked); its units are read when looked up.

    Only the root attributes and the list of units are read here. Each unit is read from
    the file, and its shapes checked, on access (``post.units[u]``, iteration); a few
    recently read units are kept. A file replaced after this call is refused on access
    rather than mixed with the first one. Posteriors written before the draws were thinned
    (every pooled draw, uncompressed) read the same way.

    ``draws=False`` leaves each unit's draws in the file (``samples`` [0, n_s, d],
    ``samples_from`` = n_y): what ``calibrate --update`` continues from (a
    ``twinmon.posterior/1`` file is always read whole). ``trend=False`` leaves the joint
    trend there too (``trend`` is empty): with ``draws=False``, a unit's per-year record
    alone, what a fleet's summary needs.

    Raises
    ------
    ArtifactError
        Missing file, wrong schema, no units; on access: missing datasets, inconsistent
        shapes or damaged bytes (naming the file and the dataset).
    """
    path = Path(path)
    with artifacts.open_artifact(path, "posterior") as f:
        if "input_names" not in f.attrs:
            raise ArtifactError(f"{path}: root attribute input_names is missing")
        names = json.loads(f.attrs["input_names"])
        if "units" not in f or len(f["units"]) == 0:
            raise ArtifactError(f"{path}: group /units is missing or empty")
        unit_names = list(f["units"])
        windows = json.loads(f.attrs["fit_windows"]) if "fit_windows" in f.attrs else []
    units = artifacts.LazyUnits(path, "posterior", unit_names,
                                lambda f, unit, p: _read_unit(f, unit, p, names, draws,
                                                              trend))
    return Posterior(names, units, path, windows)


def _read_unit(f: h5py.File, unit: str, path: Path, names: list[str],
               draws: bool = True, trend: bool = True) -> UnitPosterior:
    """Read and check one unit of an open ``posterior.h5`` (either layout); without its
    draws if not ``draws``, without its trend's draws if not ``trend`` (see
    :func:`read_posterior`)."""
    if f"units/{unit}" not in f:
        raise ArtifactError(f"{path}: group /units/{unit} is missing")
    g = f["units"][unit]
    if "record" not in g and "years" in g:
        return _read_unit_v1(g, unit, path, names)
    if "record" not in g:
        raise ArtifactError(f"{path}: dataset /units/{unit}/record is missing")
    rec = artifacts.get(g, "record", path)
    if draws:
        samples = artifacts.get(g, "samples", path).astype(float)
    else:
        shape = artifacts.get_shape(g, "samples", path)
        samples = np.empty((0,) + shape[1:])
    n_y, d = len(rec), len(names)
    fields = rec.dtype.names or ()
    missing = [k for k in ("year", "mean", "median", "q05", "q95", "rhat", "ess",
                           "acceptance", "noise_std") if k not in fields]
    if missing:
        raise ArtifactError(f"{path}: /units/{unit}/record lacks the field {missing[0]!r}")
    if rec.dtype["mean"].shape != (d,):
        raise ArtifactError(f"{path}: /units/{unit}/record['mean'] has {rec.dtype['mean'].shape}"
                            f" per year, expected ({d},)")
    shape = samples.shape if draws else shape
    if len(shape) != 3 or shape[::2] != (n_y, d):
        raise ArtifactError(f"{path}: /units/{unit}/samples has shape {shape}, "
                            f"expected ({n_y}, n_s, {d})")
    # Each field copied out of the record (a field of a structured array is a strided view).
    arrs = {k: np.ascontiguousarray(rec[k]) for k in (
        "mean", "median", "q05", "q95", "rhat", "ess", "acceptance", "noise_std",
        "surrogate_var_ratio")}
    if "var" in fields:
        arrs.update(var=np.ascontiguousarray(rec["var"]),
                    chain_end=np.ascontiguousarray(rec["chain_end"]),
                    digest=np.array([v.decode() for v in rec["digest"]]))
    fit = {}
    if "fit_status" in fields:
        fit = {k: np.ascontiguousarray(rec[f"fit_{k}"]) for k in FIT_FIELDS}
        fit["converged"] = fit["converged"].astype(bool)
        fit["status"] = np.array([v.decode() for v in fit["status"]])
        if "fit_channel_rms" in fields:
            fit["channel_rms"] = np.ascontiguousarray(rec["fit_channel_rms"])
    site = {}
    if "site_x" in fields:
        for key, want in (("site_x", (d,)), ("site_cov", (d, d)), ("site_var", None),
                          ("site_ratio", ())):
            if key not in fields:
                raise ArtifactError(f"{path}: /units/{unit}/record lacks the field {key!r}")
            if want is not None and rec.dtype[key].shape != want:
                raise ArtifactError(f"{path}: /units/{unit}/record[{key!r}] has "
                                    f"{rec.dtype[key].shape} per year, expected {want}")
        site = {k: np.ascontiguousarray(rec[f"site_{k}"]) for k in SITE_FIELDS}
    src = g.attrs.get("noise_source", "")
    return UnitPosterior(years=np.ascontiguousarray(rec["year"]), samples=samples,
                         samples_from=0 if draws else n_y,
                         noise_source=src.decode() if isinstance(src, bytes) else str(src),
                         fit=fit, channels=json.loads(g.attrs.get("channels", "{}")),
                         trend=_get_trend(g, path) if trend else {}, **arrs, site=site,
                         events=[tuple(e) for e in json.loads(g.attrs.get("events", "[]"))],
                         found_repairs=json.loads(g.attrs.get("found_repairs", "[]")))


#: Per-unit datasets of the first layout (``twinmon.posterior/1``: one dataset per field).
_V1_DATASETS = ("years", "samples", "mean", "median", "q05", "q95", "rhat", "ess",
                "acceptance", "noise_std", "surrogate_var_ratio")


def _read_unit_v1(g: h5py.Group, unit: str, path: Path, names: list[str]) -> UnitPosterior:
    """One unit of a ``twinmon.posterior/1`` file (a dataset per field, written before
    ``record``); read as it always was."""
    arrs = {n: artifacts.get(g, n, path) for n in _V1_DATASETS
            if n != "surrogate_var_ratio" or n in g}
    n_y, d = len(arrs["years"]), len(names)
    for n in ("mean", "median", "q05", "q95", "rhat", "ess"):
        if arrs[n].shape != (n_y, d):
            raise ArtifactError(f"{path}: /units/{unit}/{n} has shape {arrs[n].shape}, "
                                f"expected ({n_y}, {d})")
    if arrs["samples"].ndim != 3 or arrs["samples"].shape[::2] != (n_y, d):
        raise ArtifactError(f"{path}: /units/{unit}/samples has shape "
                            f"{arrs['samples'].shape}, expected ({n_y}, n_s, {d})")
    src = g.attrs.get("noise_source", "")
    fit = {}
    if "fit" in g:
        fit = {key: artifacts.get(g["fit"], key, path) for key in FIT_FIELDS}
        fit["converged"] = fit["converged"].astype(bool)
        if len(fit["status"]) != n_y:
            raise ArtifactError(f"{path}: /units/{unit}/fit/status has "
                                f"{len(fit['status'])} years, expected {n_y}")
    channels = json.loads(g.attrs.get("channels", "{}"))
    if channels and "fit" in g and "channel_rms" in g["fit"]:
        fit["channel_rms"] = artifacts.get(g["fit"], "channel_rms", path)
    arrs.update({n: artifacts.get(g, n, path) for n in _CONTINUATION if n in g})
    return UnitPosterior(noise_source=src.decode() if isinstance(src, bytes) else str(src),
                         fit=fit, channels=channels, trend=_get_trend(g, path), **arrs,
                         events=[tuple(e) for e in json.loads(g.attrs.get("events", "[]"))])
