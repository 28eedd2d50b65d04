"""Blind benchmark of ``twinmon diagnose``: random withheld effects, scored against the truth.

Each case is one fabricated unit (random degradation trajectory, random candidate effect
and magnitude, random onset year, its own noise); null cases carry no effect, out-of-list
cases an additive disturbance. All cases of a run share one observations file (one unit per
case), diagnosed exactly as ``twinmon diagnose`` does; only this script reads the truth.

The gap of a case is the RMS, in noise standard deviations, of (flow with the effect - flow
of the same unit without it) over its worst config window and its affected years. The
targets are measured on cases whose gap is at least 3.

Usage: ``python benchmarks/gap_blind.py [--cases 60] [--nulls 20] [--out-of-list 10]
[--years 8] [--seed 7] [--workers 2]``

``--pairs N`` runs the two-effect benchmark instead: N units per machine (the pump,
configs/fleet_gap.yaml, and the DC drive, configs/dcdrive_gap.yaml) each with two withheld
effects -- transient + plateau, transient + transient, plateau + plateau in turn, onsets
coinciding in every other case and a year or two apart in the others -- plus ``--nulls``
clean units per machine (see :func:`pair_main`). The DC drive's cases are run twice: on its
speed alone ("dcdrive") and with its armature current recorded too ("dcdrive+current");
each set-up is scored on its own. Tuning seeds: 1 to 4 (the method was changed after looking
at their misses); held-out seeds: 5 and 6 (run once the code was fixed, never tuned on).
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

from twinmon.config import config_from_mapping, load_config  # noqa: E402
from twinmon.diagnose import diagnose  # noqa: E402
from twinmon.config import Disturbance  # noqa: E402
from twinmon.fabricate import disturbance_signal, fabricate, read_truth  # noqa: E402
from twinmon.errors import SimulationError  # noqa: E402
from twinmon.fmu import FMUModel, resolve_fmu  # noqa: E402

#: Effects whose flow signature is distinct (the transient-type effects of docs/model.md);
#: the plateau-type ones look alike on the flow channel alone.
FLOW_SEPARABLE = ("sensor.tau", "valve.opening_time", "motor.start_delay")


def _window_gap(cfg, delta_sigma: np.ndarray) -> float:
    """Max over windows of the RMS of [years, time] deltas (noise units)."""
    t = cfg.model.output.times.times
    best = 0.0
    for w in cfg.diagnose_windows().values():
        m = (t >= w.start) & (t < w.stop)
        if m.any():
            best = max(best, float(np.sqrt(np.mean(delta_sigma[:, m] ** 2))))
    return best


def _gap_at(cfg, model, nominal, name, value, var, base, sigma) -> float:
    """Gap (noise units) of effect ``name`` at ``value`` on a nominal unit; 0 where the FMU
    fails (the DC drive's supply delay on a sample instant, e.g. 0.2 s)."""
    try:
        out = model.run({**nominal, name: value})[var]
    except SimulationError:
        return 0.0
    return _window_gap(cfg, ((out - base) / sigma)[None])


def min_magnitudes(cfg, model, sigma: float, target: float = 3.0) -> dict:
    """Per effect, the value (on each side of the baseline) whose gap at nominal inputs is
    ``target`` noise standard deviations; None if the range never gets there."""
    nominal = {s.variable: s.nominal for s in cfg.model.inputs.values()}
    var = cfg.model.output.variable
    base = model.run(nominal)[var]
    out = {}
    for name, e in cfg.model.effects.items():
        sides = []
        for end in (e.high, e.low):
            if end == e.baseline:
                continue
            vals = e.baseline + np.linspace(0, 1, 101)[1:] * (end - e.baseline)
            gaps = [_gap_at(cfg, model, nominal, name, v, var, base, sigma) for v in vals]
            ok = np.flatnonzero(np.array(gaps) >= target)
            if ok.size:
                sides.append((vals[ok[0]], end))
        out[name] = sides
    return out


def build_cases(cfg, rng, n_cases, n_nulls, n_ool, years, mags):
    units, labels = {}, {}
    effects = [n for n in cfg.model.effects if mags[n]]
    for i in range(n_cases + n_nulls + n_ool):
        u = f"case{i:03d}"
        spec = {"trajectories": {
            "motor_damping": {"start": float(rng.uniform(9.0, 11.0)),
                              "slope": float(rng.uniform(0.0, 0.8)), "jitter": 0.15},
            "pump_coef": {"start": float(rng.uniform(3.5, 3.8)),
                          "slope": float(rng.uniform(-0.06, -0.01)), "jitter": 0.01}}}
        onset = int(rng.integers(2, years))
        if i < n_cases:
            name = effects[i % len(effects)]
            lo, end = mags[name][int(rng.integers(len(mags[name])))]
            value = float(lo + rng.uniform(0, 1) * (end - lo))
            spec["effects"] = {name: {"value": value, "onset": onset}}
            labels[u] = ("effect", name)
        elif i < n_cases + n_nulls:
            labels[u] = ("none", None)
        else:
            shape = "sine" if rng.uniform() < 0.5 else "bump"
            spec["disturbance"] = {"amplitude": float(rng.uniform(12.0, 24.0)),
                                   "period": float(rng.uniform(5.0, 12.0)),
                                   "onset": onset, "shape": shape}
            labels[u] = ("out-of-list", shape)
        units[u] = spec
    return units, labels


def main(argv=None):
    if argv is None and "--pairs" in sys.argv:
        return pair_main(sys.argv[1:])
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog="--pairs N: two withheld effects at once instead, N pair units per machine "
               "(its own options: gap_blind.py --pairs 24 --help)")
    ap.add_argument("--cases", type=int, default=63, help="effect cases (9 per candidate)")
    ap.add_argument("--nulls", type=int, default=20)
    ap.add_argument("--out-of-list", type=int, default=10)
    ap.add_argument("--years", type=int, default=8)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("-v", "--verbose", action="count", default=0,
                    help="list the cases missed (-vv: every case)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "fleet_gap.yaml"))
    ap.add_argument("--noise-unrecorded", action="store_true",
                    help="observations without their noise level (and no "
                         "calibrate.noise_std): diagnose estimates it from the data")
    args = ap.parse_args(argv)

    base = load_config(args.config)
    raw = copy.deepcopy(dict(base.raw))
    sigma = base.fabricate.noise_std          # output units (configs/fleet_gap.yaml: 4 kg/s)
    fmu = resolve_fmu(base.model.fmu)
    t = base.model.output.times.times
    with FMUModel(fmu, ["sensor.m_flow"], t) as model:
        mags = min_magnitudes(base, model, sigma)
    rng = np.random.default_rng(args.seed)
    units, labels = build_cases(base, rng, args.cases, args.nulls, args.out_of_list,
                                args.years, mags)
    raw["fabricate"] = {"years": args.years, "noise_std": sigma,
                        "seed": int(rng.integers(1 << 30)), "units": units,
                        "record_noise": not args.noise_unrecorded}
    if args.noise_unrecorded:
        raw.setdefault("calibrate", {})["noise_std"] = None
    cfg = config_from_mapping(raw, Path(args.config))

    with tempfile.TemporaryDirectory(prefix="gap-blind-") as tmp:
        obs, truth_path = Path(tmp) / "obs.h5", Path(tmp) / "truth.h5"
        fabricate(cfg, obs, truth_path)
        t0 = time.perf_counter()
        summary = diagnose(cfg, obs, Path(tmp) / "gap.h5", workers=args.workers)
        wall = time.perf_counter() - t0
        truth = read_truth(truth_path)          # only the scorer reads it
        gaps = case_gaps(cfg, fmu, truth, sigma)

        # Timing target: 3 units x 10 years x 7 candidates.
        cfg3 = load_config(args.config)
        obs3 = Path(tmp) / "fleet3.h5"
        fabricate(cfg3, obs3, Path(tmp) / "fleet3_truth.h5")
        t1 = time.perf_counter()
        diagnose(cfg3, obs3, Path(tmp) / "gap3.h5", workers=args.workers)
        wall3 = time.perf_counter() - t1

    report(cfg, summary, labels, gaps, wall, wall3, args, mags)


def case_gaps(cfg, fmu, truth, sigma) -> dict:
    """Gap (noise units, worst window, affected years) of each effect case, from the truth."""
    t = cfg.model.output.times.times
    out = {}
    with FMUModel(fmu, ["sensor.m_flow"], t) as model:
        for u, eff in truth.effects.items():
            if not eff:
                continue
            on = np.all([np.isfinite(v) for v in eff.values()], axis=0)
            clean = []
            for k in np.flatnonzero(on):
                p = {cfg.model.inputs[n].variable: float(v[k]) for n, v in truth.inputs[u].items()}
                clean.append(model.run(p)["sensor.m_flow"])
            # m_flow_clean is not in Truth: rebuild the with-effect run too.
            with_eff = []
            for k in np.flatnonzero(on):
                p = {cfg.model.inputs[n].variable: float(v[k]) for n, v in truth.inputs[u].items()}
                p.update({n: float(v[k]) for n, v in eff.items()})
                with_eff.append(model.run(p)["sensor.m_flow"])
            out[u] = _window_gap(cfg, (np.array(with_eff) - np.array(clean)) / sigma)
    for u, d in truth.disturbance.items():
        sig = disturbance_signal(Disturbance(**d), t)
        out[u] = _window_gap(cfg, sig[None] / sigma)
    return out


def report(cfg, summary, labels, gaps, wall, wall3, args, mags):
    names = list(cfg.model.effects)
    cols = names + ["none", "unexplained"]
    conf = {n: {c: 0 for c in cols} for n in names + ["none"]}
    top1 = {n: [0, 0] for n in names}
    in_group, group_sizes, closed, detected, n_eff = 0, [], [], 0, 0
    below = []
    for u, (kind, name) in labels.items():
        g = summary.units[u]
        if kind != "effect":
            continue
        if gaps[u] < 3.0:
            below.append(u)
            continue
        n_eff += 1
        pred = g.effects[0] if g.verdict == "effect" else g.verdict
        conf[name][pred] += 1
        top1[name][1] += 1
        top1[name][0] += int(pred == name)
        detected += int(g.verdict != "none")
        if g.verdict == "effect":
            group_sizes.append(len(g.group))
            in_group += int(name in g.effects)
            if name in g.effects:
                closed.append(g.closed_percent)
    nulls = [u for u, (k, _) in labels.items() if k == "none"]
    for u in nulls:
        g = summary.units[u]
        conf["none"][g.effects[0] if g.verdict == "effect" else g.verdict] += 1
    false_alarms = sum(summary.units[u].verdict != "none" for u in nulls)
    ool = [u for u, (k, _) in labels.items() if k == "out-of-list"]

    print(f"gap_blind: {n_eff} effect cases with gap >= 3 sigma ({len(below)} below, "
          f"excluded), {len(nulls)} null, {len(ool)} out-of-list; {args.years} years each, "
          f"onset years 2..{args.years - 1}, noise 1 % of nominal, seed {args.seed}"
          + (", noise level not recorded (estimated)" if args.noise_unrecorded else ""))
    print("smallest magnitude with a 3-sigma gap at nominal inputs: " + ", ".join(
        f"{n} {'/'.join(f'{lo:.3g}' for lo, _ in s)}" for n, s in mags.items() if s))
    w = max(len(c) for c in cols)
    print("\nconfusion matrix (rows: truth; columns: verdict's first effect, or none/unexplained)")
    print(" " * (w + 2) + " ".join(f"{i:>4d}" for i in range(len(cols))))
    for r in names + ["none"]:
        print(f"{r:>{w}}  " + " ".join(f"{conf[r][c]:>4d}" for c in cols))
    print("columns: " + ", ".join(f"{i}={c}" for i, c in enumerate(cols)))

    def pct(a, b):
        return f"{100 * a / b:.1f} % ({a}/{b})" if b else "n/a"
    sep_hits = sum(top1[n][0] for n in FLOW_SEPARABLE)
    sep_n = sum(top1[n][1] for n in FLOW_SEPARABLE)
    print(f"\ndetection (verdict != none)             : {pct(detected, n_eff)}   target >= 95 %")
    print(f"true effect inside the reported group   : {pct(in_group, n_eff)}   target >= 95 %")
    print(f"top-1 accuracy, all effects             : {pct(sum(v[0] for v in top1.values()), n_eff)}")
    print(f"top-1 accuracy, flow-separable effects  : {pct(sep_hits, sep_n)}   target >= 80 %"
          f"   ({', '.join(FLOW_SEPARABLE)})")
    for n in names:
        print(f"    top-1 {n:<20s}: {pct(*top1[n])}")
    print(f"mean group size                         : "
          f"{np.mean(group_sizes) if group_sizes else float('nan'):.2f}")
    print(f"false alarms on null cases              : {pct(false_alarms, len(nulls))}   target <= 5 %")
    print(f"mean % of excess gap closed (true effect found): "
          f"{np.mean(closed) if closed else float('nan'):.1f} %   target >= 90 %"
          f"   (min {np.min(closed) if closed else float('nan'):.1f} %)")
    v_ool = [summary.units[u].verdict for u in ool if gaps[u] >= 3.0]
    print(f"out-of-list disturbances, gap >= 3 sigma: " + ", ".join(
        f"{v} {v_ool.count(v)}" for v in ("unexplained", "effect", "none"))
        + f"   ({sum(gaps[u] < 3.0 for u in ool)} below 3 sigma excluded)")
    if closed_ool := [summary.units[u].closed_percent for u in ool
                      if gaps[u] >= 3.0 and summary.units[u].verdict == "effect"]:
        print(f"    closed % when an effect was (wrongly) accepted: "
              + ", ".join(f"{c:.0f}" for c in closed_ool))
    if args.verbose:
        for u, (kind, name) in labels.items():
            g = summary.units[u]
            ok = (kind == "effect" and name in g.effects) or (kind == "none" and g.verdict == "none") \
                or (kind == "out-of-list" and g.verdict == "unexplained")
            if not ok or args.verbose > 1:
                print(f"  {u} truth {kind} {name or ''} gap {gaps.get(u, float('nan')):.1f}: "
                      f"{g.verdict} {g.effects} onset {g.onset} p_gap {g.p_gap:.2g} "
                      f"rms {g.rms_before:.2f}->{g.rms_after:.2f} closed {g.closed_percent:.0f} "
                      f"ranking " + ", ".join(f"{c} {b:.0f}" for c, b in
                                               zip(g.candidates[:3], g.delta_bic[:3])))
    print(f"\nwall time: {wall:.1f} s for {len(labels)} units x {args.years} years "
          f"({args.workers} workers)")
    print(f"wall time, 3 units x 10 years x 7 candidates (configs/fleet_gap.yaml): "
          f"{wall3:.1f} s on {args.workers} workers   target < 120 s")


# -- two withheld effects at once -----------------------------------------------------------------
#: Per machine: its gap config, the kind of each candidate effect on the observed output
#: alone (transient: a distinct shape in the start-up; plateau: a shift of the settled
#: level, alike between them), and a random degradation trajectory.
PAIR_MACHINES = {
    "pump": {
        "config": ROOT / "configs" / "fleet_gap.yaml",
        "transient": ("sensor.tau", "valve.opening_time", "motor.start_delay"),
        "plateau": ("sensor.gain", "pipe.fouling", "pump.leak", "motor.supply_ratio"),
        "trajectories": lambda rng: {
            "motor_damping": {"start": float(rng.uniform(9.0, 11.0)),
                              "slope": float(rng.uniform(0.0, 0.8)), "jitter": 0.15},
            "pump_coef": {"start": float(rng.uniform(3.5, 3.8)),
                          "slope": float(rng.uniform(-0.06, -0.01)), "jitter": 0.01}},
    },
    "dcdrive": {
        "config": ROOT / "configs" / "dcdrive_gap.yaml",
        "transient": ("tacho.tau", "supply.delay"),
        "plateau": ("tacho.gain", "supply.ratio", "load.extra"),
        "trajectories": lambda rng: {
            "bearing_friction": {"start": float(rng.uniform(0.0009, 0.0011)),
                                 "slope": float(rng.uniform(0.0, 1.0e-4)), "jitter": 2.0e-5},
            "winding_resistance": {"start": float(rng.uniform(0.95, 1.02)),
                                   "slope": float(rng.uniform(0.0, 0.01)), "jitter": 0.005}},
    },
}
#: The DC drive's cases (same units, effects, magnitudes and onsets as "dcdrive") with the
#: plant recording the armature current beside the speed (noise 1 % of its healthy range,
#: as fabricate draws it). Its plateau-type effects are absorbed by the degradation inputs
#: on the speed alone; this says whether a second channel makes them visible. The torque
#: channel the model also offers is Kt times the current: not recorded, it adds nothing.
PAIR_MACHINES["dcdrive+current"] = {**PAIR_MACHINES["dcdrive"], "cases_of": "dcdrive",
                                    "record": ("armature.i",)}
PAIR_KINDS = ("transient+plateau", "transient+transient", "plateau+plateau")
#: Visible gap (noise sigma, worst window, after refitting the degradation inputs:
#: :func:`effect_gaps`) below which an effect counts as absorbed by them.
ABSORBED = 1.0


def build_pairs(machine: dict, rng, n_pairs: int, n_nulls: int, years: int, mags: dict):
    """Pair cases (kinds in turn, onsets coinciding in every other case) and clean units:
    ``units`` (fabricate specs) and ``labels`` {unit: (kind, {effect: (value, onset)})}."""
    units, labels = {}, {}
    for i in range(n_pairs + n_nulls):
        u = f"case{i:03d}"
        spec = {"trajectories": machine["trajectories"](rng)}
        if i >= n_pairs:
            units[u], labels[u] = spec, ("clean", {})
            continue
        kind = PAIR_KINDS[i % len(PAIR_KINDS)]
        first, second = kind.split("+")
        a = str(rng.choice([n for n in machine[first] if mags[n]]))
        b = str(rng.choice([n for n in machine[second] if mags[n] and n != a]))
        on_a = int(rng.integers(2, years - 2))
        on_b = on_a if (i // len(PAIR_KINDS)) % 2 == 0 else on_a + int(rng.integers(1, 3))
        if rng.uniform() < 0.5:
            on_a, on_b = on_b, on_a
        truth = {}
        for name, on in ((a, on_a), (b, on_b)):
            lo, end = mags[name][int(rng.integers(len(mags[name])))]
            truth[name] = (float(lo + rng.uniform(0, 0.7) * (end - lo)), on)
        spec["effects"] = {n: {"value": v, "onset": on} for n, (v, on) in truth.items()}
        onsets = "same onset" if on_a == on_b else "onsets apart"
        units[u], labels[u] = spec, (f"{kind}, {onsets}", truth)
    return units, labels


def effect_gaps(cfg, fmu, truth, sigma: float, recorded: dict | None = None) -> tuple:
    """Gap (noise units, worst window, its years on) of each withheld effect, raw and
    visible: ``({unit: {effect: gap}}, {unit: {effect: visible gap}})``.

    The raw gap compares the unit's output with both effects and with this one off, at its
    true degradation inputs (the single-effect benchmark's gap; the output alone, whatever
    else is recorded, so that the cases scored are the same). The visible gap is what
    remains once the twin with this effect off (the other at its true value) has its
    degradation inputs refitted (least squares, noise-free) to the recorded channels with
    both: the part of the effect no degradation can take up, hence what any diagnosis on
    the recorded channels can see of it (the worst channel's gap).

    ``recorded``: further recorded channels ``{FMU variable: noise std (its units)}``."""
    from scipy.optimize import least_squares
    t = cfg.model.output.times.times
    var = cfg.model.output.variable
    ins = list(cfg.model.inputs.values())
    chans = {var: sigma, **(recorded or {})}
    raw, visible = {}, {}
    with FMUModel(fmu, list(chans), t) as model:
        def run(p):
            try:
                res = model.run(p)
                return np.concatenate([res[c] / s for c, s in chans.items()]) * sigma
            except SimulationError:
                return np.full(t.size * len(chans), 1e6)

        def out(p):
            return run(p)[:t.size]

        def window_gap(delta):
            # Worst recorded channel; ``delta`` [years, channels * n_t] in output units.
            return max(_window_gap(cfg, delta[:, i * t.size:(i + 1) * t.size] / sigma)
                       for i in range(len(chans)))
        for u, eff in truth.effects.items():
            raw[u], visible[u] = {}, {}
            for name, vals in eff.items():
                lo = np.array([q.low for q in ins])
                hi = np.array([q.high for q in ins])
                deltas, vis = [], []
                for k in np.flatnonzero(np.isfinite(vals)):
                    p = {q.variable: float(truth.inputs[u][n][k])
                         for n, q in cfg.model.inputs.items()}
                    both = {**p, **{n: float(v[k]) for n, v in eff.items() if np.isfinite(v[k])}}
                    target = out(both)
                    off = {**both, name: cfg.model.effects[name].baseline}
                    deltas.append(target - out(off))
                    x0 = np.array([p[q.variable] for q in ins])

                    target_all = run(both)

                    def resid(z, off=off, target=target_all):
                        x = lo + z * (hi - lo)
                        return (run({**off, **{q.variable: float(v) for q, v in zip(ins, x)}})
                                - target) / sigma
                    fit = least_squares(resid, np.clip((x0 - lo) / (hi - lo), 0, 1),
                                        bounds=(0, 1), diff_step=1e-4, max_nfev=40)
                    vis.append(resid(fit.x) * sigma)
                raw[u][name] = _window_gap(cfg, np.array(deltas) / sigma) if deltas else 0.0
                visible[u][name] = window_gap(np.array(vis)) if vis else 0.0
    return raw, visible


def run_pairs(name: str, machine: dict, args) -> dict:
    """Fabricate and diagnose one machine's pair cases; the scores (see :func:`pair_report`)."""
    base = load_config(machine["config"])
    raw = copy.deepcopy(dict(base.raw))
    sigma = base.fabricate.noise_std           # 1 % of the nominal output
    fmu = resolve_fmu(base.model.fmu)
    t = base.model.output.times.times
    with FMUModel(fmu, [base.model.output.variable], t) as model:
        mags = min_magnitudes(base, model, sigma)
    # A variant of another machine's cases draws the same ones.
    rng = np.random.default_rng([args.seed, list(PAIR_MACHINES).index(
        machine.get("cases_of", name))])
    units, labels = build_pairs(machine, rng, args.pairs, args.nulls, args.years, mags)
    record = tuple(machine.get("record", ()))
    raw["fabricate"] = {"years": args.years, "noise_std": sigma, "record_channels": bool(record),
                        "seed": int(rng.integers(1 << 30)), "units": units}
    cfg = config_from_mapping(raw, Path(machine["config"]))
    with tempfile.TemporaryDirectory(prefix="gap-pairs-") as tmp:
        obs, truth_path = Path(tmp) / "obs.h5", Path(tmp) / "truth.h5"
        fabricate(cfg, obs, truth_path)
        ch_noise = _keep_channels(cfg, obs, record) if record else {}
        t0 = time.perf_counter()
        summary = diagnose(cfg, obs, Path(tmp) / "gap.h5", workers=args.workers)
        wall = time.perf_counter() - t0
        truth = read_truth(truth_path)           # only the scorer reads it
        gaps, visible = effect_gaps(cfg, fmu, truth, sigma, ch_noise)
    return {"summary": summary, "labels": labels, "gaps": gaps, "visible": visible,
            "wall": wall, "cfg": cfg}


def _keep_channels(cfg, path: Path, record: tuple) -> dict:
    """Leave only the output and the channels ``record`` in the observations at ``path``
    (fabricate records every ``model.channels`` entry); their noise std ``{channel: std}``."""
    import dataclasses
    from twinmon.observations import read_observations, write_observations
    obs = read_observations(path)
    keep = {cfg.model.output.name, *record}
    units = {u: dataclasses.replace(
        uo, channels={c: v for c, v in uo.channels.items() if c in keep},
        noise_std={c: v for c, v in uo.noise_std.items() if c in keep})
        for u, uo in obs.units.items()}
    write_observations(path, dataclasses.replace(obs, units=units),
                       units=cfg.model.channel_units)
    return {c: next(iter(units.values())).noise_std[c] for c in record}


def pair_scores(runs: dict, verbose: int = 0, absorbed: float = 0.0) -> dict:
    """Score pair cases whose every withheld effect alone has a raw gap of at least 3 sigma
    and a visible gap (:func:`effect_gaps`) of at least ``absorbed`` sigma."""
    sc = {"n": 0, "below": 0, "detected": 0, "all_in": 0, "closed90": 0, "closed": [],
          "sizes": [], "two_named": 0, "clean": 0, "false": 0, "spread": 0,
          "multi": 0, "sep": 0, "by_kind": {}, "absorbed": absorbed,
          "hidden_n": 0, "hidden_said": 0, "hidden_channel": 0}
    for machine, r in runs.items():
        for u, (kind, truth) in r["labels"].items():
            g = r["summary"].units[u]
            if kind == "clean":
                sc["clean"] += 1
                sc["false"] += int(g.verdict != "none")
                continue
            if min(r["gaps"][u].values()) < 3.0 or min(r["visible"][u].values()) < absorbed:
                sc["below"] += 1
                continue
            sc["n"] += 1
            # A true effect the degradation inputs take up: does diagnose say it cannot see
            # it, and name a channel that would?
            for n in truth:
                if r["visible"][u][n] < ABSORBED:
                    sc["hidden_n"] += 1
                    sc["hidden_said"] += int(n in g.hidden)
                    sc["hidden_channel"] += int(bool(g.hidden.get(n, {}).get("channel")))
            k = sc["by_kind"].setdefault(f"{machine}: {kind}", [0, 0, 0])
            k[0] += 1
            members = [set(m["effect"] for m in grp["members"]) for grp in g.groups]
            found = all(any(n in mem for mem in members) for n in truth)
            sc["detected"] += int(g.verdict != "none")
            sc["all_in"] += int(g.verdict == "effect" and found)
            k[1] += int(g.verdict == "effect" and found)
            ok90 = g.verdict == "effect" and g.closed_percent >= 90.0
            sc["closed90"] += int(ok90)
            k[2] += int(ok90)
            sc["closed"].append(g.closed_percent)
            sc["two_named"] += int(len(g.groups) == 2)
            for grp in g.groups:
                sc["sizes"].append(len(grp["members"]))
                if len(grp["members"]) > 1:
                    sc["multi"] += 1
                    sc["sep"] += int(bool(grp["separating_channel"]))
                sc["spread"] += int(grp["failure_year_spread"])
            if verbose and (g.verdict != "effect" or not found or not ok90 or verbose > 1):
                print(f"  {machine} {u} {kind}: truth "
                      + ", ".join(f"{n} {v:.3g} from {on} (gap {r['gaps'][u][n]:.1f}, "
                                  f"visible {r['visible'][u][n]:.1f})"
                                  for n, (v, on) in truth.items())
                      + f"; {g.verdict}, closed {g.closed_percent:.1f} %, groups "
                      + "; ".join("[" + ", ".join(f"{m['effect']} {m['weight']:.2f}"
                                                  for m in grp["members"]) + f"] from "
                                  f"{grp['onset']}" for grp in g.groups))
    return sc


def pair_report(runs: dict, sc: dict, singles, args) -> None:
    def pct(a, b):
        return f"{a / b:.2f} ({a}/{b})" if b else "n/a"
    n = sc["n"]
    what = "gap >= 3 sigma" + (f" and visible gap >= {sc['absorbed']:g} sigma (not absorbed "
                               "by the degradation inputs)" if sc["absorbed"] else "")
    print(f"\n{n} pair cases with every effect's {what} ({sc['below']} others excluded)")
    print(f"every true effect inside a reported group : {pct(sc['all_in'], n)}   target >= 0.90")
    print(f"mean group size                           : "
          f"{np.mean(sc['sizes']) if sc['sizes'] else float('nan'):.2f}   target <= 3")
    print(f">= 90 % of the excess gap closed          : {pct(sc['closed90'], n)}   target >= 0.90")
    print(f"false alarms on clean units               : {pct(sc['false'], sc['clean'])}   "
          "target <= 0.05")
    print(f"detection (verdict != none)               : {pct(sc['detected'], n)}   —")
    print(f"two effects named (a group each)          : {pct(sc['two_named'], n)}   —")
    print(f"median % of the excess gap closed         : "
          f"{np.median(sc['closed']) if sc['closed'] else float('nan'):.1f} %   —")
    print(f"groups of 2+ with a separating channel    : {pct(sc['sep'], sc['multi'])}   —")
    print(f"groups whose failure years spread > 1 year: {sc['spread']}   —")
    if sc["hidden_n"]:
        print(f"true effects absorbed (visible < {ABSORBED:g} sigma) stated as unseen: "
              f"{pct(sc['hidden_said'], sc['hidden_n'])}, with a channel to record "
              f"{pct(sc['hidden_channel'], sc['hidden_n'])}   —")
    print("by machine and kind (cases, all true effects in groups, >= 90 % closed):")
    for k, (c, a, cl) in sorted(sc["by_kind"].items()):
        print(f"    {k:<48s} {c:>3d} {a:>3d} {cl:>3d}")
    for m in runs:
        rows = [v for k, v in sc["by_kind"].items() if k.startswith(f"{m}:")]
        c, a, cl = (sum(r[i] for r in rows) for i in range(3))
        print(f"    {m + ', all kinds':<48s} {c:>3d} {a:>3d} {cl:>3d}   "
              f"(in groups {pct(a, c)}, >= 90 % closed {pct(cl, c)})")
    print("wall time: " + ", ".join(f"{m} {r['wall']:.1f} s" for m, r in runs.items())
          + f" on {args.workers} workers; FMU runs per unit: " + ", ".join(
              f"{m} {np.mean([g.fmu_runs for g in r['summary'].units.values()]):.0f}"
              for m, r in runs.items()))


def pair_main(argv) -> None:
    """The two-effect benchmark (``--pairs N``): N pair units and ``--nulls`` clean units per
    machine, scored against the targets."""
    ap = argparse.ArgumentParser(description="gap_blind, two withheld effects at once")
    ap.add_argument("--pairs", type=int, default=24, help="pair units per machine")
    ap.add_argument("--nulls", type=int, default=8, help="clean units per machine")
    ap.add_argument("--years", type=int, default=8)
    ap.add_argument("--seed", type=int, default=5,
                    help="1 to 4: tuning seeds; 5 and 6: held out")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--machines", default="pump,dcdrive,dcdrive+current",
                    help="of " + ", ".join(PAIR_MACHINES))
    ap.add_argument("-v", "--verbose", action="count", default=0,
                    help="list the cases missed (-vv: every case)")
    args = ap.parse_args(argv)
    runs = {m: run_pairs(m, PAIR_MACHINES[m], args) for m in args.machines.split(",")}
    print(f"gap_blind --pairs: seed {args.seed}, {args.pairs} pair units + {args.nulls} clean "
          f"units per machine ({', '.join(runs)}), {args.years} years, noise 1 % of nominal")
    # Two set-ups, each scored on its own: every machine recording its output alone, then
    # with the further channels of the "+" variants in place of their output-only runs
    # (the same cases; the pump records its flow alone in both).
    variants = {m for m in runs if PAIR_MACHINES[m].get("record")}
    replaced = {PAIR_MACHINES[m]["cases_of"] for m in variants}
    setups = {"output only": {m: r for m, r in runs.items() if m not in variants}}
    if variants:
        setups["with " + ", ".join(sorted({c for m in variants
                                             for c in PAIR_MACHINES[m]["record"]}))
               + " recorded"] = {m: r for m, r in runs.items() if m not in replaced}
    if args.verbose:
        # The misses of each machine once (-vv: every case), whatever set-ups it is in.
        for m, r in runs.items():
            pair_scores({m: r}, args.verbose, 0.0)
    for label, sub in setups.items():
        if not sub:
            continue
        print(f"\n== {label}: {', '.join(sub)} ==")
        # Every case with a 3-sigma gap, as for one effect; then those whose effects the
        # degradation inputs do not absorb (an absorbed effect is invisible to any
        # diagnosis on the recorded channels: on the DC drive's speed alone its plateau
        # effects, a load torque looking like friction, a supply ratio like a winding
        # resistance).
        for absorbed in (0.0, ABSORBED):
            pair_report(sub, pair_scores(sub, 0, absorbed), None, args)


if __name__ == "__main__":
    main()
