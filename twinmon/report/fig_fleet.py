"""Fleet figure: time to failure across the fleet (the overview of a large fleet)."""
from __future__ import annotations

import numpy as np

from .common import LIMIT_COLOUR, Figures
from .load import Inputs


def fig_fleet_failure(figs: Figures, inp: Inputs, summaries: dict) -> bool:
    """Units by years to failure, and the fleet's failures and expected unsafe units per
    year ahead. Returns False (no figure) when no unit has a prognosis.

    ``summaries``: {unit: UnitSummary}; years are counted from each unit's last observation,
    so units observed up to different years line up.
    """
    w, limit = inp.words, inp.cfg.safety.failure_probability
    with_p = [s for s in summaries.values() if s.p_unsafe_ahead]
    if not with_p:
        return False
    h = max(len(s.p_unsafe_ahead) for s in with_p)
    ahead = np.arange(1, h + 1)
    fails = np.array([s.failure_year - s.last_year for s in with_p
                      if s.failure_year is not None and s.last_year is not None], int)
    n_fail = np.array([np.sum(fails == k) for k in ahead])
    n_none = len(with_p) - fails.size
    n_judged_not = len(summaries) - len(with_p)
    # P(unsafe) of each unit per year ahead (a shorter horizon keeps its last value).
    p = np.array([np.pad(s.p_unsafe_ahead, (0, h - len(s.p_unsafe_ahead)), mode="edge")
                  for s in with_p])

    fig = figs.new(11, 4.2)
    ax1, ax2 = fig.subplots(1, 2, width_ratios=[1.25, 1])
    x = np.arange(h + 2)
    heights = np.concatenate([n_fail, [n_none, n_judged_not]])
    colours = [LIMIT_COLOUR] * h + ["#2ca02c", "#bbbbbb"]
    bars = ax1.bar(x, heights, color=colours, edgecolor="k", lw=0.5)
    ax1.bar_label(bars, [str(int(v)) if v else "" for v in heights], fontsize=8, padding=2)
    ax1.set_xticks(x, [str(k) for k in ahead] + [f"none in\n{h} years", "no\nprognosis"],
                   fontsize=8)
    ax1.set_xlabel("years from the last observation to the failure year")
    ax1.set_ylabel("units")
    ax1.set_ylim(0, max(heights.max(), 1) * 1.15)
    ax1.set_title(f"When the {len(summaries)} units fail", fontsize=10)
    ax1.grid(alpha=0.3, axis="y")

    failed = np.cumsum(n_fail)
    b2 = ax2.bar(ahead, failed, color=LIMIT_COLOUR, alpha=0.35, edgecolor=LIMIT_COLOUR,
                 label=f"units past their failure year (P(unsafe) > {100 * limit:g} %)")
    ax2.bar_label(b2, [str(int(v)) for v in failed], fontsize=8, padding=2)
    ax2.plot(ahead, p.sum(axis=0), "o-", color="k", ms=4, lw=1.2,
             label="expected unsafe units (sum of P(unsafe))")
    ax2.set_xticks(ahead)
    ax2.set_xlabel("years from the last observation")
    ax2.set_ylabel("units")
    ax2.set_ylim(0, max(float(failed[-1]), float(p.sum(axis=0).max()), 1.0) * 1.3)
    ax2.set_title("Fleet failures over the horizon", fontsize=10)
    ax2.legend(fontsize=8, loc="upper left")
    ax2.grid(alpha=0.3)
    fig.suptitle(f"Time to failure across the fleet ({w.ind.name} {w.side} {w.limit_text})")
    figs.save(fig, "fleet_failure", "fleet", "Time to failure across the fleet",
              "Left: units by the number of years from their last observation to their failure "
              "year (the first year whose P(unsafe) passes "
              f"{100 * limit:g} %), those that do not fail within the horizon, and those "
              "without a prognosis (withheld or not forecast). Right: how many units are past "
              "their failure year by each year ahead (bars), and the expected number of unsafe "
              "units that year (the sum of the units' P(unsafe)).")
    return True
