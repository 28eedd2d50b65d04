"""Prognosis benchmark: detection, attribution, intervals and time to failure.

A seeded fleet of units of one model (``--config``, default configs/pump.yaml) over ten
years: healthy units whose inputs age anywhere inside their normal band, faults of each
component and of several at once, with excess rates from barely above the tolerance (1.25x)
to fast (``benchmarks/families.py`` derives them from the config's ``model.inputs``). Each
unit-year goes through the real FMU; the output carries 1 % noise (the pump: 4 kg/s; another
model: 1 % of the healthy unit's largest output, two significant digits), each further
channel 1 % of its healthy range. Every configuration -- calibration method x channels (the
output alone / with further channels) -- is calibrated, forecast and scored against the
truth, which only this script reads:

* confusion matrix of verdict vs truth;
* detection of faulty units whose excess rate is at least twice the tolerance; false alarms
  on healthy units; wrong component named; ambiguous share;
* coverage of the 90 % prediction intervals of the true future indicator and inputs (the
  truth file's recorded future: the trajectory with its year-to-year jitter; a truth file
  from before it was recorded is written again, the observations checked unchanged);
* failure year within +-1 of the truth, for units that fail within the horizon;
* alpha-lambda accuracy (alpha 0.2, lambda 0.5) of the time to failure over cut years.

The failure year is scored twice: ``failure_year`` (first year with P(unsafe) > 5 %, the
year to act by) and ``median_failure_year`` (first year with P(unsafe) >= 0.5, the point
forecast); "fail+-1" and "a-l" are the first, "fail50" and "a-l50" the second.

Usage: ``python benchmarks/prognosis.py [--config configs/dcdrive.yaml] [--seed 11 [12 ...]]
[--methods sequential,joint] [--channels flow,speed] [--workdir DIR] [--reuse]``; about 2
minutes per seed and configuration with the sequential method on 2 cores (the joint method:
about 10, its alpha-lambda cuts calibrated again; the laplace method without alpha-lambda
10-25 s, the pump's fleet or the DC drive's). Several seeds are pooled: a pump seed has 12
healthy units and 23 faulty ones with an excess of at least twice the tolerance, so one unit
moves a seed's false-alarm rate by 0.083 and its detection by 0.043; the pooled counts come
with their 90 % Wilson intervals.

``--channels`` lists channel sets, each calibrated on its own: ``output`` (or ``flow``, the
pump's word) is the config's output alone; ``speed`` adds the first of ``model.channels``
(the pump's ``motor.w``), ``all`` every one of them, and names of ``model.channels`` joined
by ``+`` (``armature.i+shaft.torque``) those. The surrogate is reduced on every channel a set
names, and always on the first further one, once per work folder: a set naming a channel
the folder's surrogate lacks needs a new folder.
``--reuse`` takes the posteriors already in ``--workdir`` (to measure a change of
``forecast`` without calibrating again).

``--healthy-only N`` fabricates fleets of N healthy units alone: a mixed fleet has 12, so a
seed moves the false-alarm rate by 0.083 a unit; 96 a seed resolve it to about 0.02.

``--oracle`` also scores, per channel set, the sequential posteriors moved to be unbiased:
each year's draws keep their spread and shape, but are centred on the true inputs plus an
error drawn from their own covariance (clipped to the design box). It is what the forecast
would achieve from calibrated yearly estimates of the same precision that do not trail a
trend: the bound the forecast stage itself sets, apart from the calibration.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.backtest import calibrate_cut, truncate, ttf_scores, wilson_interval  # noqa: E402
from twinmon.calibrate import Posterior, calibrate, read_posterior  # noqa: E402
from twinmon.config import load_config  # noqa: E402
from twinmon.fabricate import fabricate, read_truth  # noqa: E402
from twinmon.forecast import forecast, forecast_units  # noqa: E402
from twinmon.observations import read_observations  # noqa: E402
from twinmon.reduce import read_surrogate, reduce  # noqa: E402
from twinmon.simulate import simulate  # noqa: E402

from families import FAMILIES, PUMP, FleetModel, fleet  # noqa: E402


def channel_sets(cfg, names: str) -> dict[str, list[str]]:
    """``--channels`` as set name -> the further channels calibrated with the output."""
    further = list(cfg.model.channels)
    out = {}
    for name in names.split(","):
        if name in ("output", "flow"):
            out[name] = []
        elif name == "speed" or name == "all":
            if not further:
                raise SystemExit(f"--channels {name}: {cfg.source} has no model.channels")
            out[name] = further[:1] if name == "speed" else further
        else:
            bad = [c for c in name.split("+") if c not in further]
            if bad:
                raise SystemExit(f"--channels {name}: {', '.join(bad)} not in model.channels "
                                 f"of {cfg.source} ({', '.join(further) or 'none'}); or one "
                                 "of output, flow, speed, all")
            out[name] = name.split("+")
    return out


def output_noise(cfg, model: FleetModel) -> float:
    """The output's noise sd: the pump's 4 kg/s (1 % of its 400 kg/s nominal flow); for
    another model 1 % of the healthy unit's (every input at nominal) largest output, to
    two significant digits."""
    if model is PUMP:
        return 4.0
    from twinmon.simulate import run_batch, spec_for
    out = cfg.model.output.variable
    run = run_batch(spec_for(cfg, outputs=[out]),
                    [{s.variable: s.nominal for s in cfg.model.inputs.values()}])
    if not run.ok.all():
        raise SystemExit(f"{cfg.source}: the healthy unit failed to simulate: "
                         f"{run.messages[0]}")
    return float(f"{0.01 * float(np.max(np.abs(run.outputs[out][0]))):.2g}")


#: Cut years of the alpha-lambda scores: from the fifth year to the tenth, the whole recorded
#: history. ``twinmon backtest`` stops at the last year but one, because it scores against
#: later recordings. Here the truth knows the years after the tenth, so the forecast made in
#: year 10 can be scored too. Without it, a unit failing in year 15 (lambda = 0.5 falls on
#: year 10) or later would be scored on the year-9 forecast, i.e. at lambda of about 0.4.
ALPHA_LAMBDA_CUTS = range(5, 11)


def true_end_of_life(cfg, uf, truth, unit) -> int | None:
    """First year the true (noise-free) unit is unsafe: observed years from the truth file's
    clean output, later years from the forecast's extended true trajectories."""
    from twinmon.safety import Indicator, is_unsafe
    ind = Indicator.from_config(cfg)
    clean = truth_clean[unit]
    v = ind(truth_time, clean)
    bad = is_unsafe(v, cfg.safety, None)
    if bad.any():
        return int(truth.years[unit][np.argmax(bad)])
    return uf.true_failure_year


def alpha_lambda(cfg, post, sur, truth_eol: dict, cuts, work: Path | None = None,
                 name: str = "", truth=None) -> tuple[dict, dict, dict]:
    """Per unit failing after the first cut: TTF scores of forecasts made at each cut, of the
    failure year and of the median failure year; and per cut, the coverage of the true
    future indicator by the 90 % intervals of every unit's forecast made there ((hits, n):
    the record's last cut is the forecast the other scores read; earlier cuts are shorter
    records, where the trend's shape is less known). A unit's forecast does not depend on
    the others but through the fleet's priors of a trend posterior, its sigma and its
    trend shapes.

    The sequential posterior truncated at a cut is what calibrating the years up to the cut
    gives. A joint or laplace posterior's years were estimated knowing the later ones, so
    for those methods each cut's history is calibrated again, every unit of the fleet (in
    ``work``, files tagged ``name``), and the fleet's priors are fitted on all of them, as
    a forecast made at that cut would fit them: fitted on the failing units alone, the
    fleet's prior of the trend shapes would learn that every unit wears as they do."""
    scored = [u for u, eol in truth_eol.items() if eol is not None and eol > min(cuts)]
    preds = {u: {} for u in scored}
    coverage = {}
    for k in cuts:
        fleet = None
        if cfg.calibrate.method in ("joint", "laplace"):
            cut = recalibrate_cut(cfg, work, list(post.units), k, name)
            sub = dict(cut)
            fleet = Posterior(post.input_names, cut, post.path, post.fit_windows)
        else:
            sub = {u: truncate(post.units[u], k) for u in post.units}
        res, _, _ = forecast_units(cfg, Posterior(post.input_names, sub, post.path,
                                                  post.fit_windows), sur, pool_over=fleet,
                                   truth=truth, truth_path=work / "truth.h5")
        hits = []
        for u, uf in res.items():
            if u in preds:
                preds[u][k] = tuple(-1 if y is None else int(y)
                                    for y in (uf.failure_year, uf.median_failure_year))
            if uf.true_indicator is not None:
                q05, _, q95 = uf.indicator_quantiles((0.05, 0.5, 0.95))
                ti = np.asarray(uf.true_indicator, float)
                hits += list((q05 <= ti) & (ti <= q95))
        coverage[k] = (int(np.sum(hits)), len(hits))
    out = ({}, {})
    for u in scored:
        ks = np.array(sorted(preds[u]))
        for j in range(2):
            s = ttf_scores(ks, np.array([preds[u][k][j] for k in ks]), truth_eol[u],
                           cfg.forecast.horizon, cfg.backtest.alpha, cfg.backtest.lambda_value)
            if s is not None:
                out[j][u] = s
    return (*out, coverage)


def recalibrate_cut(cfg, work: Path, units: list, k: int, name: str) -> dict:
    """``units``' posteriors calibrated from their years up to ``k`` alone
    (:func:`twinmon.backtest.calibrate_cut`, in ``work``/cuts_<name>/, reused when there)."""
    cuts = work / f"cuts_{name}"
    out = cuts / f"posterior_to_{k}.h5"
    if out.exists():
        return dict(read_posterior(out).units)
    cuts.mkdir(exist_ok=True)
    obs = read_observations(work / "obs.h5", cfg.model.output.name)
    return calibrate_cut(cfg, work / "sur.h5", obs, units, k, cuts, cfg.calibrate.method)


truth_clean, truth_time = {}, None


def score(cfg, summary, kinds, truth, components: list[str]) -> dict:
    """Scores of a forecast's summary against the truth; ``components`` are the fault
    groups' (the model's component words, the verdicts naming one part)."""
    kinds_all = ["healthy", *components, "both"]
    labels = [*kinds_all, "ambiguous", "withheld"]
    conf = {k: dict.fromkeys(labels, 0) for k in kinds_all}
    rows = {}
    for u, f in summary.units.items():
        kind, m = kinds[u]
        v = f.root_cause if f.root_cause in labels else "withheld"
        conf[kind][v] += 1
        rows[u] = (kind, m, v, f)
    faulty = [r for r in rows.values() if r[0] != "healthy"]
    strong = [r for r in faulty if r[1] >= 2]
    ci, cx = [], []
    for u, f in summary.units.items():
        # forecast()'s summary keeps these quantiles only (its units are slim).
        q05, _, q95 = f.indicator_quantiles((0.05, 0.5, 0.95))
        ci += list((q05 <= f.true_indicator) & (f.true_indicator <= q95))
        for n in f.trends:
            cx += list((f.pred_lo[n] <= f.true_inputs[n]) & (f.true_inputs[n] <= f.pred_hi[n]))
    eol = {u: true_end_of_life(cfg, f, truth, u) for u, f in summary.units.items()}
    horizon_end = {u: int(f.years_future[-1]) for u, f in summary.units.items()}
    last = {u: int(f.years_observed[-1]) for u, f in summary.units.items()}
    fails = [u for u in rows if eol[u] is not None and last[u] < eol[u] <= horizon_end[u]]
    within = [rows[u][3].failure_year is not None and abs(rows[u][3].failure_year - eol[u]) <= 1
              for u in fails]
    within50 = [rows[u][3].median_failure_year is not None
                and abs(rows[u][3].median_failure_year - eol[u]) <= 1 for u in fails]
    healthy = [r for r in rows.values() if r[0] == "healthy"]
    # A unit that truly fails within 3 years of its last record must not be told it is
    # fine: max P(unsafe) under 5 % with status ok is a confident miss.
    soon = [u for u in rows if eol[u] is not None and last[u] < eol[u] <= last[u] + 3]
    missed_soon = [u for u in soon if rows[u][3].status == "ok"
                   and float(np.max(rows[u][3].p_unsafe)) < 0.05]
    # (successes, trials) of every rate: seeds pool by adding them.
    counts = {"detected": (sum(r[2] != "healthy" for r in strong), len(strong)),
              "false_alarm": (sum(r[2] != "healthy" for r in healthy), len(healthy)),
              "wrong": (sum(r[2] not in ("healthy", "ambiguous", r[0]) for r in faulty),
                        len(faulty)),
              "ambiguous": (sum(r[2] == "ambiguous" for r in faulty), len(faulty)),
              "cover_indicator": (int(np.sum(ci)), len(ci)),
              "cover_inputs": (int(np.sum(cx)), len(cx)),
              "fail_within1": (int(np.sum(within)), len(within)),
              "fail50_within1": (int(np.sum(within50)), len(within50)),
              "soon_missed": (len(missed_soon), len(soon)),
              "unreliable_healthy": (sum(r[3].status == "unreliable" for r in healthy),
                                     len(healthy)),
              "unreliable_faulty": (sum(r[3].status == "unreliable" for r in faulty),
                                    len(faulty)),
              # Withheld units (the twin misses the data, or its estimates sit on the box's
              # edge) count among the false alarms and the wrong components above.
              "withheld_healthy": (sum(r[2] == "withheld" for r in healthy), len(healthy)),
              "withheld_faulty": (sum(r[2] == "withheld" for r in faulty), len(faulty))}
    # Repairs nobody recorded: found (the right year and component) on the units that had
    # one, and found where there was none.
    hidden = {u: {(int(y), c) for y, c in truth.unrecorded.get(u, ())} for u in rows}
    # A finding naming several components (the output cannot tell them apart) is right
    # when the repaired one is among them.
    found = {u: {(r["year"], c) for r in rows[u][3].repairs for c in r["components"]}
             for u in rows}
    had = [u for u in rows if hidden[u]]
    counts["repair_found"] = (sum(bool(found[u] & hidden[u]) for u in had), len(had))
    counts["repair_false"] = (sum(not any(hidden[u] & {(r["year"], c) for c in r["components"]})
                                  for u in rows for r in rows[u][3].repairs), len(rows))
    out = {key: k / n if n else float("nan") for key, (k, n) in counts.items()}
    return {**out, "counts": counts, "confusion": conf, "labels": labels,
            "n_strong": len(strong),
            "failure_years": {u: (rows[u][3].failure_year, rows[u][3].median_failure_year,
                                  eol[u]) for u in fails},
            "n_fail": len(fails), "eol": eol, "missed_soon": missed_soon,
            "misses": [(u, rows[u][0], round(rows[u][1], 2), rows[u][2]) for u in rows
                       if (rows[u][0] == "healthy") != (rows[u][2] == "healthy")
                       or rows[u][2] not in ("healthy", "ambiguous", rows[u][0])]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "pump.yaml",
                    help="the model's twinmon config (default configs/pump.yaml)")
    ap.add_argument("--seed", type=int, nargs="+", default=[11],
                    help="one fleet per seed; several are pooled (each in --workdir/seedN)")
    ap.add_argument("--methods", default="sequential")
    ap.add_argument("--channels", default="flow,speed",
                    help="channel sets: output (flow), speed (the first of model.channels), "
                         "all, or model.channels names joined by +")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--no-alpha-lambda", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every configuration (as twinmon's --set)")
    ap.add_argument("--reuse", action="store_true",
                    help="take the posteriors already in --workdir instead of calibrating")
    ap.add_argument("--healthy-only", type=int, default=None, metavar="N",
                    help="fleets of N healthy units and no faulty one: the false-alarm rate "
                         "measured on more units than a mixed fleet's 12")
    ap.add_argument("--family", default="linear", choices=FAMILIES,
                    help="the shape of the faulty units' wear (benchmarks/families.py)")
    ap.add_argument("--oracle", action="store_true",
                    help="also score the sequential posteriors centred on the truth "
                         "(tag oracle/CHANNELS)")
    a = ap.parse_args()
    a.config = a.config.resolve()
    a.base = load_config(a.config)
    a.model = FleetModel.from_config(a.base)
    a.sets = channel_sets(a.base, a.channels)
    root = Path(a.workdir or tempfile.mkdtemp(prefix="twinmon-prognosis-"))
    per_seed = {}
    for seed in a.seed:
        work = root / f"seed{seed}" if len(a.seed) > 1 else root
        per_seed[seed] = run_fleet(a, seed, work)
    tags = list(per_seed[a.seed[0]])
    print("\nsummary (targets: detect >= 0.95, false alarm <= 0.05, wrong <= 0.05, ambiguous "
          "<= 0.25 output alone / 0.05 with a further channel, coverage 0.85-0.95, failure "
          "+-1 >= 0.90, alpha-lambda >= 0.80; the inputs' mean relative error per component)")
    inputs = a.model.inputs
    print(f"{'config':26s} detect  falsealm wrong  ambig  cov_ind cov_inp fail+-1 a-l    "
          "fail50 a-l50  " + " ".join(f"{a.model.component[n][:8] + '_err':12s}"
                                      for n in inputs) + " t_cal")
    for tag in tags:
        for seed, results in per_seed.items():
            r = results[tag]
            tc = r["truth_check"] or {}
            print(f"{tag + f' seed {seed}':26s} {r['detected']:.3f}  {r['false_alarm']:.3f}    "
                  f"{r['wrong']:.3f}  {r['ambiguous']:.3f}  {r['cover_indicator']:.3f}   "
                  f"{r['cover_inputs']:.3f}   {r['fail_within1']:.3f}   "
                  f"{r.get('alpha_lambda', float('nan')):.3f}  {r['fail50_within1']:.3f}  "
                  f"{r.get('alpha_lambda50', float('nan')):.3f}  "
                  + " ".join(f"{rel_error(tc, n):12s}" for n in inputs)
                  + f" {r['t_cal']:.0f} s")
    if len(a.seed) > 1:
        print(f"\npooled over seeds {a.seed}: k/n, rate and its 90 % Wilson interval")
        for tag in tags:
            pooled = {}
            for seed, results in per_seed.items():
                for key, (k, n) in results[tag]["counts"].items():
                    k0, n0 = pooled.get(key, (0, 0))
                    pooled[key] = (k0 + k, n0 + n)
            print(f"  {tag}:")
            for key, (k, n) in pooled.items():
                lo, hi = wilson_interval(k / n if n else 0.0, n)
                print(f"    {key:17s} {k:4d}/{n:<4d} {k / max(n, 1):.3f}  [{lo:.3f}, {hi:.3f}]")
    return 0


def rel_error(truth_check: dict, name: str) -> str:
    """An input's mean relative calibration error, as printed (nan % when not checked)."""
    return f"{100 * truth_check.get(name, {}).get('mean_rel_error', np.nan):.2f} %"


def run_fleet(a, seed: int, work: Path) -> dict:
    """Fabricate (or reuse) one seed's fleet in ``work``, calibrate, forecast and score each
    configuration; print each one's confusion matrix. Returns tag -> scores."""
    global truth_time
    work.mkdir(parents=True, exist_ok=True)
    units, kinds = (fleet(seed, a.family, model=a.model) if a.healthy_only is None
                    else fleet(seed, a.family, n_healthy=a.healthy_only, faulty=False,
                               model=a.model))
    base = a.base
    # The surrogate learns every further channel a set calibrates on, and the first one
    # always (the pump's motor speed: its surrogates stay what they were).
    reduced = list(dict.fromkeys([*list(base.model.channels)[:1],
                                  *(c for chans in a.sets.values() for c in chans)]))
    cfg_path = work / "bench.yaml"
    cfg_path.write_text(yaml.safe_dump({
        "extends": str(a.config),
        "reduce": {"channels": reduced},
        "fabricate": {"years": 10, "noise_std": output_noise(base, a.model),
                      "record_channels": True, "channel_noise_fraction": 0.01,
                      # The pump's true flow was kept; nothing here reads it.
                      "truth_variables": ["pump.m_flow"] if a.model is PUMP else [],
                      "seed": seed + 4231, "units": units}}, sort_keys=False))
    cfg = load_config(cfg_path)
    t0 = time.perf_counter()
    obs, tru = work / "obs.h5", work / "truth.h5"
    if not obs.exists():
        fabricate(cfg, obs, tru)
    elif not read_truth(tru).future_years:
        refresh_truth(cfg, work)
    if not (work / "sur.h5").exists():
        simulate(cfg, work / "sim.h5")
        reduce(cfg, work / "sim.h5", work / "sur.h5")
    print(f"fleet seed {seed}: {len(units)} units x 10 years; fabricate+simulate+reduce "
          f"{time.perf_counter() - t0:.0f} s; workdir {work}")
    truth = read_truth(tru)
    import h5py
    truth_clean.clear()
    with h5py.File(tru) as f:
        truth_time = f["time"][()]
        for u in f["units"]:
            truth_clean[u] = f[f"units/{u}/{cfg.model.output.name}_clean"][()]
    sur = read_surrogate(work / "sur.h5")
    results = {}
    for method in a.methods.split(","):
        for ch, chans in a.sets.items():
            over = [f"calibrate.channels={chans}", f"calibrate.method={method}", *a.set]
            c = load_config(cfg_path, over)
            tag = f"{method}/{ch}"
            post = work / f"post_{method}_{ch}.h5"
            t1 = time.perf_counter()
            if a.reuse and post.exists():
                cal, t_cal = None, float("nan")
            else:
                cal = calibrate(c, work / "sur.h5", obs, post, truth_path=tru)
                t_cal = time.perf_counter() - t1
                for w in cal.warnings:
                    print(f"calibrate {tag}: {w}")
            r = forecast_and_score(a, c, post, work, f"{method}_{ch}", kinds, truth, sur)
            r["t_cal"] = t_cal
            r["truth_check"] = cal.truth_check if cal is not None else None
            results[tag] = r
            report(f"{tag} seed {seed}", r)
            if a.oracle and method == "sequential":
                oracle = work / f"post_oracle_{ch}.h5"
                oracle_posterior(c, post, truth, tru, oracle, seed)
                r = forecast_and_score(a, c, oracle, work, f"oracle_{ch}", kinds, truth, sur)
                r["t_cal"], r["truth_check"] = float("nan"), None
                results[f"oracle/{ch}"] = r
                report(f"oracle/{ch} seed {seed}", r)
    return results


def refresh_truth(cfg, work: Path) -> None:
    """Write the recorded future into a truth file from before it was recorded: fabricate
    the fleet again (its future comes from its own stream) and keep the new truth only if
    the observations are the same, so the posteriors in ``work`` still belong to them."""
    obs, tru = work / "obs.h5", work / "truth.h5"
    fresh_obs, fresh_tru = work / "obs_refresh.h5", work / "truth_refresh.h5"
    fabricate(cfg, fresh_obs, fresh_tru)
    old, new = read_observations(obs), read_observations(fresh_obs)
    same = set(old.units) == set(new.units) and all(
        np.array_equal(old.units[u].channels[c], new.units[u].channels[c])
        for u in old.units for c in old.units[u].channels)
    fresh_obs.unlink()
    if not same:
        fresh_tru.unlink()
        raise SystemExit(f"{work}: fabricating again gave other observations; "
                         "remove the folder to start afresh")
    fresh_tru.replace(tru)
    print(f"{tru}: the recorded future added (observations unchanged)")


def forecast_and_score(a, c, post: Path, work: Path, name: str, kinds, truth, sur) -> dict:
    """Forecast from ``post`` (with the truth) and score it, alpha-lambda included unless
    ``--no-alpha-lambda``."""
    tru = work / "truth.h5"
    s = forecast(c, post, work / "sur.h5", work / f"fc_{name}.h5", truth_path=tru)
    for w in s.warnings:
        print(f"forecast {name}: {w}")
    r = score(c, s, kinds, truth, a.model.components)
    if not a.no_alpha_lambda:
        p = read_posterior(post)
        al, al50, cov = alpha_lambda(c, p, sur, r["eol"], cuts=ALPHA_LAMBDA_CUTS, work=work,
                                     name=name, truth=truth)
        for key, sc in (("alpha_lambda", al), ("alpha_lambda50", al50)):
            r[key] = float(np.mean([v.alpha_lambda for v in sc.values()])) \
                if sc else float("nan")
            r["counts"][key] = (sum(v.alpha_lambda for v in sc.values()), len(sc))
        r["n_al"] = len(al)
        for k, hn in cov.items():
            r["counts"][f"cover_indicator_cut{k}"] = hn
        print(f"{name}: 90 % intervals of the true indicator, forecasts made at each cut "
              "(years of record): " + ", ".join(f"{k}: {h}/{n} = {h / n:.3f}" if n else
                                                f"{k}: -" for k, (h, n) in cov.items()))
    return r


def oracle_posterior(cfg, post: Path, truth, truth_path: Path, out: Path, seed: int) -> None:
    """Write ``out``: the posterior ``post`` with each unit-year's draws, mean and quantiles
    moved so that the mean is the true input plus an error drawn from the draws' own
    covariance; draws clipped to the design box (calibration's prior never leaves it)."""
    from twinmon import artifacts
    from twinmon.calibrate import write_posterior
    p = read_posterior(post)
    names, box = p.input_names, cfg.model.bounds
    rng = np.random.default_rng(seed)
    units = {u: p.units[u] for u in p.units}            # p.units reads each unit lazily
    for u, up in units.items():
        years = list(truth.years[u])
        for k, y in enumerate(up.years):
            draws = up.samples[k]
            true = np.array([truth.inputs[u][n][years.index(y)] for n in names])
            chol = np.linalg.cholesky(np.cov(draws.T) + 1e-12 * np.eye(len(names)))
            shift = true + chol @ rng.standard_normal(len(names)) - draws.mean(axis=0)
            up.samples[k] = np.clip(draws + shift, box[:, 0], box[:, 1])
            for key in ("mean", "median", "q05", "q95"):
                getattr(up, key)[k] += shift
    made = artifacts.read_provenance(post)
    write_posterior(out, units, names, cfg, [post, truth_path],
                    surrogate_id=made.get("surrogate_id", ""))


def report(tag: str, r: dict) -> None:
    print(f"\n== {tag}: confusion (rows truth, columns verdict)")
    print(f"{'':9s}" + " ".join(f"{lab:>9s}" for lab in r["labels"]))
    for k, row in r["confusion"].items():
        print(f"{k:9s}" + " ".join(f"{row[lab]:9d}" for lab in r["labels"]))
    print(f"detected {r['detected']:.3f} of {r['n_strong']} (excess >= 2 tol); false alarms "
          f"{r['false_alarm']:.3f}; wrong component {r['wrong']:.3f}; ambiguous "
          f"{r['ambiguous']:.3f}; coverage indicator {r['cover_indicator']:.3f} inputs "
          f"{r['cover_inputs']:.3f}; failure year +-1 {r['fail_within1']:.3f} of {r['n_fail']} "
          f"(median failure year {r['fail50_within1']:.3f})")
    print("  failure years (P>5 %, median, true):",
          " ".join(f"{u} {a}/{b}/{c}" for u, (a, b, c) in sorted(r["failure_years"].items())))
    (kh, nh), (kf, nf) = r["counts"]["unreliable_healthy"], r["counts"]["unreliable_faulty"]
    print("  status unreliable (a twin that did not converge, a trend its history does not "
          f"follow, or a record too short to show a fault): healthy {kh}/{nh}, faulty {kf}/{nf}")
    (kr, nr), (kx, nx) = r["counts"]["repair_found"], r["counts"]["repair_false"]
    print(f"  unrecorded repairs found (year right, the repaired component among those named): "
          f"{kr}/{nr} repaired units; findings with no such repair: {kx} on {nx} units")
    k, n = r["counts"]["soon_missed"]
    print(f"  failing within 3 years of the record but told ok with max P(unsafe) < 5 %: "
          f"{k} of {n} (target 0){': ' + ', '.join(r['missed_soon']) if k else ''}")
    print("  counts (k/n): " + ", ".join(f"{key} {k}/{n}" for key, (k, n) in r["counts"].items()))
    if r["misses"]:
        print("  not right:", r["misses"])


if __name__ == "__main__":
    sys.exit(main())
