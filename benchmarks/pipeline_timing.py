"""Wall time of each stage of `twinmon run` on the paper case (target: < 60 s on 2 cores).

Runs the whole pipeline from scratch (--force) on data/fleet.h5 (diagnosing data/fleet_gap.h5)
in a temporary folder, after set-up (the FMU is built and cached beforehand), and prints each
stage's time and the calibration / forecast figures against the truth.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.config import load_config  # noqa: E402
from twinmon.fmu import build_fmu  # noqa: E402
from twinmon.pipeline import run_pipeline  # noqa: E402


def main() -> None:
    cfg = load_config(ROOT / "configs" / "pump.yaml")
    build_fmu(cfg.model.fmu)
    with tempfile.TemporaryDirectory() as wd:
        start = time.perf_counter()
        summary = run_pipeline(cfg, ROOT / "data" / "fleet.h5", wd,
                               gap_observations=ROOT / "data" / "fleet_gap.h5",
                               truth=ROOT / "data" / "fleet_truth.h5", force=True)
        wall = time.perf_counter() - start
    print(f"{'stage':<10} {'seconds':>8}")
    for s in summary.stages:
        print(f"{s.name:<10} {s.seconds:8.2f}")
    print(f"{'total':<10} {wall:8.2f}   (target < 60 s on 2 cores)")
    d = {s.name: s.summary for s in summary.stages}
    red = d["reduce"]
    print(f"surrogate: {red['modes']} modes, variance {red['variance_ratio']:.6f}, "
          f"test max rel error {100 * red['test']['max_rel_error']:.3f} %, "
          f"mean {100 * red['test']['mean_rel_error']:.4f} % (paper 1.5 % / 0.2 %)")
    tc = d["calibrate"].get("truth_check", {})
    for p, v in tc.items():
        print(f"calibration {p}: max rel error {100 * v['max_rel_error']:.2f} %, mean "
              f"{100 * v['mean_rel_error']:.2f} %, 90 % coverage {100 * v['coverage_90']:.1f} %")
    for u, f in d["forecast"]["units"].items():
        print(f"forecast {u}: root cause {f['root_cause']}, failure year {f['failure_year']}, "
              f"true {f.get('true_failure_year')}")
    for u, g in d["diagnose"]["units"].items():
        print(f"diagnose {u} (fleet_gap): {g['verdict']} {g['effects']}, "
              f"closed {g['shrink']['closed_percent']}")


if __name__ == "__main__":
    main()
