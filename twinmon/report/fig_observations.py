"""Observations figures: the last recorded transient per unit (Figure 2) and the observed
health indicator per year (Figure 3)."""
from __future__ import annotations

import numpy as np

from .common import LIMIT_COLOUR, Figures, Words, indicator_limit_line, qty
from .load import Inputs

#: Colour of the marks that say where the indicator is read (not a limit: not red).
MARK_COLOUR = "#444444"


def _indicator_marks(ax, w: Words, t_end: float) -> str:
    """Draw on an output-vs-time axis where the indicator is read and, when the indicator is
    computed from this output, its level or limit; return the words for the caption."""
    ind, spec = w.ind, w.ind.spec
    kind = spec.kind
    words = []
    if kind == "time_to_reach":
        verb = "reach" if spec.direction == "up" else "fall to"
        level = qty(float(spec.level), w.var_units)
        if w.on_output:
            ax.axhline(float(spec.level), color=LIMIT_COLOUR, ls="--", lw=1.2,
                       label=f"{ind.name} level ({level})")
            words.append(f"The {ind.name} is the time the {w.var_label} takes to {verb} the "
                         f"dashed level ({level})")
        else:
            words.append(f"The {ind.name} is the time the {w.var_label} (not drawn here) takes "
                         f"to {verb} {level}")
        ax.axvline(ind.limit, color=LIMIT_COLOUR, ls=":", lw=1.5, label=f"{w.limit_text} limit")
        late = "after" if ind.sense > 0 else "before"
        words.append(f"a crossing {late} the dotted {w.limit_text} line is unsafe"
                     if w.on_output else f"dotted: the {w.limit_text} limit")
        return "; ".join(words) + "."
    if kind == "value_at":
        ax.axvline(float(spec.at), color=MARK_COLOUR, ls=":", lw=1.5,
                   label=f"{ind.name} read at {spec.at:g} s")
        words.append(f"The {ind.name} is the {w.var_label} at {spec.at:g} s (dotted line)")
    elif kind in ("max", "min", "mean"):
        what = {"max": "maximum", "min": "minimum", "mean": "mean"}[kind]
        if spec.window is not None:
            a, b = float(spec.window[0]), float(spec.window[1])
            ax.axvspan(max(a, 0.0), min(b, t_end * 1.02), color=MARK_COLOUR, alpha=0.08, lw=0,
                       label=f"{ind.name} window ({a:g}-{min(b, t_end):g} s)")
            words.append(f"The {ind.name} is the {what} of the {w.var_label} over the shaded "
                         "window")
        else:
            words.append(f"The {ind.name} is the {what} of the {w.var_label} over the record")
    else:  # final
        ax.axvline(t_end, color=MARK_COLOUR, ls=":", lw=1.5, label=f"{ind.name}: last sample")
        words.append(f"The {ind.name} is the last sample of the {w.var_label} (dotted line)")
    if w.on_output:
        ax.axhline(ind.limit, color=LIMIT_COLOUR, ls="--", lw=1.2,
                   label=f"{w.limit_text} limit ({w.side} is unsafe)")
        words.append(f"dashed: its {w.limit_text} limit")
    else:
        words[-1] = words[-1].replace(f"the {w.var_label}", f"the {w.var_label} (not drawn here)")
    return "; ".join(words) + "."


def fig_last_transients(figs: Figures, inp: Inputs, colours: dict, observed: dict) -> None:
    """Figure 2: the last recorded transient of every unit, with where the indicator is read.

    ``observed``: {unit: (years, indicator)} from :func:`~.load.observed_indicator`."""
    obs, w = inp.obs, inp.words
    fig = figs.new(8, 4.8)
    ax = fig.add_subplot()
    for unit, u in obs.units.items():
        y = obs.output_of(unit)[-1]
        ok = np.isfinite(y)
        label = f"{unit} (year {int(u.years[-1])}"
        if unit in observed:
            label += f", {w.ind.name} {w.ind.fmt(float(observed[unit][1][-1]))}"
        ax.plot(obs.time[ok], y[ok], "o-", ms=4, lw=1.2, color=colours[unit], label=label + ")")
    marks = _indicator_marks(ax, w, float(obs.time[-1]))
    ax.set_xlabel("time since start (s)")
    ax.set_ylabel(w.out_axis)
    ax.set_xlim(0, obs.time[-1] * 1.02)
    ax.set_title("Last recorded transient per unit")
    ax.legend(loc="best", fontsize=9)
    ax.grid(alpha=0.3)
    figs.save(fig, "fig2_last_transients", "observations", "Last recorded transients",
              f"Measured {w.out_label} of each unit's last recorded transient (dots: samples). "
              f"{marks} The unit is unsafe when {w.unsafe_text}.")


def fig_indicator_history(figs: Figures, inp: Inputs, colours: dict, observed: dict) -> None:
    """Figure 3: the health indicator of each recorded transient, per year, with its limit."""
    w = inp.words
    ind = w.ind
    ttr = w.kind == "time_to_reach"
    record = float(inp.obs.time[-1])
    fig = figs.new(8, 4.8)
    ax = fig.add_subplot()
    never = False
    values = []
    for unit, (yrs, v) in observed.items():
        fin = np.isfinite(v)
        values.append(v[fin])
        ax.plot(yrs[fin], v[fin], "o-", color=colours[unit], label=unit)
        if ttr and np.isinf(v).any():
            never = True
            inf = np.isinf(v)
            ax.plot(yrs[inf], np.full(inf.sum(), record), "^", ms=9, color=colours[unit],
                    mec="k")
    indicator_limit_line(ax, w)
    if never:
        ax.plot([], [], "^", color="grey", mec="k", label=f"not reached within {record:g} s")
    ax.set_xlabel("year of service")
    ax.set_ylabel(w.ind_axis)
    ax.set_title(f"Observed {ind.label} ({ind.name}) per year")
    ax.xaxis.get_major_locator().set_params(integer=True)
    vals = np.concatenate(values + [[ind.limit]] + ([[record]] if never else []))
    lo, hi = float(vals.min()), float(vals.max())
    if ttr and lo >= 0:            # a time since start: 0 is its natural origin
        ax.set_ylim(0, max(ind.limit * 1.1, hi * 1.08))
    else:
        pad = 0.08 * ((hi - lo) or abs(hi) or 1.0)
        ax.set_ylim(lo - pad, hi + pad)
    ax.legend(loc="best", fontsize=9)
    ax.grid(alpha=0.3)
    how = "linear interpolation between samples, " if ttr or w.kind == "value_at" else ""
    label = ind.label[:1].upper() + ind.label[1:]
    figs.save(fig, "fig3_indicator_history", "observations", f"{ind.name} history",
              f"{label} ({ind.name}) computed from each year's recorded transient ({how}"
              "missing samples left out). A drift towards the limit hints at a fault but does "
              "not say which component.")
