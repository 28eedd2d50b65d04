"""The laplace method's widened sites, on a water heater whose record has gaps.

The fleet of ``configs/heattank_fleet.yaml`` (four units, ten years, sensor noise 0.3 K)
with two more sound units: ``Elm3``, three years with a fifth of the samples lost, and
``Fir``, ten years with half of them lost (``fabricate.units.*.last_year`` /
``nan_fraction``). A year with so few samples can leave its Laplace site at one end of a
flat ridge between two inputs, and the importance weights then rest on a few draws.

``calibrate`` (the laplace method, in this process) runs once per seed as the default does
(the widening of the sites the draws miss, ``SiteModel.importance_widened``, then, for a
unit still short, the resample-move of ``twinmon.calibrate.rejuvenate``) and once without
either (both steps turned into no-ops here); per seed it prints the units left
``unconverged`` and each unit's smallest effective number, and the units the default moved
by its Markov chain. A unit that converges either way has the same draws in both runs (the
widening runs only for a unit still short after its longer runs).

Usage: ``python benchmarks/laplace_widening.py [--seeds 1 2 3 ...] [--workdir DIR]``
(the default 16 seeds take about 4 minutes on 2 cores).
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
from twinmon.calibrate.methods import laplace  # noqa: E402
from twinmon.calibrate.rejuvenate import moved_by_chain  # noqa: E402
from twinmon.calibrate.gaussian_trend import SiteModel  # noqa: E402
from twinmon.config import config_from_mapping, load_config  # noqa: E402
from twinmon.fabricate import fabricate  # noqa: E402
from twinmon.reduce import reduce  # noqa: E402
from twinmon.simulate import simulate  # noqa: E402

#: The two units added to the shipped fleet: sound parts, records with gaps.
SOUND = {"element_resistance": {"start": 26.45, "slope": 0.05, "jitter": 0.1},
         "element_conductance": {"start": 100.0, "slope": -1.0, "jitter": 1.5},
         "insulation_loss": {"start": 1.5, "slope": 0.1, "jitter": 0.1}}
EXTRA = {"Elm3": {"last_year": 3, "nan_fraction": 0.2, "trajectories": SOUND},
         "Fir": {"nan_fraction": 0.5, "trajectories": SOUND}}


def _run(cfg, sur: Path, obs: Path, out: Path, widen: bool) -> dict:
    """Calibrate; per unit: (smallest effective number, every year converged, moved by the
    Markov chain)."""
    original, chain = SiteModel.importance_widened, laplace.rejuvenate
    if not widen:
        SiteModel.importance_widened = lambda self, loglik, n, rng, bounds, first, mark: first
        laplace.rejuvenate = lambda *args, **kwargs: None
    try:
        calibrate(cfg, sur, obs, out)
    finally:
        SiteModel.importance_widened, laplace.rejuvenate = original, chain
    post = read_posterior(out)
    return {u: (float(np.min(p.ess)), bool(np.all(p.fit["converged"])),
                moved_by_chain(p.acceptance, p.trend.get("acceptance")))
            for u, p in post.units.items()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 17)))
    ap.add_argument("--workdir", type=Path, default=None)
    a = ap.parse_args()
    work = a.workdir or Path(tempfile.mkdtemp(prefix="twinmon-widening-"))
    work.mkdir(parents=True, exist_ok=True)

    # The shipped fleet's config, resolved (its paths relative to configs/), two units more.
    source = ROOT / "configs" / "heattank_fleet.yaml"
    raw = copy.deepcopy(dict(load_config(source).raw))
    raw["fabricate"]["seed"] = 8181
    raw["fabricate"]["units"].update(copy.deepcopy(EXTRA))
    raw["calibrate"].update(method="laplace", workers=1)
    cfg = config_from_mapping(raw, source)

    t0 = time.perf_counter()
    sims, sur = work / "simulations.h5", work / "surrogate.h5"
    obs, truth = work / "observations.h5", work / "truth.h5"
    if not sur.exists():
        simulate(cfg, sims)
        reduce(cfg, sims, sur)
    if not obs.exists():
        fabricate(cfg, obs, truth)
    print(f"water heater, {len(raw['fabricate']['units'])} units x "
          f"{raw['fabricate']['years']} years (Fir: half its samples lost; Elm3: 3 years, a "
          f"fifth lost); set-up {time.perf_counter() - t0:.0f} s; workdir {work}")

    counts, moved = {True: 0, False: 0}, 0
    for seed in a.seeds:
        rows = {}
        cfg_s = config_from_mapping({**raw, "seed": seed}, source)
        for widen in (False, True):
            rows[widen] = _run(cfg_s, sur, obs, work / f"posterior_{seed}_{int(widen)}.h5",
                               widen)
        for widen in (False, True):
            counts[widen] += sum(not ok for _, ok, _ in rows[widen].values())
        moved += sum(m for _, _, m in rows[True].values())
        line = "  ".join(f"{u} {rows[False][u][0]:.0f}->{rows[True][u][0]:.0f}"
                         f"{'' if rows[True][u][1] else ' UNCONVERGED'}"
                         f"{' (moved)' if rows[True][u][2] else ''}"
                         f"{' (was unconverged)' if not rows[False][u][1] else ''}"
                         for u in rows[True])
        print(f"seed {seed:3d}: smallest effective number without -> with widening: {line}")
    n = len(a.seeds) * len(raw["fabricate"]["units"])
    print(f"units left unconverged over {len(a.seeds)} seeds ({n} unit-runs): without the "
          f"widening and the chain {counts[False]}, with them {counts[True]} (target 0); "
          f"moved by the chain {moved}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
