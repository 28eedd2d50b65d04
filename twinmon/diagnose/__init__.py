"""Stage ``diagnose``: where the twin misses the plant, what causes it, and how far it shrinks.

A calibrated twin never matches a plant exactly. An unmodelled effect (a lagging flowmeter, a
valve that opens slowly, fouling, a leak, a weak supply, ...) leaves a structured residual and,
worse, is partly absorbed into the degradation estimates and so into the time to failure. For
each unit this module

1. **locates** the gap: the twin (the real FMU, degradation inputs fitted by maximum likelihood
   year by year, warm-started) is compared with the observations; standardised residuals by
   year, channel and time window; per-year chi-square of the whitened residual and a
   Ljung-Box test of structure, pooled tests from every possible onset year, all at a
   Bonferroni-corrected level; the onset year; how much of the effect's signature the
   degradation inputs absorb (its share in the span of their sensitivities);
2. **identifies** the cause: every candidate effect (an FMU parameter of ``model.effects``) is
   screened by how much of the residual its signature explains once the degradation inputs
   are linearly re-adjusted (a grid over the effect's range and every onset year: cheap), then
   confirmed by the augmented fit through the FMU (per-year degradation inputs plus the effect,
   one value per unit from its onset) and compared by BIC; candidates within ``group_bic``
   of the best are reported as one group, with the FMU channel that would separate them;
   further effects are added only while the BIC gain stays above ``bic_gain``;
3. **measures the shrink**: residual RMS over noise before and after, percentage of the excess
   gap closed, the BIC gain, the effect estimate with a 90 % interval, and how the degradation
   estimates and the projected failure year move once the effect is in the twin.

The diagnosing side reads only observations (and optionally a posterior); never a truth file.
The artifact is ``gap.h5`` (``twinmon.gap/2``, layout in :func:`write_gap`).

Layout: each step has its file, over one small state object.

=================  ==========================================================================
``__init__``       the stage :func:`diagnose` (process pool over units), :func:`diagnose_unit`,
                   :func:`candidate_names`, :class:`DiagnoseSummary`
``unit.py``        :func:`~.unit.run_unit`: the three steps in order for one unit -> UnitGap
``state.py``       :class:`~.state.UnitState`: one unit's data, twin and base twin
``locate.py``      step 1: base fit, per-year and pooled tests, residual maps, window RMS,
                   significant windows, absorbed share
``identify.py``    step 2: screening and confirming every candidate, the final model, its
                   groups, the ranking table
``screen.py``      the linearised screening of a candidate (grid of values x onsets)
``confirm.py``     confirmation by the augmented fit through the FMU, BIC
``several.py``     further effects on top of the current model; each effect's group by swaps
``groups.py``      :class:`~.groups.EffectGroup`, evidence shares, separating channel
``hidden.py``      candidates the recorded channels cannot see, and the channel that would
``shrink.py``      step 3: RMS before/after, % of the excess closed, verdict, estimates and
                   intervals, before/after twins, projected failure year
``twin.py``        :class:`Twin`: the FMU with normalised parameters, whitened outputs
``fit.py``         :class:`JointFit`, :class:`FitResult`: least squares through the FMU
``stats.py``       :func:`ljung_box`, :func:`pooled_onset_pvalues`, :func:`plateau_noise`,
                   :func:`noise_sf` (tests with estimated noise levels)
``result.py``      :class:`UnitGap`: one unit's diagnosis (``--json`` via ``as_dict``)
``artifact.py``    :func:`write_gap`, :func:`read_gap`, :class:`GapFile` (``gap.h5``)
``update.py``      ``--update``: :class:`~.update.YearCache` (per-year base fit and screening
                   gains kept in ``gap.h5``), :func:`~.update.plan_update`
=================  ==========================================================================
"""
from __future__ import annotations

import math
import os
import time as _time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from .. import artifacts, lineage
from ..config import Config
from ..errors import ArtifactError, ConfigError, InputDataError, Interrupted, SimulationError
from ..observations import read_observations
from ..plausibility import check_observations
from .artifact import SECTIONS, GapFile, read_gap, write_gap
from .fit import FD_STEP, FitResult, JointFit
from .result import VERDICTS, UnitGap
from .state import UnitState
from .stats import estimate_noise, ljung_box, noise_sf, plateau_noise, pooled_onset_pvalues
from .twin import SNAP, Twin, release_spare
from .unit import run_unit
from .update import YearCache, plan_update, unit_digests

__all__ = ["diagnose", "diagnose_unit", "candidate_names", "DiagnoseSummary", "SECTIONS",
           "VERDICTS", "FD_STEP", "SNAP", "Twin", "JointFit", "FitResult", "UnitGap",
           "GapFile", "write_gap", "read_gap", "YearCache", "ljung_box",
           "pooled_onset_pvalues", "estimate_noise", "plateau_noise", "noise_sf"]


@dataclass
class DiagnoseSummary:
    """What ``diagnose`` did: ``units`` {unit: UnitGap}, the artifact written, wall time (s),
    worker processes used, and with ``--update`` what was kept and recomputed
    (:func:`~.update.plan_update`'s ``{"from", "kept_years", "new_years", "new_units",
    "redone_units", "dropped_units"}``; None for a full run)."""

    units: dict
    output: str
    wall_time: float
    workers: int
    update: Optional[dict] = None

    def as_dict(self) -> dict:
        out = {"units": {u: g.as_dict() for u, g in self.units.items()},
               "output": self.output, "wall_time": round(self.wall_time, 3),
               "workers": self.workers}
        if self.update is not None:
            out["update"] = self.update
        return out


def candidate_names(cfg: Config) -> list:
    """The candidate effects: ``diagnose.candidates`` or every ``model.effects`` entry."""
    names = list(cfg.diagnose.candidates) or list(cfg.model.effects)
    for n in names:
        if n not in cfg.model.effects:
            raise ConfigError(f"{cfg.source}: diagnose.candidates: {n!r} is not in model.effects "
                              f"(known: {', '.join(cfg.model.effects) or 'none'})")
    return names


def no_candidates_hint(cfg: Config) -> str:
    """What to do when the config lists no candidate effect: diagnose can locate a gap but
    not name it."""
    return (f"no candidate effects to test (model.effects in {cfg.source.name} is empty): "
            "list the FMU parameters that could explain a gap under model.effects, one a line, "
            "e.g. `NAME: {baseline: B, low: L, high: H, units: U}` where B gives exactly the "
            "calibrated model (`twinmon init MODEL.fmu` lists the candidates)")


def _unit_sigma(cfg: Config, uo, time: np.ndarray) -> tuple[dict, dict]:
    """Each channel's noise standard deviation (channel units) and the degrees of freedom it
    carries: ``inf`` where the observations (or ``calibrate.noise_std``, the output's) record
    it; where not, estimated where the transient is calmest, the last window, and its few
    degrees of freedom counted by the tests (:func:`.stats.noise_sf`)."""
    plateau = list(cfg.diagnose_windows().values())[-1].start
    sig, dof = {}, {}
    for ch, arr in uo.channels.items():
        s = uo.noise_std.get(ch)
        if s is None and ch == cfg.model.output.name and cfg.calibrate.noise_std is not None:
            s = cfg.calibrate.noise_std
        if s is not None:
            sig[ch], dof[ch] = float(s), math.inf
        else:
            sig[ch], dof[ch] = plateau_noise(arr, time, plateau)
    return sig, dof


def _whitened(cfg: Config, channels: dict, noise_std: dict) -> tuple[list, np.ndarray]:
    """The observed channels (the output first) and the whitened observations
    [n_y, n_ch * n_t] (channel-major)."""
    out = cfg.model.output.name
    chans = [out] + sorted(c for c in channels if c != out and c in cfg.model.channels)
    Y = np.concatenate([np.asarray(channels[c], float) / noise_std[c] for c in chans], axis=1)
    return chans, Y


def diagnose_unit(cfg: Config, fmu_path, unit: str, time: np.ndarray, years: np.ndarray,
                  channels: dict, noise_std: dict, twin: Twin | None = None,
                  posterior: tuple | None = None, kept: YearCache | None = None,
                  noise_dof: dict | None = None) -> UnitGap:
    """Diagnose one unit.

    Parameters
    ----------
    cfg : Config
    fmu_path : path-like
        The built ``.fmu``.
    unit : str
    time : ndarray, shape [n_t]
        Sample times (s).
    years : ndarray of int, shape [n_y]
    channels : dict of str to ndarray, each [n_y, n_t]
        The output (under ``model.output.name``) and any further observed FMU channel, each
        in its units; NaN = missing.
    noise_std : dict of str to float
        Noise standard deviation per channel (channel units).
    twin : Twin, optional
        Reused if given (must have the same channels and noise).
    posterior : (ndarray [n_y, d], ndarray [n_y, d, d]), optional
        Posterior mean and covariance of the degradation inputs per year (input units); if
        given, the standardised residual map is taken against this posterior predictive
        instead of the maximum-likelihood twin (the tests and fits are unchanged).
    kept : YearCache, optional
        Records of the unit's first years from an earlier ``gap.h5`` (``--update``; their
        digests checked by :func:`~.update.plan_update`): their base fit and screening are
        not run again.
    noise_dof : dict of str to float, optional
        Degrees of freedom of each channel's noise level where it was estimated (the tests
        count them); a channel not in it (or ``inf``) has its noise known.
    """
    chans, Y = _whitened(cfg, channels, noise_std)
    names = candidate_names(cfg)
    own = twin is None
    if own:
        twin = Twin(cfg, fmu_path, chans, time, noise_std, names)
    try:
        nu = [float((noise_dof or {}).get(c, math.inf)) for c in chans]
        return run_unit(UnitState(twin, cfg, unit, years, Y, posterior, kept, nu), names)
    finally:
        if own:
            twin.close()


def _job(args):
    return diagnose_unit(*args)


def _map_units(cfg: Config, jobs: list, n_workers: int, fmu, progress) -> dict:
    """Diagnose the units of ``jobs`` on ``n_workers`` processes: ``{unit: UnitGap}`` in the
    order of ``jobs``. The workers are the project's detached pool workers (they ignore
    Ctrl-C, which the parent handles); a worker that dies (a crash in the FMU's native code)
    ends the stage at once with a one-line :class:`~twinmon.errors.SimulationError`."""
    from ..executors import closing_pool, open_pool

    results = {}
    pool = open_pool(cfg, "diagnose", n_workers, files=(fmu,))
    # After an error or an interrupt, no queued unit starts.
    with closing_pool(pool, SimulationError(
            f"{fmu}: a worker process died while diagnosing (a crash in the FMU's native "
            "code?); nothing was written; re-run with -j 1 to see which unit")):
        for i, (j, g) in enumerate(zip(jobs, pool.map(_job, jobs)), 1):
            results[j[2]] = g
            if progress:
                progress(i)
    return results


def _posterior_for(posterior_path, post, cfg: Config, unit: str, years: np.ndarray):
    if post is None:
        return None
    up = post.units.get(unit)
    if up is None:
        raise ArtifactError(f"{posterior_path}: no posterior for unit {unit!r}")
    if list(post.input_names) != cfg.model.input_names:
        raise ArtifactError(f"{posterior_path}: inputs {post.input_names} differ from the "
                            f"config's {cfg.model.input_names}")
    if not np.array_equal(np.asarray(up.years), np.asarray(years)):
        raise ArtifactError(f"{posterior_path}: /units/{unit}/years {list(up.years)} differ "
                            f"from the observations' {list(years)}")
    cov = np.array([np.atleast_2d(np.cov(s, rowvar=False)) for s in up.samples])
    return np.asarray(up.mean, float), cov


@artifacts.locks_output("output", "twinmon diagnose")
def diagnose(cfg: Config, observations: str | os.PathLike, output: str | os.PathLike,
             workers: int | None = None, progress=None,
             posterior: str | os.PathLike | None = None,
             update: bool = False) -> DiagnoseSummary:
    """Run ``diagnose`` on every unit of an observations file and write ``gap.h5``.

    Parameters
    ----------
    cfg : Config
    observations : path-like
        ``twinmon.observations/1`` file (truth files are never read).
    output : path-like
        ``gap.h5`` to write.
    workers : int, optional
        Processes over units (default ``diagnose.workers``; 0 = one per core).
    progress : callable, optional
        Called with the number of units done.
    posterior : path-like, optional
        ``posterior.h5`` of ``calibrate``: the residual map is then standardised against
        the calibrated twin's posterior predictive.
    update : bool
        Continue the ``gap.h5`` already at ``output``: the base fit and screening of its
        years are kept, those of the years added since are run, the rest of each unit's
        diagnosis is recomputed (:mod:`.update`; the result equals a full run's). No
        ``gap.h5`` yet: a full run.

    Raises
    ------
    ArtifactError
        ``update`` and the ``gap.h5`` at ``output`` was made with another config or FMU, or
        before its per-year records existed: one line naming the file and the difference.
    SimulationError
        A worker process died (a crash in the FMU's native code): one line naming the FMU;
        nothing is written.
    Interrupted
        Ctrl-C: the workers ignore it, the parent stops the pool; nothing is written.
    """
    from ..fmu import resolve_fmu

    t0 = _time.perf_counter()
    from ..executors import check_workers
    from ..simulate import check_model
    check_workers(workers if workers is not None else cfg.diagnose.workers)
    check_model(cfg)
    obs = read_observations(observations, cfg.model.output.name)
    check_observations(cfg, obs)
    candidate_names(cfg)
    expected = cfg.model.output.times.times
    if obs.time.shape != expected.shape or not np.allclose(obs.time, expected):
        raise InputDataError(f"{observations}: /time does not match the config's output grid "
                             f"({expected[0]:g}..{expected[-1]:g} s, {expected.size} samples)")
    fmu = resolve_fmu(cfg.model.fmu)
    post = None
    if posterior is not None:
        from ..calibrate import read_posterior
        post = read_posterior(posterior)
        lineage.check_made_for_model(posterior, "posterior", cfg.section_yaml("model"))
    noise = {u: _unit_sigma(cfg, uo, obs.time) for u, uo in obs.units.items()}
    sigma = {u: n[0] for u, n in noise.items()}
    kept, update_info = {}, None
    if update:
        digests = {}
        for u, uo in obs.units.items():
            chans, Y = _whitened(cfg, uo.channels, sigma[u])
            digests[u] = (uo.years, unit_digests(Y, [sigma[u][c] for c in chans]))
        kept, update_info = plan_update(cfg, fmu, output, digests, SECTIONS)
    # The kept records travel with the unit's job, to a pool or Dask worker alike; so does
    # the config, without what the workers do not read (each job pickles its own copy).
    wcfg = cfg.for_workers()
    jobs = [(wcfg, fmu, u, obs.time, uo.years, uo.channels, sigma[u],
             None, _posterior_for(posterior, post, cfg, u, uo.years), kept.get(u), noise[u][1])
            for u, uo in obs.units.items()]
    n_workers = workers if workers is not None else cfg.diagnose.workers
    # The cores this process may use (taskset, a batch scheduler's binding), as the other
    # stages count them; os.cpu_count() is the machine's.
    n_workers = min(n_workers or len(os.sched_getaffinity(0)), len(jobs))
    try:
        if n_workers <= 1 and not (cfg.diagnose.executor == "dask" and cfg.dask.address):
            results = {}
            try:
                for i, j in enumerate(jobs, 1):
                    results[j[2]] = _job(j)
                    if progress:
                        progress(i)
            finally:
                # The units shared one FMU instance; a library call leaves none behind. (A
                # pool worker's goes with its process and the pool's scratch folder.)
                release_spare()
        else:
            results = _map_units(cfg, jobs, n_workers, fmu, progress)
        write_gap(output, results, cfg, obs.time,
                  [observations, fmu] + ([posterior] if posterior is not None else []))
    except KeyboardInterrupt:
        # gap.h5 is written atomically (temporary file, then rename): an interrupt leaves
        # any previous artifact as it was.
        raise Interrupted(f"{output}: interrupted; nothing was written") from None
    return DiagnoseSummary(results, str(output), _time.perf_counter() - t0, n_workers,
                           update_info)
