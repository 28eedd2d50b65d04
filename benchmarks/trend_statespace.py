"""Candidate trend models measured on the prognosis families: per unit, an average over a
local linear trend, an accelerating trend and a step, on per-year likelihood summaries, their
variances pooled over the fleet.

Each unit-year is calibrated alone under the design box's uniform prior (the sequential
method's first year), which summarises that year's likelihood by the draws' mean ``m_k`` and
covariance ``P_k``. Kalman filters then carry each unit's inputs through the years, with
``m_k = level_k + jitter_k + error_k`` (jitter sd ``s``, the true year-to-year variation;
error covariance ``P_k``), under three trend models:

* ``llt``, the local linear trend: ``level' = level + slope``, ``slope' = slope + drift``
  (drift sd ``q`` a year);
* ``acc``, the same plus an acceleration: ``level' = level + slope + acc / 2``,
  ``slope' = slope + acc + drift``, ``acc' = acc + acc drift``, the acceleration's prior sd
  ``a`` at the first year and its drift sd ``q3`` a year;
* ``step``, the local linear trend plus one jump of the level (sd ``j``) and of the slope
  (sd ``js``) in one year after the first, each such year equally likely; in the future it
  expects further jumps at that rate (one per record), their variance added to each year's.

A recorded replacement restarts the part's level and slope (its acceleration back to 0). The variances per
input are fitted by empirical Bayes (as ``forecast.pool_sigma`` pools the joint method's sd):
``q`` and ``s`` by maximising the fleet's summed marginal likelihood under the local linear
trend alone, so that on straight lines the average stays that model; then ``a``, ``q3``,
``j`` and ``js`` by maximising the fleet's summed likelihood of the mixture. A unit's models
are weighted by prior (0.6 on the straight line, 0.2 on each other) times the likelihood of
their one-step-ahead predictions from the unit's third year. The future state is drawn from
the mixture (each model's share of the draws its weight), so the intervals carry the shape's
uncertainty; it runs through the twin (surrogate inside the box, FMU outside) for P(unsafe)
and the failure year.

Detection (``detected``, ``false_alarm``) tests, under the mixture, whether an input wore
more over its record (last level minus first, or since a recorded replacement) than normal
ageing plus tolerance would; ``detected_slope`` and ``false_alarm_slope`` test the last
slope instead. ``--models llt`` is the local linear trend alone.

This measures whether such a model could replace the joint method's straight line (cost and
honesty on wear that is not a line); it is not wired into ``twinmon``. Attribution here is
crude (an input's test alone, no ``ambiguous``), so "wrong" is not comparable with the
benchmark's.

Usage: ``python benchmarks/trend_statespace.py [--workdir DIR] [--family F] [--seed S]
[--models llt,acc,step]``; the fleet is fabricated in ``DIR`` as ``benchmarks/prognosis.py``
makes it (or taken from there when that script already made it), about a minute on 2 cores.
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


#: The trend models averaged per unit, and their prior weights (the straight line first).
MODELS = ("llt", "acc", "step")
PRIOR = {"llt": 0.6, "acc": 0.2, "step": 0.2}
#: Each model's fleet-pooled variances (per input, relative to the box width squared).
HYPER = {"llt": ("q", "s2"), "acc": ("a2", "q3"), "step": ("j2", "js2")}


class TrendModels:
    """Kalman filters of one fleet's inputs (d of them) under several trend models, run as
    one batch of tracks (a unit under a model; a step model's track per candidate year).

    The state is ``[level, slope, acceleration, anchor]`` (d each): ``level' = level + slope
    + acc / 2``, ``slope' = slope + acc + drift`` (sd ``q``), ``acc' = acc + acc drift`` (sd
    ``q3``), ``anchor`` the level at the first year (or at a recorded replacement), kept to
    test the wear over the record. Observation: ``m_k = level_k + jitter_k + error_k``.

    * ``llt``: the local linear trend (acceleration 0);
    * ``acc``: acceleration with prior sd ``a`` at the first year, drifting (sd ``q3``);
    * ``step``: the local linear trend plus, at one year ``tau`` after the first (uniform
      prior over the unit's years), a level jump (sd ``j``) and a slope jump (sd ``js``).
    """

    def __init__(self, cfg, models=MODELS):
        names = cfg.model.input_names
        self.d = d = len(names)
        box = cfg.model.bounds
        self.width = box[:, 1] - box[:, 0]
        self.normal = np.array([cfg.model.inputs[n].normal_rate for n in names])
        self.tol = np.array([cfg.model.inputs[n].normal_rate_tolerance for n in names])
        self.sign = np.array([1 if cfg.model.inputs[n].degrading == "up" else -1 for n in names])
        self.comp = np.array([cfg.model.inputs[n].component or n for n in names])
        self.models = tuple(models)
        self.hyper = [h for m in self.models for h in HYPER[m]]
        n = 4 * d
        I, Z = np.eye(d), np.zeros((d, d))
        self.F = np.block([[I, I, I / 2, Z], [Z, I, I, Z], [Z, Z, I, Z], [Z, Z, Z, I]])
        self.H = np.hstack([I, Z, Z, Z])
        self.L, self.S, self.A, self.N = (slice(k * d, (k + 1) * d) for k in range(4))
        self.n = n

    def tracks(self, summaries, events):
        """The batch: per track its unit, model and step year; the units' observations on a
        common year grid."""
        units = list(summaries)
        y_lo = min(r[0][0] for r in summaries.values())
        y_hi = max(r[-1][0] for r in summaries.values())
        years = np.arange(y_lo, y_hi + 1)
        U, T, d = len(units), len(years), self.d
        m = np.zeros((U, T, d))
        Pk = np.tile(np.eye(d), (U, T, 1, 1))
        seen = np.zeros((U, T), bool)
        for i, u in enumerate(units):
            for y, mk, Pkk in summaries[u]:
                t = y - y_lo
                m[i, t], Pk[i, t], seen[i, t] = mk, np.atleast_2d(Pkk), True
        unit, model, tau = [], [], []
        for i, u in enumerate(units):
            ys = [r[0] for r in summaries[u]]
            for mod in self.models:
                for t in (ys[1:] if mod == "step" else [None]):
                    unit.append(i), model.append(mod), tau.append(-1 if t is None else t - y_lo)
        unit, tau = np.array(unit), np.array(tau)
        model = np.array(model)
        # Each track's prior weight: the model's, a step model's shared by its years.
        n_tau = np.array([np.sum((unit == unit[b]) & (model == "step")) for b in range(len(unit))])
        prior = np.array([PRIOR[mo] / (n_tau[b] if mo == "step" else 1) for b, mo in enumerate(model)])
        prior /= np.array([sum(PRIOR[mo] for mo in self.models)])
        ev = {}
        for i, u in enumerate(units):
            for ey, ec in events.get(u, ()):
                ev.setdefault(ey - y_lo, []).append((i, ec))
        return dict(units=units, years=years, m=m, Pk=Pk, seen=seen, unit=unit, model=model,
                    tau=tau, n_tau=n_tau, logprior=np.log(prior), events=ev)

    def variances(self, theta):
        w2 = self.width ** 2
        v = {h: np.exp(theta[k * self.d:(k + 1) * self.d]) * w2 for k, h in enumerate(self.hyper)}
        for h in ("q", "s2", "a2", "q3", "j2", "js2"):
            v.setdefault(h, np.zeros(self.d))
        return v

    def run(self, tr, theta):
        """Filter every track: log-likelihood of the one-step predictions from a unit's third
        year, last state [B, n] and covariance [B, n, n], chi-square of the standardised
        innovations and its degrees of freedom."""
        v = self.variances(theta)
        d, n, F, H = self.d, self.n, self.F, self.H
        L, S, A, N = self.L, self.S, self.A, self.N
        unit, model, tau = tr["unit"], tr["model"], tr["tau"]
        B = len(unit)
        seen, m, Pk = tr["seen"][unit], tr["m"][unit], tr["Pk"][unit]
        T = seen.shape[1]
        first = np.argmax(seen, axis=1)
        last = T - 1 - np.argmax(seen[:, ::-1], axis=1)
        Qb = np.zeros((B, n, n))
        Qb[:, S, S] = np.diag(v["q"])
        acc = model == "acc"
        Qb[np.ix_(acc, range(2 * d, 3 * d), range(2 * d, 3 * d))] = np.diag(v["q3"])
        Qj = np.zeros((n, n))
        Qj[L, L], Qj[S, S] = np.diag(v["j2"]), np.diag(v["js2"])
        x = np.zeros((B, n))
        P = np.zeros((B, n, n))
        x0 = m[np.arange(B), first]
        x[:, L], x[:, S], x[:, N] = x0, self.normal, x0
        big = np.diag((2 * self.width) ** 2)
        P[:, L, L] = P[:, N, N] = P[:, L, N] = P[:, N, L] = big
        P[:, S, S] = np.diag((self.width / 2) ** 2)
        P[np.ix_(acc, range(2 * d, 3 * d), range(2 * d, 3 * d))] = np.diag(v["a2"])
        ll, chi, nchi = np.zeros(B), np.zeros(B), np.zeros(B)
        count = np.zeros(B, int)
        Js2 = np.diag(v["s2"])
        for t in range(T):
            go = (t > first) & (t <= last)
            xn = x @ F.T
            Pn = F @ P @ F.T + Qb + (tau == t)[:, None, None] * Qj
            x = np.where(go[:, None], xn, x)
            P = np.where(go[:, None, None], Pn, P)
            for i, ec in tr["events"].get(t, ()):
                for b in np.flatnonzero(unit == i):
                    self._replace(x[b], P[b], m[b, t], ec)
            ob = seen[:, t]
            Sk = P[:, L, L] + Js2 + Pk[:, t]
            vk = m[:, t] - x[:, L]
            Si = np.linalg.inv(Sk)
            q = np.einsum("bi,bij,bj->b", vk, Si, vk)
            score = ob & (count >= 2)
            ll -= np.where(score, 0.5 * (q + np.linalg.slogdet(Sk)[1] + d * np.log(2 * np.pi)), 0)
            chi += np.where(score, q, 0)
            nchi += np.where(score, d, 0)
            K = P[:, :, L] @ Si
            x = np.where(ob[:, None], x + np.einsum("bij,bj->bi", K, vk), x)
            P = np.where(ob[:, None, None], P - K @ Sk @ np.swapaxes(K, 1, 2), P)
            count += ob
        return ll, x, P, chi, nchi

    def _replace(self, x, P, m, ec):
        """A recorded replacement: the part's level, slope and anchor start again."""
        d = self.d
        for i in np.flatnonzero(self.comp == ec):
            for k in (i, d + i, 2 * d + i, 3 * d + i):
                P[k, :] = P[:, k] = 0.0
            x[i] = x[3 * d + i] = m[i]
            x[d + i], x[2 * d + i] = self.normal[i], 0.0
            P[i, i] = P[3 * d + i, 3 * d + i] = P[i, 3 * d + i] = P[3 * d + i, i] = (2 * self.width[i]) ** 2
            P[d + i, d + i] = (2 * self.tol[i]) ** 2

    def unit_loglik(self, tr, ll):
        """Per unit, log of the prior-weighted predictive likelihood summed over its tracks."""
        lp = tr["logprior"] + ll
        out = np.full(len(tr["units"]), -np.inf)
        np.logaddexp.at(out, tr["unit"], lp)
        return out

    def fit(self, tr):
        """Fleet-pooled variances (empirical Bayes): maximise the fleet's summed log
        marginal likelihood of the model mixture."""
        d = self.d
        start = {"q": 0.1 * (self.tol / self.width) ** 2, "s2": 1e-4 * np.ones(d),
                 "a2": 0.1 * (self.tol / self.width) ** 2, "q3": 0.01 * (self.tol / self.width) ** 2,
                 "j2": 1e-2 * np.ones(d), "js2": (self.tol / self.width) ** 2}
        th0 = np.log(np.concatenate([start[h] for h in self.hyper]))
        fixed = 0
        if self.models != ("llt",) and "llt" in self.models:
            # The straight line's variances first, from its own fit (the special case stays
            # the local linear trend alone); the other models' then, by the mixture.
            llt = TrendModels.__new__(TrendModels)
            llt.__dict__.update(self.__dict__, models=("llt",), hyper=list(HYPER["llt"]))
            sub = {k: (v[tr["model"] == "llt"] if isinstance(v, np.ndarray) and k in
                       ("unit", "model", "tau", "n_tau", "logprior") else v) for k, v in tr.items()}
            sub["logprior"] = np.zeros(int(np.sum(tr["model"] == "llt")))
            th_llt, _ = llt.fit(sub)
            fixed = len(th_llt)
            th0[:fixed] = th_llt

        def nll(free):
            theta = np.clip(np.concatenate([th0[:fixed], free]), -40, 5)
            return -self.unit_loglik(tr, self.run(tr, theta)[0]).sum()
        res = optimize.minimize(nll, th0[fixed:], method="Nelder-Mead",
                                options={"maxiter": 300 * len(th0), "xatol": 1e-3, "fatol": 1e-3})
        return np.clip(np.concatenate([th0[:fixed], res.x]), -40, 5), res

    def predict(self, x, P, theta, h, tr):
        """Mean [B, h, d] and covariance [B, h, d, d] of the true state 1..h years ahead. A
        step model expects further steps at the rate of its prior (one in the unit's record):
        their variance is added to each year's (moment-matched)."""
        v = self.variances(theta)
        d = self.d
        Q = np.zeros((len(x), self.n, self.n))
        Q[:, self.S, self.S] = np.diag(v["q"])
        Q[np.ix_(tr["model"] == "acc", range(2 * d, 3 * d), range(2 * d, 3 * d))] = np.diag(v["q3"])
        step = tr["model"] == "step"
        Qj = np.zeros((self.n, self.n))
        Qj[self.L, self.L], Qj[self.S, self.S] = np.diag(v["j2"]), np.diag(v["js2"])
        Q[step] += Qj / tr["n_tau"][step, None, None]
        mu, cov = [], []
        for _ in range(h):
            x, P = x @ self.F.T, self.F @ P @ self.F.T + Q
            mu.append(x[:, self.L])
            cov.append(P[:, self.L, self.L] + np.diag(v["s2"]))
        return np.stack(mu, 1), np.stack(cov, 1)


def mixture_quantile(w, mu, sd, p, iters=60):
    """Quantile ``p`` of the mixture sum_c w_c N(mu_c, sd_c^2), elementwise over mu's
    trailing axes (components first)."""
    wb = w.reshape((-1,) + (1,) * (mu.ndim - 1))
    lo, hi = (mu - 6 * sd).min(0), (mu + 6 * sd).max(0)
    for _ in range(iters):
        mid = (lo + hi) / 2
        below = (wb * stats.norm.cdf((mid - mu) / np.maximum(sd, 1e-300))).sum(0) < p
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return (lo + hi) / 2


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--family", default="linear")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--models", default=",".join(MODELS),
                    help=f"trend models averaged, of {','.join(MODELS)} (llt alone: the local "
                         "linear trend without averaging)")
    a = ap.parse_args()
    models = tuple(a.models.split(","))
    if not models or set(models) - set(MODELS):
        raise SystemExit(f"--models {a.models!r}: a comma-separated subset of {','.join(MODELS)}")
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
    tm = TrendModels(cfg, models)
    tr = tm.tracks(summ, events)
    t1 = time.perf_counter()
    theta, _ = tm.fit(tr)
    v = tm.variances(theta)
    print(f"models {','.join(models)}: fleet-pooled sd per input "
          + ", ".join(f"{h} {np.array2string(np.sqrt(v[h]), precision=4)}" for h in tm.hyper)
          + f" ({time.perf_counter() - t1:.1f} s, {len(tr['unit'])} tracks)")
    ll, x, P, chi, nchi = tm.run(tr, theta)
    mu, cov = tm.predict(x, P, theta, HORIZON, tr)
    w = np.exp(tr["logprior"] + ll - tm.unit_loglik(tr, ll)[tr["unit"]])
    d, S, L, N = tm.d, tm.S, tm.L, tm.N
    sign, normal, tol = tm.sign, tm.normal, tm.tol
    # Per track: P(the input wears no faster than normal ageing plus tolerance), by its
    # current slope, and by the wear over the record (level minus anchor, since the first
    # year or a recorded replacement).
    sd_s = np.sqrt(np.diagonal(P[:, S, S], axis1=1, axis2=2))
    p_slope = stats.norm.cdf(((sign * normal + tol) - sign * x[:, S]) / sd_s)
    span = np.zeros((len(x), d))
    for b, i in enumerate(tr["unit"]):
        u = tr["units"][i]
        for k in range(d):
            start = max([summ[u][0][0]] + [ey for ey, ec in events[u] if ec == tm.comp[k]])
            span[b, k] = summ[u][-1][0] - start
    dP = (np.diagonal(P[:, L, L], axis1=1, axis2=2) + np.diagonal(P[:, N, N], axis1=1, axis2=2)
          - 2 * np.diagonal(P[:, L, N], axis1=1, axis2=2))
    p_wear = stats.norm.cdf(((sign * normal + tol) * span - sign * (x[:, L] - x[:, N]))
                            / np.sqrt(np.maximum(dP, 1e-300)))
    rng = np.random.default_rng(a.seed)
    X, res = [], {}
    share = {}
    for ui, u in enumerate(tr["units"]):
        rows = summ[u]
        c = np.flatnonzero(tr["unit"] == ui)
        wc = w[c] / w[c].sum()
        for mo in models:
            share.setdefault((kinds[u][0] == "healthy", mo), []).append(wc[tr["model"][c] == mo].sum())
        top = c[np.argmax(wc)]
        wm = {mo: round(float(wc[tr["model"][c] == mo].sum()), 2) for mo in models}
        sd = np.sqrt(np.diagonal(cov[c], axis1=2, axis2=3))
        fut_y = truth.future_years[u][:HORIZON]
        true_x = np.column_stack([truth.future_inputs[u][n][:HORIZON] for n in names])
        res[u] = dict(last=rows[-1][0], lo=mixture_quantile(wc, mu[c], sd, 0.05),
                      hi=mixture_quantile(wc, mu[c], sd, 0.95),
                      rejects=(wc @ p_wear[c]) < cfg.forecast.alpha,
                      rejects_slope=(wc @ p_slope[c]) < cfg.forecast.alpha,
                      gate=stats.chi2.sf(chi[top], nchi[top]) if nchi[top] else 1.0,
                      true_x=true_x, wm=wm, sl=slice(len(X), len(X) + HORIZON * SAMPLES))
        pick = (rng.choice(len(c), size=(HORIZON, SAMPLES), p=wc) if len(c) > 1
                else np.zeros((HORIZON, SAMPLES), int))
        for k in range(HORIZON):
            X.extend(np.concatenate([rng.multivariate_normal(mu[c[j], k], cov[c[j], k], np.sum(pick[k] == j))
                                     for j in np.unique(pick[k])]))
        res[u]["tsl"] = slice(len(X), len(X) + len(fut_y))
        X.extend(true_x)
    twin = evaluate_twin(cfg, sur, np.array(X))
    unsafe = is_unsafe(twin.value, cfg.safety, twin.nonphysical)
    print(f"cost: {time.perf_counter() - t0:.1f} s for {sum(map(len, summ.values()))} unit-years "
          "(calibration, filter, twin)")
    print("mean posterior model weight, healthy / faulty units: " + ", ".join(
        f"{mo} {np.mean(share[(True, mo)]):.2f} / {np.mean(share.get((False, mo), [np.nan])):.2f}"
        for mo in models))
    ind = Indicator.from_config(cfg)
    with h5py.File(work / "truth.h5") as f:
        tt = f["time"][()]
        clean = {u: f[f"units/{u}/{cfg.model.output.name}_clean"][()] for u in summ}
    score = {k: [] for k in ("detected", "false_alarm", "detected_slope", "false_alarm_slope",
                             "cover_inputs", "cover_indicator", "fail_within1", "fail50_within1",
                             "gate_flags")}
    soon = []
    for u, r in res.items():
        kind, m = kinds[u]
        val = twin.value[r["sl"]].reshape(HORIZON, SAMPLES)
        pu = unsafe[r["sl"]].reshape(HORIZON, SAMPLES).mean(1)
        tval, tuns = twin.value[r["tsl"]], unsafe[r["tsl"]]
        n = len(tval)
        lo, hi = r["lo"], r["hi"]
        score["cover_inputs"] += list(((lo[:n] <= r["true_x"]) & (r["true_x"] <= hi[:n])).ravel())
        # As the forecast's indicator quantiles: a failed run is an unreached level (inf),
        # and the empirical quantile never interpolates between two infinities.
        q05, q95 = np.quantile(np.where(np.isnan(val), np.inf, val), [0.05, 0.95], axis=1,
                               method="inverted_cdf")
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
        for sfx, key in (("", "rejects"), ("_slope", "rejects_slope")):
            flagged = bool(r[key].any())
            if kind == "healthy":
                score["false_alarm" + sfx].append(flagged)
            elif m >= 2:
                score["detected" + sfx].append(flagged)
        score["gate_flags"].append(r["gate"] < 0.01)
    print(f"{a.family} seed {a.seed}, models {','.join(models)} (targets: detect >= 0.95, false "
          "alarm <= 0.05, coverage 0.85-0.95, failure year +-1 >= 0.85-0.90, no unit failing "
          "within 3 years missed)")
    for k, v in score.items():
        print(f"  {k:17s} {np.mean(v) if v else float('nan'):.3f}  ({int(np.sum(v))}/{len(v)})")
    print(f"  {'soon_missed':17s} {int(np.sum(soon))}/{len(soon)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
