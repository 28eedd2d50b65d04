"""Step 2, **identify**: which candidate effect causes the gap.

Every candidate effect (an FMU parameter of ``model.effects``) is

- **screened** (:func:`screen`): how much of the residual its signature explains once the
  degradation inputs are linearly re-adjusted, on a grid over the effect's range and for every
  onset year at once (cheap);
- **confirmed** (:func:`confirm`): the augmented fit through the FMU (per-year degradation
  inputs plus the effect, one value per unit from its onset), compared with the base twin by
  BIC (:func:`bic`).

Candidates within ``group_bic`` of the best form one **group**; :func:`separation` names the
unobserved FMU channel that would separate them. Further effects are added
(:func:`_further`) only while the BIC gain stays above ``bic_gain``; a model of several
effects then gets a group per effect (:func:`swap_groups`: each effect swapped for every
other candidate, the others held), each with the channel that would separate it
(:func:`group_separation`). :func:`identify` runs all
this and returns an :class:`Identification`; :func:`ranking` tabulates the candidates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy import stats

from ..errors import SimulationError
from .fit import JointFit
from .state import UnitState


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


@dataclass
class Member:
    """One member of an :class:`EffectGroup`: the final model with this candidate in the
    group's place.

    Attributes
    ----------
    name : str
        The candidate (FMU parameter).
    onset : int
    value : float
        Its fitted value (effect units).
    index : int
        Its position among the fit's effects.
    dbic : float
        BIC of this model minus the group's best (>= 0).
    weight : float
        Evidence share within the group, ``exp(-dbic / 2)`` normalised over the members
        (the BIC approximation of the posterior model weight, equal prior weights).
    fit : (float, FitResult, int)
        Chi-square, fit and first fitted row of this model.
    effects : list of (str, int)
        The model's effects with their onsets.
    values : list of float
        Their values (effect units).
    """

    name: str
    onset: int
    value: float
    index: int
    dbic: float
    weight: float
    fit: tuple
    effects: list
    values: list


@dataclass
class EffectGroup:
    """The effects the data cannot tell apart in one place of the final model: the named one
    (the best) first, then the others by BIC (each within ``group_bic`` of the best)."""

    members: list

    @property
    def name(self) -> str:
        return self.members[0].name


def _weighted(members: list) -> list:
    """``members`` sorted by ``dbic`` with their evidence shares set."""
    members = sorted(members, key=lambda m: m.dbic)
    w = np.exp(-0.5 * np.array([m.dbic for m in members]))
    for m, wi in zip(members, w / w.sum()):
        m.weight = float(wi)
    return members


def single_group(s: UnitState, group: list, confirmed: dict, dbic: dict) -> EffectGroup:
    """The group of a one-effect model, its members' fits being the confirmation fits."""
    top = max(dbic[n] for n in group)
    members = []
    for n in group:
        chi2, fit, k0, on = confirmed[n]
        ue, _ = fit.problem.unpack(fit.x)
        v = s.twin.effect_of(n, ue[0])
        members.append(Member(n, int(on), v, 0, float(top - dbic[n]), 0.0, (chi2, fit, k0),
                              [(n, on)], [v]))
    return EffectGroup(_weighted(members))


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
        p_lr = min(1.0, stats.chi2.sf(lr, 2) * len(candidates) * s.n_y)
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
            nxt = _further(s, final, model_effects, model_values, candidates)
            if nxt is None:
                break
            final, model_effects, model_values = nxt
    groups = []
    if final is not None and len(model_effects) == 1:
        groups = [single_group(s, group, confirmed, dbic)]
    elif final is not None:
        final, model_effects, model_values, groups = swap_groups(
            s, final, model_effects, model_values, candidates)
        group = [m.name for m in groups[0].members]
    return Identification(screened, confirmed, dbic, order, best, bic_base, significant,
                          p_gap, model_effects, model_values, final, group, groups)


def to_confirm(screened: dict, top: int, floor: float = 0.0) -> set:
    """Candidates worth a full fit: the ``top`` best screening scores (0: all), and any other
    scoring at least half the best (a group of near-equivalent effects stays whole); none
    when the best scores below ``floor`` (with ``top`` > 0).

    The screening's chi-square reduction is linearised: it misjudges sizes, rarely the
    ranking of candidates that matter (on the shipped gap fleet the effects that enter the
    model screen 100-230 and are all in the first three, an effect that explains nothing
    below 60; on 12 units without a gap the best screens 6 at most and its fit gains 8 in
    chi-square, against the 21 an accepted effect needs)."""
    if top <= 0:
        return set(screened)
    ranked = sorted(screened, key=lambda n: -screened[n][0])
    best = screened[ranked[0]][0] if ranked else 0.0
    if best < floor:
        return set()
    return set(ranked[:top]) | {n for n in ranked if best > 0 and screened[n][0] >= 0.5 * best}


# -- screening -----------------------------------------------------------------------------------
def _grid(s: UnitState, name: str) -> np.ndarray:
    """Screening values of effect ``name``: ``screen_points`` per side of its baseline."""
    e = s.twin.effects[name]
    n = s.dc.screen_points
    fr = np.arange(1, n + 1) / n
    vals = []
    if e.high > e.baseline:
        vals += list(e.baseline + fr * (e.high - e.baseline))
    if e.low < e.baseline:
        vals += list(e.baseline - fr * (e.baseline - e.low))
    return np.array(vals)


def screen(s: UnitState, name: str, u_inputs, rows, Qs, fixed: dict,
           known: np.ndarray | None = None) -> tuple:
    """Chi-square reduction of adding effect ``name`` (value on a grid, onset any year),
    the degradation inputs re-adjusted linearly.

    Returns ``(score, value, onset, gain [n_v, n_y])``; ``fixed`` maps years index ->
    effects already in the twin. ``known`` [n_v, n_k]: the gains of the first ``n_k`` years,
    taken as they are (a year's gains depend on that year alone)."""
    grid = _grid(s, name)
    gains = np.zeros((grid.size, s.n_y))
    n_known = 0
    if known is not None:
        n_known = known.shape[1]
        gains[:, :n_known] = known
    for k in range(n_known, s.n_y):
        theta = s.twin.theta_of(u_inputs[k])
        eff0 = fixed.get(k, {})
        mask = np.isfinite(s.Y[k])
        try:
            f0 = s.twin.predict(theta, eff0)[mask]
        except SimulationError:
            continue
        Q = Qs[k]
        r = rows[k]
        rp = r - Q @ (Q.T @ r)
        base = float(rp @ rp)
        for i, v in enumerate(grid):
            try:
                f = s.twin.predict(theta, {**eff0, name: v})[mask]
            except SimulationError:
                gains[i, k] = -np.inf
                continue
            r2 = r - (f - f0)
            r2 = r2 - Q @ (Q.T @ r2)
            gains[i, k] = base - float(r2 @ r2)
    cum = np.cumsum(gains[:, ::-1], axis=1)[:, ::-1]      # [n_v, onset index]
    i, o = np.unravel_index(int(np.argmax(cum)), cum.shape)
    return float(cum[i, o]), float(grid[i]), int(s.years[o]), gains


# -- confirmation by the augmented fit -------------------------------------------------------
def fit_with(s: UnitState, effects: list, values: list, u_start: np.ndarray):
    """Fit the twin with ``effects`` [(name, onset)] from start values; years before the
    earliest onset keep the base fit. Returns ``(chi2 total, FitResult, first row)``."""
    first = min(on for _, on in effects)
    k0 = int(np.searchsorted(s.years, first))
    if k0 >= s.n_y:
        return np.inf, None, k0
    prob = JointFit(s.twin, s.Y[k0:], s.years[k0:], effects)
    x0 = np.concatenate([[s.twin.effect_u(n, v) for (n, _), v in zip(effects, values)],
                         np.asarray(u_start)[k0:].ravel()])
    fit = prob.solve(x0)
    chi2 = float(s.chi2_base[:k0].sum() + fit.chi2_rows.sum())
    return chi2, fit, k0


def bic(s: UnitState, chi2: float, n_effects: int) -> float:
    """BIC of a model of the unit with per-year degradation inputs and ``n_effects`` effects."""
    # Each effect costs its value and its onset year.
    return chi2 + (s.d * s.n_y + 2 * n_effects) * s.ln_n


def confirm(s: UnitState, name: str, value: float, onset: int, fixed_fit=None):
    """Best augmented fit of candidate ``name`` over onsets ``onset +- onset_search``:
    ``(chi2, FitResult, first fitted row, onset)``, or None if no onset is within the years."""
    best = None
    for on in range(onset - s.dc.onset_search, onset + s.dc.onset_search + 1):
        if on < s.years[0] or on > s.years[-1]:
            continue
        u0 = _readjusted_start(s, name, value, on)
        chi2, fit, k0 = fit_with(s, [(name, on)], [value], u0)
        if fit is not None and (best is None or chi2 < best[0]):
            best = (chi2, fit, k0, on)
    return best


def _readjusted_start(s: UnitState, name, value, onset):
    """Base inputs moved by one linear step to make room for the effect."""
    u = s.base_u.copy()
    for k in range(s.n_y):
        if s.years[k] < onset:
            continue
        mask = np.isfinite(s.Y[k])
        theta = s.twin.theta_of(u[k])
        try:
            df = (s.twin.predict(theta, {name: value}) - s.twin.predict(theta))[mask]
        except SimulationError:
            continue
        J = -s.base_J[k]                        # d f / d u
        step = np.linalg.lstsq(J, s.base_rows[k] - df, rcond=None)[0]
        u[k] = np.clip(u[k] + step, 0.0, 1.0)
    return u


# -- further effects -------------------------------------------------------------------------------
def _fixed(s: UnitState, effects: list, values: list) -> dict:
    """Years index -> the effects of ``effects`` [(name, onset)] active that year."""
    return {k: {n: v for (n, on), v in zip(effects, values) if s.years[k] >= on}
            for k in range(s.n_y)}


def _current(s: UnitState, final, model_effects, model_values, held: int | None = None) -> tuple:
    """The current model as the screening needs it: normalised inputs [n_y, d], whitened
    residual rows, the effects per year, and per year an orthonormal basis of the
    sensitivities of its inputs and of the effects active that year.

    The effects' sensitivities are in the basis so that a new effect is screened with the
    effects already in the twin re-adjusted too (linearly, each year on its own: a
    relaxation the confirming fit removes): a delay-type effect fitted alone takes up part
    of a lag-type one, and held at that value it would hide the lag from the screening.
    ``held``: the index of an effect left out of the basis (the one being swapped: its
    alternatives must not be projected onto it)."""
    chi2_cur, fit, k0 = final
    _, ut = fit.problem.unpack(fit.x)
    u_now = s.base_u.copy()
    u_now[k0:] = ut
    rows = list(s.base_rows[:k0]) + list(fit.rows)
    fixed = _fixed(s, model_effects, model_values)
    Qs = []
    for k in range(s.n_y):
        prob = JointFit(s.twin, s.Y[k:k + 1], s.years[k:k + 1],
                        [(n, on) for n, on in model_effects])
        # Sensitivities of this year's inputs at the current model (effects held).
        x = np.concatenate([[s.twin.effect_u(n, v) for (n, _), v in
                             zip(model_effects, model_values)], u_now[k]])
        J = prob.jacobian(x)
        cols = [j for j in prob.active[0] if j != held] + list(range(len(model_effects),
                                                                      J.shape[1]))
        Qs.append(np.linalg.qr(J[:, cols])[0])
    return u_now, rows, fixed, Qs


def _further(s: UnitState, final, model_effects, model_values, candidates):
    """Try one more effect on top of the current model; None unless the BIC gain is
    above ``bic_gain``."""
    chi2_cur = final[0]
    u_now, rows, fixed, Qs = _current(s, final, model_effects, model_values)
    used = {n for n, _ in model_effects}
    scores = []
    for name in candidates:
        if name in used:
            continue
        sc, v, on, _ = screen(s, name, u_now, rows, Qs, fixed)
        scores.append((sc, name, v, on))
    scores.sort(reverse=True)
    best = None
    for sc, name, v, on in scores[:s.dc.confirm_further]:
        effs = model_effects + [(name, on)]
        vals = model_values + [v]
        chi2, fit2, k02 = fit_with(s, effs, vals, u_now)
        if fit2 is not None and (best is None or chi2 < best[0][0]):
            ue, _ = fit2.problem.unpack(fit2.x)
            best = ((chi2, fit2, k02), effs,
                    [s.twin.effect_of(n, ue[j]) for j, (n, _) in enumerate(effs)])
    if best is None:
        return None
    gain = bic(s, chi2_cur, len(model_effects)) - bic(s, best[0][0], len(best[1]))
    return best if gain > s.dc.bic_gain else None


# -- groups of a several-effect model --------------------------------------------------------------
def swap_groups(s: UnitState, final, model_effects: list, model_values: list,
                candidates: list) -> tuple:
    """The group of each effect of a several-effect model, found by swapping it.

    For each place ``j`` of the model, every other candidate is screened in its place (the
    other effects held at their fitted values, the degradation inputs re-adjusted
    linearly); the ``confirm_further`` best, and any screening at least half as well as the
    effect in place, are fitted with the other effects through the FMU. Those whose BIC lies
    within ``group_bic`` of the best form the place's group: alike on the observed channels
    *given* the other effects, which the single-effect fits cannot tell (a plateau-type
    partner of a transient effect looks different alone than beside it). A member fitting
    better than the effect in place takes its place, so the named effect is the best.

    Returns ``(final, model_effects, model_values, groups)``: the model with any swap made
    and one :class:`EffectGroup` per place.
    """
    for _ in range(2):
        # A swap changes what the other places are screened beside: once more if any.
        final, model_effects, model_values, groups, swapped = _swap_pass(
            s, final, model_effects, model_values, candidates)
        if not swapped:
            break
    return final, model_effects, model_values, groups


def _swap_pass(s: UnitState, final, model_effects: list, model_values: list,
               candidates: list) -> tuple:
    """One pass of :func:`swap_groups` over the places of the model; also whether a place
    changed effect."""
    groups, swapped = [], False
    for j, (name_j, on_j) in enumerate(model_effects):
        u_now, rows, fixed, Qs = _current(s, final, model_effects, model_values, held=j)
        others = [e for i, e in enumerate(model_effects) if i != j]
        o_vals = [v for i, v in enumerate(model_values) if i != j]
        # The residual with effect j taken out of the twin (inputs as fitted).
        fixed_o = _fixed(s, others, o_vals)
        rows_o = []
        for k in range(s.n_y):
            mask = np.isfinite(s.Y[k])
            theta = s.twin.theta_of(u_now[k])
            try:
                df = (s.twin.predict(theta, fixed[k]) - s.twin.predict(theta, fixed_o[k]))[mask]
            except SimulationError:
                df = 0.0
            rows_o.append(rows[k] + df)
        used = {n for n, _ in others}
        scored = []
        for name in candidates:
            if name in used:
                continue
            sc, v, on, _ = screen(s, name, u_now, rows_o, Qs, fixed_o)
            scored.append((sc, name, v, on))
        scored.sort(reverse=True)
        own = next((sc for sc, n, _, _ in scored if n == name_j), 0.0)
        # The effect in place is tried again around its screened onset (beside a new
        # partner its onset may move).
        tries = [t for i, t in enumerate(scored) if t[1] == name_j or (
            i < s.dc.confirm_further or (own > 0 and t[0] >= 0.5 * own))]
        fits = [(name_j, on_j, final, list(model_effects), list(model_values))]
        for sc, name, v, on_s in tries:
            best = None
            # The screened onset and onset_search years either side, as for one effect.
            for on in range(on_s - s.dc.onset_search, on_s + s.dc.onset_search + 1):
                if on < s.years[0] or on > s.years[-1] or (name, on) == (name_j, on_j):
                    continue
                effs = list(model_effects)
                effs[j] = (name, on)
                vals = list(model_values)
                vals[j] = v
                chi2, fit2, k02 = fit_with(s, effs, vals, u_now)
                if fit2 is not None and (best is None or chi2 < best[2][0]):
                    ue, _ = fit2.problem.unpack(fit2.x)
                    best = (name, on, (chi2, fit2, k02), effs,
                            [s.twin.effect_of(n, ue[i]) for i, (n, _) in enumerate(effs)])
            if best is not None:
                fits.append(best)
        # One model per candidate: its best onset.
        by_name = {}
        for f in fits:
            if f[0] not in by_name or f[2][0] < by_name[f[0]][2][0]:
                by_name[f[0]] = f
        fits = list(by_name.values())
        # Every model here has the same number of effects: BIC differences are chi-square's.
        best_chi2 = min(f[2][0] for f in fits)
        members = [Member(n, int(on), vals[j], j, float(fit_[0] - best_chi2), 0.0, fit_, effs,
                          vals)
                   for n, on, fit_, effs, vals in fits if fit_[0] - best_chi2 <= s.dc.group_bic]
        members = _weighted(members)
        groups.append(EffectGroup(members))
        top = members[0]
        if top.name != name_j or top.onset != on_j:
            # A better partner than the effect in place: it takes the place (and the next
            # place is screened against it).
            final, model_effects, model_values = top.fit, list(top.effects), list(top.values)
            swapped = True
    return final, model_effects, model_values, groups, swapped


# -- the group: separating channel, ranking table ------------------------------------------------
def separation(s: UnitState, group: list, confirmed: dict) -> tuple:
    """The unobserved FMU channel on which the group's fitted twins differ most,
    relative to its noise (``channel_noise_fraction`` of its healthy plateau, or of its
    range for a channel that ends near 0). Returns ``(channel, {channel: score})``."""
    sims = []
    for n in group:
        chi2, fit, k0, on = confirmed[n]
        ue, ut = fit.problem.unpack(fit.x)
        sims.append((ut[-1], {n: s.twin.effect_of(n, ue[0])}))
    return separating_channel(s, sims)


def group_separation(s: UnitState, group: EffectGroup) -> tuple:
    """:func:`separation` of an :class:`EffectGroup`: each member's whole model (the other
    effects included) at its last fitted year."""
    sims = []
    for m in group.members:
        _, fit, _ = m.fit
        _, ut = fit.problem.unpack(fit.x)
        sims.append((ut[-1], dict(zip([n for n, _ in m.effects], m.values))))
    return separating_channel(s, sims)


def separating_channel(s: UnitState, sims: list) -> tuple:
    """The unobserved FMU channel on which twins ``sims`` [(normalised inputs [d],
    {effect: value})] differ most, relative to its noise; ``("", {})`` if every channel
    is observed. Returns ``(channel, {channel: score})``."""
    chans = [c for c in s.cfg.model.channels if c not in s.twin.channels]
    if not chans:
        return "", {}
    healthy = s.twin.run(np.array([p.nominal for p in s.cfg.model.inputs.values()]))

    def scale(x: np.ndarray) -> float:
        final, span = abs(float(x[-1])), float(x.max() - x.min())
        return max(final if final > 0.1 * span else span, 1e-12)

    noise = {c: s.dc.channel_noise_fraction * scale(healthy[c]) for c in chans}
    sims = [s.twin.run(s.twin.theta_of(u), eff) for u, eff in sims]
    scores = {}
    for c in chans:
        best = 0.0
        for i in range(len(sims)):
            for j in range(i + 1, len(sims)):
                diff = (sims[i][c] - sims[j][c]) / noise[c]
                best = max(best, float(np.sqrt(np.mean(diff ** 2))))
        scores[c] = best
    return max(scores, key=scores.get), scores


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
