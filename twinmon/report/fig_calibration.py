"""Calibration figure (Figure 6): posterior estimates of the degradation inputs per year."""
from __future__ import annotations

import numpy as np

from .common import Figures, input_label
from .load import Inputs, truth_at


def fig_estimates(figs: Figures, inp: Inputs, colours: dict) -> dict:
    """Figure 6: posterior estimates per year with 90 % intervals (+ truth). Returns truth
    errors per input when the truth is known."""
    post, cfg, truth = inp.posterior, inp.cfg, inp.truth
    names, units = list(post.input_names), list(post.units)
    fig = figs.new(3.6 * len(units) + 0.8, 2.9 * len(names) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(names), len(units), sharey="row", sharex=True,
                                      squeeze=False))
    errors: dict = {}
    for j, name in enumerate(names):
        rel, cover = [], []
        for i, unit in enumerate(units):
            ax = axes[j, i]
            p = post.units[unit]
            yrs = np.asarray(p.years)
            m, lo, hi = p.mean[:, j], p.q05[:, j], p.q95[:, j]
            # A skewed posterior may put its mean outside its 90 % interval.
            ax.errorbar(yrs, m, yerr=[np.maximum(m - lo, 0), np.maximum(hi - m, 0)], fmt="o",
                        ms=4, capsize=3,
                        color=colours[unit], label="estimate (90 % interval)")
            tv = truth_at(truth, unit, name, yrs)
            if tv is not None:
                ax.plot(yrs, tv, "D", ms=4, color="k", mfc="none", label="true value")
                ok = np.isfinite(tv) & (tv != 0)
                rel.append(np.abs(m[ok] - tv[ok]) / np.abs(tv[ok]))
                ok = np.isfinite(tv)
                cover.append((lo[ok] <= tv[ok]) & (tv[ok] <= hi[ok]))
            if j == 0:
                ax.set_title(unit, color=colours[unit], fontweight="bold")
            if j == len(names) - 1:
                ax.set_xlabel("year of service")
            if i == 0:
                ax.set_ylabel(input_label(cfg, name))
            ax.xaxis.get_major_locator().set_params(integer=True)
            ax.grid(alpha=0.3)
        if rel:
            r, c = np.concatenate(rel), np.concatenate(cover)
            if r.size and c.size:
                errors[name] = {"max_rel_error": float(r.max()),
                                "mean_rel_error": float(r.mean()),
                                "coverage_90": float(c.mean())}
    axes[0, -1].legend(fontsize=8, loc="best")
    title = "Calibrated degradation inputs per year (posterior mean and 90 % interval)"
    if errors:
        title += "\n" + "; ".join(
            f"{n}: error max {100 * e['max_rel_error']:.1f} %, mean "
            f"{100 * e['mean_rel_error']:.1f} %, 90 % coverage {100 * e['coverage_90']:.0f} %"
            for n, e in errors.items())
    fig.suptitle(title)
    figs.save(fig, "fig6_estimates", "calibration", "Estimates per year",
              "Each year's recorded transient is calibrated by Bayesian inference through the "
              "surrogate; dots are posterior means, bars the 90 % credible intervals"
              + (", open diamonds the true values used to fabricate the data." if errors
                 else "."))
    return errors
