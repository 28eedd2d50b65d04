"""Stage ``calibrate``: posterior of the degradation inputs per unit and year.

For each unit, each year's start-up transient is inverted through the surrogate by Bayesian
inference, as in the paper (section V):

* prior: year 1 uniform on the design box; year k > 1 Gaussian (independent per input,
  truncated to the box) centred on year k-1's posterior mean, standard deviation
  ``sqrt((prior_width * (high - low))^2 + previous posterior variance)`` per input (the
  second term with ``prior_carry_variance``, the default; see docs/calibration.md);
* likelihood: Gaussian, independent per time step, variance = measurement noise variance +
  surrogate predictive variance; missing (NaN) samples are left out;
* sampling: OpenTURNS' random-walk Metropolis-Hastings, several chains started around the
  maximum a posteriori (MAP) point with a proposal shaped on the Laplace (Gauss-Newton)
  covariance there; OpenTURNS returns the burn-in with the chain, so it is cut here; the
  chains of all units' same year run in parallel processes (``calibrate.sampler:
  openturns``, the reference). The default ``vectorised`` sampler (:mod:`.samplers.vectorised`)
  moves every chain of every unit's same year in one numpy step and runs them until the
  ESS is met; ``--update`` (:mod:`.update`) samples only the years added since;
* diagnostics: rank-normalised split R-hat and bulk effective sample size (Vehtari et al.
  2021) and the acceptance rate per chain, with warnings when they are poor.

The result is ``posterior.h5`` (``twinmon.posterior/2``)::

    attrs input_names, input_units (JSON lists), record_fields (JSON {field: [units,
          description]}), channels (JSON list: the channels in the likelihood, the output's
          name first), fit_windows (JSON list: the window names fit_window indexes)
    /units/<U>/record       compound [n_y]        one row per year (posterior.RECORD_FIELDS):
                            year; mean, median, q05, q95, rhat, ess, var [d]; acceptance
                            [chains]; noise_std (output units, used in the likelihood);
                            surrogate_var_ratio; chain_end [chains, d] and digest (what
                            --update continues from); fit_<field> for each of FIT_FIELDS
                            (rms, p_chi2, p_ljung_box, window, window_rms, edge_share [d],
                            extensions, converged, status ok|misfit|edge|unconverged),
                            fit_channel_rms [n_ch] when further channels were in the
                            likelihood, and (laplace) each year's site: site_x [d], site_cov
                            [d, d], site_var [n_out], site_ratio (what --update keeps)
    /units/<U>/samples      float64 [n_y, n_s, d] pooled post-burn-in draws (input units),
                            evenly thinned to calibrate.keep_draws (statistics use them all)
    /units/<U>/trend/<field>                   methods joint and laplace only: the trend's
                            posterior (joint.TREND_FIELDS): start [S, d]; intercept, slope
                            [draw, S, d]; sigma [draw, d]; rhat, ess [3, d]; acceptance [chain]
                            (NaN for laplace's weighted draws, as the years' acceptance)
    /units/<U>.attrs noise_source  "file" | "config" | "estimated" | "differences" (estimated
                                   from the residuals' second differences: they hold more
                                   than noise)
    /units/<U>.attrs channels      JSON {channel: {std, source}} when further channels were
                                   in the likelihood (the output first)
    /units/<U>.attrs events        JSON [[year, component, action]] (maintenance events)
    /units/<U>.attrs found_repairs JSON [{year, components, steps, p_value}]: falls back
                                   towards nominal no event records, where the joint
                                   or laplace method started a trend segment (forecast.repair_alpha)

``twinmon.posterior/1`` files (a dataset per field) are still read.

Goodness of fit: each year's residual at the posterior mean, standardised by the likelihood's
variance, is tested for size and structure; a year whose residual is well above the noise
(``calibrate.fit_min_rms``) and significant (``fit_alpha``) is "misfit" -- the twin misses the
plant -- and one whose draws pile against a bound of the design box is "edge". A year whose
R-hat or ESS is poor is sampled again with longer chains (``max_extensions`` times); still
poor, it is "unconverged". ``forecast`` withholds or flags a prognosis on these verdicts.

Further recorded channels (``model.channels``) that ``reduce`` learnt enter the likelihood
with their own noise (``calibrate.channels`` restricts them; see ``channels``).

Modules: ``base`` (the method and sampler interfaces), ``methods`` (one module per method:
``sequential``, the paper's year by year; ``joint``, a unit's history with its trend;
``laplace``, the joint model on each year's Laplace approximation, drawn without a chain),
``samplers`` (``openturns``, the reference; ``vectorised`` and ``joint_vectorised``, numpy,
through ``gpbatch``), ``shared`` (what methods and samplers share: priors, starting points,
tasks, worker state), ``density`` (prior, log-posterior, MAP, noise estimate),
``diagnostics`` (R-hat, ESS), ``channels`` (several channels in one likelihood), ``trend``
(the joint method's trend model), ``fit`` (goodness of fit), ``posterior`` (per-unit results,
the artifact), ``update`` (``--update``), ``fleet`` (the fleet's prior of the trend's sd);
this module is the stage's entry point: it picks the method (``calibrate.method``,
:func:`resolve_method`) and the sampler (``calibrate.sampler``) through those interfaces.
"""
from __future__ import annotations

import os
import zlib
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError, InputDataError
from ..executors import one_blas_thread
from ..observations import check_events, read_observations
from ..plausibility import check_observations
from .base import Method, Sampler, Work
from .channels import StackedSurrogate, channel_noise, select_channels, stacked_rows
from .density import (LogDensity, NoiseEstimate, Prior, estimate_noise, estimate_noise_checked,
                      find_map, make_log_density)
from .diagnostics import ess, split_rhat
from .fit import FIT_FIELDS, STATUS_EDGE, STATUS_MISFIT, STATUS_OK, STATUS_UNCONVERGED, year_fit
from .methods import method_named
from .methods.sequential import calibrate_unit, plan_chains, run_chain, sample_posterior
from .posterior import SECTIONS, SEED_OFFSET, Posterior, UnitPosterior, read_posterior, slim
from .posterior_writer import PosteriorWriter, write_posterior
from .shared import init_worker, year_prior
from .update import Kept, plan_update, year_digests

__all__ = [
    "ACCEPTANCE_RANGE", "FIT_FIELDS", "SECTIONS", "SEED_OFFSET", "STATUS_EDGE", "STATUS_MISFIT",
    "STATUS_OK", "STATUS_UNCONVERGED", "CalibrateSummary", "LogDensity", "Method",
    "NoiseEstimate", "Posterior", "Prior", "Sampler", "UnitPosterior", "Work", "calibrate",
    "calibrate_unit", "diagnostics_warnings", "ess", "estimate_noise", "estimate_noise_checked",
    "find_map", "fit_warnings", "make_log_density", "plan_chains", "read_posterior",
    "resolve_method", "run_chain",
    "sample_posterior", "split_rhat", "truth_check", "write_posterior", "year_fit",
    "year_prior",
]

#: Acceptance rates outside this range make a warning (random-walk MH is efficient near
#: 0.2-0.4 in low dimension; far outside, the proposal scale was badly adapted).
ACCEPTANCE_RANGE = (0.1, 0.7)


# ---------------------------------------------------------------------------------------
# Stage entry point
# ---------------------------------------------------------------------------------------
@dataclass
class CalibrateSummary:
    """What :func:`calibrate` did; ``as_dict`` is the ``--json`` output."""

    input_names: list[str]
    #: Each unit's statistics, fit and sites, without its draws (:func:`.posterior.slim`):
    #: the draws are in the file (``read_posterior(output)``), written unit by unit.
    posterior: dict[str, UnitPosterior]
    warnings: list[str]
    output: str
    truth_check: Optional[dict] = None
    #: Names of the windows the fit's ``window`` indexes.
    windows: list = field(default_factory=list)
    #: Channels in the likelihood: the output's name, then the further channels used.
    channels: list = field(default_factory=list)
    #: What ``--update`` kept and sampled (:func:`.update.plan_update`); None for a full run.
    update: Optional[dict] = None
    #: The method the units were sampled with, and why (``calibrate.method: auto``).
    method: str = "sequential"
    method_reason: str = ""

    def as_dict(self) -> dict:
        units = {}
        for u, p in self.posterior.items():
            params = {name: {stat: getattr(p, stat)[:, j].tolist()
                             for stat in ("mean", "median", "q05", "q95")}
                      for j, name in enumerate(self.input_names)}
            f = p.fit
            fit = {"status": [str(v) for v in p.status],
                   "rms": np.round(f["rms"], 3).tolist(),
                   "p_chi2": [float(f"{v:.3g}") for v in f["p_chi2"]],
                   "p_ljung_box": [float(f"{v:.3g}") for v in f["p_ljung_box"]],
                   "worst_window": [self.windows[i] for i in f["window"]],
                   "worst_window_rms": np.round(f["window_rms"], 3).tolist(),
                   "edge_share": np.round(f["edge_share"], 3).tolist(),
                   "extensions": f["extensions"].tolist()} if f else {}
            if f and "channel_rms" in f:
                fit["channel_rms"] = {ch: np.round(f["channel_rms"][:, i], 3).tolist()
                                      for i, ch in enumerate(p.channels)}
            units[u] = {"years": p.years.tolist(), "params": params, "fit": fit,
                        "found_repairs": list(p.found_repairs)}
        out = {
            "units": units,
            "noise": {u: {"std": float(p.noise_std[0]), "source": p.noise_source,
                          **({"channels": p.channels} if p.channels else {})}
                      for u, p in self.posterior.items()},
            "channels": list(self.channels),
            "diagnostics": {u: {"rhat": p.rhat.tolist(), "ess": p.ess.tolist(),
                                "acceptance": p.acceptance.tolist()}
                            for u, p in self.posterior.items()},
            "warnings": list(self.warnings),
            "output": self.output,
            "method": self.method,
            "method_reason": self.method_reason,
        }
        if self.truth_check is not None:
            out["truth_check"] = self.truth_check
        if self.update is not None:
            out["update"] = self.update
        return out


def resolve_method(cfg: Config, n_units: int) -> tuple[str, str]:
    """The method a calibration of ``n_units`` units uses, and why.

    ``calibrate.method`` when it names one; ``auto`` is ``laplace`` (the joint model, drawn
    without a chain) when ``forecast`` will pool the year-to-year sd over the fleet
    (``forecast.pool_sigma`` and ``n_units >= forecast.pool_min_units``), else
    ``sequential``. The joint model is the better calibrated one only pooled: with each
    unit's own sd its intervals are too wide, and the paper's method is the one for a unit
    or a handful (docs/forecast.md, "The default method"). ``laplace`` draws the joint
    model's posterior at a fraction of the Gibbs sampler's cost (docs/calibration.md).

    Returns
    -------
    method : {"sequential", "joint", "laplace"}
    reason : str
        One line for the user ("" when the config named the method).
    """
    method = cfg.calibrate.method
    if method != "auto":
        return method, ""
    fc = cfg.forecast
    if fc.pool_sigma and n_units >= fc.pool_min_units:
        return "laplace", (f"calibrate.method auto: laplace, {n_units} units >= "
                         f"forecast.pool_min_units {fc.pool_min_units} share a pooled "
                         "year-to-year sd")
    why = ("forecast.pool_sigma is false" if not fc.pool_sigma else
           f"{n_units} unit(s) < forecast.pool_min_units {fc.pool_min_units}")
    return "sequential", f"calibrate.method auto: sequential, {why}"


def _unit_seed(cfg: Config, unit: str) -> int:
    # From the unit's name, not its position: adding a unit does not change the others.
    return (cfg.seed + SEED_OFFSET + zlib.crc32(unit.encode())) % (2 ** 31 - 10 ** 6)


def _noise_for(cfg: Config, u) -> tuple[Optional[float], str]:
    if cfg.model.output.name in u.noise_std:
        return float(u.noise_std[cfg.model.output.name]), "file"
    if cfg.calibrate.noise_std is not None:
        return float(cfg.calibrate.noise_std), "config"
    return None, "estimated"


def _check_inputs(cfg: Config, surrogate, surrogate_path, obs) -> None:
    from ..reduce import check_made_for
    check_made_for(cfg, surrogate_path, surrogate.input_names, surrogate.time,
                   surrogate.bounds, "simulate and reduce")
    t_s, t_o = np.asarray(surrogate.time), np.asarray(obs.time)
    if t_s.shape != t_o.shape or not np.allclose(t_s, t_o, rtol=0, atol=1e-6):
        raise InputDataError(
            f"{obs.path}: time grid ({t_o.size} samples, {t_o[0]:g}..{t_o[-1]:g} s) differs "
            f"from the surrogate's in {surrogate_path} ({t_s.size} samples, "
            f"{t_s[0]:g}..{t_s[-1]:g} s)")
    check_observed_range(cfg, surrogate, obs)


def check_observed_range(cfg: Config, surrogate, obs, channel: str = "") -> None:
    """Observed values of the output (or of a further ``channel``, with that channel's
    surrogate) must lie near what the design's simulations produced
    (:func:`~twinmon.plausibility.refuse_far_values`).

    Raises
    ------
    InputDataError
        A value further than ``RANGE_FACTOR`` times the simulated range from it, naming the
        unit, year, time and value."""
    from ..plausibility import refuse_far_values
    train = surrogate.training_outputs()
    name = channel or cfg.model.output.name
    refuse_far_values(obs, obs.path, name, cfg.model.channel_units.get(name, ""),
                      float(np.min(train)), float(np.max(train)),
                      "the design's simulations produced")


def _likelihood_model(cfg: Config, surrogate, surrogate_path, obs):
    """The surrogate the likelihood predicts through, the further channels in it, and
    warnings about recorded channels left out (:func:`.channels.select_channels`).

    Without further channels it is the output's ``surrogate`` itself; else a
    :class:`.channels.StackedSurrogate`, each channel's observations range-checked."""
    from ..reduce import read_channel_surrogates
    channels, warnings = select_channels(cfg, surrogate, obs, surrogate_path)
    if not channels:
        return surrogate, [], warnings
    parts = read_channel_surrogates(surrogate_path, channels)
    for ch, s in parts.items():
        check_observed_range(cfg, s, obs, ch)
    return StackedSurrogate({cfg.model.output.name: surrogate, **parts}), channels, warnings


@artifacts.locks_output("output", "twinmon calibrate")
def calibrate(cfg: Config, surrogate_path: str | os.PathLike,
              observations_path: str | os.PathLike, output: str | os.PathLike,
              truth_path: str | os.PathLike | None = None,
              progress: Optional[Callable[[int, int], None]] = None,
              update: bool = False) -> CalibrateSummary:
    """Calibrate every unit of an observations file and write ``posterior.h5``.

    Years within a unit run in order (each year's prior is centred on the previous estimate);
    the chains of every unit's same year run in parallel worker processes
    (``calibrate.workers``; 0 = one per core, 1 = in this process). Results do not depend on
    the number of workers. The laplace method's units are written to ``output`` as they are
    finished, so the fleet's draws never sit in memory together (what stays is a few kB of
    statistics a unit); the file is renamed into place at the end, and an error or
    interrupt leaves the earlier one as it was.

    Parameters
    ----------
    cfg : Config
    surrogate_path, observations_path : path-like
        ``twinmon.surrogate/1`` and ``twinmon.observations/1`` artifacts.
    output : path-like
        ``posterior.h5`` to write.
    truth_path : path-like, optional
        A ``twinmon.truth/1`` file: adds the relative errors and 90 % interval coverage.
    progress : callable(done, total), optional
        Called as unit-years complete.
    update : bool
        Continue the posterior already at ``output``: its years are kept as they are and
        only the years added since are sampled (:mod:`.update`; the result equals a full
        run's). Refused (``ArtifactError``) when it was made with another config or
        surrogate.

    Raises
    ------
    ArtifactError
        Surrogate inputs or box unlike the config's.
    InputDataError
        Observations on another time grid than the surrogate; an event naming a component
        the config's inputs do not have.
    """
    from ..reduce import read_surrogate
    surrogate = read_surrogate(surrogate_path)
    obs = read_observations(observations_path, cfg.model.output.name)
    check_events(cfg, obs)
    _check_inputs(cfg, surrogate, surrogate_path, obs)
    check_observations(cfg, obs)
    truth = None
    if truth_path is not None:
        from ..fabricate import read_truth
        truth = read_truth(truth_path)
        missing = [u for u in obs.units if u not in truth.inputs]
        if missing:
            raise ArtifactError(f"{truth_path}: no truth for unit {missing[0]!r}")

    model, channels, channel_warnings = _likelihood_model(cfg, surrogate, surrogate_path, obs)
    name, method_reason = resolve_method(cfg, len(obs.units))
    method = method_named(name)
    sampler = method.sampler(cfg.calibrate.sampler)
    runs, channel_info, noise_warnings = {}, {}, []
    # Each unit's run carries the config to the workers' tasks (a Dask scheduler holds
    # every submitted task until it runs): without what they do not read.
    wcfg = cfg.for_workers()
    out = cfg.model.output
    for unit, u in obs.units.items():
        noise, source = _noise_for(cfg, u)
        y = obs.output_of(unit)
        if noise is None:
            est = estimate_noise_checked(surrogate, cfg, y)
            noise, source = est.std, est.source
            if est.structured:
                noise_warnings.append(est.warning(unit, out.name, out.units))
        if channels:  # one noise per channel, records side by side
            noise, channel_info[unit] = channel_noise(cfg, u, model, noise, source, unit,
                                                      noise_warnings)
            y = stacked_rows(u, model, cfg.model.output.name)
        runs[unit] = method.start(model, wcfg, u.years, y, noise, _unit_seed(cfg, unit),
                                  source, getattr(u, "events", []))
    digests = {unit: year_digests(r.flows, r.noise) for unit, r in runs.items()}
    resume, update_info = plan_update(cfg, surrogate.fingerprint(), output, runs, method) \
        if update else ({}, None)
    for unit, p in resume.items():
        if len(p.years) == len(runs[unit].years):
            runs[unit] = Kept(p)          # nothing new: kept as it is (either method)
        else:
            runs[unit].resume(p)          # continue after the stored years
    # A forked worker has the surrogate already; a spawned one rebuilds it from the file.
    fork = hasattr(os, "fork") or cfg.calibrate.executor == "dask"
    pool_args = (init_worker, (model if fork else None, str(surrogate_path),
                               cfg.model.output.name, tuple(channels)))
    names = cfg.model.input_names
    # The truth only feeds the summary, but it is recorded so that `twinmon run` re-runs
    # the stage (and its truth check) when it changes.
    inputs = [surrogate_path, observations_path] + ([truth_path] if truth_path else [])
    # An update appends to a copy of the posterior it continues: the kept years' draws are
    # neither read nor compressed again.
    base = output if any(getattr(r, "samples_from", 0) for r in runs.values()) else None
    posterior: dict[str, UnitPosterior] = {}
    with PosteriorWriter(output, names, cfg, inputs, surrogate.fingerprint(), base,
                         method.name) as writer:
        def emit(unit: str) -> None:
            # Written as soon as it is finished; the summary keeps its statistics only.
            run = runs[unit]
            p = run.result()
            p.digest = np.array(digests[unit])
            # Recorded with the posterior: forecast restarts a repaired component's trend.
            p.events = [(e.year, e.component, e.action) for e in obs.units[unit].events]
            if hasattr(run, "found_repairs"):     # a kept unit keeps those it has
                p.found_repairs = [r.as_dict() for r in run.found_repairs]
            if unit in channel_info:
                p.channels = channel_info[unit]
            writer.add(unit, p)
            posterior[unit] = slim(p)
            runs[unit] = Kept(posterior[unit])

        # Here or in the workers, each unit's small factorisations on one BLAS thread
        # (executors.threads: OpenBLAS's threads make them several times slower on busy
        # cores).
        with one_blas_thread():
            sampler.finish(Work(cfg, model, runs, resume, output, progress, pool_args, emit))
        for unit in runs:
            if unit not in posterior:     # a sampler that finishes its units all at once
                emit(unit)
    posterior = {unit: posterior[unit] for unit in runs}
    windows = list(cfg.diagnose_windows())
    warnings = channel_warnings + noise_warnings + fit_warnings(posterior, names, windows, cfg) + \
        diagnostics_warnings(posterior, names, cfg)
    check = truth_check(posterior, truth, names) if truth is not None else None
    return CalibrateSummary(names, posterior, warnings, str(output), check, windows,
                            channels=[cfg.model.output.name] + channels, update=update_info,
                            method=method.name, method_reason=method_reason)


def fit_warnings(posterior: dict[str, UnitPosterior], names: list[str], windows: list,
                 cfg: Config) -> list[str]:
    """One line per unit-year whose twin misses the plant, sits on the box edge, or did not
    converge even with longer chains."""
    out = []
    for unit, p in posterior.items():
        f = p.fit
        for k, year in enumerate(p.years):
            st = p.status[k]
            if st == STATUS_MISFIT:
                out.append(f"{unit} year {int(year)}: the twin misses the plant: residual RMS "
                           f"{f['rms'][k]:.1f} x noise (worst in the {windows[f['window'][k]]} "
                           f"window, {f['window_rms'][k]:.1f} x), chi-square p = "
                           f"{f['p_chi2'][k]:.2g}, Ljung-Box p = {f['p_ljung_box'][k]:.2g}")
            elif st == STATUS_EDGE:
                j = int(np.argmax(f["edge_share"][k]))
                out.append(f"{unit} year {int(year)}: {100 * f['edge_share'][k][j]:.0f} % of "
                           f"the posterior of {names[j]} sits on the design box's edge")
            if not f["converged"][k]:
                out.append(f"{unit} year {int(year)}: not converged after "
                           f"{f['extensions'][k]} longer run(s): unreliable")
    return out


def diagnostics_warnings(posterior: dict[str, UnitPosterior], names: list[str],
                         cfg: Config) -> list[str]:
    """One line per unit and diagnosis of its poor R-hat, ESS or acceptance rate, naming the
    years that share it (``U0007 years 1-10: ESS 197 < 400 ...``: the laplace method draws a
    unit's years together, so one figure holds for all of them)."""
    from .diagnostics import year_ranges
    cc = cfg.calibrate
    out = []
    for unit, p in posterior.items():
        said: dict = {}
        for k, year in enumerate(p.years):
            bad = []
            for j, name in enumerate(names):
                if not p.rhat[k, j] <= cc.rhat_warn:
                    bad.append(f"R-hat {p.rhat[k, j]:.3f} > {cc.rhat_warn:g} for {name}")
                if not p.ess[k, j] >= cc.ess_warn:
                    bad.append(f"ESS {p.ess[k, j]:.0f} < {cc.ess_warn:g} for {name}")
            lo, hi = ACCEPTANCE_RANGE
            a = p.acceptance[k]
            if np.any((a < lo) | (a > hi)):
                bad.append(f"acceptance {a.min():.2f}..{a.max():.2f} outside [{lo:g}, {hi:g}]")
            if bad:
                said.setdefault("; ".join(bad), []).append(int(year))
        for text, years in said.items():
            out.append(f"{unit} year{'s' if len(years) > 1 else ''} {year_ranges(years)}: "
                       + text)
    return out


def truth_check(posterior: dict[str, UnitPosterior], truth, names: list[str]) -> dict:
    """Relative error of the posterior mean and 90 % interval coverage against a truth file.

    Returns
    -------
    dict name -> {"max_rel_error", "mean_rel_error", "coverage_90"}
        Ratios (not percent), over all units and years.
    """
    out = {}
    for j, name in enumerate(names):
        rel, cover = [], []
        for unit, p in posterior.items():
            ty = np.asarray(truth.years[unit])
            tv = np.asarray(truth.inputs[unit][name])
            idx = np.searchsorted(ty, p.years)
            if np.any(idx >= len(ty)) or np.any(ty[np.minimum(idx, len(ty) - 1)] != p.years):
                raise ArtifactError(f"truth file: unit {unit!r} lacks some observed years")
            t = tv[idx]
            rel.append(np.abs(p.mean[:, j] - t) / np.abs(t))
            cover.append((p.q05[:, j] <= t) & (t <= p.q95[:, j]))
        rel, cover = np.concatenate(rel), np.concatenate(cover)
        out[name] = {"max_rel_error": float(rel.max()), "mean_rel_error": float(rel.mean()),
                     "coverage_90": float(cover.mean())}
    return out
