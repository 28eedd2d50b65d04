"""Cost of calibrate per unit-year: OpenTURNS vs vectorised sampler, fleet size, --update.

Fleets of N units x 10 years are made from the shipped fleet (data/fleet.h5, 3 units): each
unit is replicated under new names (so new seeds), with 1 kg/s of fresh Gaussian noise added
to its flows (the recorded noise sd becomes sqrt(4^2 + 1)). The surrogate is the shipped
configs/fleet.yaml one (simulate + reduce once). Prints, per sampler and fleet size, the wall
time and the CPU time (this process and its workers) per unit-year; then the time of a yearly
update (years 1..9 calibrated, then --update with year 10) against the full 10-year run; then
the accuracy on the shipped fleet against its truth.

    .venv/bin/python benchmarks/calibrate_speed.py [--units 3 30 300] [--samplers vectorised
        openturns] [--openturns-max 30] [--update-units 300] [--workdir /tmp/calib_bench]
"""
from __future__ import annotations

import argparse
import dataclasses
import resource
import time
from pathlib import Path

import numpy as np

from twinmon.calibrate import calibrate
from twinmon.config import load_config
from twinmon.observations import read_observations, write_observations
from twinmon.reduce import reduce
from twinmon.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def make_fleet(path: Path, n_units: int, years: int = 10, seed: int = 0) -> Path:
    """The shipped fleet's units replicated to ``n_units``, each with fresh noise (drawn for
    all ten years, then cut: the first years of a shorter fleet are the same data)."""
    obs = read_observations(ROOT / "data" / "fleet.h5")
    rng = np.random.default_rng(seed)
    base = list(obs.units.items())
    units = {}
    for i in range(n_units):
        name, u = base[i % len(base)]
        flows = {c: (v + rng.normal(0.0, 1.0, v.shape))[:years]
                 for c, v in u.channels.items()}
        noise = {c: float(np.hypot(s, 1.0)) for c, s in u.noise_std.items()}
        units[f"{name}-{i:04d}"] = dataclasses.replace(u, years=u.years[:years],
                                                       channels=flows, noise_std=noise,
                                                       events=[])
    write_observations(path, dataclasses.replace(obs, units=units))
    return path


def timed(fn):
    w, c = time.perf_counter(), _cpu()
    out = fn()
    return out, time.perf_counter() - w, _cpu() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, nargs="*", default=[3, 30, 300])
    ap.add_argument("--samplers", nargs="+", default=["vectorised", "openturns"])
    ap.add_argument("--openturns-max", type=int, default=30,
                    help="largest fleet run with the OpenTURNS sampler (~0.6 s a unit-year)")
    ap.add_argument("--update-units", type=int, default=300)
    ap.add_argument("--no-accuracy", action="store_true")
    ap.add_argument("--workdir", default="/tmp/calib_bench")
    args = ap.parse_args()
    wd = Path(args.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    base = load_config(ROOT / "configs" / "fleet.yaml")
    sur = wd / "sur.h5"
    if not sur.exists():
        simulate(base, wd / "sims.h5")
        reduce(base, wd / "sims.h5", sur)

    # The sequential method's samplers are timed here (auto would sample 30 units or more
    # jointly); the joint method's cost is in docs/calibration.md.
    def cfg_for(sampler):
        return load_config(ROOT / "configs" / "fleet.yaml", [f"calibrate.sampler={sampler}",
                                                             "calibrate.method=sequential"])

    print("| sampler | units | unit-years | wall s | wall s / unit-year | CPU s / unit-year |")
    print("|---|---|---|---|---|---|")
    for n in args.units:
        obs = make_fleet(wd / f"fleet{n}.h5", n)
        for sampler in args.samplers:
            if sampler == "openturns" and n > args.openturns_max:
                continue
            _, wall, cpu = timed(lambda: calibrate(cfg_for(sampler), sur, obs,
                                                   wd / f"post_{sampler}_{n}.h5"))
            uy = 10 * n
            print(f"| {sampler} | {n} | {uy} | {wall:.1f} | {wall / uy:.4f} | {cpu / uy:.4f} |",
                  flush=True)

    n = args.update_units
    if n:
        cfg = cfg_for("vectorised")
        full10 = make_fleet(wd / f"fleet{n}.h5", n)
        nine = make_fleet(wd / f"fleet{n}_9.h5", n, years=9)
        _, wall_full, cpu_full = timed(lambda: calibrate(cfg, sur, full10, wd / "full10.h5"))
        calibrate(cfg, sur, nine, wd / "upd.h5")
        s, wall_up, cpu_up = timed(lambda: calibrate(cfg, sur, full10, wd / "upd.h5",
                                                     update=True))
        print(f"\nyearly update, {n} units (years 1..9 -> 1..10, vectorised): full 10-year run "
              f"{wall_full:.1f} s wall ({cpu_full:.1f} s CPU); update {wall_up:.1f} s wall "
              f"({cpu_up:.1f} s CPU) = {100 * wall_up / wall_full:.1f} % of the full run's wall "
              f"time ({100 * cpu_up / cpu_full:.1f} % of its CPU); {s.update['new_years']} "
              f"unit-years sampled, {s.update['kept_years']} kept")

    if args.no_accuracy:
        return
    print("\naccuracy on the shipped fleet (data/fleet.h5 against data/fleet_truth.h5):")
    for sampler in args.samplers:
        s = calibrate(cfg_for(sampler), sur, ROOT / "data" / "fleet.h5",
                      wd / f"shipped_{sampler}.h5", truth_path=ROOT / "data" / "fleet_truth.h5")
        figs = "; ".join(f"{k} max {100 * v['max_rel_error']:.2f} % mean "
                         f"{100 * v['mean_rel_error']:.2f} % cov {100 * v['coverage_90']:.1f} %"
                         for k, v in s.truth_check.items())
        print(f"  {sampler}: {figs}; {len(s.warnings)} warning(s)")


if __name__ == "__main__":
    main()
