"""One unit, start to end: the three steps in order over one
:class:`~twinmon.diagnose.state.UnitState`, gathered into a
:class:`~twinmon.diagnose.result.UnitGap`.
"""
from __future__ import annotations

import time as _time

import numpy as np

from . import hidden, identify, locate, shrink
from .result import UnitGap
from .state import UnitState
from .update import YearCache


def run_unit(s: UnitState, candidates: list) -> UnitGap:
    """Locate, identify and shrink the gap of one unit against ``candidates`` (FMU
    parameters of ``model.effects``).

    ``fmu_runs`` and ``wall_time`` are this call's: with ``s.kept`` (``diagnose --update``)
    the kept years' base fit and screening are not run again, and do not count."""
    t0 = _time.perf_counter()
    runs0 = s.twin.runs
    # 1. locate: the base twin and its tests.
    locate.fit_base(s)
    locate.detect(s)
    # 2. identify: screening, confirmation, the final model and its group.
    idn = identify.identify(s, candidates)
    # 3. shrink: before / after, verdict, estimates.
    sh = shrink.shrink(s, idn)
    verdict = sh.verdict

    # What the report shows, in the order the FMU runs them (the run count is recorded).
    z_before, z_after, w_before, w_after = locate.residual_maps(s, sh.after_rows, sh.after_lev)
    where_w, where_y = locate.where(s, z_before, sh.aff) if verdict != "none" else ([], [])
    pred_b, pred_a = shrink.predictions(s, sh)
    sd_b, sd_a = shrink.input_sd(s, sh)
    absorbed = (locate.absorbed_share(s, idn.model_effects[0][0], sh.after_u, sh.eff_year,
                                      sh.aff)
                if verdict == "effect" else float("nan"))
    groups = shrink.group_records(s, sh, idn)
    sep_channel, sep_scores = "", {}
    if verdict == "effect" and len(idn.group) > 1:
        # The first effect's group: one effect alone, or its place in a combination.
        sep_channel = groups[0]["separating_channel"] or ""
        sep_scores = groups[0]["separation_scores"]
    fy_b, fy_a = shrink.failure_years(s, sh)
    # What no diagnosis on these channels could name, and the channel that would show it.
    in_groups = {m["effect"] for g in groups for m in g["members"]}
    blind = hidden.hidden_effects(s, [c for c in candidates if c not in in_groups],
                                  sh.after_u[-1], sh.eff_year[-1])
    table = identify.ranking(s, idn)
    return UnitGap(
        unit=s.unit, years=s.years, verdict=verdict, effects=sh.effects,
        group=idn.group if verdict == "effect" else [], onset=sh.onset,
        where_windows=where_w, where_years=where_y, rms_before=sh.rms_before,
        rms_after=sh.rms_after, closed_percent=sh.closed_percent,
        delta_bic_final=sh.delta_bic_final,
        estimate=sh.estimate, separating_channel=sep_channel, separation_scores=sep_scores,
        absorbed_share=absorbed, p_gap=float(idn.p_gap), noise_std=float(s.twin.sigma[0]),
        residual_before=z_before, residual_after=z_after,
        chi2_before=s.chi2_base, chi2_after=sh.chi2_after, dof=s.dof,
        p_chi2_before=s.p_chi2_before, p_ljung_box_before=s.p_lb_before,
        p_chi2_after=sh.p_chi2_after, significant_years=s.significant_years,
        window_rms_before=w_before, window_rms_after=w_after,
        observed=s.Y[:, :s.n_t] * s.twin.sigma[0],
        predicted_before=pred_b, predicted_after=pred_a,
        inputs_before=s.twin.theta_of(s.base_u), inputs_after=s.twin.theta_of(sh.after_u),
        inputs_sd_before=sd_b, inputs_sd_after=sd_a,
        **table,
        failure_year_before=fy_b, failure_year_after=fy_a,
        effect_onsets=({n: int(on) for n, on in idn.model_effects} if verdict == "effect"
                       else {}),
        groups=groups, hidden=blind,
        cache=YearCache.of(s, idn.screened),
        noise_dof=float(s.noise_dof[0]) if np.isfinite(s.noise_dof[0]) else None,
        fmu_runs=s.twin.runs - runs0, wall_time=_time.perf_counter() - t0)
