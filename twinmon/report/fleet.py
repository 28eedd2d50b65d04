"""The fleet overview: what a page about hundreds of units opens on.

When a report covers more units than ``report.detail_units``, the page opens on the fleet:
verdict counts, every unit ranked by its largest P(unsafe) over the horizon then its failure
year, and the fleet's time to failure (:func:`~.fig_fleet.fig_fleet_failure`). Per-unit figures
are drawn only for the units asked for (``report --unit``) and the units at risk, at most
``report.detail_units`` of them, so the page stays quick to open whatever the fleet's size.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Optional, Sequence

from ..config import Config
from ..errors import ConfigError
from .common import pct
from .unit_summary import UnitSummary


@dataclass
class FleetView:
    """Ranking, verdict counts and the units drawn in detail.

    Attributes
    ----------
    ranking : list of str
        Every unit, highest P(unsafe) first (then earliest failure year, then name); units
        without a prognosis (withheld, no forecast) last.
    counts : dict of str to int
        Units per verdict (the summary's short health words), most frequent first.
    at_risk : dict of str to list of str
        The units at risk, in rank order, with why: a failure year within the horizon, a
        verdict other than healthy, a prognosis status other than ok, a gap found by
        diagnose, or an unsafe last recording.
    requested : list of str
        Units asked for with ``report --unit``.
    detail : list of str
        Units drawn in detail, in rank order: the requested ones, then the units at risk up
        to ``report.detail_units``.
    """

    ranking: list
    counts: dict
    at_risk: dict
    requested: list = field(default_factory=list)
    detail: list = field(default_factory=list)

    @property
    def not_shown(self) -> list:
        """Units at risk left without figures (beyond ``report.detail_units``)."""
        shown = set(self.detail)
        return [u for u in self.at_risk if u not in shown]

    def as_dict(self) -> dict:
        return {"ranking": list(self.ranking), "counts": dict(self.counts),
                "at_risk": {u: list(r) for u, r in self.at_risk.items()},
                "requested": list(self.requested), "detail": list(self.detail)}


def risk_reasons(s: UnitSummary, limit: float) -> list[str]:
    """Why a unit needs a look (empty: it does not)."""
    why = []
    if s.unsafe_since is not None:
        why.append(f"{s.maybe}unsafe since year {s.unsafe_since}")
    elif s.failure_year is not None:
        why.append(f"fails in year {s.failure_year}")
    elif s.p_unsafe_max is not None and s.p_unsafe_max > limit:
        why.append(f"P(unsafe) {pct(s.p_unsafe_max)}")
    if s.root_cause not in (None, "healthy", "withheld"):
        why.append(s.short_health)
    if s.status not in ("ok", "none"):
        why.append(f"prognosis {s.status}")
    if s.diagnose is not None and s.diagnose.get("verdict") not in (None, "none"):
        why.append("diagnose: " + ("effect " + ", ".join(s.diagnose.get("effects", []))
                                   if s.diagnose["verdict"] == "effect" else "gap unexplained"))
    if s.unsafe_since is None and s.measured_unsafe_since is not None:
        # The recorded transients themselves, whatever the twin could say (a withheld
        # prognosis, no forecast).
        why.append(f"measured unsafe since year {s.measured_unsafe_since}")
    return why


def _rank_key(item: tuple[str, UnitSummary]) -> tuple:
    unit, s = item
    if s.p_unsafe_max is not None:
        group, p = 0, -s.p_unsafe_max
    else:
        group, p = (1 if s.status != "none" else 2), 0.0
    fy = s.failure_year if s.failure_year is not None else float("inf")
    return group, p, fy, unit


def check_requested(summaries: dict, requested: Sequence[str]) -> None:
    """Raise :class:`ConfigError` when a unit asked for is in none of the artifacts."""
    missing = [u for u in requested if u not in summaries]
    if missing:
        some = ", ".join(list(summaries)[:5]) + (", ..." if len(summaries) > 5 else "")
        raise ConfigError(f"--unit {missing[0]}: no such unit in the artifacts given "
                          f"({len(summaries)} units: {some or 'none'})")


def fleet_view(cfg: Config, summaries: dict[str, UnitSummary],
               requested: Sequence[str] = ()) -> FleetView:
    """Rank the fleet and choose the units drawn in detail.

    Raises
    ------
    ConfigError
        A requested unit is in none of the artifacts.
    """
    check_requested(summaries, requested)
    ranking = [u for u, _ in sorted(summaries.items(), key=_rank_key)]
    limit = cfg.safety.failure_probability
    at_risk = {}
    for u in ranking:
        why = risk_reasons(summaries[u], limit)
        if why:
            at_risk[u] = why
    counts = Counter(summaries[u].short_health for u in ranking)
    requested = list(dict.fromkeys(requested))
    room = max(cfg.report.detail_units - len(requested), 0)
    extra = [u for u in at_risk if u not in requested][:room]
    detail = [u for u in ranking if u in set(requested) | set(extra)]
    return FleetView(ranking, dict(counts.most_common()), at_risk, requested, detail)


def is_fleet(cfg: Config, n_units: int) -> bool:
    """True when the page opens on the fleet overview."""
    return n_units > cfg.report.detail_units


def failure_cell(s: UnitSummary) -> str:
    """``year 14 (+3)``: the failure year and the years after the last observation."""
    if s.unsafe_since is not None:
        return f"{s.maybe}unsafe since {s.unsafe_since}"
    if s.status == "withheld" and not s.forced:
        return ("withheld, measured unsafe since " f"{s.measured_unsafe_since}"
                if s.measured_unsafe_since is not None else "withheld")
    if s.failure_year is None:
        return "-" if s.root_cause is None else f"none by {s.horizon_end}"
    ahead = f" (+{s.failure_year - s.last_year})" if s.last_year is not None else ""
    return f"year {s.failure_year}{ahead}"


def p_cell(s: UnitSummary) -> str:
    return "-" if s.p_unsafe_max is None else pct(s.p_unsafe_max)


def overview_lines(fleet: FleetView, summaries: dict[str, UnitSummary],
                   horizon: Optional[int]) -> list[str]:
    """Plain-text lines for the terminal: counts, then the units at risk shown in detail."""
    n = len(summaries)
    counts = ", ".join(f"{k} {v}" for k, v in fleet.counts.items())
    failing = sum(1 for s in summaries.values() if s.failure_year is not None)
    lines = [f"fleet of {n} units: {counts}",
             f"{failing} fail within the horizon" + (f" ({horizon} years)" if horizon else "")
             + f"; {len(fleet.at_risk)} at risk"]
    shown = [u for u in fleet.ranking if u in set(fleet.detail)]
    if shown:
        w = max(len(u) for u in shown)
        lines += [f"{u:<{w}}  {summaries[u].short_health}  {summaries[u].time_to_failure}"
                  + (f"  -> {summaries[u].action}" if summaries[u].action else "")
                  for u in shown]
    rest = len(fleet.not_shown)
    if rest:
        lines.append(f"... and {rest} more at risk: ranked in index.html "
                     "(twinmon report --unit U draws one)")
    return lines
