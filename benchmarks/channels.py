"""Flow only against flow + further channels in the likelihood, on fabricated data.

The shipped fleet (configs/fleet.yaml: three units, ten years, flow noise 1 % of nominal) is
fabricated again with the further channels recorded (``fabricate.record_channels``; each
channel's noise is 1 % of its healthy range). The design records every channel; ``reduce``
learns the output and the chosen channels (``reduce.channels``); ``calibrate`` runs twice on
the same observations and the same seeds: ``calibrate.channels: []`` (flow only) and the
chosen channels. Only this script reads the truth.

Figures per input, over all unit-years: mean and max relative error of the posterior mean,
90 % interval coverage, mean 90 % interval width (percent of the true value), and the
correlation between the two inputs' draws within a year (mean and mean |.| over unit-years:
near -1 or +1, the data cannot tell one input's change from the other's, which blurs the
root cause). Reduce is timed with no channel, the chosen ones and every channel.

Usage: ``python benchmarks/channels.py [--channels motor.w] [--years 10] [--workers 0]``
"""
from __future__ import annotations

import argparse
import copy
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.calibrate import calibrate, read_posterior  # noqa: E402
from twinmon.config import config_from_mapping, load_config  # noqa: E402
from twinmon.fabricate import fabricate, read_truth  # noqa: E402
from twinmon.reduce import reduce  # noqa: E402
from twinmon.simulate import simulate  # noqa: E402


def _config(raw: dict, source: Path, **sections):
    raw = copy.deepcopy(raw)
    for section, keys in sections.items():
        raw.setdefault(section, {}).update(keys)
    return config_from_mapping(raw, source)


def _figures(summary, truth, names) -> dict:
    """Per input: errors, coverage, width; and the draws' correlation between inputs."""
    out = {}
    for j, name in enumerate(names):
        rel, cover, width = [], [], []
        for unit, p in summary.posterior.items():
            t = np.asarray(truth.inputs[unit][name])[np.searchsorted(truth.years[unit], p.years)]
            rel.append(np.abs(p.mean[:, j] / t - 1))
            cover.append((p.q05[:, j] <= t) & (t <= p.q95[:, j]))
            width.append((p.q95[:, j] - p.q05[:, j]) / np.abs(t))
        rel, cover, width = map(np.concatenate, (rel, cover, width))
        out[name] = {"mean": rel.mean(), "max": rel.max(), "cover": cover.mean(),
                     "width": width.mean()}
    # The draws are in the posterior file (the summary keeps the statistics).
    draws = read_posterior(summary.output).units
    corr = np.array([np.corrcoef(q.samples[k, :, 0], q.samples[k, :, 1])[0, 1]
                     for q in (draws[u] for u in summary.posterior)
                     for k in range(len(q.years))])
    out["corr"] = {"mean": corr.mean(), "abs": np.abs(corr).mean(), "min": corr.min(),
                   "max": corr.max()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--channels", nargs="+", default=["motor.w"],
                    help="further channels in the likelihood (keys of model.channels)")
    ap.add_argument("--years", type=int, default=10)
    ap.add_argument("--workers", type=int, default=0, help="calibrate.workers (0: one per core)")
    args = ap.parse_args()

    base = load_config(ROOT / "configs" / "fleet.yaml")
    raw = copy.deepcopy(dict(base.raw))
    raw["fabricate"].update(record_channels=True, years=args.years)
    raw["calibrate"]["workers"] = args.workers
    src = ROOT / "configs" / "fleet.yaml"
    names = base.model.input_names
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cfg = _config(raw, src, reduce={"channels": list(args.channels)})
        t0 = time.perf_counter()
        simulate(cfg, tmp / "sims.h5")
        print(f"simulate (design records every channel): {time.perf_counter() - t0:.1f} s")
        times = {}
        for label, chans in (("output only", []), ("+ " + ", ".join(args.channels),
                                                   list(args.channels)),
                             ("+ every channel", None)):
            c = _config(raw, src, reduce={"channels": chans})
            t0 = time.perf_counter()
            reduce(c, tmp / "sims.h5", tmp / f"sur_{len(times)}.h5")
            times[label] = time.perf_counter() - t0
        print("reduce wall time: " + "; ".join(f"{k} {v:.1f} s" for k, v in times.items()))
        sur = tmp / "sur_1.h5"      # the output and the chosen channels
        fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
        truth = read_truth(tmp / "truth.h5")
        runs = {}
        for label, chans in (("flow only", []),
                             ("flow + " + ", ".join(args.channels), list(args.channels))):
            c = _config(raw, src, reduce={"channels": list(args.channels)},
                        calibrate={"channels": chans})
            t0 = time.perf_counter()
            s = calibrate(c, sur, tmp / "obs.h5", tmp / f"post_{len(runs)}.h5")
            wall = time.perf_counter() - t0
            runs[label] = (_figures(s, truth, names), wall, s)
            for w in s.warnings:
                print(f"  warning ({label}): {w}")

    units = len(base.fabricate.units)
    print(f"\n{units} units x {args.years} years (configs/fleet.yaml, every channel recorded, "
          "1 % noise each)")
    w = max(22, *(len(k) for k in runs))
    head = f"{'likelihood':<{w}} {'input':<14} {'mean err':>9} {'max err':>8} {'cover90':>8} " \
           f"{'width90':>8}"
    print(head)
    print("-" * len(head))
    for label, (fig, wall, _) in runs.items():
        for name in names:
            f = fig[name]
            print(f"{label:<{w}} {name:<14} {100 * f['mean']:8.2f}% {100 * f['max']:7.2f}% "
                  f"{100 * f['cover']:7.1f}% {100 * f['width']:7.2f}%")
    print(f"\n{'likelihood':<{w}} {'corr(draws) mean':>17} {'mean |corr|':>12} {'range':>16} "
          f"{'calibrate':>10}")
    for label, (fig, wall, s) in runs.items():
        c = fig["corr"]
        print(f"{label:<{w}} {c['mean']:17.3f} {c['abs']:12.3f} "
              f"{c['min']:7.3f}..{c['max']:6.3f} {wall:9.1f}s")
    ref, new = list(runs.values())[0][0], list(runs.values())[1][0]
    print("\nratio (with channels / flow only): " + "; ".join(
        f"{n}: mean err {new[n]['mean'] / ref[n]['mean']:.2f}, width "
        f"{new[n]['width'] / ref[n]['width']:.2f}" for n in names))


if __name__ == "__main__":
    main()
