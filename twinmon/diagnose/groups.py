"""Groups of effects the data cannot tell apart: :class:`Member`, :class:`EffectGroup`, the
evidence shares of their members, and the unobserved channel that would separate them
(:func:`separating_channel`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .state import UnitState


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
    together : list of str
        For a member that is the named effect *together with* this candidate (see
        :func:`~twinmon.diagnose.several.alike_members`): the named effect; else empty.
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
    together: list = field(default_factory=list)


@dataclass
class EffectGroup:
    """The effects the data cannot tell apart in one place of the final model: the named one
    (the best) first, then the others by BIC (each within ``group_bic`` of the best), then
    those alike to the named one that explain the gap only together with it."""

    members: list

    @property
    def name(self) -> str:
        return self.members[0].name


def _weighted(members: list, keep_first: bool = False) -> list:
    """``members`` sorted by ``dbic`` (the first left first with ``keep_first``) with their
    evidence shares set."""
    members = members[:1] * keep_first + sorted(members[keep_first:], key=lambda m: m.dbic)
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
    # Channels equal in all but rounding (the DC drive's torque is Kt times its current):
    # the first in the config's order, so the answer does not flip between runs.
    top = max(scores.values())
    return next(c for c in chans if scores[c] >= top * (1 - 1e-9)), scores
