"""Forecast figures: trends of the inputs (Figure 7), their forecast distributions
(Figure 8) and the health indicator's distribution per year with P(unsafe) (Figure 9)."""
from __future__ import annotations

from typing import Optional

import numpy as np

from .common import (LIMIT_COLOUR, Figures, indicator_limit_line, input_label, named, pct,
                     state_words)
from .load import Inputs, truth_at


def fig_trends(figs: Figures, inp: Inputs, colours: dict) -> None:
    """Figure 7: trend lines with prediction intervals over the horizon."""
    fc, cfg, truth = inp.forecast, inp.cfg, inp.truth
    names, units = list(fc.input_names), list(fc.units)
    conf = fc.confidence
    fig = figs.new(3.6 * len(units) + 0.8, 2.9 * len(names) + 0.6)
    axes = np.atleast_2d(fig.subplots(len(names), len(units), sharey="row", sharex=True,
                                      squeeze=False))
    try:
        # The values the model can take (a drag is not negative): the band is held there.
        # (From the model description as it is: the report builds no FMU.)
        from ..simulate import declared_range
        rng = dict(zip(cfg.model.input_names, declared_range(cfg, build=False)))
    except Exception:  # noqa: BLE001 -- the FMU is not needed to draw the report
        rng = {}
    for j, name in enumerate(names):
        for i, unit in enumerate(units):
            ax = axes[j, i]
            u = fc.units[unit]
            c = colours[unit]
            yo, yf = np.asarray(u.years_observed), np.asarray(u.years_future)
            t = u.trends[name]
            # The line of the part in place: fitted on its last n years (after a repair).
            first = yo[-t.n] if 0 < t.n <= yo.size else yo[0]
            grid = np.linspace(first, yf[-1], 200)
            mean, lo, hi, _ = t.predict(grid, conf)
            if name in rng:
                lo, hi = np.clip(lo, *rng[name]), np.clip(hi, *rng[name])
            ax.fill_between(grid, lo, hi, color=c, alpha=0.2, lw=0)
            ax.plot(grid, mean, "-", color=c, lw=1.5)
            ax.plot(yo, u.estimates[name], "x", color="k", ms=6, mew=1.5)
            tv = truth_at(truth, unit, name, yo)
            if tv is not None:
                ax.plot(yo, tv, "o", ms=4, color="k", mfc="none")
            if u.has_truth and u.true_inputs is not None:
                ax.plot(yf, u.true_inputs[name], "o", ms=4, color="grey", mfc="none")
            ax.axvline(yo[-1] + 0.5, color="grey", ls=":", lw=1)
            # The slope in the corner the line leaves free.
            up = t.slope >= 0
            # Beyond normal ageing alone, where the unit's tests together found no fault:
            # not the fault's red.
            lone = t.rejects and u.root_cause == "healthy"
            ax.text(0.03 if up else 0.97, 0.95, f"slope {t.slope:+.3g}/yr"
                    + (("\nbeyond normal alone (p = %.1g)" if lone else "\nabnormal (p = %.1g)")
                       % t.p_value if t.rejects else ""),
                    transform=ax.transAxes, ha="left" if up else "right", va="top", fontsize=9,
                    color="darkorange" if lone else LIMIT_COLOUR if t.rejects else "k",
                    bbox={"fc": "white", "alpha": 0.8, "lw": 0})
            if j == 0:
                ax.set_title(f"{unit}: {state_words(u.root_cause, u.status_reason, named(u))}",
                             color=c,
                             fontweight="bold")
            if j == len(names) - 1:
                ax.set_xlabel("year of service")
            if i == 0:
                ax.set_ylabel(input_label(cfg, name))
            ax.xaxis.get_major_locator().set_params(integer=True)
            ax.grid(alpha=0.3)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    handles = [Line2D([], [], color="k", lw=1.5, label="linear trend (unit colour)"),
               Patch(color="grey", alpha=0.3, label=f"{100 * conf:g} % prediction interval"),
               Line2D([], [], ls="", marker="x", color="k", mew=1.5, label="yearly estimate")]
    if truth is not None:
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", color="k",
                              label="true value"))
    sources = {f.truth_source for f in fc.units.values() if f.has_truth}
    if sources:
        # Recorded futures (jitter included) or, from older truth files, fitted lines.
        handles.append(Line2D([], [], ls="", marker="o", mfc="none", color="grey",
                              label="true future" if sources == {"recorded future"}
                              else "true trend, extended"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=9)
    # A posterior that weighed bent shapes forecasts with them too: the straight line drawn
    # here is then one view of the trend, not the forecast's (figure 9 is).
    bent = any(isinstance(p, (int, float)) and k != "line" and p > 0.05
               for f in fc.units.values() for k, p in (f.shape or {}).items())
    fig.suptitle(f"Straight-line trends of the estimates, {len(yf)} years ahead, with "
                 f"{100 * conf:g} % prediction intervals (dotted: last observation)"
                 + ("\nthe forecast also weighs accelerating and changed trends: see the "
                    "indicator forecast's figure" if bent else ""))
    figs.save(fig, "fig7_trends", "forecast", "Trends with prediction intervals",
              "A straight line is fitted to each input's yearly estimates (crosses) and extended "
              "past the last observation; the band is where a new year's value is expected with "
              f"{100 * conf:g} % probability. A slope beyond normal ageing is marked abnormal.")


def selected_years(years_future: np.ndarray) -> list[int]:
    """Future years shown in Figure 8: next year, three years on, end of the horizon."""
    first = int(years_future[0])
    want = [first, first + 2, int(years_future[-1])]
    return [y for y in dict.fromkeys(want) if y in set(years_future.tolist())]


#: Share of a forecast input's draws left out at each end of figure 8's axis: a few draws
#: of a wear shape extended far (an exponential's tail: 0.9 % of a water heater's draws)
#: would set a range tens of times the bulk's and squeeze every histogram into a bin.
MARGINAL_TAIL = 0.01


def shown_range(draws: list, marks=()) -> tuple[float, float]:
    """Figure 8's axis range for one input: the draws of every year drawn without their
    extreme :data:`MARGINAL_TAIL` at each end, and the ``marks`` (true values), padded."""
    lo = min(float(np.nanquantile(x, MARGINAL_TAIL)) for x in draws)
    hi = max(float(np.nanquantile(x, 1 - MARGINAL_TAIL)) for x in draws)
    finite = [m for m in marks if np.isfinite(m)]
    lo, hi = min([lo] + finite), max([hi] + finite)
    pad = 0.04 * (hi - lo) if hi > lo else max(abs(lo), 1.0) * 0.05
    return lo - pad, hi + pad


def fig_marginals(figs: Figures, inp: Inputs, colours: dict) -> list[str]:
    """Figure 8: marginal distributions of the forecast inputs; returns the units shown."""
    import matplotlib
    fc, cfg, w = inp.forecast, inp.cfg, inp.words
    names = list(fc.input_names)
    faulty = [u for u, f in fc.units.items() if f.root_cause not in ("healthy", "withheld")]
    shown = faulty or list(fc.units)
    fig = figs.new(4.6 * len(names) + 0.6, 2.9 * len(shown) + 0.7)
    axes = np.atleast_2d(fig.subplots(len(shown), len(names), squeeze=False))
    cmap = matplotlib.colormaps["viridis"]
    for i, unit in enumerate(shown):
        u = fc.units[unit]
        yrs = selected_years(np.asarray(u.years_future))
        idxs = [int(np.flatnonzero(u.years_future == y)[0]) for y in yrs]
        for j, name in enumerate(names):
            ax = axes[i, j]
            truth = ([float(u.true_inputs[name][idx]) for idx in idxs]
                     if u.has_truth and u.true_inputs is not None else [])
            shown = shown_range([u.samples[idx, :, j] for idx in idxs], truth)
            for k, (y, idx) in enumerate(zip(yrs, idxs)):
                x = u.samples[idx, :, j]
                col = cmap(k / max(len(yrs) - 1, 1) * 0.85)
                ax.hist(x, bins=40, range=shown, density=True, histtype="stepfilled",
                        alpha=0.3, color=col)
                ax.hist(x, bins=40, range=shown, density=True, histtype="step", lw=1.3,
                        color=col, label=f"year {y}")
                if truth:
                    ax.axvline(truth[k], color=col, ls="--", lw=1)
            ax.set_xlim(*shown)
            spec = cfg.model.inputs.get(name)
            if spec is not None:
                x0, x1 = ax.get_xlim()
                if x0 < spec.low:
                    ax.axvspan(x0, spec.low, color="grey", alpha=0.15, lw=0)
                if x1 > spec.high:
                    ax.axvspan(spec.high, x1, color="grey", alpha=0.15, lw=0)
                ax.set_xlim(x0, x1)
            ax.set_xlabel(input_label(cfg, name))
            ax.set_ylabel("probability density")
            words = state_words(u.root_cause, u.status_reason, named(u))
            ax.set_title(f"{unit} ({words}): {name}",
                         color=colours[unit], fontsize=10)
            ax.grid(alpha=0.3)
            if j == 0:
                if u.has_truth:
                    ax.plot([], [], "k--", lw=1, label="true value")
                ax.legend(fontsize=8)
    fig.suptitle("Forecast distributions of the degradation inputs"
                 + (" (units with a detected fault)" if faulty else "")
                 + "\ngrey background: outside the surrogate's training box (the FMU is run "
                 "there)")
    figs.save(fig, "fig8_marginals", "forecast", "Marginal distributions of the forecast inputs",
              "Monte Carlo samples of each input for the next year, three years on and the end "
              "of the horizon, drawn from the trend's predictive distribution; they are "
              f"propagated through the twin to get the {w.ind.name} distribution of Figure 9.")
    return shown


def _box_data(rows, ttr: bool, cap: float) -> list[np.ndarray]:
    """Values per box: for a time to reach, a level never reached (inf) or a failed run (NaN)
    is drawn at ``cap``; for other indicators a failed run (NaN) is left out of the box."""
    out = []
    for r in rows:
        r = np.asarray(r, float)
        if ttr:
            out.append(np.clip(np.nan_to_num(r, nan=np.inf), None, cap))
        else:
            fin = r[np.isfinite(r)]
            out.append(fin if fin.size else np.array([np.nan]))
    return out


def failure_words(u, last_year: int) -> str:
    """Figure 9's verdict on unit forecast ``u``: its failure year, none by ``last_year``,
    or, for a prognosis withheld (not forced), no failure year at all: the P(unsafe) drawn
    beside it may pass the limit, but the forecast does not date a failure it withholds."""
    if u.status == "withheld" and not u.forced:
        return "no failure year (prognosis withheld)"
    if getattr(u, "unsafe_since", None) is not None:
        # Past the limit in its last recorded years already: the first future year past it
        # says nothing of when.
        return f"unsafe since year {u.unsafe_since}"
    if u.failure_year is not None:
        return f"fails in year {u.failure_year}"
    return f"no failure by year {last_year}"


def fig_indicator_forecast(figs: Figures, inp: Inputs, colours: dict,
                           observed: Optional[dict]) -> None:
    """Figure 9: the indicator's distribution per year per unit, P(unsafe), failure year.

    ``observed``: {unit: (years, indicator)} measured on the recorded transients, or None."""
    fc, safety, w = inp.forecast, inp.cfg.safety, inp.words
    ind = w.ind
    ttr = w.kind == "time_to_reach"
    units = list(fc.units)
    record = float(inp.cfg.model.output.times.stop)
    cap = record * 1.04                                    # "never reached" drawn here
    fig = figs.new(11, 3.1 * len(units) + 0.6)
    axes = np.atleast_1d(fig.subplots(len(units), 1, sharex=True, squeeze=False)[:, 0])
    limit = safety.failure_probability
    for ax, unit in zip(axes, units):
        u = fc.units[unit]
        c = colours[unit]
        yo, yf = np.asarray(u.years_observed), np.asarray(u.years_future)
        data_o = _box_data(u.indicator_observed, ttr, cap)
        data_f = _box_data(u.indicator, ttr, cap)
        kw = dict(widths=0.6, whis=(5, 95), showfliers=False, patch_artist=True,
                  medianprops={"color": "k"})
        bo = ax.boxplot(data_o, positions=yo, **kw)
        bf = ax.boxplot(data_f, positions=yf, **kw)
        for b in bo["boxes"]:
            b.set(facecolor=c, alpha=0.35)
        for b in bf["boxes"]:
            b.set(facecolor=c, alpha=0.8)
        if observed is not None and unit in observed:
            oy, ov = observed[unit]
            ov = np.clip(ov, None, cap) if ttr else ov
            ax.plot(oy, ov, "D", color="k", ms=4, mfc="white", label=f"measured {ind.name}",
                    zorder=5)
        indicator_limit_line(ax, w)
        # The P(unsafe) labels sit at a fixed height of the axes, whatever its range.
        lab = ax.get_xaxis_transform()
        for y, p in zip(yf, u.p_unsafe):
            ax.text(y, 0.97, pct(p), ha="center", va="top", fontsize=8, transform=lab,
                    color=LIMIT_COLOUR if p > limit else "k")
        if u.failure_year is not None:
            ax.axvspan(u.failure_year - 0.45, u.failure_year + 0.45, color=LIMIT_COLOUR,
                       alpha=0.12, lw=0, label=f"failure year {u.failure_year}")
        if u.has_truth and u.true_failure_year is not None:
            ax.plot([u.true_failure_year], [0.86], "v", color="k", ms=8, transform=lab,
                    label=f"true failure year {u.true_failure_year}")
        ax.axvline(yo[-1] + 0.5, color="grey", ls=":", lw=1)
        _zoom(ax, data_o, data_f, ind.limit, ttr, cap)
        ax.set_ylabel(w.ind_axis)
        ax.set_title(f"{unit} ({state_words(u.root_cause, u.status_reason, named(u))}): "
                     + failure_words(u, int(yf[-1])) + "; numbers: P(unsafe) per future year",
                     color=c, fontsize=10, loc="left")
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8, loc="upper left")
    axes[-1].set_xlabel("year of service (light boxes: observed years from the posterior; "
                        "dark boxes: forecast)")
    ticks = np.arange(min(int(fc.units[u].years_observed[0]) for u in units),
                      max(int(fc.units[u].years_future[-1]) for u in units) + 1)
    axes[-1].set_xticks(ticks)
    axes[-1].set_xticklabels([str(t) for t in ticks])
    label = ind.label[:1].upper() + ind.label[1:]
    fig.suptitle(f"{label} ({ind.name}): distribution per year (box 25-75 %, whiskers 5-95 %)"
                 + (f"\nvalues at the top never reached the level within {record:g} s" if ttr
                    else ""))
    physical = " (or leaving the physical domain)" if w.has_nonphysical else ""
    failed = ("" if ttr else " Failed twin runs are left out of the boxes but counted unsafe.")
    figs.save(fig, "fig9_indicator_forecast", "forecast", f"{ind.name} distribution per year",
              f"The forecast inputs pushed through the twin give a {ind.name} distribution per "
              f"year. The unit fails in the first year whose probability of being {w.side} "
              f"{w.limit_text}{physical} passes {100 * limit:g} % (shaded).{failed}")


def _zoom(ax, data_o, data_f, limit: float, ttr: bool, cap: float) -> None:
    """Zoom on the boxes (narrow ones vanish on a wide axis); keep the limit in view, and the
    "never reached" level when some draw never reached it."""
    boxes = [np.ravel(d)[np.isfinite(np.ravel(d))] for d in data_o + data_f]
    boxes = [b for b in boxes if b.size]
    if not boxes:
        return
    allv = np.concatenate(boxes)
    lo_v = float(np.quantile(allv, 0.01))
    hi_v = float(np.max([np.quantile(b, 0.95) for b in boxes]))
    if ttr and lo_v >= 0:
        top = cap * 1.02 if hi_v >= cap else max(limit, hi_v) * 1.12 + 1.0
        ax.set_ylim(max(0.0, min(lo_v, limit) * 0.85 - 1.0), top * 1.08)
        return
    lo, hi = min(lo_v, limit), max(hi_v, limit)
    span = (hi - lo) or abs(hi) or 1.0
    # Room at the top for the P(unsafe) labels.
    ax.set_ylim(lo - 0.1 * span, hi + 0.3 * span)
