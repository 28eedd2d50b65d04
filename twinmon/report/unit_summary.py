"""The plain-language state of one unit: what the report's tables, its terminal text and
``summary.json`` say about it."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..safety import trailing_run  # noqa: F401  (re-exported: the report's helpers)
from .common import pct, state_words, withheld_words


@dataclass
class UnitSummary:
    """Plain-language state of one unit, derived from the artifacts given.

    Attributes
    ----------
    name : str
    health : str
        ``"healthy"``, ``"degrading: <component>"`` (components from the config's inputs), ...
        or ``"unknown"`` when no forecast was given.
    root_cause : str or None
        The forecast's verdict (``healthy``, a component name, ``both``), None without one.
    failure_year : int or None
        First future year with P(unsafe) above the limit (year of service): the year to act by.
    median_failure_year : int or None
        First future year with P(unsafe) >= 0.5: the point forecast of the failure.
    p_unsafe : float or None
        P(unsafe) in the failure year, or the largest over the horizon when none fails.
    last_year : int or None
        Last observed (or calibrated) year.
    horizon_end : int or None
        Last forecast year.
    last_indicator : float or None
        Health indicator of the last recorded transient (its units); inf for a level never
        reached.
    indicator : str
        The health indicator's name (from the config).
    last_indicator_text : str
        ``last_indicator`` for people, with its units.
    action : str
        Short recommendation, e.g. ``"inspect the <component> before year 13 ends"``.
    plan : str
        The forecast's full maintenance plan with its evidence ("" without a forecast).
    estimates : dict
        Latest year's estimate per input: ``{name: {year, mean, q05, q95, units}}``.
    confidence : str
        What the statements rest on (tests, diagnostics), in one or two sentences.
    diagnose : dict or None
        The sim-to-real gap verdict of this unit, if a gap artifact was given.
    true_failure_year : int or None
        From the forecast's truth check, when the data were fabricated.
    unsafe_since : int or None
        The first of the last recorded years in a row whose P(unsafe) (the posterior's, through
        the twin) is above the limit, when the last one's is: the unit is unsafe already, and
        ``failure_year`` (the year after the record) is only the year to act by.
    measured_unsafe_since : int or None
        The same from the indicator of each recorded transient itself (no twin): the first of
        the last recorded years in a row whose measured indicator is past the limit. It holds
        whatever the prognosis's status, a withheld one included.
    """

    name: str
    health: str = "unknown"
    root_cause: Optional[str] = None
    #: The components the verdict names (several for root cause ``both``).
    components: list = field(default_factory=list)
    failure_year: Optional[int] = None
    median_failure_year: Optional[int] = None
    p_unsafe: Optional[float] = None
    last_year: Optional[int] = None
    horizon_end: Optional[int] = None
    last_indicator: Optional[float] = None
    indicator: str = "indicator"
    last_indicator_text: str = ""
    action: str = ""
    plan: str = ""
    estimates: dict = field(default_factory=dict)
    confidence: str = ""
    diagnose: Optional[dict] = None
    true_failure_year: Optional[int] = None
    #: The prognosis status (``ok``, ``withheld``, ``unreliable``; ``none`` without a
    #: forecast), why, and whether a withheld prognosis was forced.
    status: str = "none"
    status_reason: str = ""
    forced: bool = False
    #: Largest P(unsafe) over the horizon, and P(unsafe) 1, 2, ... years after the last
    #: observation (the fleet overview ranks and sums them); None / () without a prognosis.
    p_unsafe_max: Optional[float] = None
    p_unsafe_ahead: tuple = ()
    unsafe_since: Optional[int] = None
    measured_unsafe_since: Optional[int] = None
    #: P(unsafe) of the last recorded year (the posterior's, through the twin).
    p_unsafe_last: Optional[float] = None

    @property
    def status_words(self) -> str:
        """The status as a maintenance engineer reads it at a glance."""
        return {"ok": "prognosis given: the twin fits the data",
                "withheld": withheld_words(self.status_reason, self.forced),
                "unreliable": "prognosis unreliable (the reason is given with the unit)",
                "none": "no forecast"}.get(self.status, self.status)

    @property
    def short_health(self) -> str:
        if self.status == "withheld" and not self.forced:
            return "prognosis withheld"
        if self.root_cause is None and self.health != "unknown":
            return self.health              # not forecast, and why (too few years)
        words = state_words(self.root_cause, self.status_reason, self.components)
        return f"{words} (forced)" if self.forced else \
            f"{words} (unreliable)" if self.status == "unreliable" else words

    @property
    def median_note(self) -> str:
        """``"; median year 15"`` where the median failure year (the point forecast) differs
        from the year to act by, ``"; median after year 17"`` past the horizon, else ""."""
        med = self.median_failure_year
        if self.failure_year is None or med == self.failure_year:
            return ""
        return f"; median year {med}" if med is not None else \
            f"; median after year {self.horizon_end}"

    @property
    def maybe(self) -> str:
        """``"possibly "`` before "unsafe since" while the last year's P(unsafe) is past
        the limit but under even odds ("unsafe" alone would overstate it), else ""."""
        return "" if self.p_unsafe_last is None or self.p_unsafe_last >= 0.5 else "possibly "

    @property
    def time_to_failure(self) -> str:
        """e.g. ``"fails in year 14 (P(unsafe) 12 % in 14; median year 15)"`` (the median
        year where it differs from the year to act by)."""
        measured = (f"; measured unsafe since year {self.measured_unsafe_since}"
                    if self.measured_unsafe_since is not None else "")
        if self.status == "withheld" and not self.forced:
            from ..forecast.judge import box_bound_of
            return ("withheld: the plant is at the twin's box" if box_bound_of(self.status_reason)
                    else "withheld: the twin misses the plant") + measured
        if self.root_cause is None:
            if self.last_indicator is None:
                return "no forecast"
            return f"last {self.indicator} {self.last_indicator_text} (no forecast)"
        if self.unsafe_since is not None:
            # Unsafe already: the year after the record is only the year to act by. Past the
            # limit (safety.failure_probability) but under even odds, "unsafe" alone would
            # overstate it.
            return (f"{self.maybe}unsafe since year {self.unsafe_since} (P(unsafe) "
                    f"{pct(self.p_unsafe_last)} in {self.last_year}{measured})")
        if self.failure_year is not None:
            return (f"fails in year {self.failure_year} "
                    f"(P(unsafe) {pct(self.p_unsafe)} in {self.failure_year}{self.median_note})")
        return (f"no failure by year {self.horizon_end} (max P(unsafe) {pct(self.p_unsafe)}"
                f"{measured})")

    def as_dict(self) -> dict:
        return {
            "health": self.health, "root_cause": self.root_cause,
            "components": list(self.components),
            "failure_year": self.failure_year,
            "median_failure_year": self.median_failure_year, "p_unsafe": self.p_unsafe,
            "last_year": self.last_year, "horizon_end": self.horizon_end,
            "last_indicator": (None if self.last_indicator is None
                               or not np.isfinite(self.last_indicator)
                               else round(float(self.last_indicator), 3)),
            "last_indicator_text": self.last_indicator_text or None,
            "time_to_failure": self.time_to_failure, "action": self.action, "plan": self.plan,
            "estimates": self.estimates, "confidence": self.confidence,
            "diagnose": self.diagnose, "true_failure_year": self.true_failure_year,
            "status": self.status, "status_reason": self.status_reason or None,
            "status_words": self.status_words, "forced": self.forced,
            "p_unsafe_max": self.p_unsafe_max, "unsafe_since": self.unsafe_since,
            "measured_unsafe_since": self.measured_unsafe_since,
        }
