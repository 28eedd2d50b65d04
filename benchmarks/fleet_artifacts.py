"""Size and reading memory of fleet-sized artifacts (targets: the posterior of 1000 units of
10 years <= 200 MB; peak RSS <= 2 GB).

One real unit of a finished run (its posterior with every draw, its forecast) is written under
``--units`` names with calibrate's and forecast's writers; then a fresh process opens each
artifact and reads every unit in turn (as forecast and report do), and its peak RSS is
printed beside the RSS of the same process before reading. ``--before`` does the same with
the source run's own layout (every draw) and the reader of commit ``BEFORE``.

    .venv/bin/python benchmarks/fleet_artifacts.py --config configs/dcdrive.yaml \\
        --run out-dcdrive --units 1000 --before
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.config import load_config  # noqa: E402

READER = r"""
import importlib.util, sys, time
import numpy as np


def hwm():
    # VmHWM: this process's peak resident memory (ru_maxrss would include the parent's,
    # inherited through fork).
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM"):
            return float(line.split()[1]) / 1024


kind, path = sys.argv[1], sys.argv[2]
if kind == "posterior-before":
    # The reader as it was before the draws were thinned (every unit read at once).
    import twinmon.calibrate  # noqa: F401  (the package its relative imports need)
    spec = importlib.util.spec_from_file_location("twinmon.calibrate._before", sys.argv[3])
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    read = module.read_posterior
elif kind == "posterior":
    from twinmon.calibrate import read_posterior as read
else:
    from twinmon.forecast import read_forecast as read
import twinmon.forecast  # noqa: F401  (the same imports in every case)
rss0 = hwm()
t = time.perf_counter()
art = read(path)
total = 0.0
for unit, u in art.units.items():
    total += float(np.sum(u.samples))        # touch the largest array
print(rss0, hwm(), time.perf_counter() - t, len(art.units))
"""

#: The commit whose posterior reader read every unit at once (the layout ``--before`` measures).
BEFORE = "1bc8e1f"


def _read_in_child(kind: str, path: Path, *extra: str) -> tuple[float, float, float, int]:
    r = subprocess.run([sys.executable, "-c", READER, kind, str(path), *extra],
                       capture_output=True, text=True, cwd=ROOT)
    if r.returncode:
        raise SystemExit(f"reading {kind} failed:\n{r.stderr}")
    out = r.stdout.split()
    return float(out[0]), float(out[1]), float(out[2]), int(out[3])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "dcdrive.yaml"))
    ap.add_argument("--run", default=str(ROOT / "out-dcdrive"),
                    help="folder of a finished run holding posterior.h5 and forecast.h5")
    ap.add_argument("--units", type=int, default=1000)
    ap.add_argument("--before", action="store_true",
                    help="also write the source's layout under every name and read it with "
                         "the reader of commit BEFORE (about 1 MB per unit on disk)")
    args = ap.parse_args()
    cfg = load_config(args.config)
    from twinmon.calibrate import read_posterior, write_posterior
    from twinmon.forecast import Direction, read_forecast
    from twinmon.forecast.artifact import _open_forecast, _write_unit

    run = Path(args.run)
    if not (run / "posterior.h5").exists() or not (run / "forecast.h5").exists():
        print(f"skipped: {run} holds no posterior.h5 and forecast.h5 (make them with "
              f"`twinmon run -c {args.config} --observations ... --workdir {run}`)")
        return
    post = read_posterior(run / "posterior.h5")
    unit = next(iter(post.units))
    up = post.units[unit]
    n_y = len(up.years)
    src_bytes = os.path.getsize(run / "posterior.h5") / sum(
        len(post.units[u].years) for u in post.units)
    fc = read_forecast(run / "forecast.h5")
    uf = fc.units[unit]
    with h5_attrs(run / "forecast.h5") as attrs:
        sources = json.loads(attrs["direction_sources"])
    directions = {n: Direction(int(fc.directions[n]), **sources[n]) for n in fc.input_names}

    names = [f"U{i:04d}" for i in range(args.units)]
    with tempfile.TemporaryDirectory() as wd:
        wd = Path(wd)
        t = time.perf_counter()
        write_posterior(wd / "posterior.h5", {n: up for n in names}, post.input_names, cfg, [])
        t_post = time.perf_counter() - t
        t = time.perf_counter()
        with _open_forecast(wd / "forecast.h5", cfg, list(fc.input_names), directions, True,
                            seed=0, inputs=[]) as f:
            for n in names:
                _write_unit(f, cfg, n, uf, list(fc.input_names))
        t_fc = time.perf_counter() - t
        size_p = os.path.getsize(wd / "posterior.h5")
        size_f = os.path.getsize(wd / "forecast.h5")
        print(f"source run {run}: unit {unit}, {n_y} years, {up.samples.shape[1]} draws per "
              f"year stored there, {src_bytes:,.0f} bytes per unit-year")
        print(f"posterior, {args.units} units: {size_p / 1e6:.1f} MB "
              f"({size_p / args.units / n_y:,.0f} bytes per unit-year, keep_draws "
              f"{cfg.calibrate.keep_draws}); written in {t_post:.1f} s")
        print(f"forecast,  {args.units} units: {size_f / 1e6:.1f} MB "
              f"({size_f / args.units:,.0f} bytes per unit); written in {t_fc:.1f} s")
        for kind in ("posterior", "forecast"):
            rss0, rss1, secs, n = _read_in_child(kind, wd / f"{kind}.h5")
            print(f"read {kind} + every unit's samples ({n} units): peak RSS {rss1:.0f} MB "
                  f"(process before reading {rss0:.0f} MB), {secs:.1f} s")
        if args.before:
            # The same unit in the layout the source run was written in, under every name,
            # read by the reader of commit BEFORE.
            import h5py
            old = wd / "posterior_before.h5"
            with h5py.File(run / "posterior.h5", "r") as src, h5py.File(old, "w") as dst:
                for k, v in src.attrs.items():
                    dst.attrs[k] = v
                for n in names:
                    dst.copy(src[f"units/{unit}"], f"units/{n}")
            code = wd / "posterior_before.py"
            code.write_text(subprocess.run(
                ["git", "show", f"{BEFORE}:twinmon/calibrate/posterior.py"], check=True,
                capture_output=True, text=True, cwd=ROOT).stdout)
            rss0, rss1, secs, n = _read_in_child("posterior-before", old, str(code))
            print(f"before ({BEFORE}): posterior {os.path.getsize(old) / 1e6:.1f} MB; read + "
                  f"every unit's samples: peak RSS {rss1:.0f} MB (process before reading "
                  f"{rss0:.0f} MB), {secs:.1f} s")


class h5_attrs:
    """The root attributes of an HDF5 file, as a context manager."""

    def __init__(self, path: Path):
        import h5py
        self.f = h5py.File(path, "r")

    def __enter__(self):
        return self.f.attrs

    def __exit__(self, *exc):
        self.f.close()


if __name__ == "__main__":
    main()
