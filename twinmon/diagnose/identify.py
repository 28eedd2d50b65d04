"""Step 2, **identify**: which candidate effect causes the gap.

Every candidate effect (an FMU parameter of ``model.effects``) is

- **screened** (:func:`~twinmon.diagnose.screen.screen`): how much of the residual its signature explains once the
  degradation inputs are linearly re-adjusted, on a grid over the effect's range and for every
  onset year at once (cheap);
- **confirmed** (:func:`~twinmon.diagnose.confirm.confirm`): the augmented fit through the
  FMU (per-year degradation inputs plus the effect, one value per unit from its onset),
  compared with the base twin by BIC (:func:`~twinmon.diagnose.confirm.bic`).

Candidates within ``group_bic`` of the best form one **group**
(:mod:`~twinmon.diagnose.groups`, which also names the unobserved FMU channel that would
separate them). Further effects are added (:func:`~twinmon.diagnose.several.further`) only
while the BIC gain stays above ``bic_gain``; a model of several effects then gets a group per
effect (:func:`~twinmon.diagnose.several.swap_groups`: each effect swapped for every other
candidate, the others held), each with the channel that would separate it.
:func:`identify` runs all this and returns an :class:`Identification`; :func:`ranking`
tabulates the candidates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .confirm import bic, confirm
from .groups import EffectGroup, _weighted, single_group
from .screen import screen, to_confirm
from .several import alike_members, further, swap_groups
from .state import UnitState
from .stats import chi2_sf

__all__ = ["Identification", "identify", "ranking", "bic", "EffectGroup"]


@dataclass
class Identification:
    """What step 2 found for one unit.

    Attributes
    ----------
    screened : dict of str to tuple
        ``{candidate: (score, value, onset, gain [n_v, n_y])}`` from :func:`screen`.
    confirmed : dict of str to tuple or None
        ``{candidate: (chi2, FitResult, first fitted row, onset)}`` from :func:`confirm`.
    dbic : dict of str to float
        BIC of the base twin minus BIC with the candidate (higher = better).
    order : list of str
        Candidates by ``dbic``, best first; ``best`` is the first (None if no candidate).
    bic_base : float
    significant : bool
        A gap by the omnibus tests, or a candidate above ``bic_gain``.
    p_gap : float
        Omnibus p-value, lowered by the best candidate's likelihood ratio.
    model_effects : list of (str, int)
        Effects of the final model with their onset years (empty if none accepted).
    model_values : list of float
        Their values (effect units).
    final : (float, FitResult, int) or None
        Chi-square, fit and first fitted row of the final model.
    group : list of str
        Candidates within ``group_bic`` of the best (empty if none accepted); with several
        effects, the first effect's group (``groups[0]``).
    groups : list of EffectGroup
        One per effect of the final model, in its order: the effects the data cannot tell
        apart in that place (empty if none accepted).
    """

    screened: dict
    confirmed: dict
    dbic: dict
    order: list
    best: Optional[str]
    bic_base: float
    significant: bool
    p_gap: float
    model_effects: list
    model_values: list
    final: Optional[tuple]
    group: list
    groups: list = field(default_factory=list)


def identify(s: UnitState, candidates: list) -> Identification:
    """Screen and confirm every candidate, then build the final model (needs step 1)."""
    bic_base = bic(s, float(s.chi2_base.sum()), 0)

    # Screening of every candidate (linearised, a few runs each), then full fits of those
    # the screening puts in front (the fits are 80 % of a unit's FMU runs).
    screened = {}
    for name in candidates:
        # The kept years' gains (diagnose --update) are those of their base fit, unchanged.
        known = s.kept.screen_gains.get(name) if s.kept is not None else None
        screened[name] = screen(s, name, s.base_u, s.base_rows, s.base_Q, {}, known)
    # A unit whose tests see no gap and whose best screening gains less than a quarter of
    # what an accepted effect must (its BIC cost plus bic_gain) has nothing to confirm.
    floor = 0.0 if s.p_omnibus < s.dc.alpha else 0.25 * (s.dc.bic_gain + 2 * s.ln_n)
    chosen = to_confirm(screened, s.dc.confirm_first, floor)
    confirmed = {}
    for name in candidates:
        score, v, on, _ = screened[name]
        confirmed[name] = confirm(s, name, v, on) if name in chosen else None
    dbic = {n: (bic_base - bic(s, c[0], 1)) if c else -np.inf for n, c in confirmed.items()}
    # Ranked by fitted BIC gain; candidates the screening left unfitted by their score.
    order = sorted(candidates, key=lambda n: (-dbic[n], -screened[n][0]))
    best = order[0] if order else None

    significant = s.p_omnibus < s.dc.alpha or (
        best is not None and dbic[best] > s.dc.bic_gain)
    p_gap = s.p_omnibus
    if best is not None and dbic[best] > 0:
        # Likelihood-ratio p-value of the best candidate, Bonferroni over candidates and
        # onsets (value and onset both free: 2 degrees of freedom).
        lr = float(s.chi2_base.sum() - confirmed[best][0])
        p_lr = min(1.0, chi2_sf(lr, 2) * len(candidates) * s.n_y)
        p_gap = min(p_gap, p_lr)

    # The final model: effects added while the BIC gain stays above bic_gain.
    model_effects, model_values, final = [], [], None
    group = []
    if significant and best is not None and dbic[best] > s.dc.bic_gain:
        chi2_b, fit_b, k0_b, on_b = confirmed[best]
        ue, _ = fit_b.problem.unpack(fit_b.x)
        model_effects = [(best, on_b)]
        model_values = [s.twin.effect_of(best, ue[0])]
        final = (chi2_b, fit_b, k0_b)
        group = [n for n in order if dbic[n] > s.dc.bic_gain
                 and dbic[best] - dbic[n] <= s.dc.group_bic]
        while len(model_effects) < s.dc.max_effects:
            nxt = further(s, final, model_effects, model_values, candidates)
            if nxt is None:
                break
            final, model_effects, model_values = nxt
    groups = []
    if final is not None and len(model_effects) == 1:
        groups = [single_group(s, group, confirmed, dbic)]
    elif final is not None:
        final, model_effects, model_values, groups = swap_groups(
            s, final, model_effects, model_values, candidates)
    # Candidates alike to a named effect that explain its gap only together with it.
    for j, g in enumerate(groups):
        g.members = _weighted(g.members + alike_members(s, g, j, candidates), keep_first=True)
    if groups:
        group = [m.name for m in groups[0].members]
    return Identification(screened, confirmed, dbic, order, best, bic_base, significant,
                          p_gap, model_effects, model_values, final, group, groups)


def ranking(s: UnitState, idn: Identification) -> dict:
    """The candidates in ranking order with their screening and confirmed fits, as the
    :class:`~twinmon.diagnose.result.UnitGap` fields ``candidates`` and ``screen_score``,
    ``screen_onset``, ``fit_onset``, ``fit_value``, ``fit_sd``, ``delta_bic`` (each [n_c];
    ``fit_onset`` -1 and NaN values for a candidate with no fit)."""
    order, confirmed, screened = idn.order, idn.confirmed, idn.screened
    fit_on, fit_val, fit_sd = [], [], []
    for n in order:
        c = confirmed[n]
        if c is None:
            fit_on.append(-1), fit_val.append(np.nan), fit_sd.append(np.nan)
            continue
        ue, _ = c[1].problem.unpack(c[1].x)
        e = s.twin.effects[n]
        fit_on.append(c[3])
        fit_val.append(s.twin.effect_of(n, ue[0]))
        fit_sd.append(math.sqrt(max(c[1].covariance()[0, 0], 0.0)) * (e.high - e.low))
    return dict(candidates=order,
                screen_score=np.array([screened[n][0] for n in order]),
                screen_onset=np.array([screened[n][2] for n in order]),
                fit_onset=np.array(fit_on), fit_value=np.array(fit_val),
                fit_sd=np.array(fit_sd),
                delta_bic=np.array([idn.dbic[n] for n in order]))
