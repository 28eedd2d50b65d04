"""Figure of the back-test section: past forecasts of the indicator against what came."""
from __future__ import annotations

import numpy as np

from ..safety import with_units
from .common import Figures, indicator_limit_line
from .load import Inputs

#: Units drawn: the ones whose history reached unsafe first, then the largest forecast errors.
MAX_UNITS = 6


def fig_backtest(figs: Figures, inp: Inputs, colours: dict) -> None:
    """Per unit, the observed indicator per year (black) and, from each cut year, the
    forecast's median (line) and its prediction interval (band, the last cut's darkest):
    where the bands missed the later years, the forecast was overconfident."""
    bt, w = inp.backtest, inp.words
    ind = w.ind

    def worst(u):
        b = bt.units[u]
        miss = [abs(b.pred_med[c, j] - b.observed[np.flatnonzero(b.years == y)[0]])
                for c, j, y in b.pairs()]
        finite = [m for m in miss if np.isfinite(m)]
        return (b.end_of_life is None, -(max(finite) if finite else 0.0))

    units = sorted(bt.units, key=worst)[:MAX_UNITS]
    if not units:
        return
    fig = figs.new(11, 2.6 * len(units) + 0.8)
    axes = np.atleast_1d(fig.subplots(len(units), 1, sharex=True, squeeze=False)[:, 0])
    cmap = __import__("matplotlib").colormaps["viridis"]
    for ax, u in zip(axes, units):
        b = bt.units[u]
        n = max(len(b.cuts), 1)
        for ci, k in enumerate(b.cuts):
            yrs = k + 1 + np.arange(b.horizon)
            col = cmap(ci / n)
            lo, med, hi = b.pred_lo[ci], b.pred_med[ci], b.pred_hi[ci]
            ok = np.isfinite(lo) & np.isfinite(hi)
            ax.fill_between(yrs[ok], lo[ok], hi[ok], color=col, alpha=0.10 + 0.25 * (ci == n - 1))
            ax.plot(yrs, np.where(np.isfinite(med), med, np.nan), color=col, lw=1.2,
                    label=f"forecast from year {k}" if ci in (0, n - 1) else None)
        obs = np.where(np.isfinite(b.observed), b.observed, np.nan)
        ax.plot(b.years, obs, "D-", color="k", ms=4, mfc="white", lw=1,
                label=f"observed {ind.name}", zorder=5)
        indicator_limit_line(ax, w)
        title = f"{u}"
        if b.end_of_life is not None:
            ax.axvline(b.end_of_life, color="k", ls=":", lw=1)
            title += f": reached unsafe in year {b.end_of_life}"
            s = bt.ttf.get(u)
            if s is not None:
                title += (f"; at year {s.cut_lambda} the predicted RUL was "
                          f"{int(s.rul_pred[list(s.rul_true).index(s.end_of_life - s.cut_lambda)])}"
                          f" (true {s.end_of_life - s.cut_lambda}), "
                          f"{'inside' if s.alpha_lambda else 'outside'} the alpha cone")
        ax.set_title(title, fontsize=10, loc="left")
        ax.set_ylabel(w.ind_axis)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    axes[-1].set_xlabel("year of service")
    cover = "n/a" if not np.isfinite(bt.coverage) else f"{100 * bt.coverage:.0f} %"
    if not bt.coverage_in_band:
        lo, hi = bt.coverage_band
        cover = (f"Only {cover}" if bt.coverage < lo else cover) + (
            f" (outside {100 * lo:.0f}-{100 * hi:.0f} %: the forecast's intervals do not hold "
            "on this history, so its failure years should not be relied on)")
    short = [f"{100 * v['coverage']:.0f} % from {n} years" for n, v in bt.by_record.items()
             if not v["in_band"]]
    # A pooled coverage can hold while the forecasts from the shortest records miss.
    short = (" Outside the band by the years recorded when the forecast was made: "
             f"{', '.join(short)}." if short else "")
    early = bt.unsafe_before_cuts
    al = (f"; alpha-lambda accuracy {100 * bt.alpha_lambda:.0f} % over {len(bt.ttf)} unit(s) "
          "that reached unsafe" if bt.ttf else "" if early
          else "; no unit reached unsafe in its history")
    if early:
        al += ("; not scored, unsafe already at the first cut: " + ", ".join(
            f"{u} (from year {y})" for u, y in early.items()))
    figs.save(fig, "fig_backtest", "backtest", f"Past forecasts of {ind.name} vs what came",
              f"Each coloured line and band is the forecast made from the years up to a cut "
              f"year; black is the {ind.name} later observed (calibrated twin, posterior "
              f"median). {cover} of the later observations fell inside the "
              f"{100 * bt.confidence:.0f} % intervals (median absolute error "
              f"{with_units(f'{bt.indicator_mae:.3g}', ind.units)}){al}.{short} Units shown: up to "
              f"{MAX_UNITS}, "
              "those that reached unsafe first, then the largest misses.")
