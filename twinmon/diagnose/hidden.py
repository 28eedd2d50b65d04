"""Candidate effects the recorded channels cannot see.

An effect whose signature on the recorded channels lies (almost) wholly in the span of the
degradation inputs is taken up by them when they are refitted: a load torque looks like
bearing friction, a supply voltage like a winding resistance. No diagnosis on these channels
can name it, however large; it only biases the degradation estimates. :func:`hidden_effects`
says which candidates are so hidden at the unit's last fitted state, and which unrecorded
channel of ``model.channels`` would show them.
"""
from __future__ import annotations

import numpy as np

from ..errors import SimulationError
from .fit import JointFit
from .groups import separating_channel
from .state import UnitState

#: An effect is hidden when, at an end of its range, it moves the recorded channels by at
#: least HIDDEN_GAP noise standard deviations (RMS over the worst window; the gap the blind
#: benchmarks call significant) ...
HIDDEN_GAP = 3.0
#: ... and the degradation inputs, refitted to it, leave less than HIDDEN_VISIBLE of it.
HIDDEN_VISIBLE = 1.0


def _window_gap(s: UnitState, z: np.ndarray) -> float:
    """Worst RMS over the config windows and the recorded channels of ``z`` [n_ch * n_t]
    (whitened, channel-major)."""
    z = z.reshape(-1, s.n_t)
    return max((float(np.sqrt(np.mean(z[:, m] ** 2))) for m in s.win_masks if m.any()),
               default=0.0)


def hidden_effects(s: UnitState, candidates: list) -> dict:
    """The candidates the degradation inputs take up on the recorded channels (needs step 1).

    Each candidate is set to each end of its range at the unit's last year's base fit; where
    that moves the recorded channels by a gap of at least ``HIDDEN_GAP`` (noise standard
    deviations, worst window), the year's degradation inputs are refitted to the result
    through the FMU (noise-free). A candidate whose every such end leaves less than
    ``HIDDEN_VISIBLE`` is hidden.

    Returns
    -------
    dict
        ``{effect: {"value": the end tried (effect units), "gap": its gap (sigma),
        "visible": what the refit leaves (sigma), "channel": the unrecorded channel on
        which the effect and its refitted stand-in differ most (None: every channel is
        recorded), "channel_score": that difference (RMS over the channel's noise)}}``
        for the hidden candidates; the end with the larger gap is reported.
    """
    k = s.n_y - 1
    u0 = s.base_u[k]
    theta = s.twin.theta_of(u0)
    try:
        base = s.twin.predict(theta)
    except SimulationError:
        return {}
    Q = np.linalg.qr(s.base_J[k])[0] if np.isfinite(s.Y[k]).all() else None
    out = {}
    for name in candidates:
        e = s.twin.effects[name]
        ends, hidden = [], True
        for end in (e.high, e.low):
            if end == e.baseline:
                continue
            try:
                y = s.twin.predict(theta, {name: end})
            except SimulationError:
                continue
            gap = _window_gap(s, y - base)
            if gap < HIDDEN_GAP:
                continue
            if Q is not None:
                # A first look, linearised: an effect far outside the inputs' span is
                # visible without a refit (the sensor lags, the delays).
                d = y - base
                if _window_gap(s, d - Q @ (Q.T @ d)) > 3 * HIDDEN_VISIBLE:
                    hidden = False
                    break
            fit = JointFit(s.twin, y[None], s.years[k:k + 1]).solve(u0)
            visible = _window_gap(s, fit.rows[0])
            if visible >= HIDDEN_VISIBLE:
                hidden = False
                break
            ends.append((gap, end, visible, fit.x))
        if not hidden or not ends:
            continue
        gap, end, visible, u_fit = max(ends, key=lambda t: t[0])
        channel, scores = separating_channel(s, [(u0, {name: end}), (u_fit, {})])
        out[name] = {"value": float(end), "gap": float(gap), "visible": float(visible),
                     "channel": channel or None,
                     "channel_score": float(scores[channel]) if channel else None}
    return out
