"""The twin at Monte Carlo points: the surrogate inside its training box, the FMU outside.

:func:`evaluate_twin` computes the health indicator of input points through the Gaussian
process surrogate where it was trained (vectorised) and through the FMU itself elsewhere, so
the surrogate is never extrapolated; outside the box, a limit-state model
(:mod:`.limitstate`, ``forecast.outside_box: learn``) answers the points it is sure are
unsafe, and only the others run through the FMU. A point is unsafe
(:meth:`TwinResult.unsafe`) when its indicator passes ``safety.unsafe_if``, when the FMU
reports the non-physical mode, when the FMU run fails, or when the limit-state model is sure
of it. The surrogate has no non-physical output: :func:`box_is_physical` checks the box's
corners on the FMU; when one is not physical, the limit-state model learns the box too, the
surrogate answers only the points of the box the model is sure are safe (a non-physical run
lies on the unsafe side of its margin), and the FMU the rest the model is not sure of.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from ..config import Config

#: Where a Monte Carlo point was evaluated: the surrogate (in the box), the FMU, a failed FMU
#: run, the limit-state model (outside the box, surely unsafe; its indicator an estimate).
SOURCE_SURROGATE, SOURCE_FMU, SOURCE_FAILED, SOURCE_MODEL = 0, 1, 2, 3


@dataclass
class TwinResult:
    """The twin evaluated at Monte Carlo points.

    Attributes
    ----------
    value : ndarray, shape [m]
        The health indicator (its units); ``inf`` for a level never reached, NaN if the FMU
        failed; the limit-state model's estimate at its points.
    nonphysical : ndarray of bool, shape [m]
    source : ndarray of int8, shape [m]
        0 surrogate, 1 FMU, 2 FMU run failed, 3 limit-state model.
    messages : list of str
        One message per failed FMU run.
    """

    value: np.ndarray
    nonphysical: np.ndarray
    source: np.ndarray
    messages: list = field(default_factory=list)

    def unsafe(self, safety) -> np.ndarray:
        """Unsafe per point [m]: the indicator passes its limit, non-physical, a failed run,
        or a point the limit-state model is sure of."""
        from ..safety import is_unsafe
        told = (self.source == SOURCE_FAILED) | (self.source == SOURCE_MODEL)
        return is_unsafe(self.value, safety, self.nonphysical) | told


def evaluate_twin(cfg: Config, surrogate, X: np.ndarray, executor=None,
                  fmu_everywhere: bool = False,
                  progress: Optional[Callable[[int, int], None]] = None,
                  predict: Optional[Callable[[np.ndarray], np.ndarray]] = None,
                  spec=None, limit_state=None) -> TwinResult:
    """Health indicator and non-physical flag of input points [m, d]: surrogate in its box,
    FMU outside.

    The surrogate has no non-physical output: inside its training box the flag is taken as 0
    (the box is checked to be physical, see :func:`box_is_physical`). ``fmu_everywhere`` sends
    every point to the FMU; so does an indicator computed from another variable than the
    output the surrogate learnt. ``predict`` replaces ``surrogate.predict`` (its numpy form,
    :func:`~twinmon.calibrate.samplers.gpbatch.make_predictor`); ``spec`` the config's FMU spec (a
    worker's copy of the FMU); ``limit_state`` a :class:`~.limitstate.LimitState`, which
    answers the points outside the box it is sure are unsafe (the others go to the FMU).

    Each distinct point is evaluated once (:func:`distinct_rows`) and its result copied to
    its repeats: a joint posterior's future points are drawn with replacement from its
    trend draws, and its years' draws are resampled, so about half of a unit's points are
    repeats. A point's result depends on that point alone (the surrogate's rows are
    computed independently, the FMU is reset before every run), so the copies are what
    evaluating every point would give, bit for bit. ``messages`` has one message per
    failed run, a repeated point's once.
    """
    X = np.asarray(X, float).reshape(-1, len(cfg.model.inputs))
    U, inv = distinct_rows(X)
    if len(U) == len(X):
        return _evaluate_distinct(cfg, surrogate, X, executor, fmu_everywhere, progress,
                                  predict, spec, limit_state)
    out = _evaluate_distinct(cfg, surrogate, U, executor, fmu_everywhere, progress, predict,
                             spec, limit_state)
    return TwinResult(out.value[inv], out.nonphysical[inv], out.source[inv], out.messages)


def distinct_rows(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``X`` [m, d] (sorted) and, per row of ``X``, the index of its
    distinct row: ``U[inv]`` is ``X``. A few times faster than ``np.unique(axis=0)``."""
    if len(X) < 2:
        return X, np.arange(len(X))
    if X.shape[1] == 2 and X.dtype == np.float64:
        # Two inputs: each row one complex number, whose sort is the rows' lexicographic
        # order in one key (1.6 times faster than lexsort's two passes).
        order = np.argsort(np.ascontiguousarray(X).view(np.complex128)[:, 0], kind="stable")
    else:
        order = np.lexsort(X.T[::-1])
    Xs = X[order]
    new = np.ones(len(X), bool)
    new[1:] = np.any(Xs[1:] != Xs[:-1], axis=1)
    inv = np.empty(len(X), np.int64)
    inv[order] = np.cumsum(new) - 1
    return Xs[new], inv


def _evaluate_distinct(cfg: Config, surrogate, X: np.ndarray, executor, fmu_everywhere: bool,
                       progress, predict, spec, limit_state=None) -> TwinResult:
    """:func:`evaluate_twin` at every row of ``X`` [m, d] (input units)."""
    from ..safety import Indicator
    from ..simulate import as_parameters, run_batch, spec_for
    ind = Indicator.from_config(cfg)
    m = len(X)
    value = np.full(m, np.nan)
    nph = np.zeros(m, bool)
    source = np.full(m, SOURCE_SURROGATE, np.int8)
    learnt = ind.variable == cfg.model.output.variable
    on_surrogate = not fmu_everywhere and learnt
    inside = surrogate.in_box(X) if on_surrogate else np.zeros(m, bool)
    if fmu_everywhere and learnt and getattr(limit_state, "covers_box", False):
        # A box that is not physical: the surrogate answers the points of the box the
        # model is sure are safe (a non-physical run is on the unsafe side of its margin).
        box = np.flatnonzero(surrogate.in_box(X))
        inside[box[limit_state.surely_safe(X[box])]] = True
        on_surrogate = True
    if inside.any():
        # Chunks keep the [chunk, n_t] intermediate arrays small.
        idx = np.flatnonzero(inside)
        for lo in range(0, idx.size, 20000):
            j = idx[lo:lo + 20000]
            value[j] = ind(surrogate.time, (predict or surrogate.predict)(X[j]))
    messages = []
    out = np.flatnonzero(~inside)
    if out.size and on_surrogate and limit_state is not None:
        # The model decides each point on its own (row-wise sums): the same whatever batch.
        sure, estimate = limit_state.classify(X[out])
        value[out[sure]] = estimate[sure]
        source[out[sure]] = SOURCE_MODEL
        out = out[~sure]
    if out.size:
        spec = spec or spec_for(cfg)
        batch = run_batch(spec, as_parameters(cfg, X[out]), executor,
                          (lambda k: progress(k, out.size)) if progress else None)
        value[out] = np.where(batch.ok, ind(spec.times, batch.outputs[ind.variable]), np.nan)
        if cfg.model.nonphysical:
            nph[out] = batch.ok & (batch.outputs[cfg.model.nonphysical][:, -1] > 0.5)
        source[out] = np.where(batch.ok, SOURCE_FMU, SOURCE_FAILED)
        messages = [batch.messages[k] for k in np.flatnonzero(~batch.ok)]
    return TwinResult(value, nph, source, messages)


def box_is_physical(cfg: Config) -> bool:
    """True when the FMU is physical at every corner of the surrogate's box (2^d runs).

    The surrogate cannot say when the twin leaves its physical domain; if a corner of the
    box is non-physical, the forecast sends every point to the FMU instead."""
    if not cfg.model.nonphysical or len(cfg.model.inputs) > 10:
        return True
    from itertools import product
    from ..simulate import as_parameters, run_batch, spec_for
    corners = np.array(list(product(*cfg.model.bounds)))
    batch = run_batch(spec_for(cfg), as_parameters(cfg, corners))
    flag = batch.outputs[cfg.model.nonphysical][:, -1]
    return bool(np.all(batch.ok) and np.all(flag[batch.ok] < 0.5))
