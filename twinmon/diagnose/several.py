"""Models of several effects: a further effect on top of the current model
(:func:`further`), the group of each effect of a several-effect model, found by swapping
it for every other candidate (:func:`swap_groups`), and the candidates that explain a
group's gap together with its named effect (:func:`alike_members`).
"""
from __future__ import annotations

import numpy as np

from ..errors import SimulationError
from .confirm import bic, fit_with
from .fit import JointFit
from .groups import EffectGroup, Member, _weighted
from .screen import _grid, screen
from .state import UnitState


def _fixed(s: UnitState, effects: list, values: list) -> dict:
    """Years index -> the effects of ``effects`` [(name, onset)] active that year."""
    return {k: {n: v for (n, on), v in zip(effects, values) if s.years[k] >= on}
            for k in range(s.n_y)}


def _current(s: UnitState, final, model_effects, model_values, held: int | None = None) -> tuple:
    """The current model as the screening needs it: normalised inputs [n_y, d], whitened
    residual rows, the effects per year, per year an orthonormal basis of the sensitivities
    of its inputs [n_k, d], and per year the sensitivities of the model's effects
    [n_k, n_e] (zero columns before an effect's onset).

    The effects' sensitivities go to the screening so that a new effect is screened with
    the effects already in the twin re-adjusted too (linearly, one change of each value
    shared by its years, as the confirming fit has it): a delay-type effect fitted alone
    takes up part of a lag-type one, and held at that value it would hide the lag from the
    screening. ``held``: the index of an effect left out (the one being swapped: its
    alternatives must not be projected onto it)."""
    chi2_cur, fit, k0 = final
    _, ut = fit.problem.unpack(fit.x)
    u_now = s.base_u.copy()
    u_now[k0:] = ut
    rows = list(s.base_rows[:k0]) + list(fit.rows)
    fixed = _fixed(s, model_effects, model_values)
    n_e = len(model_effects)
    keep = [j for j in range(n_e) if j != held]
    Qs, Gs = [], []
    for k in range(s.n_y):
        prob = JointFit(s.twin, s.Y[k:k + 1], s.years[k:k + 1],
                        [(n, on) for n, on in model_effects])
        # Sensitivities of this year's inputs and effects at the current model.
        x = np.concatenate([[s.twin.effect_u(n, v) for (n, _), v in
                             zip(model_effects, model_values)], u_now[k]])
        J = prob.jacobian(x)
        Qs.append(np.linalg.qr(J[:, n_e:])[0])
        Gs.append(J[:, keep])        # an inactive effect's column is zero
    return u_now, rows, fixed, Qs, (Gs if Gs and keep else None)


def _screened(s: UnitState, candidates, in_model, u_now, rows, Qs, fixed, Gs) -> list:
    """``(score, name, value, onset)`` of each candidate not in ``in_model`` (its
    ``(name, onset)`` pairs) screened on top of it (:func:`~.screen.screen`), best first."""
    used = {n for n, _ in in_model}
    scores = []
    for name in candidates:
        if name not in used:
            sc, v, on, _ = screen(s, name, u_now, rows, Qs, fixed, Gs=Gs)
            scores.append((sc, name, v, on))
    scores.sort(reverse=True)
    return scores


def further(s: UnitState, final, model_effects, model_values, candidates):
    """Try one more effect on top of the current model; None unless the BIC gain is
    above ``bic_gain``."""
    chi2_cur = final[0]
    u_now, rows, fixed, Qs, Gs = _current(s, final, model_effects, model_values)
    scores = _screened(s, candidates, model_effects, u_now, rows, Qs, fixed, Gs)
    bic_cur = bic(s, chi2_cur, len(model_effects))
    best, near = None, []
    for sc, name, v, on in scores[:s.dc.confirm_further]:
        fitted = _further_fit(s, model_effects, model_values, name, on, v, u_now)
        if fitted is None:
            continue
        if 0 < bic_cur - bic(s, fitted[0][0], len(fitted[1])) <= s.dc.bic_gain:
            near.append((name, on, v))
        if best is None or fitted[0][0] < best[0][0]:
            best = fitted
    if best is not None and bic_cur - bic(s, best[0][0], len(best[1])) <= s.dc.bic_gain:
        # Near misses are fitted again from the neighbouring values of the screening grid:
        # a transient's value can sit in a local minimum (a valve opening time fitted beside
        # a plateau shift from two years only: 5.2 s from the screened 6.25 s, 6.9 s, and an
        # accepted pair, from 7.5 s).
        for name, on, v in near:
            grid = _grid(s, name)
            i = int(np.argmin(np.abs(grid - v)))
            side = np.sign(grid - s.twin.effects[name].baseline)
            for i2 in (i - 1, i + 1):
                # The grid runs up one side of the baseline, then down the other.
                if 0 <= i2 < grid.size and side[i2] == side[i]:
                    fitted = _further_fit(s, model_effects, model_values, name, on,
                                          float(grid[i2]), u_now)
                    if fitted is not None and fitted[0][0] < best[0][0]:
                        best = fitted
    if best is None:
        return None
    gain = bic_cur - bic(s, best[0][0], len(best[1]))
    return best if gain > s.dc.bic_gain else None


def _further_fit(s: UnitState, model_effects, model_values, name, onset, value, u_now):
    """The current model plus ``name`` from ``onset``, fitted from ``value``:
    ``((chi2, fit, first row), effects, values)`` or None."""
    effs = model_effects + [(name, onset)]
    chi2, fit2, k02 = fit_with(s, effs, model_values + [value], u_now)
    if fit2 is None:
        return None
    ue, _ = fit2.problem.unpack(fit2.x)
    return ((chi2, fit2, k02), effs,
            [s.twin.effect_of(n, ue[j]) for j, (n, _) in enumerate(effs)])


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
        u_now, rows, fixed, Qs, Gs = _current(s, final, model_effects, model_values, held=j)
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
        scored = _screened(s, candidates, others, u_now, rows_o, Qs, fixed_o, Gs)
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


# -- alike effects: the gap explained together -----------------------------------------------------
#: |correlation| of two effects' estimates in one fit (linearised) above which the data see
#: only their sum: 0.999-1.000 between any two of the pump's plateau-type effects from one
#: year, 0.2-0.45 between a transient-type effect and one of them.
ALIKE_RHO = 0.99
#: A candidate is fitted beside the named effect (the test above) only if its signature,
#: out of the span of the degradation inputs, points within this cosine of the named
#: effect's (a cheap first look: one FMU run per candidate and side), and at the end of its
#: range explains at least ``bic_gain`` of the last year's chi-square there: an effect the
#: degradation inputs absorb (the DC drive's supply ratio on its speed alone) correlates
#: with anything in a fit, but is no part of what the data see.
ALIKE_COS = 0.9


def alike_members(s: UnitState, group: EffectGroup, j: int, candidates: list) -> list:
    """Candidates that explain the gap of place ``j`` *together with* the group's named
    effect: members of the form "named effect + candidate", both from the named one's onset.

    Two routes lead into the group:

    - *alike*: two plateau-type effects from the same year shift the output as one; the
      data see their sum, never the split. A candidate alike to the named effect but unable
      to reach the sum alone within its range (so outside the group by BIC) is as good an
      explanation together with it: a member when, fitted beside the named effect (the
      model's other effects in the fit too), their estimates correlate beyond
      ``ALIKE_RHO`` and the fit is within ``group_bic`` in chi-square of the named one's;
    - *evidence*: a candidate that, beside the named effect from its onset, lowers the
      chi-square by at least ``ln n`` (one more value; the onset is shared), so that the
      pair's BIC is at least as good as the named effect's alone, though short of the
      ``bic_gain`` (value and onset) that accepts a further effect: a small transient
      inside a larger one from the same year, which the larger one's value takes up.

    A member's ``dbic`` is its model's BIC minus the named member's, one more value counted,
    so its evidence share is the BIC weight of a two-effect explanation (larger than the
    named effect's by the evidence route).

    Parameters
    ----------
    group : EffectGroup
        The place's group so far; its first member's model is the final one.
    j : int
        The place: the index of the group's effect among that model's effects.
    candidates : list of str
        Every candidate effect (those already in the group or the model are skipped).

    Returns
    -------
    list of Member
        The new members (``together`` set to the named effect), unsorted.
    """
    top = group.members[0]
    chi2_top, fit_top, k0_top = top.fit
    effs, vals = list(top.effects), list(top.values)
    name_j, on_j = effs[j]
    inside = {m.name for m in group.members} | {n for n, _ in effs}
    u_now, rows, fixed, Qs, Gs = _current(s, top.fit, effs, vals)
    out = []
    for c in candidates:
        if c in inside:
            continue
        start = _alike_start(s, u_now[-1], dict(zip([n for n, _ in effs], vals)), name_j, c)
        if start is None:
            # Worth a fit only if its screening beside the model, from the same onset,
            # gains what one more value costs.
            score, start, _, _ = screen(s, c, u_now, rows, Qs, fixed, Gs=Gs, onset=on_j)
            if score < s.ln_n:
                continue
        chi2, fit, k0 = fit_with(s, effs + [(c, on_j)], vals + [start], u_now)
        if fit is None:
            continue
        cov = fit.covariance()
        i = len(effs)
        rho = abs(cov[j, i]) / np.sqrt(max(cov[j, j] * cov[i, i], 1e-300))
        gain = chi2_top - chi2
        if not ((rho >= ALIKE_RHO and gain >= -s.dc.group_bic) or gain >= s.ln_n):
            continue
        ue, _ = fit.problem.unpack(fit.x)
        values = [s.twin.effect_of(n, ue[q]) for q, (n, _) in enumerate(effs + [(c, on_j)])]
        dbic = top.dbic - gain + s.ln_n
        out.append(Member(c, int(on_j), values[i], i, float(dbic), 0.0, (chi2, fit, k0),
                          effs + [(c, on_j)], values, [name_j]))
    return out


def _alike_start(s: UnitState, u_last: np.ndarray, effects: dict, name: str, cand: str):
    """A start value of ``cand`` for its fit beside ``name`` (half-way to the end of its
    range on the side whose signature at that end, at the last year and out of the span of
    the degradation inputs, points like ``name``'s and is large enough to be seen: see
    ``ALIKE_COS``), or None if neither side does."""
    theta = s.twin.theta_of(u_last)
    k = s.n_y - 1
    mask = np.isfinite(s.Y[k])
    Q = s.base_Q[k]
    try:
        f = s.twin.predict(theta, effects)[mask]
        sig = f - s.twin.predict(theta, {n: v for n, v in effects.items() if n != name})[mask]
    except SimulationError:
        return None
    sig = sig - Q @ (Q.T @ sig)
    e = s.twin.effects[cand]
    for end in (e.high, e.low):
        if end == e.baseline:
            continue
        try:
            d = s.twin.predict(theta, {**effects, cand: end})[mask] - f
        except SimulationError:
            continue
        d = d - Q @ (Q.T @ d)
        den = float(np.linalg.norm(sig) * np.linalg.norm(d))
        if den > 0 and float(d @ d) >= s.dc.bic_gain and float(sig @ d) / den >= ALIKE_COS:
            return e.baseline + 0.5 * (end - e.baseline)
    return None
