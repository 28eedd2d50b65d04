"""The ``report`` section: how many units get figures of their own, and the processes
that write the figures."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ReportConfig:
    """The report page (docs/report.md)."""

    #: A fleet of more units than this opens on a fleet overview (verdict counts, every unit
    #: ranked by P(unsafe), time to failure across the fleet), and per-unit figures are drawn
    #: for at most this many units: those asked for with ``report --unit``, then the units at
    #: risk in rank order. Smaller fleets get every unit's figures.
    detail_units: int = 12
    #: Processes that lay out and write the figures while the next ones are built (0: one
    #: per core; 1: all in the report's own process).
    workers: int = 0

    def _check(self):
        if self.detail_units < 1:
            yield "detail_units", "must be >= 1", self.detail_units
        if self.workers < 0:
            yield "workers", "must be >= 0 (0: one per core)", self.workers
