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


def hidden_effects(s: UnitState, candidates: list, u_last: np.ndarray | None = None,
                   effects: dict | None = None) -> dict:
    """The candidates the degradation inputs take up on the recorded channels.

    Each candidate is set to each end of its range at the unit's last year (normalised
    inputs ``u_last`` [d], default the base fit's, and the ``effects`` already in its final
    twin, ``{fmu parameter: value}``); where that moves the recorded channels by a gap of at
    least ``HIDDEN_GAP`` (noise standard deviations, worst window), the year's degradation
    inputs are refitted to the result through the FMU (noise-free). A candidate is hidden
    when at an end the refit leaves less than ``HIDDEN_VISIBLE``: in that direction no
    diagnosis on these channels can see it.

    Returns
    -------
    dict
        ``{effect: {"value": the end (effect units), "gap": its gap (sigma), "visible": what
        the refit leaves (sigma), "channel": the unrecorded channel on which the effect and
        its refitted stand-in differ most (None: every channel is recorded),
        "channel_score": that difference (RMS over the channel's noise)}}`` for the hidden
        candidates, at the hidden end with the larger gap.
    """
    k = s.n_y - 1
    u0 = s.base_u[k] if u_last is None else np.asarray(u_last, float)
    eff0 = dict(effects or {})
    theta = s.twin.theta_of(u0)
    try:
        base = s.twin.predict(theta, eff0)
    except SimulationError:
        return {}
    # The span of the inputs' sensitivities there, for a cheap first look.
    J = JointFit(s.twin, base[None], s.years[k:k + 1], [(n, 0) for n in eff0])
    x = np.concatenate([[s.twin.effect_u(n, v) for n, v in eff0.items()], u0])
    J_u = J.jacobian(x)[:, len(eff0):]
    Q = np.linalg.qr(J_u)[0]
    out = {}
    for name in candidates:
        e = s.twin.effects[name]
        ends = []
        for end in (e.high, e.low):
            if end == e.baseline:
                continue
            try:
                y = s.twin.predict(theta, {**eff0, name: end})
            except SimulationError:
                continue
            d = y - base
            gap = _window_gap(s, d)
            # Too small to matter, or far outside the inputs' span (linearised): the sensor
            # lags, the delays.
            if gap < HIDDEN_GAP or _window_gap(s, d - Q @ (Q.T @ d)) > 3 * HIDDEN_VISIBLE:
                continue
            prob = JointFit(s.twin, y[None], s.years[k:k + 1], [(n, 0) for n in eff0])
            # The effects in the twin stay at their values: only the inputs move, from
            # the linearised fit's point (one Gauss-Newton step: r = d at u0, dr/du = J_u),
            # which saves the refit its first iterations.
            step = np.linalg.lstsq(J_u, -d, rcond=None)[0]
            start = np.concatenate([x[:len(eff0)], np.clip(u0 + step, 0.0, 1.0)])
            fit = _refit_inputs(prob, start, len(eff0))
            visible = _window_gap(s, fit[0])
            if visible < HIDDEN_VISIBLE:
                ends.append((gap, end, visible, fit[1]))
        if not ends:
            continue
        gap, end, visible, u_fit = max(ends, key=lambda t: t[0])
        channel, scores = separating_channel(s, [(u0, {**eff0, name: end}), (u_fit, eff0)])
        out[name] = {"value": float(end), "gap": float(gap), "visible": float(visible),
                     "channel": channel or None,
                     "channel_score": float(scores[channel]) if channel else None}
    return out


def _refit_inputs(prob: JointFit, x0: np.ndarray, n_e: int) -> tuple:
    """Least squares of the degradation inputs alone of a one-year ``prob`` whose effects
    are held at ``x0[:n_e]``: ``(whitened residual [m], normalised inputs [d])``."""
    from scipy.optimize import least_squares
    fixed = x0[:n_e]

    def resid(u):
        return prob.residuals(np.concatenate([fixed, u]))

    def jac(u):
        return prob.jacobian(np.concatenate([fixed, u]))[:, n_e:]
    res = least_squares(resid, np.clip(x0[n_e:], 1e-9, 1 - 1e-9), jac=jac, bounds=(0.0, 1.0),
                        method="trf", x_scale="jac", max_nfev=100)
    # The residual at the solution is the fit's own last evaluation (res.fun).
    return res.fun, res.x
