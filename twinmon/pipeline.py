"""``twinmon run``: every stage in order, skipping those whose output is up to date.

A stage is up to date when its artifact exists, has the right schema, and records the same
config sections, the same input hashes and the same twinmon version as this run would use
(DVC-style provenance; no timestamps involved, so a fresh clone or a touched file does not
trigger needless work, while an upgrade of twinmon makes every stage again; ``--force``
does too).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from . import artifacts
from .config import Config


#: ``twinmon run --smoke``: every stage with small sizes, to see the whole chain work on a
#: config in about a minute (CI, a first try), not for results. Applied as ``--set``
#: overrides before the user's own (which win); docs/ci.md lists them.
SMOKE = (
    "simulate.train_size=24", "simulate.test_size=6",
    "calibrate.chains=2", "calibrate.samples=150", "calibrate.burn_in=100",
    "calibrate.max_extensions=0", "calibrate.keep_draws=150", "calibrate.ess_warn=0",
    "forecast.samples=200", "forecast.observed_samples=50", "forecast.horizon=3",
    "diagnose.screen_points=4", "diagnose.confirm_first=1", "diagnose.confirm_further=1",
    "diagnose.max_effects=1",
)


@dataclass
class StageRun:
    name: str
    output: str
    skipped: bool
    seconds: float
    summary: dict = field(default_factory=dict)


@dataclass
class RunSummary:
    stages: list[StageRun]
    report: str | None
    terminal: str = ""

    def as_dict(self) -> dict:
        return {"stages": [{"stage": s.name, "output": s.output, "skipped": s.skipped,
                            "seconds": round(s.seconds, 3), "summary": s.summary}
                           for s in self.stages],
                "report": self.report,
                "total_seconds": round(sum(s.seconds for s in self.stages), 3)}


def _stage(cfg: Config, name: str, kind: str, sections, output: Path, inputs, force: bool,
           fn: Callable[[], object], log) -> StageRun:
    start = time.perf_counter()
    config = cfg.section_yaml(*sections)
    if not force and artifacts.is_up_to_date(output, kind, config, inputs):
        log(f"{name}: up to date ({output})")
        return StageRun(name, str(output), True, time.perf_counter() - start)
    summary = fn()
    seconds = time.perf_counter() - start
    log(f"{name}: done in {seconds:.1f} s -> {output}")
    as_dict = summary.as_dict() if hasattr(summary, "as_dict") else {}
    return StageRun(name, str(output), False, seconds, as_dict)


def run_pipeline(cfg: Config, observations: str | os.PathLike, workdir: str | os.PathLike = "out",
                 *, gap_observations: str | os.PathLike | None = None,
                 truth: str | os.PathLike | None = None, force: bool = False,
                 update: bool = False,
                 log: Callable[[str], None] = lambda s: None) -> RunSummary:
    """Run simulate, reduce, calibrate, forecast, diagnose and report.

    Parameters
    ----------
    cfg : Config
    observations : path-like
        The plant's observations (calibrated and forecast).
    workdir : path-like
        Folder of the artifacts (``simulations.h5``, ``surrogate.h5``, ...) and ``report/``.
    gap_observations : path-like, optional
        Observations to diagnose for a sim-to-real gap (default: ``observations``).
    truth : path-like, optional
        A truth file (fabricated data only): adds errors against the truth to the outputs.
    force : bool
        Re-run every stage even when its output is up to date.
    update : bool
        When calibrate runs (its observations changed, or ``force``), it keeps the years
        already in ``posterior.h5`` and samples only the new ones (``calibrate --update``);
        when diagnose runs, it keeps the per-year base fits and screening of ``gap.h5`` and
        runs only the new years' (``diagnose --update``). Both give a full run's result and
        refuse (``ArtifactError``) an artifact made with another config. forecast and report
        re-run in full as usual (they are cheap), as their inputs changed.
    log : callable
        Receives one human line per stage.
    """
    from . import simulate
    from .errors import InputDataError

    obs = Path(observations)
    gap_obs = Path(gap_observations) if gap_observations else obs
    # Every input is checked before the first stage runs: a typo in the last argument must
    # not cost the user the first stages' time.
    for what, path in (("--observations", obs), ("--gap-observations", gap_obs),
                       ("--truth", Path(truth) if truth else None)):
        if path is not None and not path.is_file():
            raise InputDataError(f"{path}: {what} file not found")
    simulate.check_model(cfg)
    wd = Path(workdir)
    wd.mkdir(parents=True, exist_ok=True)
    # Two runs into one workdir would race on every artifact: the second one stops at once.
    with artifacts.output_lock(wd, "twinmon run"):
        return _run_locked(cfg, obs, gap_obs, wd, truth, force, log, update)


def _run_locked(cfg: Config, obs: Path, gap_obs: Path, wd: Path, truth, force: bool,
                log, update: bool = False) -> RunSummary:
    from . import calibrate, diagnose, forecast, reduce, report, simulate
    p = {k: wd / f"{k}.h5" for k in ("simulations", "surrogate", "posterior", "forecast", "gap")}
    extra = [truth] if truth else []
    stages = []
    spec_fmu = simulate.spec_for(cfg).fmu
    stages.append(_stage(cfg, "simulate", "simulations", simulate.SECTIONS, p["simulations"],
                         [spec_fmu], force,
                         lambda: simulate.simulate(cfg, p["simulations"]), log))
    stages.append(_stage(cfg, "reduce", "surrogate", reduce.SECTIONS, p["surrogate"],
                         [p["simulations"]], force,
                         lambda: reduce.reduce(cfg, p["simulations"], p["surrogate"]), log))
    stages.append(_stage(cfg, "calibrate", "posterior", calibrate.SECTIONS, p["posterior"],
                         [p["surrogate"], obs] + extra, force,
                         lambda: calibrate.calibrate(cfg, p["surrogate"], obs, p["posterior"],
                                                     truth, update=update), log))
    stages.append(_stage(cfg, "forecast", "forecast", forecast.SECTIONS, p["forecast"],
                         [p["posterior"], p["surrogate"]] + extra, force,
                         lambda: forecast.forecast(cfg, p["posterior"], p["surrogate"],
                                                   p["forecast"], truth), log))
    stages.append(_stage(cfg, "diagnose", "gap", diagnose.SECTIONS, p["gap"],
                         [gap_obs, spec_fmu], force,
                         lambda: diagnose.diagnose(cfg, gap_obs, p["gap"], update=update),
                         log))
    start = time.perf_counter()
    paths = {"observations": obs, "simulations": p["simulations"], "surrogate": p["surrogate"],
             "posterior": p["posterior"], "forecast": p["forecast"], "gap": p["gap"],
             "truth": truth}
    # The report too is made again only when what it reads changed (its figures take
    # seconds to a minute).
    done = None if force else report.is_up_to_date(cfg, wd / "report", paths)
    if done is not None:
        index = wd / "report" / "index.html"
        log(f"report: up to date ({index})")
        stages.append(StageRun("report", str(wd / "report"), True,
                               time.perf_counter() - start))
        return RunSummary(stages, str(index), done.get("terminal", ""))
    rep = report.report(cfg, wd / "report", **paths)
    seconds = time.perf_counter() - start
    log(f"report: done in {seconds:.1f} s -> {rep.index}")
    stages.append(StageRun("report", str(wd / "report"), False, seconds, rep.as_dict()))
    return RunSummary(stages, str(rep.index), rep.terminal())
