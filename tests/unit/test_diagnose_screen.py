"""The screening of twinmon.diagnose.screen against explicit least squares, on a linear
stand-in for the twin (the algebra alone: no FMU)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from twinmon.diagnose.screen import screen

N_Y, N_T, D = 6, 40, 2


class LinearTwin:
    """Output = B @ theta + sum of value * signature over the effects, already whitened."""

    def __init__(self, rng):
        self.B = rng.standard_normal((N_T, D))
        t = np.linspace(0, 1, N_T)
        # "old": an effect in the twin; "new": a candidate alike to it in part.
        self.sig = {"old": np.ones(N_T) + 0.3 * t, "new": np.ones(N_T) + 0.3 * t + np.sin(6 * t)}
        self.effects = {n: SimpleNamespace(baseline=0.0, low=0.0, high=1.0) for n in self.sig}

    def theta_of(self, u):
        return np.asarray(u, float)

    def predict(self, theta, effects=None):
        out = self.B @ theta
        for n, v in (effects or {}).items():
            out = out + v * self.sig[n]
        return out


def _state(twin, Y):
    return SimpleNamespace(twin=twin, dc=SimpleNamespace(screen_points=4), n_y=N_Y,
                           years=np.arange(1, N_Y + 1), Y=Y)


def test_effects_in_the_twin_are_readjusted_by_one_shared_change():
    """With the effect already in the twin passed as ``Gs``, the screening's gain equals the
    chi-square drop of the linear least squares in which that effect's value moves by one
    change shared by its years (and each year's inputs freely); year by year, a candidate
    alike to the effect in the twin from a later onset would be taken up by it."""
    rng = np.random.default_rng(3)
    twin = LinearTwin(rng)
    on_old, on_new, v_new = 2, 4, 0.5          # year indices 1 and 3
    u = rng.uniform(0.2, 0.8, (N_Y, D))
    Y = np.array([twin.predict(u[k], {"old": 0.4} if k >= on_old - 1 else {})
                  + (v_new * twin.sig["new"] if k >= on_new - 1 else 0)
                  + 0.1 * rng.standard_normal(N_T) for k in range(N_Y)])
    s = _state(twin, Y)
    # The current model: the "old" effect from year 2 at a value off its best, inputs as
    # they were (the screening is linear: where it is taken does not matter).
    fixed = {k: ({"old": 0.3} if k >= on_old - 1 else {}) for k in range(N_Y)}
    rows = [Y[k] - twin.predict(u[k], fixed[k]) for k in range(N_Y)]
    Q = np.linalg.qr(twin.B)[0]
    Gs = [twin.sig["old"][:, None] * (k >= on_old - 1) for k in range(N_Y)]
    score, value, onset, _ = screen(s, "new", u, rows, [Q] * N_Y, fixed, Gs=Gs)

    def chi2(with_new: float, from_year: int) -> float:
        # Unknowns: the old effect's change, then each year's inputs.
        A = np.zeros((N_Y * N_T, 1 + N_Y * D))
        b = np.concatenate([rows[k] - (with_new * twin.sig["new"] if k >= from_year - 1 else 0)
                            for k in range(N_Y)])
        for k in range(N_Y):
            A[k * N_T:(k + 1) * N_T, 0] = Gs[k][:, 0]
            A[k * N_T:(k + 1) * N_T, 1 + k * D:1 + (k + 1) * D] = twin.B
        r = b - A @ np.linalg.lstsq(A, b, rcond=None)[0]
        return float(r @ r)

    assert onset == on_new and value == v_new
    assert np.isclose(score, chi2(0.0, 1) - chi2(value, onset), rtol=1e-9)
    # Re-adjusted year by year (the effect's signature in each year's basis) the candidate
    # keeps only what is unlike the effect in the twin: a much smaller gain.
    Q_year = [np.linalg.qr(np.column_stack([twin.B, G]))[0] if G.any() else Q for G in Gs]
    loose, _, _, _ = screen(s, "new", u, rows, Q_year, fixed)
    assert loose < 0.7 * score
