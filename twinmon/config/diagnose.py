"""The ``diagnose`` section: the search for the sim-to-real gap (time windows, tests, the
screening and confirmation of candidate effects, and where it runs)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal


@dataclass(frozen=True)
class WindowSpec:
    start: float
    stop: float


@dataclass(frozen=True)
class DiagnoseConfig:
    """Settings of ``diagnose`` (the sim-to-real gap); docs/diagnose.md explains each."""

    #: Named time windows of the record (seconds), for locating the gap; empty: the record
    #: split into thirds named early, middle and late (see :func:`diagnose_windows`).
    windows: dict[str, WindowSpec] = field(default_factory=dict)
    #: Significance level of the gap tests (family-wise: Bonferroni over years and tests).
    alpha: float = 0.01
    #: Minimum BIC gain to accept an effect (or a further one).
    bic_gain: float = 10.0
    #: Candidates whose fitted BIC lie within this of the best are reported as one group.
    group_bic: float = 6.0
    max_effects: int = 2
    #: Candidate effects (FMU parameters, keys of model.effects); empty: all of them.
    candidates: tuple[str, ...] = ()
    #: Confirmation fits try the screened onset year and this many years either side.
    onset_search: int = 1
    #: Effect values per side of the baseline on the screening grid.
    screen_points: int = 8
    #: Candidates confirmed by full fits (the best screened first; any other whose screening
    #: score is at least half the best's too); 0: every candidate.
    confirm_first: int = 3
    #: Candidates confirmed by a full fit when looking for a further effect.
    confirm_further: int = 3
    #: Below this percentage of the excess gap closed, the verdict is "unexplained".
    min_closed: float = 50.0
    #: An accepted effect that closes at least this percentage of the excess gap is the
    #: verdict even when the remainder still fails the noise tests.
    explained_closed: float = 90.0
    #: The degradation inputs are fitted in their design box widened by this fraction of
    #: its width on each side (a twin far outside its box is itself a sign of a gap).
    fit_margin: float = 0.1
    #: Lags of the Ljung-Box test of structure in a year's residual.
    ljung_box_lags: int = 5
    #: Noise of an unrecorded channel, as a fraction of its healthy plateau, for choosing
    #: the channel that would separate a group.
    channel_noise_fraction: float = 0.01
    #: Worker processes over units; 0 means one per core.
    workers: int = 0
    #: ``dask``: the units run on a Dask cluster (the ``dask`` section; docs/cluster.md).
    executor: Literal["process", "dask"] = "process"

    def _check(self):
        for name, w in self.windows.items():
            if not w.start < w.stop:
                yield f"windows.{name}.stop", f"must be greater than start ({w.start})", w.stop
        if not 0 < self.alpha < 1:
            yield "alpha", "must lie in (0, 1)", self.alpha
        if self.bic_gain < 0:
            yield "bic_gain", "must be >= 0", self.bic_gain
        if self.group_bic < 0:
            yield "group_bic", "must be >= 0", self.group_bic
        if self.max_effects < 1:
            yield "max_effects", "must be >= 1", self.max_effects
        if self.onset_search < 0:
            yield "onset_search", "must be >= 0", self.onset_search
        if self.screen_points < 2:
            yield "screen_points", "must be >= 2", self.screen_points
        if self.confirm_first < 0:
            yield "confirm_first", "must be >= 0 (0: every candidate)", self.confirm_first
        if self.confirm_further < 1:
            yield "confirm_further", "must be >= 1", self.confirm_further
        if not 0 <= self.min_closed <= 100:
            yield "min_closed", "must lie in [0, 100]", self.min_closed
        if not self.min_closed <= self.explained_closed <= 100:
            yield "explained_closed", f"must lie in [min_closed ({self.min_closed}), 100]", \
                self.explained_closed
        if self.fit_margin < 0:
            yield "fit_margin", "must be >= 0", self.fit_margin
        if self.ljung_box_lags < 1:
            yield "ljung_box_lags", "must be >= 1", self.ljung_box_lags
        if self.channel_noise_fraction <= 0:
            yield "channel_noise_fraction", "must be > 0", self.channel_noise_fraction
        if self.workers < 0:
            yield "workers", "must be >= 0", self.workers
