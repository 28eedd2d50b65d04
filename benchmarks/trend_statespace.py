"""A candidate trend model measured on the prognosis families: a local linear trend on
per-year likelihood summaries, its hyperparameters pooled over the fleet.

Each unit-year is calibrated alone under the design box's uniform prior (the sequential
method's first year), which summarises that year's likelihood by the draws' mean ``m_k`` and
covariance ``P_k``. A Kalman filter then carries each unit's level and slope through the
years: ``level' = level + slope``, ``slope' = slope + drift`` (drift sd ``q`` a year, the
acceleration the trend may take), ``m_k = level_k + jitter_k + error_k`` (jitter sd ``s``,
the true year-to-year variation; error covariance ``P_k``). A recorded replacement restarts
the part's level and slope. ``q`` and ``s`` per input are fitted by maximising the fleet's
summed marginal likelihood (empirical Bayes, as ``forecast.pool_sigma`` pools the joint
method's sd). The future state is the filter's prediction plus the jitter; it runs through
the twin (surrogate inside the box, FMU outside) for P(unsafe) and the failure year.
Detection tests the last filtered slope against normal ageing plus tolerance.

This measures whether such a model could replace the joint method's straight line (cost and
honesty on wear that is not a line); it is not wired into ``twinmon``. Attribution here is
crude (an input's test alone, no ``ambiguous``), so "wrong" is not comparable with the
benchmark's.

Usage: ``python benchmarks/trend_statespace.py [--workdir DIR] [--family F] [--seed S]``;
the fleet is fabricated in ``DIR`` as ``benchmarks/prognosis.py`` makes it (or taken from
there when that script already made it), about a minute on 2 cores.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import yaml
from scipy import optimize, stats

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from families import fleet  # noqa: E402
from twinmon.calibrate import calibrate, read_posterior  # noqa: E402
from twinmon.config import load_config  # noqa: E402
from twinmon.fabricate import fabricate, read_truth  # noqa: E402
from twinmon.forecast import evaluate_twin  # noqa: E402
from twinmon.observations import (Observations, UnitObservations, read_observations,  # noqa: E402
                                  write_observations)
from twinmon.reduce import read_surrogate, reduce  # noqa: E402
from twinmon.safety import Indicator, is_unsafe  # noqa: E402
from twinmon.simulate import simulate  # noqa: E402

HORIZON = 7
SAMPLES = 400


def make_fleet(work: Path, family: str, seed: int) -> None:
    """The family's fleet, its simulations and surrogate in ``work`` (as
    ``benchmarks/prognosis.py`` makes them; kept when already there)."""
    work.mkdir(parents=True, exist_ok=True)
    if (work / "sur.h5").exists():
        return
    units, _ = fleet(seed, family)
    (work / "bench.yaml").write_text(yaml.safe_dump({
        "extends": str(ROOT / "configs" / "pump.yaml"), "reduce": {"channels": ["motor.w"]},
        "fabricate": {"years": 10, "noise_std": 4.0, "record_channels": True,
                      "channel_noise_fraction": 0.01, "truth_variables": ["pump.m_flow"],
                      "seed": seed + 4231, "units": units}}, sort_keys=False))
    cfg = load_config(work / "bench.yaml")
    fabricate(cfg, work / "obs.h5", work / "truth.h5")
    simulate(cfg, work / "sim.h5")
    reduce(cfg, work / "sim.h5", work / "sur.h5")


def year_summaries(cfg, work: Path, obs) -> dict:
    """Per unit, [(year, mean [d], cov [d, d])] of each year calibrated alone."""
    split, post = work / "ss_split.h5", work / "ss_post.h5"
    if not post.exists():
        units = {f"{u}~{y}": UnitObservations(np.array([1]),
                                              {c: v[k:k + 1] for c, v in uo.channels.items()},
                                              dict(uo.noise_std), [])
                 for u, uo in obs.units.items() for k, y in enumerate(uo.years)}
        write_observations(split, Observations(obs.time, units, split, obs.output))
        t0 = time.perf_counter()
        calibrate(cfg, work / "sur.h5", split, post)
        print(f"each unit-year alone: {len(units)} calibrated in {time.perf_counter() - t0:.1f} s")
    p = read_posterior(post)
    out = {}
    for key in p.units:
        u, y = key.rsplit("~", 1)
        s = np.asarray(p.units[key].samples[0], float)
        out.setdefault(u, []).append((int(y), s.mean(0), np.cov(s.T)))
    return {u: sorted(r, key=lambda t: t[0]) for u, r in out.items()}


class LocalLinearTrend:
    """The Kalman filter of one fleet's inputs (d of them)."""

    def __init__(self, cfg):
        names = cfg.model.input_names
        self.d = d = len(names)
        box = cfg.model.bounds
        self.width = box[:, 1] - box[:, 0]
        self.normal = np.array([cfg.model.inputs[n].normal_rate for n in names])
        self.tol = np.array([cfg.model.inputs[n].normal_rate_tolerance for n in names])
        self.comp = [cfg.model.inputs[n].component or n for n in names]
        self.F = np.block([[np.eye(d), np.eye(d)], [np.zeros((d, d)), np.eye(d)]])
        self.H = np.hstack([np.eye(d), np.zeros((d, d))])

    def run(self, rows, q, s2, events=()):
        """Filter one unit: log-likelihood (from the third year), last state and covariance,
        standardised one-step innovations."""
        d, F, H = self.d, self.F, self.H
        y0, m0, _ = rows[0]
        x = np.concatenate([m0, self.normal])
        P = np.diag(np.concatenate([(2 * self.width) ** 2, (self.width / 2) ** 2]))
        Q = np.zeros((2 * d, 2 * d))
        Q[d:, d:] = np.diag(q)
        ll, chi, n_chi, prev = 0.0, 0.0, 0, y0 - 1
        for j, (y, m, Pk) in enumerate(rows):
            for _ in range(y - prev):
                x, P = F @ x, F @ P @ F.T + Q
            prev = y
            for ey, ec in events:
                if ey == y:       # a recorded replacement: the part starts again
                    for i in np.flatnonzero(np.array(self.comp) == ec):
                        for k in (i, d + i):
                            P[k, :] = P[:, k] = 0.0
                        x[i], x[d + i] = m[i], self.normal[i]
                        P[i, i], P[d + i, d + i] = (2 * self.width[i]) ** 2, (2 * self.tol[i]) ** 2
            S = H @ P @ H.T + np.diag(s2) + Pk
            v = m - H @ x
            Si = np.linalg.inv(S)
            if j >= 2:
                ll -= 0.5 * (v @ Si @ v + np.linalg.slogdet(S)[1] + d * np.log(2 * np.pi))
                chi, n_chi = chi + v @ Si @ v, n_chi + d
            K = P @ H.T @ Si
            x, P = x + K @ v, P - K @ S @ K.T
        return ll, x, P, (chi, n_chi)

    def fit(self, summaries, events):
        """Fleet-pooled slope drift and jitter variances [d] each (empirical Bayes)."""
        w2 = self.width ** 2

        def nll(theta):
            q, s2 = np.exp(theta[:self.d]) * w2, np.exp(theta[self.d:]) * w2
            return -sum(self.run(r, q, s2, events[u])[0] for u, r in summaries.items())
        th0 = np.log(np.concatenate([0.1 * (self.tol / self.width) ** 2, 1e-4 * np.ones(self.d)]))
        res = optimize.minimize(nll, th0, method="Nelder-Mead",
                                options={"maxiter": 600, "xatol": 1e-3, "fatol": 1e-3})
        return np.exp(res.x[:self.d]) * w2, np.exp(res.x[self.d:]) * w2

    def predict(self, x, P, q, s2, h):
        """Mean [h, d] and covariance [h, d, d] of the true state 1..h years ahead."""
        d = self.d
        Q = np.zeros((2 * d, 2 * d))
        Q[d:, d:] = np.diag(q)
        mu, cov = [], []
        for _ in range(h):
            x, P = self.F @ x, self.F @ P @ self.F.T + Q
            mu.append(self.H @ x)
            cov.append(self.H @ P @ self.H.T + np.diag(s2))
        return np.array(mu), np.array(cov)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--family", default="linear")
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args()
    work = a.workdir or Path(tempfile.mkdtemp(prefix="twinmon-statespace-"))
    make_fleet(work, a.family, a.seed)
    cfg = load_config(work / "bench.yaml", ["calibrate.method=sequential", "calibrate.channels=[]"])
    names = cfg.model.input_names
    obs = read_observations(work / "obs.h5", cfg.model.output.name)
    truth = read_truth(work / "truth.h5")
    sur = read_surrogate(work / "sur.h5")
    _, kinds = fleet(a.seed, a.family)
    t0 = time.perf_counter()
    summ = year_summaries(cfg, work, obs)
    events = {u: [(e.year, e.component) for e in obs.units[u].events] for u in obs.units}
    llt = LocalLinearTrend(cfg)
    t1 = time.perf_counter()
    q, s2 = llt.fit(summ, events)
    print(f"fleet-pooled slope drift sd {np.sqrt(q)} a year, jitter sd {np.sqrt(s2)} "
          f"({time.perf_counter() - t1:.1f} s)")
    sign = np.array([1 if cfg.model.inputs[n].degrading == "up" else -1 for n in names])
    rng = np.random.default_rng(a.seed)
    X, res = [], {}
    for u, rows in summ.items():
        _, x, P, (chi, n_chi) = llt.run(rows, q, s2, events[u])
        mu, cov = llt.predict(x, P, q, s2, HORIZON)
        z = (sign * x[llt.d:] - (sign * llt.normal + llt.tol)) / np.sqrt(np.diag(P)[llt.d:])
        fut_y = truth.future_years[u][:HORIZON]
        true_x = np.column_stack([truth.future_inputs[u][n][:HORIZON] for n in names])
        res[u] = dict(last=rows[-1][0], mu=mu, cov=cov, rejects=stats.norm.sf(z) < cfg.forecast.alpha,
                      gate=stats.chi2.sf(chi, n_chi) if n_chi else 1.0, true_x=true_x,
                      sl=slice(len(X), len(X) + HORIZON * SAMPLES))
        X.extend(np.concatenate([rng.multivariate_normal(mu[k], cov[k], SAMPLES)
                                 for k in range(HORIZON)]))
        res[u]["tsl"] = slice(len(X), len(X) + len(fut_y))
        X.extend(true_x)
    twin = evaluate_twin(cfg, sur, np.array(X))
    unsafe = is_unsafe(twin.value, cfg.safety, twin.nonphysical)
    print(f"cost: {time.perf_counter() - t0:.1f} s for {sum(map(len, summ.values()))} unit-years "
          "(calibration, filter, twin)")
    ind = Indicator.from_config(cfg)
    with h5py.File(work / "truth.h5") as f:
        tt = f["time"][()]
        clean = {u: f[f"units/{u}/{cfg.model.output.name}_clean"][()] for u in summ}
    score = {k: [] for k in ("detected", "false_alarm", "cover_inputs", "cover_indicator",
                             "fail_within1", "fail50_within1", "gate_flags")}
    soon = []
    for u, r in res.items():
        kind, m = kinds[u]
        val = twin.value[r["sl"]].reshape(HORIZON, SAMPLES)
        pu = unsafe[r["sl"]].reshape(HORIZON, SAMPLES).mean(1)
        tval, tuns = twin.value[r["tsl"]], unsafe[r["tsl"]]
        sd = np.sqrt(np.diagonal(r["cov"], axis1=1, axis2=2))
        n = len(tval)
        lo, hi = r["mu"] - 1.645 * sd, r["mu"] + 1.645 * sd
        score["cover_inputs"] += list(((lo[:n] <= r["true_x"]) & (r["true_x"] <= hi[:n])).ravel())
        q05, q95 = np.nanquantile(val, [0.05, 0.95], axis=1)
        score["cover_indicator"] += list((q05[:n] <= tval) & (tval <= q95[:n]))
        bad = is_unsafe(ind(tt, clean[u]), cfg.safety, None)
        eol = (int(truth.years[u][np.argmax(bad)]) if bad.any()
               else int(truth.future_years[u][np.argmax(tuns)]) if tuns.any() else None)
        first = lambda mask: int(r["last"] + 1 + np.argmax(mask)) if mask.any() else None  # noqa: E731
        if eol is not None and r["last"] < eol <= r["last"] + HORIZON:
            f5, f50 = first(pu > 0.05), first(pu >= 0.5)
            score["fail_within1"].append(f5 is not None and abs(f5 - eol) <= 1)
            score["fail50_within1"].append(f50 is not None and abs(f50 - eol) <= 1)
            if eol <= r["last"] + 3:
                soon.append(pu.max() < 0.05 and r["gate"] >= 0.01)
        flagged = bool(r["rejects"].any())
        if kind == "healthy":
            score["false_alarm"].append(flagged)
        elif m >= 2:
            score["detected"].append(flagged)
        score["gate_flags"].append(r["gate"] < 0.01)
    print(f"{a.family} seed {a.seed} (targets: detect >= 0.95, false alarm <= 0.05, coverage "
          "0.85-0.95, failure year +-1 >= 0.85-0.90, no unit failing within 3 years missed)")
    for k, v in score.items():
        print(f"  {k:16s} {np.mean(v) if v else float('nan'):.3f}  ({int(np.sum(v))}/{len(v)})")
    print(f"  {'soon_missed':16s} {int(np.sum(soon))}/{len(soon)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
