"""Sim-to-real gap figures (diagnose): residual map, candidate ranking, before/after overlay."""
from __future__ import annotations

import numpy as np

from .common import LIMIT_COLOUR, Figures
from .load import Inputs


def effects_text(g) -> str:
    """The diagnosed effects: ``a / b`` for a group the data cannot tell apart, each group's
    members with their evidence share when the twin needs several effects
    (``a 60 % / b 40 % + c``)."""
    groups = getattr(g, "groups", None) or []
    if len(groups) > 1:
        return " + ".join(" / ".join(f"{m['effect']} {100 * m['weight']:.0f} %"
                                     if len(grp["members"]) > 1 else m["effect"]
                                     for m in grp["members"]) for grp in groups)
    return " / ".join(g.group) if len(g.group) > 1 else ", ".join(g.effects)


def gap_title(g) -> str:
    if g.verdict == "effect":
        eff = effects_text(g)
        return f"effect {eff}" + (f" from year {g.onset}" if g.onset is not None else "")
    if g.verdict == "unexplained":
        return "gap not explained by any candidate"
    return "no significant gap"


def fig_residual_map(figs: Figures, inp: Inputs, colours: dict) -> None:
    """Residual (observation - twin) / noise by year and time, before and after the effect."""
    from matplotlib.colors import TwoSlopeNorm
    gap, w = inp.gap, inp.words
    units = list(gap.units)
    fig = figs.new(max(4.2 * len(units) + 1.2, 9.0), 7.2)
    axes = fig.subplots(2, len(units), squeeze=False, sharex=True)
    allr = np.concatenate([np.abs(np.concatenate([g.residual_before, g.residual_after]).ravel())
                           for g in gap.units.values()])
    allr = allr[np.isfinite(allr)]
    vmax = float(max(np.quantile(allr, 0.99) if allr.size else 3.0, 3.0))
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-vmax, vmax=vmax)
    t = np.asarray(gap.time)
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    im = None
    for i, unit in enumerate(units):
        g = gap.units[unit]
        yrs = np.asarray(g.years)
        for r, (res, label) in enumerate(((g.residual_before, "base twin"),
                                          (g.residual_after, "final twin"))):
            ax = axes[r, i]
            im = ax.imshow(res, aspect="auto", origin="lower", cmap="RdBu_r", norm=norm,
                           extent=(t[0] - dt / 2, t[-1] + dt / 2, yrs[0] - 0.5, yrs[-1] + 0.5),
                           interpolation="nearest")
            for k, (name, (a, b)) in enumerate(zip(gap.windows, gap.window_bounds)):
                if t[0] < a < t[-1]:
                    ax.axvline(a, color="k", lw=1, ls="--")
                if r == 0:
                    mid = (max(a, t[0] - dt / 2) + min(b, t[-1] + dt / 2)) / 2
                    ax.text(mid, yrs[-1] + 0.45, name, ha="center", va="top", fontsize=8,
                            bbox={"fc": "white", "alpha": 0.7, "lw": 0, "pad": 1})
            if r == 0:
                for y in yrs[np.asarray(g.significant_years, bool)]:
                    ax.plot(t[-1] + dt / 2, y, "<", color="k", ms=6, clip_on=False)
                ax.set_title(f"{unit}: {gap_title(g)}\nbase twin", color=colours[unit],
                             fontsize=10)
            else:
                ax.set_title(f"after ({', '.join(g.effects) if g.effects else 'no effect added'}"
                             f"): RMS {g.rms_before:.2f} -> {g.rms_after:.2f}", fontsize=9)
                ax.set_xlabel("time since start (s)")
            if i == 0:
                ax.set_ylabel(f"year of service ({label})")
            ax.yaxis.get_major_locator().set_params(integer=True)
    cb = fig.colorbar(im, ax=axes, shrink=0.85, pad=0.01)
    cb.set_label("standardised residual (observed - twin) / noise std (-)")
    fig.suptitle(f"Where the twin misses the plant: {w.out_label} residual by year and time\n"
                 "(dashed: window boundaries; arrow: year with a significant gap)")
    figs.save(fig, "diag_residual_map", "diagnose", "Residual map",
              "Top row: residual of the base twin (degradation inputs fitted year by year); "
              f"bottom row: after adding the diagnosed effect. Red: the plant's {w.out_label} "
              "is above the twin's, blue: below. A structured band that starts in some year "
              "points at an unmodelled effect.")


def fig_candidates(figs: Figures, inp: Inputs, colours: dict) -> bool:
    """Candidate effects ranked by BIC gain, one panel per unit, group highlighted; False
    (nothing drawn) when no unit had a candidate to rank."""
    from matplotlib.ticker import StrMethodFormatter
    gap, cfg, w = inp.gap, inp.cfg, inp.words
    units = list(gap.units)
    n_c = max(len(g.candidates) for g in gap.units.values())
    if n_c == 0:
        return False
    fig = figs.new(max(4.0 * len(units) + 1.0, 8.0), 0.38 * n_c + 2.0)
    axes = fig.subplots(1, len(units), squeeze=False)[0]
    thr = cfg.diagnose.bic_gain
    for ax, unit in zip(axes, units):
        g = gap.units[unit]
        cands = list(g.candidates)
        vals = np.asarray(g.delta_bic, float)
        y = np.arange(len(cands))[::-1]
        cols = [colours[unit] if c in g.group and g.verdict == "effect"
                else ("#555555" if c in g.effects else "#bbbbbb") for c in cands]
        # -inf: a candidate the screening left unconfirmed (no fit, no bar).
        ax.barh(y, np.where(np.isfinite(vals), vals, 0.0), color=cols, edgecolor="k", lw=0.5)
        ax.set_yticks(y)
        ax.set_yticklabels(cands, fontsize=8)
        ax.axvline(thr, color=LIMIT_COLOUR, ls="--", lw=1.2, label=f"acceptance ({thr:g})")
        ax.axvline(0, color="k", lw=0.8)
        # symlog: gains span from about -10 (a useless extra parameter) to thousands.
        ax.set_xscale("symlog", linthresh=10)
        ax.xaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
        fin = vals[np.isfinite(vals)]
        hi = max(thr * 3, float(fin.max()) * 3 if fin.size else thr * 3)
        lo = min(-thr * 2, float(fin.min()) * 1.5 if fin.size else -thr)
        ax.set_xlim(lo, hi)
        for yy, v in zip(y, vals):
            if not np.isfinite(v):
                ax.text(0.0, yy, " screened out ", va="center", ha="left", fontsize=7,
                        color="#777777")
            elif np.isfinite(v):
                # Gains right of the bar's end; losses inside the bar, clear of the names.
                ax.text(v if v >= 0 else 0.0, yy,
                        f" {v:.0f} " if abs(v) >= 10 else f" {v:.1f} ", va="center",
                        ha="left" if v >= 0 else "right", fontsize=7)
        ax.set_xlabel("BIC gain over the base twin (-)")
        ax.set_title(f"{unit}: {gap_title(g)}", color=colours[unit], fontsize=10)
        ax.grid(alpha=0.3, axis="x")
        if g.verdict == "effect":
            ax.bar([0], [0], color=colours[unit],
                   label="diagnosed effect" if len(g.group) <= 1
                   else "best group (indistinguishable)")
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle("Candidate unmodelled effects ranked by BIC gain (higher explains more)")
    figs.save(fig, "diag_candidates", "diagnose", "Candidate ranking",
              "Each candidate effect is fitted with the degradation inputs through the FMU; the "
              "BIC gain says how much better the twin explains the observations with it. "
              f"A gain above {thr:g} is accepted; candidates within "
              f"{cfg.diagnose.group_bic:g} of the best cannot be told apart from the "
              f"{w.out_label} alone.")
    return True


def fig_overlay(figs: Figures, inp: Inputs, colours: dict) -> bool:
    """One affected year per unit with a gap: observation, base twin, augmented twin."""
    gap, w = inp.gap, inp.words
    hit = [u for u, g in gap.units.items() if g.verdict != "none"]
    if not hit:
        return False
    t = np.asarray(gap.time)
    fig = figs.new(max(4.6 * len(hit) + 0.6, 8.0), 6.2)
    axes = fig.subplots(2, len(hit), squeeze=False, sharex=True, height_ratios=[2.2, 1])
    for i, unit in enumerate(hit):
        g = gap.units[unit]
        yrs = np.asarray(g.years)
        cand = [int(y) for y in g.where_years] or [int(y) for y in yrs[g.significant_years]]
        rows = [int(np.flatnonzero(yrs == y)[0]) for y in cand if y in yrs] or list(range(len(yrs)))
        k = max(rows, key=lambda r: g.chi2_before[r])
        ax, axr = axes[0, i], axes[1, i]
        ax.plot(t, g.observed[k], "o", color="k", ms=4, label="observed")
        ax.plot(t, g.predicted_before[k], "-", color="grey", lw=1.6, label="base twin")
        ax.plot(t, g.predicted_after[k], "-", color=colours[unit], lw=1.6,
                label=f"twin + {', '.join(g.effects)}" if g.effects else "final twin")
        ax.set_ylabel(w.out_axis)
        ax.set_title(f"{unit}, year {int(yrs[k])}: {gap_title(g)}", color=colours[unit],
                     fontsize=10)
        ax.legend(fontsize=8, loc="best")
        ax.grid(alpha=0.3)
        axr.axhline(0, color="k", lw=0.8)
        axr.plot(t, g.residual_before[k], ".-", color="grey", label="base")
        axr.plot(t, g.residual_after[k], ".-", color=colours[unit], label="final")
        axr.set_xlabel("time since start (s)")
        axr.set_ylabel("residual / noise (-)")
        axr.legend(fontsize=7, loc="upper right", ncol=2)
        axr.grid(alpha=0.3)
    fig.suptitle("Before and after: the most affected year against the twin")
    figs.save(fig, "diag_overlay", "diagnose", "Before/after overlay",
              f"Recorded {w.out_label} of the most affected year (dots) against the base twin "
              "and the twin with the diagnosed effect; below, the standardised residuals.")
    return True
