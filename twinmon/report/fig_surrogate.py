"""Surrogate figure (Figure 5): the reduced model against the FMU on held-out test runs."""
from __future__ import annotations

import numpy as np

from .common import Figures, indicator_rows, qty
from .load import Inputs


#: Longest label of a drawn test run that still fits two to a row under the left panel
#: (8 pt legend text in a 6.5 in panel); the DC drive's are 49 characters.
LEGEND_PAIR_CHARS = 55


def surrogate_errors(pred: np.ndarray, Y: np.ndarray) -> dict:
    """Errors of ``pred`` against ``Y`` [n_test, n_t], as ``reduce``'s validation defines them.

    ``range``: |pred - Y| as a fraction of the output's range over the test runs (defined for
    any output); ``rel``: |pred - Y| / |Y|, only where the output stays away from 0 (every
    |Y| above 1 % of that range), else None.
    """
    err = np.abs(pred - Y)
    span = float(Y.max() - Y.min())
    scale = span if span > 0 else (float(np.abs(Y).max()) or 1.0)
    away = bool(np.all(np.abs(Y) > 0.01 * scale))
    return {"range": err / scale, "rel": err / np.abs(Y) if away else None, "span": span}


def fig_surrogate(figs: Figures, inp: Inputs) -> dict:
    """Figure 5: surrogate against the FMU on the test runs; returns the error figures."""
    from matplotlib.ticker import StrMethodFormatter
    sur, sims, w = inp.surrogate, inp.sims, inp.words
    ok = sims.ok["test"]
    X, Y = sims.X["test"][ok], sims.Y["test"][ok]
    pred, var = sur.predict_with_var(X)
    e = surrogate_errors(pred, Y)
    rng, rel = e["range"], e["rel"]                     # [n_test, n_t]
    time = sims.time
    # Four runs spanning the range of responses: ordered by the indicator when it is computed
    # from the output, else by the output's mean over the record.
    key = indicator_rows(w.ind, time, Y) if w.on_output else np.nanmean(Y, axis=1)
    order = np.argsort(np.where(np.isnan(key), np.inf, key), kind="stable")
    pick = order[np.unique(np.linspace(0, len(order) - 1, min(4, len(order))).round()
                           .astype(int))]
    fig = figs.new(12, 5.6)
    a1, a2 = fig.subplots(1, 2, width_ratios=[1.25, 1])
    cmap = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd"]
    sd = np.sqrt(np.maximum(var, 0.0))
    labels = [", ".join(f"{n}={v:.3g}" for n, v in zip(sur.input_names, X[i])) for i in pick]
    for c, i, lab in zip(cmap, pick, labels):
        a1.fill_between(time, pred[i] - 1.645 * sd[i], pred[i] + 1.645 * sd[i], color=c,
                        alpha=0.25, lw=0)
        a1.plot(time, pred[i], "-", color=c, lw=1.5, label=lab)
        a1.plot(time, Y[i], "o", color=c, ms=4, mec="k", mew=0.4)
    a1.plot([], [], "ko", ms=4, label="FMU (dots)")
    a1.plot([], [], "k-", label="surrogate (lines, 90 % band)")
    a1.set_xlabel("time since start (s)")
    a1.set_ylabel(w.out_axis)
    a1.set_title(f"{len(pick)} of {len(X)} test runs")
    # Below the axes: the runs fill the plot, whatever the output's shape.
    # Two columns while a run's label is short (two inputs of short names): longer ones,
    # side by side, are wider than the panel and push the error panel off the figure.
    a1.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14),
              ncol=2 if max(map(len, labels), default=0) <= LEGEND_PAIR_CHARS else 1)
    a1.grid(alpha=0.3)
    a2.semilogy(time, 100 * rng.max(axis=0), "o-", color="#d62728", ms=3,
                label="max over test runs (% of range)")
    a2.semilogy(time, 100 * rng.mean(axis=0), "s-", color="#1f77b4", ms=3,
                label="mean over test runs (% of range)")
    if rel is not None:
        a2.semilogy(time, 100 * rel.max(axis=0), ":", color="#d62728", lw=1.2,
                    label="max (% of the FMU value)")
        a2.semilogy(time, 100 * rel.mean(axis=0), ":", color="#1f77b4", lw=1.2,
                    label="mean (% of the FMU value)")
    a2.set_xlabel("time since start (s)")
    a2.set_ylabel("error |surrogate - FMU| (%)")
    a2.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    span = float(f"{e['span']:.3g}")
    a2.set_title(f"Error per time step (test-run range {qty(span, w.out_units)})")
    a2.legend(fontsize=8, loc="best")
    a2.grid(alpha=0.3, which="both")
    mx, mn = float(rng.max()), float(rng.mean())
    title = (f"Surrogate against FMU on {len(X)} test runs: max error {100 * mx:.2f} % of the "
             f"{w.out_label} range, mean {100 * mn:.3f} %")
    out = {"n_test": int(len(X)), "max_range_error": mx, "mean_range_error": mn,
           "output_range": e["span"], "max_rel_error": float("nan"),
           "mean_rel_error": float("nan")}
    if rel is not None:
        out["max_rel_error"], out["mean_rel_error"] = float(rel.max()), float(rel.mean())
        title += (f" (relative error: max {100 * out['max_rel_error']:.2f} %, mean "
                  f"{100 * out['mean_rel_error']:.3f} %)")
    fig.suptitle(title)
    figs.save(fig, "fig5_surrogate", "surrogate", "Surrogate against FMU",
              "Left: test transients never seen in training (FMU runs as dots, surrogate "
              "prediction as lines with its 90 % predictive band). Right: error at each time "
              f"step over all test runs, as a share of the {w.out_label}'s range over them"
              + (" (dotted: relative to the FMU value)." if rel is not None else
                 "; no relative error: the output comes near 0."))
    out["coverage_90"] = float(np.mean(np.abs(pred - Y) <= 1.6449 * sd))
    return out
