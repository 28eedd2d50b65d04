"""Attribution: which components a unit's abnormal drift comes from.

The joint sampling distribution of the inputs' slopes (OLS slopes with the covariance of
:func:`~.covariance.slope_covariance` -- it carries the inputs' trade-off -- Student t,
``n - 2`` dof; or a joint posterior's slope draws) is split into the regions "these
components beyond their normal band, the others within": :func:`attribute` gives the
probability of each set of components, given that at least one is abnormal. The verdict
names the components whose probability reaches ``forecast.attribution_confidence``; when
none does, or another component sits between 0.5 and that, it is ``ambiguous``, with the
probabilities and the unrecorded channel that would tell the leading explanations apart
(:func:`separating_channel`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product
from typing import Optional

import numpy as np

from .detection import DRAWS

#: Verdict when no component can be named with enough confidence.
AMBIGUOUS = "ambiguous"
HEALTHY = "healthy"
#: Verdict for several components at once.
SEVERAL = "both"


@dataclass
class Attribution:
    """Which components a unit's abnormal drift comes from.

    Attributes
    ----------
    verdict : str
        ``healthy``, a component name, ``both`` (several components) or ``ambiguous``.
    probabilities : dict component -> float
        P(component beyond its normal ageing | data, at least one is); empty when healthy.
    sets : dict str -> float
        Probability of each non-empty set of abnormal components ("pump", "motor+pump").
    separating_channel : str
        The unobserved channel that would tell the two leading explanations apart ("" when not
        ambiguous or none is configured).
    channel_scores : dict channel -> float
        Difference between the leading explanations on each candidate channel, in that
        channel's noise sd.
    """

    verdict: str
    probabilities: dict = field(default_factory=dict)
    sets: dict = field(default_factory=dict)
    separating_channel: str = ""
    channel_scores: dict = field(default_factory=dict)
    #: Mean slope vector [d] of the draws of the two leading sets (for the separating channel).
    leading_slopes: Optional[np.ndarray] = None
    #: The components the verdict names (one, or several for ``both``); empty otherwise.
    named: list = field(default_factory=list)

    def describe(self) -> str:
        if not self.probabilities:
            return self.verdict
        probs = ", ".join(f"{c} {p:.2f}" for c, p in
                          sorted(self.probabilities.items(), key=lambda kv: -kv[1]))
        return f"{self.verdict} ({probs})"


def attribute(trends: list, names: list, components: list, C: np.ndarray,
              normal_rate, tolerance, directions, confidence: float,
              rng: np.random.Generator, draws: Optional[np.ndarray] = None) -> Attribution:
    """Probabilities of each set of abnormal components, given that the unit drifts.

    Parameters
    ----------
    trends : list of Trend, length d
        OLS trends of the inputs (slopes and standard errors).
    names, components : list of str, length d
        Input names and the component of each.
    C : ndarray, shape [d, d]
        Covariance of the slopes (:func:`~.covariance.slope_covariance`; it ties the inputs).
    normal_rate, tolerance : ndarray, shape [d]
    directions : ndarray of int, shape [d]
        Degrading direction of each input (+1, -1, or 0 = either way).
    confidence : float
        Probability the leading set needs for a verdict naming it.
    rng : numpy Generator
    draws : ndarray, shape [n, d], optional
        Posterior draws of the slopes (the joint method's trend), used as they are instead
        of the Student-t distribution of ``trends``' slopes with covariance ``C``.
    """
    if draws is None:
        b = np.array([t.slope for t in trends])
        dof = max(trends[0].dof, 1)
        L = np.linalg.cholesky(C + 1e-300 * np.eye(len(b)))
        z = rng.standard_normal((DRAWS, len(b))) @ L.T
        draws = b + z / np.sqrt(rng.chisquare(dof, (DRAWS, 1)) / dof)
    normal_rate, tolerance = np.asarray(normal_rate, float), np.asarray(tolerance, float)
    dirs = np.asarray(directions, int)
    dev = draws - normal_rate
    beyond = np.where(dirs[None, :] == 0, np.abs(dev), dev * dirs[None, :]) > tolerance
    comps = sorted(set(components))
    comp_bad = np.column_stack([beyond[:, [c == comp for c in components]].any(axis=1)
                                for comp in comps])
    some = comp_bad.any(axis=1)
    if not some.any():
        # No draw leaves the normal band: the drift is not in any input's slope (e.g. a
        # fault on a path the inputs do not model); name nothing.
        return Attribution(AMBIGUOUS, {c: 1.0 / len(comps) for c in comps}, {})
    sets, means = {}, {}
    for pattern in product((False, True), repeat=len(comps)):
        if not any(pattern):
            continue
        sel = some & np.all(comp_bad == np.array(pattern), axis=1)
        label = "+".join(c for c, on in zip(comps, pattern) if on)
        sets[label] = float(sel.sum() / some.sum())
        if sel.any():
            means[label] = draws[sel].mean(axis=0)
    probs = {c: float(comp_bad[some, k].mean()) for k, c in enumerate(comps)}
    # The components abnormal with probability >= confidence are named (a motor fault whose
    # pump is only possibly degrading too is a motor fault, the pump's probability shown);
    # with none, the data cannot say which: ambiguous.
    sure = [c for c in comps if probs[c] >= confidence]
    # ... unless another is more likely than not abnormal too, without being sure: then
    # the data cannot say whether it is one component or several.
    doubt = [c for c in comps if 0.5 <= probs[c] < confidence]
    if sure and not doubt:
        return Attribution(sure[0] if len(sure) == 1 else SEVERAL, probs, sets, named=sure)
    ranked = sorted((s for s in sets if s in means), key=sets.get, reverse=True)
    lead = np.array([means[s] for s in ranked[:2]]) if len(ranked) >= 2 else None
    return Attribution(AMBIGUOUS, probs, sets, leading_slopes=lead)


def separating_channel(cfg, observed: set, x_first: np.ndarray, lead_slopes: np.ndarray,
                       span: float, executor=None) -> tuple[str, dict]:
    """The unobserved channel whose recording would best tell two explanations apart.

    The two explanations (mean slope vectors of the two leading sets, [2, d]) both reproduce
    the observed output; started from the unit's first-year state ``x_first`` [d], after
    ``span`` years they reach different states that look alike on the output. Each candidate
    channel (``model.channels`` not observed) is simulated at both and scored by the RMS
    difference in its noise sd (``diagnose.channel_noise_fraction`` of the
    healthy unit's range on that channel).

    Returns
    -------
    channel : str
        "" when no channel is configured or none differs.
    scores : dict channel -> float
    """
    from ..simulate import as_parameters, run_batch, spec_for
    chans = [c for c in cfg.model.channels if c not in observed]
    if not chans or lead_slopes is None:
        return "", {}
    lo, hi = cfg.model.bounds[:, 0], cfg.model.bounds[:, 1]
    ends = [np.clip(x_first + s * span, lo, hi) for s in lead_slopes]
    nominal = np.array([s.nominal for s in cfg.model.inputs.values()])
    spec = spec_for(cfg, outputs=list(dict.fromkeys([cfg.model.output.variable, *chans])))
    batch = run_batch(spec, as_parameters(cfg, np.array([*ends, nominal])), executor)
    if not batch.ok.all():
        return "", {}
    frac = cfg.diagnose.channel_noise_fraction
    scores = {}
    for c in chans:
        y = batch.outputs[c]
        healthy = y[2]
        scale = float(healthy.max() - healthy.min()) or float(abs(healthy).max()) or 1.0
        scores[c] = float(np.sqrt(np.mean((y[0] - y[1]) ** 2)) / (frac * scale))
    best = max(scores, key=scores.get)
    return (best if scores[best] > 0 else ""), scores
