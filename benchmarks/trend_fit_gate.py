"""The trend-fit gate on a finished ``benchmarks/prognosis.py`` work folder: which units it
flags ``unreliable`` and whether their forecasts missed.

Usage: ``python benchmarks/trend_fit_gate.py W [W ...] [--tag laplace_flow]`` with ``W`` a
``--workdir`` of ``benchmarks/prognosis.py --family F --seed S`` (its ``bench.yaml`` names
the fleet). Per folder it prints the units flagged by the gate (``trend_fit`` in
``forecast.h5``) among the healthy and the faulty ones, and, against the truth file's
recorded future, how many forecasts "missed": the true indicator outside the 90 % interval
in more than two of the future years, or the median failure year more than one year off
(among units that fail within the horizon). A flagged unit whose forecast missed is one the
gate kept from a confident wrong verdict; an ``ok`` unit whose forecast missed is one it let
through. With ``--deviation`` it also gives, per faulty unit, how far its true yearly inputs
lie from the best straight line or one change of level and rate (the largest deviation over
the years, in sd of that input's yearly estimate: the median over the years of the laplace
method's site sd, else of the posterior's):
the units whose history a trend model cannot follow beyond the noise.

``python benchmarks/trend_fit_gate.py --size N`` measures instead the gate's own statistics,
without a fleet: on ``N`` simulated ten-year histories of 1, 2 and 3 inputs drawn from the
model (a line per input, the year-to-year sd drawn from a log-normal fleet prior, each
year's site error correlated 0.9 between inputs, as the pump's from flow), the share
rejected at ``forecast.trend_fit_alpha`` with its 90 % Wilson interval, and the CPU time per
unit, for the shapes' model (``calibrate.shapes``' default) and the line alone. ``--cost``
times the gate per unit on each folder's posterior, as the forecast runs it.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.calibrate import read_posterior  # noqa: E402
from twinmon.config import load_config  # noqa: E402
from twinmon.fabricate import read_truth  # noqa: E402
from twinmon.forecast import read_forecast  # noqa: E402

#: A forecast "missed" when the true indicator left its 90 % interval in more than this
#: many future years (of 7), or its median failure year was more than a year off.
MISSED_YEARS = 2


def missed(uf) -> bool:
    """The forecast of one unit missed its true future (module docstring)."""
    q05, q95 = uf.indicator_quantiles((0.05, 0.95))
    t = np.where(np.isnan(uf.true_indicator), np.inf, uf.true_indicator)
    outside = int(np.sum((t < q05) | (t > q95)))
    tf, mf = uf.true_failure_year, uf.median_failure_year
    off = tf is not None and (mf is None or abs(mf - tf) > 1)
    return outside > MISSED_YEARS or off


def deviation(years: np.ndarray, true: np.ndarray, sd: float) -> float:
    """Largest deviation of a true yearly history from its best straight line or line
    with one change of level and rate (3 years each side), in ``sd``."""
    t = years.astype(float)
    best = np.inf
    designs = [np.column_stack([np.ones_like(t), t])]
    for y in t[3:-2]:
        on = (t >= y).astype(float)
        designs.append(np.column_stack([np.ones_like(t), t, on, on * (t - y)]))
    for X in designs:
        coef, *_ = np.linalg.lstsq(X, true, rcond=None)
        best = min(best, float(np.max(np.abs(true - X @ coef))))
    return best / sd


def size(n: int, seed: int = 1) -> None:
    """The ``--size`` table (module docstring)."""
    import dataclasses
    import time

    from twinmon.backtest import wilson_interval
    from twinmon.forecast.trendfit import check_trend_fit
    pump = load_config(ROOT / "configs" / "pump.yaml")
    extra = dataclasses.replace(pump.model.inputs["pump_coef"], variable="pump.eta", low=0.0,
                                high=1.0, nominal=0.5, normal_rate=0.0,
                                normal_rate_tolerance=0.01, component="extra")
    site_sd = {"motor_damping": 0.3, "pump_coef": 0.05, "extra": 0.02}
    sigma_med = {"motor_damping": 0.15, "pump_coef": 0.01, "extra": 0.005}
    years = np.arange(1, 11)
    alpha = pump.forecast.trend_fit_alpha
    # Once before the clock: the first call imports scipy's modules.
    check_trend_fit(pump, years, np.zeros((10, 2)), np.repeat(np.eye(2)[None], 10, axis=0),
                    [np.array([1])] * 2, dict(pump.calibrate.shapes))
    print(f"size at alpha {alpha}: {n} histories of 10 years drawn from the model per row")
    print(f"{'inputs':>6s} {'model':14s} {'rejected':>9s} {'90 % interval':>15s} {'ms/unit':>8s}")
    for d in (1, 2, 3):
        inputs = dict(list(pump.model.inputs.items())[:d]) if d < 3 else \
            {**pump.model.inputs, "extra": extra}
        cfg = dataclasses.replace(pump, model=dataclasses.replace(pump.model, inputs=inputs))
        names = cfg.model.input_names
        sd = np.array([site_sd[k] for k in names])
        C = 0.9 * np.outer(sd, sd) + 0.1 * np.diag(sd ** 2)
        cov = np.repeat(C[None], years.size, axis=0)
        fleet = type("Fleet", (), {"median": np.array([sigma_med[k] for k in names]),
                                   "tau": np.full(d, 0.5)})
        for label, priors in (("shapes", dict(pump.calibrate.shapes)), ("line", {"line": 1})):
            rng = np.random.default_rng([seed, d])
            rejected, cpu = 0, 0.0
            for _ in range(n):
                sig = fleet.median * np.exp(fleet.tau * rng.standard_normal(d))
                slope = 0.02 * np.ptp(cfg.model.bounds, axis=1) * rng.uniform(-1, 1, d)
                path = cfg.model.bounds.mean(axis=1) + np.outer(years - 5.5, slope)
                x = path + rng.standard_normal((years.size, d)) * sig + \
                    rng.standard_normal((years.size, d)) @ np.linalg.cholesky(C).T
                t0 = time.process_time()
                fit = check_trend_fit(cfg, years, x, cov, [np.array([1])] * d, priors, fleet)
                cpu += time.process_time() - t0
                rejected += fit.p_value < alpha
            lo, hi = wilson_interval(rejected / n, n)
            print(f"{d:6d} {label:14s} {rejected / n:9.4f} {f'{lo:.4f}-{hi:.4f}':>15s} "
                  f"{1e3 * cpu / n:8.1f}")


def cost(w: Path, tag: str) -> None:
    """CPU time of the gate per unit on a work folder's posterior, as the forecast runs it
    (the sites, the fleet's prior of sigma, the recorded shapes; one BLAS thread)."""
    import time

    from twinmon.calibrate.shapes import shape_summary
    from twinmon.executors import one_blas_thread
    from twinmon.forecast.pooling import _pool_unit, fleet_sigma_prior
    from twinmon.forecast.trendfit import (change_year, check_trend_fit, recorded_shapes,
                                           unit_sites)
    from twinmon.repairs import FoundRepair
    cfg = load_config(w / "bench.yaml")
    path = w / f"post_{tag}.h5"
    post = read_posterior(path)
    fleet = fleet_sigma_prior(cfg, post)
    priors = recorded_shapes(cfg, path)
    times = []
    with one_blas_thread():
        for u in post.units:
            up = post.units[u]
            trend = up.trend or {}
            if fleet is not None and trend:
                trend = _pool_unit(cfg, u, trend, np.asarray(up.samples), fleet)[0]
            cov = np.array([np.cov(s, rowvar=False) for s in np.asarray(up.samples)])
            t0 = time.process_time()
            x, c, starts = unit_sites(cfg, up, cov, trend, [FoundRepair(**r) for r in
                                                            up.found_repairs or ()],
                                      change_year(shape_summary(trend), priors))
            check_trend_fit(cfg, np.asarray(up.years), x, c, starts,
                            priors if "shape" in trend else {"line": 1.0},
                            fleet if trend else None)
            times.append(time.process_time() - t0)
    t = 1e3 * np.array(times[1:])      # the first call imports scipy's modules
    print(f"{w}: the gate's CPU time per unit {t.mean():.1f} ms (median {np.median(t):.1f}, "
          f"max {t.max():.1f}; {t.size} units, one BLAS thread)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workdirs", nargs="*", type=Path)
    ap.add_argument("--size", type=int, default=0, metavar="N")
    ap.add_argument("--tag", default="laplace_flow")
    ap.add_argument("--deviation", action="store_true")
    ap.add_argument("--cost", action="store_true",
                    help="also time the gate per unit on each folder's posterior")
    a = ap.parse_args()
    if a.size:
        size(a.size)
    for w in a.workdirs:
        cfg = load_config(w / "bench.yaml")
        fc = read_forecast(w / f"fc_{a.tag}.h5")
        names = cfg.model.input_names
        rows = {"healthy": [0, 0, 0, 0], "faulty": [0, 0, 0, 0]}
        flagged_units, let_through = [], []
        devs = {}
        if a.deviation:
            truth, post = read_truth(w / "truth.h5"), read_posterior(w / f"post_{a.tag}.h5")
        for u in fc.units:
            uf = fc.units[u]
            kind = "healthy" if u.startswith("H") else "faulty"
            tf = uf.trend_fit
            flag = bool(tf) and tf["p_value"] < cfg.forecast.trend_fit_alpha
            miss = missed(uf)
            r = rows[kind]
            r[0] += 1
            r[1] += flag
            r[2] += flag and miss
            r[3] += (uf.status == "ok") and miss
            if flag:
                flagged_units.append(f"{u}(p={tf['p_value']:.1g}, years {tf['missed_years']}"
                                     f"{', missed' if miss else ''})")
            elif uf.status == "ok" and miss:
                let_through.append(u)
            if a.deviation and kind == "faulty":
                up = post.units[u]
                ty = np.asarray(truth.years[u])
                site = getattr(up, "site", None) or {}
                var = (np.einsum("kii->ki", np.asarray(site["cov"])) if site
                       else np.asarray(up.var))
                sd = np.sqrt(np.median(var, axis=0))
                devs[u] = (max(deviation(ty, np.asarray(truth.inputs[u][n], float), sd[i])
                               for i, n in enumerate(names)), flag, uf.status, miss)
        print(f"{w}: trend_fit_alpha {cfg.forecast.trend_fit_alpha}")
        if a.cost:
            cost(w, a.tag)
        for kind, (n, f, fm, om) in rows.items():
            print(f"  {kind:8s} flagged {f}/{n} = {f / max(n, 1):.3f}; flagged whose forecast "
                  f"missed {fm}; status ok whose forecast missed {om}")
        print("  flagged: " + (", ".join(flagged_units) or "none"))
        print("  ok but missed: " + (", ".join(let_through) or "none"))
        if devs:
            beyond = {u: v for u, v in devs.items() if v[0] > 3}
            got = sum(v[1] for v in beyond.values())
            ok_wrong = [u for u, v in devs.items() if v[2] == "ok" and v[3]]
            print(f"  faulty units deviating > 3 sd from a line or one change: {len(beyond)}; "
                  f"flagged {got}/{len(beyond)} = {got / max(len(beyond), 1):.3f}; "
                  f"left ok with a missed forecast: {ok_wrong or 'none'}")
            for u, (dv, f, st, m) in sorted(devs.items(), key=lambda kv: -kv[1][0]):
                print(f"    {u}: deviation {dv:.1f} sd, flagged {f}, status {st}, "
                      f"missed {m}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
