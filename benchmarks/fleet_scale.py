"""Fleet scale: every stage's cost per unit-year at 30, 300 and 1000 units x 10 years.

A fabricate config is written in a work folder (it extends configs/pump.yaml; each unit is
healthy, has a pump fault or a motor fault, with start, slope and fault rate drawn from a
seeded generator, unit ``i`` the same in every fleet size; flow noise 4 kg/s, as
configs/fleet.yaml). ``simulate`` + ``reduce`` run once and their surrogate serves every size.
Then per fleet size: ``fabricate``, ``calibrate --truth`` (the fastest sampler the config
offers), ``forecast --truth``, ``diagnose`` of the same observations and ``report``, each as
its own ``twinmon`` process, so that its wall time, CPU time (itself and its workers), peak
memory and artifact size are its own. At the sizes of ``--dask-sizes`` calibrate, forecast
and diagnose each run again right after, with ``executor: dask`` (a LocalCluster with as many
workers as cores), so that both see about the same load on a shared machine.

The yearly update, right after the full calibrate it is compared with: the first 9 years of
the fleet (sliced from its 10-year file with ``write_observations``: fabricate's jitter draws
depend on the number of years, so a 9-year fabricate is not the 10-year one's first 9 years)
are calibrated, then ``calibrate --update`` adds year 10 and its arrays are checked against
the full run's; likewise, right after the full diagnose, the first 9 years are diagnosed and
``diagnose --update`` adds year 10, its gap.h5 checked against the full run's (every dataset,
the per-year records included); the whole yearly update (calibrate --update + forecast +
diagnose --update + report, forecast and report recomputing) is also compared with the whole
run. ``--reference`` calibrates the fleets
up to that size with OpenTURNS' sampler too, to hold the fast sampler's accuracy to it. One
table, then the targets.

Memory: "tree PSS" is the largest physical memory of the stage's process tree (the command,
its pool workers or Dask cluster), as the sum of their proportional set sizes sampled every
0.25 s (forked workers share the parent's pages: a sum of RSS would count them once per
process); "1 proc RSS" is the largest single process's high-water mark (``wait4``), exact.

The default (``make bench``) is the full run. On this 2-core machine 1000 units took
302 s from simulate through report (``--sizes 1000 --dask-sizes --update-sizes 1000
--reference 0``, load 1.1-2.4: 11 min 20 s in all with the 9-year runs and the updates),
and 565 s (21 min in all) on a day the machine ran at half that speed (docs/cluster.md); the
default adds 30 and 300 units, Dask at 30 and 300 and OpenTURNS' sampler at 30 units.

    .venv/bin/python benchmarks/fleet_scale.py                 # 30, 300, 1000 (make bench)
    .venv/bin/python benchmarks/fleet_scale.py --sizes 30 300 --dask-sizes 30 300 \\
        --update-sizes 300 --workdir /tmp/fleet_scale --keep
    .venv/bin/python benchmarks/fleet_scale.py --sizes 1000 --stages calibrate \\
        --dask-sizes --update-sizes 1000 --reference 0
    .venv/bin/python benchmarks/fleet_scale.py --sizes 10000 --dask-sizes 10000 --dask-only \\
        --update-sizes --reference 0 --stages calibrate forecast
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.config import CalibrateConfig  # noqa: E402
from twinmon.observations import read_observations, write_observations  # noqa: E402

TWINMON = [sys.executable, "-m", "twinmon"]
YEARS = 10
KINDS = ("healthy", "pump", "motor")
#: The stages timed per fleet size (simulate and reduce run once for all sizes).
PIPELINE = ("calibrate", "forecast", "diagnose", "report")

#: The fleet-scale targets on this 2-core machine: the whole run and the yearly update of
#: 1000 units (wall), calibrate's CPU per unit-year and forecast's wall per unit, the cost
#: per unit-year from the smallest fleet to the largest, Dask against processes, memory.
TARGET_TOTAL_S = 10 * 60
TARGET_UPDATE_S = 90
TARGET_CALIBRATE_CPU_MS = 30
TARGET_FORECAST_MS = 50
TARGET_SCALE = 1.3
TARGET_DASK = 1.25
TARGET_RSS_MB = 2048
TARGET_POSTERIOR_MB = 200


# --- the fleet ---------------------------------------------------------------------------

def unit_spec(seed: int, i: int) -> tuple[str, dict]:
    """Unit ``i``'s kind and trajectories (the same in every fleet size).

    Ranges keep every unit inside the design box over 10 years (damping <= 25 of 30, pump
    coefficient >= 2.4 of 2.2), about the shipped fleet's three units (configs/fleet.yaml).
    """
    rng = np.random.default_rng([seed, i])
    kind = KINDS[int(rng.integers(3))]
    damping = {"start": round(float(rng.uniform(9.0, 11.0)), 3),
               "slope": round(float(rng.uniform(0.0, 0.1)), 4), "jitter": 0.15}
    pump = {"start": round(float(rng.uniform(3.5, 3.8)), 4),
            "slope": round(float(rng.uniform(-0.03, -0.01)), 4), "jitter": 0.01}
    if kind == "pump":
        pump["slope"] = round(float(rng.uniform(-0.12, -0.08)), 4)
    elif kind == "motor":
        damping["slope"] = round(float(rng.uniform(0.9, 1.5)), 4)
    return kind, {"motor_damping": damping, "pump_coef": pump}


def write_fleet_config(path: Path, n_units: int, seed: int) -> dict[str, str]:
    """The fabricate config of ``n_units`` units (YAML; JSON is YAML); returns unit -> kind."""
    units, kinds = {}, {}
    for i in range(n_units):
        kind, tr = unit_spec(seed, i)
        name = f"U{i:04d}"
        units[name] = {"trajectories": tr}
        kinds[name] = kind
    cfg = {"extends": str(ROOT / "configs" / "pump.yaml"),
           "fabricate": {"years": YEARS, "noise_std": 4.0, "record_channels": False,
                         "seed": seed + n_units, "units": units}}
    path.write_text(json.dumps(cfg, indent=1))
    return kinds


def slice_years(src: Path, dst: Path, years: int) -> None:
    """The observations of ``src`` cut to each unit's first ``years`` years."""
    obs = read_observations(src)
    units = {}
    for name, u in obs.units.items():
        keep = np.asarray(u.years) <= years
        units[name] = dataclasses.replace(
            u, years=np.asarray(u.years)[keep],
            channels={c: v[keep] for c, v in u.channels.items()},
            events=[e for e in u.events if e.year <= years])
    write_observations(dst, dataclasses.replace(obs, units=units))


# --- running a stage -----------------------------------------------------------------------

@dataclasses.dataclass
class Run:
    wall: float
    cpu: float
    pss_tree_mb: float
    rss_proc_mb: float
    load: float
    out: str


def _pss_mb(pid: int) -> float:
    # Proportional set size: a page shared by n processes counts 1/n in each, so the sum over
    # a command and its forked workers is the physical memory they hold (a sum of RSS counts
    # the parent's pages again in every fork).
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return float(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _tree_pss(pid: int) -> float:
    """Summed PSS (MB) of process ``pid`` and its descendants."""
    import psutil
    try:
        kids = psutil.Process(pid).children(recursive=True)
    except psutil.Error:
        return 0.0
    return _pss_mb(pid) + sum(_pss_mb(k.pid) for k in kids)


def run_stage(args: list[str], log: Path) -> Run:
    """``twinmon <args>`` as a child process: wall, CPU (with its reaped workers), memory."""
    cmd = [*TWINMON, "-q", *args]
    with open(log, "w") as out, open(log.with_suffix(".err"), "w") as err:
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, stdout=out, stderr=err, cwd=ROOT)
        peak = 0.0
        while True:
            pid, status, ru = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            peak = max(peak, _tree_pss(p.pid))
            time.sleep(0.25)
        wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode:
        raise SystemExit(f"`twinmon {' '.join(args)}` failed (exit {p.returncode}):\n"
                         + log.with_suffix(".err").read_text()[-3000:])
    return Run(wall, ru.ru_utime + ru.ru_stime, peak, ru.ru_maxrss / 1024,
               os.getloadavg()[0], log.read_text())


def mb(path: Path) -> float:
    if path.is_dir():
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6
    return path.stat().st_size / 1e6


# --- the benchmark -------------------------------------------------------------------------

@dataclasses.dataclass
class Row:
    size: int
    stage: str
    executor: str
    run: Run
    artifact_mb: float | None = None
    note: str = ""


def sampler_overrides() -> list[str]:
    """The vectorised sampler and no method override: ``calibrate.method: auto``, the
    default a user gets (the laplace method for a fleet of 5 units or more,
    docs/calibration.md)."""
    names = {f.name for f in dataclasses.fields(CalibrateConfig)}
    return ["--set", "calibrate.sampler=vectorised"] if "sampler" in names else []


def dask_overrides() -> list[str]:
    return ["--set", "calibrate.executor=dask", "--set", "diagnose.executor=dask",
            "--set", "simulate.executor=dask"]


def accuracy(calib_json: str) -> tuple[dict, int]:
    s = json.loads(calib_json)
    return s.get("truth_check", {}), len(s.get("warnings", []))


def forecast_figures(fc_json: str, kinds: dict[str, str]) -> str:
    """Root-cause agreement with the fabricated kind, failure years within 1 of true, and
    the shares of future points the FMU and the limit-state model answered."""
    whole = json.loads(fc_json)
    units = whole["units"]
    right, n, years_ok, years_n = 0, 0, 0, 0
    for u, f in units.items():
        # Verdicts: healthy, pump, motor (the components' names), both, ambiguous, withheld.
        n += 1
        right += f.get("root_cause") == kinds[u]
        t = f.get("true_failure_year")
        if t is not None:
            years_n += 1
            fy = f.get("failure_year")
            years_ok += fy is not None and abs(fy - t) <= 1
    fmu = np.mean([f.get("fmu_fraction", 0.0) for f in units.values()])
    model = np.mean([f.get("model_fraction", 0.0) for f in units.values()])
    ls = whole.get("limit_state", {})
    learnt = (f"limit-state model {100 * model:.1f} % ({ls.get('runs')} runs)"
              if ls.get("used") else "no limit-state model")
    return (f"root cause {100 * right / n:.0f} %; failure year +-1 "
            f"{years_ok}/{years_n}; FMU {100 * fmu:.1f} % of future points, {learnt}")


def diagnose_figures(gap_json: str) -> str:
    units = json.loads(gap_json)["units"]
    verdicts = [str(g.get("verdict")) for g in units.values()]
    common = max(set(verdicts), key=verdicts.count)
    return f"{verdicts.count(common)}/{len(verdicts)} '{common}'"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[30, 300, 1000])
    ap.add_argument("--dask-sizes", type=int, nargs="*", default=[30, 300],
                    help="fleet sizes also run with executor: dask (calibrate, forecast, "
                         "diagnose)")
    ap.add_argument("--dask-only", action="store_true",
                    help="at the sizes of --dask-sizes, run with Dask alone (not the process "
                         "executor first): a fleet too large to run twice")
    ap.add_argument("--update-sizes", type=int, nargs="*", default=None,
                    help="fleet sizes whose yearly update is timed [default: the largest]")
    ap.add_argument("--reference", type=int, default=30,
                    help="also calibrate fleets up to this size with sampler openturns, for "
                         "accuracy (0: never)")
    ap.add_argument("--stages", nargs="+", default=list(PIPELINE), choices=PIPELINE,
                    help="stages to run per size (each needs the ones before it)")
    ap.add_argument("--seed", type=int, default=20240611)
    ap.add_argument("--workdir", default=None, help="keep the run here [default: a temp dir]")
    ap.add_argument("--keep", action="store_true", help="do not delete --workdir at the end")
    args = ap.parse_args()
    update_sizes = args.update_sizes if args.update_sizes is not None else [max(args.sizes)]

    if args.workdir:
        wd = Path(args.workdir)
        wd.mkdir(parents=True, exist_ok=True)
    else:
        wd = Path(tempfile.mkdtemp(prefix="fleet_scale_"))
    load0 = os.getloadavg()
    print(f"fleet_scale: work folder {wd}; {os.cpu_count()} cores; load average "
          f"{load0[0]:.1f} {load0[1]:.1f} {load0[2]:.1f}", flush=True)
    rows: list[Row] = []
    samp = sampler_overrides()
    try:
        # Shared: simulate + reduce on a config of the smallest fleet (the fabricate section
        # is no part of their provenance).
        shared = wd / "shared"
        shared.mkdir(exist_ok=True)
        cfg0 = shared / "fleet.yaml"
        write_fleet_config(cfg0, 3, args.seed)
        sims, sur = shared / "simulations.h5", shared / "surrogate.h5"
        r = run_stage(["simulate", "-c", str(cfg0), "-o", str(sims)], shared / "simulate.log")
        rows.append(Row(0, "simulate", "process", r, mb(sims)))
        _progress(rows)
        r = run_stage(["reduce", "-c", str(cfg0), "--simulations", str(sims), "-o", str(sur)],
                      shared / "reduce.log")
        rows.append(Row(0, "reduce", "process", r, mb(sur)))
        _progress(rows)

        for n in args.sizes:
            _projection(rows, n)
            d = wd / f"n{n}"
            d.mkdir(exist_ok=True)
            cfg = d / "fleet.yaml"
            kinds = write_fleet_config(cfg, n, args.seed)
            for link, target in (("simulations.h5", sims), ("surrogate.h5", sur)):
                if not (d / link).exists():
                    (d / link).symlink_to(target)
            obs, truth = d / "obs.h5", d / "truth.h5"
            c = ["-c", str(cfg)]
            r = run_stage(["fabricate", *c, "-o", str(obs), "--truth", str(truth)],
                          d / "fabricate.log")
            rows.append(Row(n, "fabricate", "process", r, mb(obs) + mb(truth)))
            _progress(rows)
            # Each stage with the process executor, then at once with Dask: the machine's
            # load drifts, so the two runs of a stage are compared under about the same load.
            execs = [("process", [], d)]
            if n in args.dask_sizes:
                (d / "dask").mkdir(exist_ok=True)
                execs = execs[:0 if args.dask_only else 1] + [("dask", dask_overrides(),
                                                                d / "dask")]
            for ex, extra, o in execs:
                r = run_stage(["calibrate", *c, *samp, *extra, "--surrogate", str(sur),
                               "--observations", str(obs), "--truth", str(truth),
                               "-o", str(o / "posterior.h5"), "--json"],
                              o / "calibrate.log")
                tc, nwarn = accuracy(r.out)
                rows.append(Row(n, "calibrate", ex, r, mb(o / "posterior.h5"),
                                _acc_note(tc, nwarn)))
                _progress(rows)
            # The yearly update right after the full calibrate it is compared with.
            if n in update_sizes:
                obs9, post_u = d / "obs9.h5", d / "posterior_update.h5"
                slice_years(obs, obs9, YEARS - 1)
                r = run_stage(["calibrate", *c, *samp, "--surrogate", str(sur),
                               "--observations", str(obs9), "-o", str(post_u)],
                              d / "calibrate9.log")
                rows.append(Row(n, "calibrate 9 y", "process", r, mb(post_u)))
                r = run_stage(["calibrate", *c, *samp, "--surrogate", str(sur),
                               "--observations", str(obs), "-o", str(post_u), "--update",
                               "--json"], d / "update.log")
                u = json.loads(r.out).get("update") or {}
                same = _same_posterior(d / "posterior.h5", post_u)
                rows.append(Row(n, "calibrate --update", "process", r, mb(post_u),
                                f"{u.get('new_years')} unit-years sampled, "
                                f"{u.get('kept_years')} kept; {same}"))
                _progress(rows)

            for ex, extra, o in execs if "forecast" in args.stages else []:
                r = run_stage(["forecast", *c, *extra, "--posterior", str(o / "posterior.h5"),
                               "--surrogate", str(sur), "--truth", str(truth),
                               "-o", str(o / "forecast.h5"), "--json"], o / "forecast.log")
                rows.append(Row(n, "forecast", ex, r, mb(o / "forecast.h5"),
                                forecast_figures(r.out, kinds)))
                _progress(rows)
            for ex, extra, o in execs if "diagnose" in args.stages else []:
                r = run_stage(["diagnose", *c, *extra, "--observations", str(obs),
                               "-o", str(o / "gap.h5"), "--json"], o / "diagnose.log")
                rows.append(Row(n, "diagnose", ex, r, mb(o / "gap.h5"),
                                diagnose_figures(r.out)))
                _progress(rows)
            # The yearly update of diagnose, right after the full diagnose it is compared with.
            if n in update_sizes and "diagnose" in args.stages:
                obs9, gap_u = d / "obs9.h5", d / "gap_update.h5"
                if not obs9.exists():
                    slice_years(obs, obs9, YEARS - 1)
                r = run_stage(["diagnose", *c, "--observations", str(obs9), "-o", str(gap_u)],
                              d / "diagnose9.log")
                rows.append(Row(n, "diagnose 9 y", "process", r, mb(gap_u)))
                _progress(rows)
                r = run_stage(["diagnose", *c, "--observations", str(obs), "-o", str(gap_u),
                               "--update", "--json"], d / "diagnose_update.log")
                u = json.loads(r.out).get("update") or {}
                rows.append(Row(n, "diagnose --update", "process", r, mb(gap_u),
                                f"{u.get('new_years')} unit-years fitted, "
                                f"{u.get('kept_years')} kept; {_same_gap(d / 'gap.h5', gap_u)}"))
                _progress(rows)
            if "report" in args.stages:
                r = run_stage(["report", *c, "--workdir", str(d), "--observations", str(obs),
                               "--truth", str(truth), "-o", str(d / "report")],
                              d / "report.log")
                rows.append(Row(n, "report", "process", r, mb(d / "report")))
                _progress(rows)

            if n <= args.reference:
                o = d / "openturns"
                o.mkdir(exist_ok=True)
                r = run_stage(["calibrate", *c, "--set", "calibrate.sampler=openturns",
                               "--surrogate", str(sur), "--observations", str(obs),
                               "--truth", str(truth), "-o", str(o / "posterior.h5"), "--json"],
                              o / "calibrate.log")
                tc, nwarn = accuracy(r.out)
                rows.append(Row(n, "calibrate openturns", "process", r,
                                mb(o / "posterior.h5"), _acc_note(tc, nwarn)))
                _progress(rows)
    finally:
        print()
        print_table(rows)
        print_targets(rows, args.sizes)
        load1 = os.getloadavg()
        print(f"load average at the end {load1[0]:.1f} {load1[1]:.1f} {load1[2]:.1f}")
        if not (args.workdir and args.keep):
            shutil.rmtree(wd, ignore_errors=True)


def _acc_note(tc: dict, nwarn: int) -> str:
    return "; ".join(f"{k} err {100 * v['mean_rel_error']:.2f} % cov "
                     f"{100 * v['coverage_90']:.0f} %" for k, v in tc.items()) + \
        f"; {nwarn} warn"


def _same_posterior(full: Path, upd: Path) -> str:
    """Whether the updated posterior's arrays equal the full run's (the update's claim):
    every field of every unit, draws included, bit for bit."""
    from twinmon.calibrate import read_posterior
    a, b = read_posterior(full), read_posterior(upd)
    if list(a.units) != list(b.units):
        return "units differ from the full run"
    for (unit, x), (_, y) in zip(a.units.each(), b.units.each()):
        for f in dataclasses.fields(x):
            v, w = getattr(x, f.name), getattr(y, f.name)
            pairs = [(np.asarray(v[k]), np.asarray(w.get(k))) for k in v] \
                if isinstance(v, dict) else [(v, w)]
            for p, q in pairs:
                same = np.array_equal(p, q, equal_nan=p.dtype.kind == "f") \
                    if isinstance(p, np.ndarray) else p == q
                if not same:
                    return f"{unit}/{f.name} differs from the full run"
    return "= full run"


def _same_gap(full: Path, upd: Path) -> str:
    """Whether the updated gap.h5 equals the full run's: every field of every unit bit for bit
    (NaN equal to NaN), the per-year records included, but the run's own cost (``fmu_runs``,
    ``wall_time``)."""
    from twinmon.diagnose.artifact import gap_differences
    bad = gap_differences(full, upd)
    return "= full run" if not bad else f"{len(bad)} differ from the full run, e.g. {bad[0]}"


def _projection(rows: list[Row], n: int) -> None:
    """Say how long size ``n`` should take, from the last size's cost per unit-year."""
    done = [r for r in rows if r.size and r.executor == "process" and r.stage in PIPELINE]
    if not done:
        return
    last = max(r.size for r in done)
    per = sum(r.run.wall for r in done if r.size == last) / (last * YEARS)
    print(f"  {n} units: about {per * n * YEARS / 60:.0f} min for calibrate through report "
          f"at {last} units' {1000 * per:.0f} ms per unit-year (load "
          f"{os.getloadavg()[0]:.1f})", flush=True)


def _progress(rows: list[Row]) -> None:
    r = rows[-1]
    print(f"  {r.size or '-':>5} {r.stage:<20} {r.executor:<8} {r.run.wall:8.1f} s wall "
          f"{r.run.cpu:8.1f} s CPU {r.run.pss_tree_mb:7.0f} MB  load {r.run.load:.1f}  "
          f"{r.note}", flush=True)


def print_table(rows: list[Row]) -> None:
    print("| units | stage | executor | wall s | wall ms / unit-year | CPU s | peak MB tree PSS "
          "/ 1 proc RSS | artifact MB | load | figures |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        uy = r.size * YEARS
        per = f"{1000 * r.run.wall / uy:.1f}" if uy else ""
        art = f"{r.artifact_mb:.1f}" if r.artifact_mb is not None else ""
        print(f"| {r.size or 'shared'} | {r.stage} | {r.executor} | {r.run.wall:.1f} | {per} | "
              f"{r.run.cpu:.1f} | {r.run.pss_tree_mb:.0f} / {r.run.rss_proc_mb:.0f} | {art} | "
              f"{r.run.load:.1f} | {r.note} |")


def print_targets(rows: list[Row], sizes: list[int]) -> None:
    def get(n, stage, ex="process"):
        return next((r for r in rows if r.size == n and r.stage == stage
                     and r.executor == ex), None)

    shared = sum(r.run.wall for r in rows if r.size == 0)
    totals = {}
    print("\nend to end, simulate through report (the shared simulate + reduce "
          f"{shared:.0f} s included):")
    for n in sizes:
        st = [get(n, s) for s in PIPELINE]
        if all(st):
            totals[n] = shared + sum(r.run.wall for r in st)
            line = ", ".join(f"{s} {r.run.wall:.0f}" for s, r in zip(PIPELINE, st))
            print(f"  {n} units: {totals[n]:.0f} s ({line}); "
                  f"{1000 * (totals[n] - shared) / (n * YEARS):.1f} ms per unit-year after "
                  "simulate + reduce")
    big = max(totals) if totals else None
    if big:
        print(f"  target <= {TARGET_TOTAL_S} s at 1000 units: {big} units took {totals[big]:.0f} s"
              + ("" if big >= 1000 else " (1000 not run)"))
    for n in sizes:
        c, f = get(n, "calibrate"), get(n, "forecast")
        if c:
            print(f"  calibrate, {n} units: {1000 * c.run.cpu / (n * YEARS):.1f} ms of CPU per "
                  f"unit-year (target <= {TARGET_CALIBRATE_CPU_MS})")
        if f:
            print(f"  forecast, {n} units: {1000 * f.run.wall / n:.0f} ms wall per unit, "
                  f"{1000 * f.run.cpu / n:.0f} ms of CPU (target <= {TARGET_FORECAST_MS} wall)")
    small = min(totals) if totals else None
    if small and big and big != small:
        for s in PIPELINE + ("total",):
            if s == "total":
                a, b = totals[small] - shared, totals[big] - shared
            else:
                a, b = get(small, s).run.wall, get(big, s).run.wall
            ratio = (b / (big * YEARS)) / (a / (small * YEARS))
            print(f"  cost per unit-year, {big} vs {small} units, {s}: {ratio:.2f}x "
                  f"(target <= {TARGET_SCALE})")
    for n in sizes:
        st = [(get(n, s), get(n, s, "dask")) for s in PIPELINE[:3]]
        if all(b for _, b in st):
            p, d = sum(a.run.wall for a, _ in st), sum(b.run.wall for _, b in st)
            pc, dc = sum(a.run.cpu for a, _ in st), sum(b.run.cpu for _, b in st)
            parts = ", ".join(f"{s} {b.run.wall / a.run.wall:.2f}x"
                              for s, (a, b) in zip(PIPELINE, st))
            print(f"  dask / process, {n} units, calibrate + forecast + diagnose: wall "
                  f"{d / p:.2f}x ({parts}; target <= {TARGET_DASK}); CPU {dc / pc:.2f}x")
    for n in sizes:
        full, upd = get(n, "calibrate"), get(n, "calibrate --update")
        dfull, dupd = get(n, "diagnose"), get(n, "diagnose --update")
        if full and upd:
            line = (f"  yearly update, {n} units: calibrate --update {upd.run.wall:.0f} s = "
                    f"{100 * upd.run.wall / full.run.wall:.1f} % of the full calibrate's wall "
                    f"time ({100 * upd.run.cpu / full.run.cpu:.1f} % of its CPU)")
            if dfull and dupd:
                line += (f"; diagnose --update {dupd.run.wall:.0f} s = "
                         f"{100 * dupd.run.wall / dfull.run.wall:.1f} % of the full diagnose's "
                         f"({100 * dupd.run.cpu / dfull.run.cpu:.1f} % of its CPU)")
            if n in totals:
                # forecast and report recompute; diagnose updates when it was timed.
                rest = sum(get(n, s).run.wall for s in ("forecast", "report"))
                rest += (dupd or dfull).run.wall
                line += (f"; with forecast + {'diagnose --update' if dupd else 'diagnose'} + "
                         f"report {upd.run.wall + rest:.0f} s = "
                         f"{100 * (upd.run.wall + rest) / totals[n]:.1f} % of the full run")
                # What no update can beat: the new year is 1/YEARS of calibrate's and
                # diagnose's per-year work, while every unit's trend (hence its forecast and
                # report) changes with it.
                floor = (full.run.wall / YEARS + (dfull.run.wall / YEARS if dfull else 0.0)
                         + sum(get(n, s).run.wall for s in ("forecast", "report")))
                line += (f"; floor (1/{YEARS} of calibrate and diagnose, forecast and report "
                         f"whole) {floor:.0f} s = {100 * floor / totals[n]:.1f} %")
            print(line + f" (target: the update <= {TARGET_UPDATE_S} s at 1000 units)")
    if rows:
        worst = max(rows, key=lambda r: r.run.pss_tree_mb)
        print(f"  peak memory (tree PSS): {worst.run.pss_tree_mb:.0f} MB ({worst.stage}, "
              f"{worst.size} units, {worst.executor}; target <= {TARGET_RSS_MB} MB)")
    for n in sizes:
        c = get(n, "calibrate")
        if c:
            print(f"  posterior, {n} units: {c.artifact_mb:.1f} MB"
                  + (f" (target <= {TARGET_POSTERIOR_MB} MB at 1000)" if n >= 1000 else ""))
    for n in sizes:
        a, b = get(n, "calibrate"), get(n, "calibrate openturns")
        if a and b:
            print(f"  accuracy, {n} units: vectorised {a.note} | openturns {b.note}")


if __name__ == "__main__":
    main()
