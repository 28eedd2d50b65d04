"""The joint method's scan for unrecorded repairs, alone, on the prognosis families.

``calibrate`` (joint method) looks for jumps back towards nominal in each unit's yearly
maximum-likelihood points before it samples (:func:`twinmon.repairs.find_repairs`); this
script runs only that step (each year's maximum-likelihood point and Laplace variance, then
the scan) on a family's fleet, and scores it against the truth file's unrecorded events:
repaired units found (year and component right) and units given a repair that was not
there. It is the cheap way to check the scan on many fleets; the full pipeline's figures
come from ``benchmarks/prognosis.py``.

Usage: ``python benchmarks/repair_scan.py --family F --seed S [--workdir DIR]``; the fleet
is made (or reused) in ``DIR`` as ``benchmarks/prognosis.py`` makes it, flow only.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from families import FAMILIES  # noqa: E402
from trend_statespace import make_fleet  # noqa: E402
from twinmon.calibrate import _noise_for  # noqa: E402
from twinmon.calibrate.density import estimate_noise  # noqa: E402
from twinmon.calibrate.methods.joint import JointRun  # noqa: E402
from twinmon.config import load_config  # noqa: E402
from twinmon.fabricate import read_truth  # noqa: E402
from twinmon.observations import read_observations  # noqa: E402
from twinmon.reduce import read_surrogate  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--family", default="repair_hidden", choices=FAMILIES)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    a = ap.parse_args()
    work = a.workdir or Path(tempfile.mkdtemp(prefix="twinmon-repair-scan-"))
    make_fleet(work, a.family, a.seed)
    cfg = load_config(work / "bench.yaml", ["calibrate.method=joint", "calibrate.channels=[]",
                                            *a.set])
    obs = read_observations(work / "obs.h5", cfg.model.output.name)
    truth = read_truth(work / "truth.h5")
    sur = read_surrogate(work / "sur.h5")
    t0 = time.perf_counter()
    found, hidden = {}, {}
    for unit, u in obs.units.items():
        y = obs.output_of(unit)
        noise, source = _noise_for(cfg, u)          # as calibrate takes it
        if noise is None:
            noise = estimate_noise(sur, cfg, y)
        run = JointRun(sur, cfg, u.years, y, noise, 0, source, u.events)
        run._prepare()
        found[unit] = [(r.year, set(r.components)) for r in run.found_repairs]
        hidden[unit] = {(int(y), c) for y, c in truth.unrecorded.get(unit, ())}
    had = [u for u in found if hidden[u]]
    # A finding naming several components (the output cannot tell them apart) is right
    # when the repaired one is among them; "several" counts those findings.
    hit = lambda u, y, cs: any((y, c) in hidden[u] for c in cs)          # noqa: E731
    right = [u for u in had if any(hit(u, y, cs) for y, cs in found[u])]
    false = [(u, y, sorted(cs)) for u in found for y, cs in found[u] if not hit(u, y, cs)]
    several = sum(len(cs) > 1 for u in found for _, cs in found[u])
    print(f"{a.family} seed {a.seed}: repaired units found {len(right)}/{len(had)} (year right, "
          f"the repaired component among those named; {several} finding(s) name two or more); "
          f"findings with no such repair: {len(false)} on {len(found)} units "
          f"({time.perf_counter() - t0:.1f} s for {len(found)} units)")
    if false:
        print("  not there:", false)
    return 0


if __name__ == "__main__":
    sys.exit(main())
