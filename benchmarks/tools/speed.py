"""A fixed reference workload, timed, so that benchmark figures taken on different days can
be told apart from the machine's own speed.

This machine's speed has moved by a factor of two from one day to another (docs/cluster.md:
every stage of the 1000-unit run took two to two and a half times as long, while the code of
the earlier run, timed again beside the current code, took the same time as it). The workload is what
twinmon's per-unit work is made of: a pure-Python loop and thousands of small numpy
operations (the draws' and the trend-fit check's 2 x 2 to 8 x 8 systems), whose cost is
their overhead more than their arithmetic. It is timed in CPU seconds of this process, so
that other processes sharing the cores move it less than they move a wall time.

    .venv/bin/python benchmarks/tools/speed.py          # prints the seconds
"""
from __future__ import annotations

import time

import numpy as np

#: Iterations of each part: about half a second of CPU a run on the 2-core machine of
#: docs/cluster.md (0.28-0.46 s within one hour of the day its 1000-unit run took 565 s:
#: the speed moves within minutes too, hence a reading at a benchmark's start and end).
LOOP = 2_000_000
SOLVES = 20_000


def reference_seconds() -> float:
    """CPU seconds of the reference workload (the best of three runs: the machine's speed,
    not a moment's interruption)."""
    rng = np.random.default_rng(0)
    A = rng.standard_normal((SOLVES, 4, 4)) + 4 * np.eye(4)
    b = rng.standard_normal(4)
    best = np.inf
    for _ in range(3):
        t = time.process_time()
        s = 0
        for i in range(LOOP):
            s += i * i
        for k in range(SOLVES):
            np.linalg.solve(A[k], b)
        best = min(best, time.process_time() - t)
    return best


if __name__ == "__main__":
    print(f"reference workload: {reference_seconds():.2f} s of CPU")
