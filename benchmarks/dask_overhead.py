"""What ``executor: dask`` costs over the process executor on the same FMU batch.

The same batch of pump runs (``configs/pump.yaml``'s FMU and design box, Co-Simulation) goes
through a :class:`~twinmon.executors.ProcessExecutor` and a
:class:`~twinmon.executors.dask.DaskExecutor` on a ``LocalCluster``, both with the same number
of worker processes, one thread each. Each is timed end to end, as a stage sees it: start
the pool / cluster, run the batch, close; best of ``--repeat`` (the machine is shared). A
second batch inside the same open executor gives the steady state, without the start-up.
The arrays of the two are checked to be identical.

Dask's costs are fixed, not per run: starting and closing the cluster (~0.3-0.5 s here; the
process pool's ~0.05 s) and ~3-10 ms a task through the scheduler. So the ratio depends on
how long the batch is: one table row per ``--runs`` size, and ``--fmi-type ModelExchange``
(runs ~20x longer) for heavier work.

Usage: ``python benchmarks/dask_overhead.py [--runs 256 4096] [--workers 2] [--repeat 3]
[--fmi-type CoSimulation]``
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.config import load_config  # noqa: E402
from twinmon.executors import ProcessExecutor  # noqa: E402
from twinmon.executors.dask import DaskExecutor  # noqa: E402
from twinmon.simulate import as_parameters, draw_design, run_batch, spec_for  # noqa: E402


def _timed(make, spec, params):
    """(end-to-end seconds, steady-state seconds of a second batch, outputs)."""
    t0 = time.perf_counter()
    with make() as ex:
        batch = run_batch(spec, params, ex)
        t1 = time.perf_counter()
        run_batch(spec, params, ex)
        t2 = time.perf_counter()
    t3 = time.perf_counter()
    return (t1 - t0) + (t3 - t2), t2 - t1, batch.outputs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, nargs="+", default=[256, 4096])
    ap.add_argument("--fmi-type", default="CoSimulation",
                    choices=["CoSimulation", "ModelExchange"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cfg = load_config(ROOT / "configs" / "pump.yaml", [f"model.fmi_type={args.fmi_type}"])
    spec = spec_for(cfg)
    print(f"pump runs ({args.fmi_type}), {args.workers} worker processes, one thread each; "
          f"best of {args.repeat}; end to end = start + batch + close")
    print(f"{'runs':>6}  {'executor':<18}{'end to end (s)':>15}{'runs/s':>8}"
          f"{'batch only (s)':>15}{'runs/s':>8}")
    ratios = []
    for n in args.runs:
        params = as_parameters(cfg, draw_design(cfg, n, cfg.seed))
        kinds = {"process": lambda: ProcessExecutor(args.workers),
                 "dask LocalCluster": lambda: DaskExecutor(args.workers)}
        best, outputs = {}, {}
        for _ in range(args.repeat):
            for name, make in kinds.items():
                total, steady, out = _timed(make, spec, params)
                b = best.setdefault(name, [np.inf, np.inf])
                b[0], b[1] = min(b[0], total), min(b[1], steady)
                outputs[name] = out
        same = all(np.array_equal(outputs["process"][o], outputs["dask LocalCluster"][o],
                                  equal_nan=True) for o in spec.outputs)
        for name, (total, steady) in best.items():
            print(f"{n:>6}  {name:<18}{total:>15.2f}{n / total:>8.0f}{steady:>15.2f}"
                  f"{n / steady:>8.0f}")
        p, d = best["process"], best["dask LocalCluster"]
        ratios.append((n, d[0] / p[0], d[1] / p[1], d[0] - d[1], same))
    # A command pays this once more (the benchmark imported it before its first timing).
    t = subprocess.run([sys.executable, "-c", "import time; t = time.perf_counter(); "
                        "import distributed; print(time.perf_counter() - t)"],
                       capture_output=True, text=True, check=True)
    print(f"import distributed in a fresh interpreter (once per command): "
          f"{float(t.stdout):.2f} s")
    for n, total, steady, fixed, same in ratios:
        print(f"{n} runs: dask / process end to end {total:.2f}x, batch only {steady:.2f}x; "
              f"dask start + close {fixed:.2f} s; arrays identical: {same}")

if __name__ == "__main__":        # the Dask workers of a spawn start re-import this file
    main()
