"""Runs per second per core: fmpy.simulate_fmu per run (as in a notebook) vs twinmon's batch path.

Both paths simulate the same 200 design points of configs/pump.yaml through the real FMU
(Co-Simulation, 25 output times). Target: batch >= 1000 runs/s per core and >= 5x the plain path.
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import fmpy
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.config import load_config  # noqa: E402
from twinmon.executors import ProcessExecutor, SerialExecutor  # noqa: E402
from twinmon.simulate import as_parameters, draw_design, run_batch, spec_for  # noqa: E402

N = 200


def plain(spec, params):
    out = []
    for p in params:
        r = fmpy.simulate_fmu(str(spec.fmu), fmi_type="CoSimulation", start_values=p,
                              stop_time=float(spec.times[-1]), output_interval=2.0,
                              output=list(spec.outputs))
        out.append(np.interp(spec.times, r["time"], r[spec.outputs[0]]))
    return np.array(out)


def main() -> None:
    cfg = load_config(ROOT / "configs" / "pump.yaml")
    spec = spec_for(cfg)
    params = as_parameters(cfg, draw_design(cfg, N, 1))
    cores = len(os.sched_getaffinity(0))

    t = time.perf_counter()
    y_plain = plain(spec, params)
    t_plain = time.perf_counter() - t

    run_batch(spec, params[:5], SerialExecutor())          # warm the FMU extraction cache
    t = time.perf_counter()
    serial = run_batch(spec, params, SerialExecutor())
    t_serial = time.perf_counter() - t

    t = time.perf_counter()
    pooled = run_batch(spec, params, ProcessExecutor(cores))
    t_pool = time.perf_counter() - t

    y_batch = serial.outputs[spec.outputs[0]]
    diff = np.max(np.abs(y_batch - y_plain) / np.abs(y_plain))
    rate_plain, rate_serial = N / t_plain, N / t_serial
    rate_pool = N / t_pool
    print(f"inputs: {N} design points of configs/pump.yaml, 25 output times, CoSimulation")
    print(f"(a) fmpy.simulate_fmu per run : {rate_plain:8.1f} runs/s on 1 core")
    print(f"(b) twinmon batch, 1 core     : {rate_serial:8.1f} runs/s per core")
    print(f"    twinmon batch, {cores} processes: {rate_pool:8.1f} runs/s "
          f"({rate_pool / cores:.1f} per core, includes pool start-up)")
    print(f"ratio b/a                     : {rate_serial / rate_plain:8.1f}x "
          f"(target >= 5x; batch target >= 1000 runs/s per core)")
    print(f"max relative difference a vs b: {diff:.2e}")
    print(f"all runs ok: {bool(serial.ok.all() and pooled.ok.all())}")


if __name__ == "__main__":
    main()
