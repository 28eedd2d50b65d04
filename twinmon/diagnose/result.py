"""The diagnosis of one unit as a record: :class:`UnitGap` (what ``gap.h5`` stores per unit and
what ``--json`` prints).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

#: The three verdicts a unit can get (see :mod:`twinmon.diagnose.shrink`).
VERDICTS = ("none", "effect", "unexplained")


@dataclass
class UnitGap:
    """Diagnosis of one unit. Arrays are per year [n_y] and per time step [n_t] of the output.

    Attributes
    ----------
    verdict : str
        ``"none"``, ``"effect"`` or ``"unexplained"``.
    effects : list of str
        The effect, or the group of indistinguishable effects (best first), then any further
        effect added; empty unless the verdict is ``"effect"``.
    group : list of str
        The first effect's group (candidates within ``group_bic`` of the best).
    residual_before, residual_after : ndarray, shape [n_y, n_t]
        Standardised output residuals of the base and the final twin.
    window_rms_before, window_rms_after : ndarray, shape [n_y, n_w]
        RMS of the standardised output residual per year and window.
    predicted_before, predicted_after, observed : ndarray, shape [n_y, n_t]
        Output (its units).
    inputs_before, inputs_after, inputs_sd_before, inputs_sd_after : ndarray, shape [n_y, d]
        Degradation input estimates and their linearised standard deviations.
    candidates : list of str
        Candidate effects, in ranking order (best BIC first).
    screen_score : ndarray, shape [n_c]
        Screening chi-square reduction.
    delta_bic : ndarray, shape [n_c]
        BIC of the base twin minus BIC of the twin with that candidate (higher = better).
    cache : YearCache or None
        The per-year base fit and screening gains, for ``diagnose --update``.
    """

    unit: str
    years: np.ndarray
    verdict: str
    effects: list
    group: list
    onset: Optional[int]
    where_windows: list
    where_years: list
    rms_before: float
    rms_after: float
    closed_percent: float
    delta_bic_final: float
    estimate: dict
    separating_channel: str
    separation_scores: dict
    absorbed_share: float
    p_gap: float
    noise_std: float
    residual_before: np.ndarray
    residual_after: np.ndarray
    chi2_before: np.ndarray
    chi2_after: np.ndarray
    dof: np.ndarray
    p_chi2_before: np.ndarray
    p_ljung_box_before: np.ndarray
    p_chi2_after: np.ndarray
    significant_years: np.ndarray
    window_rms_before: np.ndarray
    window_rms_after: np.ndarray
    observed: np.ndarray
    predicted_before: np.ndarray
    predicted_after: np.ndarray
    inputs_before: np.ndarray
    inputs_after: np.ndarray
    inputs_sd_before: np.ndarray
    inputs_sd_after: np.ndarray
    candidates: list
    screen_score: np.ndarray
    screen_onset: np.ndarray
    fit_onset: np.ndarray
    fit_value: np.ndarray
    fit_sd: np.ndarray
    delta_bic: np.ndarray
    failure_year_before: Optional[int]
    failure_year_after: Optional[int]
    #: Onset year of each effect in the final twin ({fmu parameter: year}).
    effect_onsets: dict = field(default_factory=dict)
    #: One record per effect of the final twin (its place in the model): the effects the
    #: data cannot tell apart there, each with its evidence share, value, share of the gap
    #: closed and projected failure year, the spread of those years and the channel that
    #: would separate them (:func:`~twinmon.diagnose.shrink.group_records`; empty unless the
    #: verdict is ``"effect"``).
    groups: list = field(default_factory=list)
    #: Candidates the recorded channels cannot see (the degradation inputs take them up),
    #: with the unrecorded channel that would show them
    #: (:func:`~twinmon.diagnose.hidden.hidden_effects`; ``{}`` if none).
    hidden: dict = field(default_factory=dict)
    #: Per-year records for ``diagnose --update`` (:class:`~twinmon.diagnose.update.YearCache`;
    #: None when read by ``read_gap`` without ``cache=True`` or from a gap.h5 without them).
    cache: Optional[object] = None
    #: FMU runs and wall time (s) of the run that wrote this record (an update's own, the
    #: kept years' base fit and screening not included).
    fmu_runs: int = 0
    wall_time: float = 0.0
    #: Degrees of freedom of the output's noise level ``noise_std`` where it was estimated
    #: from the record (:func:`~twinmon.diagnose.stats.plateau_noise`); None where the
    #: observations or the config gave it.
    noise_dof: Optional[float] = None

    def as_dict(self) -> dict:
        """The ``--json`` entry of this unit (the documented gap schema, plus a few extra keys)."""
        return {
            "verdict": self.verdict,
            "effects": list(self.effects),
            "where": {"windows": list(self.where_windows), "years": [int(y) for y in self.where_years]},
            "shrink": {"rms_before": _num(self.rms_before), "rms_after": _num(self.rms_after),
                       "closed_percent": _num(self.closed_percent)},
            "estimate": {k: {"mean": _num(v[0]), "q05": _num(v[1]), "q95": _num(v[2])}
                         for k, v in self.estimate.items()},
            "onset": self.onset,
            "onsets": dict(self.effect_onsets),
            "group": list(self.group),
            "groups": [_plain(g) for g in self.groups],
            "hidden": _plain(self.hidden),
            "separating_channel": self.separating_channel or None,
            "bic_gain": _num(self.delta_bic_final),
            "absorbed_share": _num(self.absorbed_share),
            "p_gap": _num(self.p_gap),
            "noise": {"std": _num(self.noise_std),
                      "estimated_dof": _num(self.noise_dof) if self.noise_dof else None},
            "failure_year": {"before": self.failure_year_before,
                             "after": self.failure_year_after},
            "ranking": [{"effect": c, "delta_bic": _num(b), "screen": _num(s)}
                        for c, b, s in zip(self.candidates, self.delta_bic, self.screen_score)],
        }


def _plain(x):
    """``x`` with every float rounded as :func:`_num` does (NaN -> None)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, float):
        return _num(x)
    return x


def _num(x) -> Optional[float]:
    x = float(x)
    return round(x, 6) if math.isfinite(x) else None
