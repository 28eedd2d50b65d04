"""Joint fits through the FMU: per-year degradation inputs, effects shared over the years from
their onset.

:class:`JointFit` is the weighted least-squares problem (whitened residuals, unknowns
normalised to [0, 1]); :class:`FitResult` is its solution with the Jacobian, the linearised
covariance and the leverages that the tests and maps of the other steps need.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import SimulationError
from .twin import SNAP, Twin

#: Forward-difference step of the Jacobians, in units of each parameter's fitting range.
#: The FMU integrates with rtol 1e-10, so this is far above its numerical noise.
FD_STEP = 1e-5
#: Whitened residual returned for a parameter set the FMU cannot simulate: large and
#: constant, so the trust-region step is rejected and the fit moves back.
_FAIL_RESIDUAL = 1e3
#: Relative tolerance of the fits (cost, step and gradient: scipy's ftol, xtol, gtol). A
#: chi-square of a few hundred is then known to a few 1e-4, against BIC margins of 2 and
#: more. On 120 units of benchmarks/fleet_scale.py, 1e-10 gave the same verdicts, effects
#: and groups, BIC gains within 2e-4 and p-values within 6e-5 of themselves, for a third
#: more FMU runs in an update: the last iterations polish digits no test reads.
FIT_TOL = 1e-6


class JointFit:
    """Weighted least squares of some years of one unit through the FMU.

    Unknowns (all normalised to [0, 1] over their fitting range): one value per effect,
    shared by the years from its onset, then the degradation inputs of each fitted year.

    Parameters
    ----------
    twin : Twin
    ydata : ndarray, shape [n_rows, m]
        Whitened observations of the fitted years (NaN = missing).
    years : ndarray of int, shape [n_rows]
    effects : list of (str, int)
        ``(fmu parameter, onset year)`` of each effect in the model.
    """

    def __init__(self, twin: Twin, ydata: np.ndarray, years: np.ndarray,
                 effects: Sequence[tuple[str, int]] = ()):
        self.twin = twin
        self.y = np.asarray(ydata, float)
        self.mask = np.isfinite(self.y)
        self.years = np.asarray(years)
        self.effects = list(effects)
        self.n_e = len(self.effects)
        self.d = len(twin.in_vars)
        self.active = [[j for j, (_, on) in enumerate(self.effects) if yr >= on]
                       for yr in self.years]
        self._cache = (None, None)

    @property
    def n_params(self) -> int:
        return self.n_e + self.d * len(self.years)

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(effect u [n_e], input u [n_rows, d])``."""
        return x[:self.n_e], x[self.n_e:].reshape(len(self.years), self.d)

    def _effects_at(self, k: int, ue: np.ndarray) -> dict:
        return {self.effects[j][0]: self.twin.effect_of(self.effects[j][0], ue[j])
                for j in self.active[k]}

    def _pred(self, k: int, ue: np.ndarray, ut: np.ndarray) -> np.ndarray:
        try:
            return self.twin.predict(self.twin.theta_of(ut), self._effects_at(k, ue))
        except SimulationError:
            return np.full(self.y.shape[1], np.nan)

    def _resid_rows(self, x):
        key = x.tobytes()
        if self._cache[0] == key:
            return self._cache[1]
        ue, ut = self.unpack(x)
        rows = []
        for k in range(len(self.years)):
            f = self._pred(k, ue, ut[k])
            r = (self.y[k] - f)[self.mask[k]]
            rows.append(np.where(np.isfinite(r), r, _FAIL_RESIDUAL))
        self._cache = (key, rows)
        return rows

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Whitened residuals of all fitted samples, shape [n_samples]."""
        return np.concatenate(self._resid_rows(x))

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """d residuals / d x by forward differences, shape [n_samples, n_params].

        Years are independent given the effects, so a year costs ``1 + d + (its active
        effects)`` FMU runs, not one run per unknown of the whole problem."""
        rows = self._resid_rows(x)
        ue, ut = self.unpack(x)
        J = np.zeros((sum(r.size for r in rows), self.n_params))
        i0 = 0
        for k, r0 in enumerate(rows):
            n = r0.size
            for j in range(self.d):
                h = FD_STEP if ut[k, j] + FD_STEP <= 1.0 else -FD_STEP
                u2 = ut[k].copy()
                u2[j] += h
                f = self._pred(k, ue, u2)
                r = (self.y[k] - f)[self.mask[k]]
                J[i0:i0 + n, self.n_e + k * self.d + j] = (r - r0) / h
            for j in self.active[k]:
                name = self.effects[j][0]
                # Step out of the snapped zone around the baseline, or the slope reads 0.
                near = abs(ue[j] - self.twin.effect_u(name, self.twin.effects[name].baseline))
                step = 2 * SNAP if near < SNAP else FD_STEP
                h = step if ue[j] + step <= 1.0 else -step
                e2 = ue.copy()
                e2[j] += h
                f = self._pred(k, e2, ut[k])
                r = (self.y[k] - f)[self.mask[k]]
                J[i0:i0 + n, j] = (r - r0) / h
            i0 += n
        return np.where(np.isfinite(J), J, 0.0)

    def solve(self, x0: np.ndarray) -> "FitResult":
        """Bounded trust-region least squares from ``x0`` (clipped into [0, 1])."""
        x0 = np.clip(np.asarray(x0, float), 1e-9, 1 - 1e-9)
        from scipy.optimize import least_squares   # 0.3-0.6 s to import: when fitting
        res = least_squares(self.residuals, x0, jac=self.jacobian, bounds=(0.0, 1.0),
                            method="trf", x_scale="jac", ftol=FIT_TOL, xtol=FIT_TOL,
                            gtol=FIT_TOL, max_nfev=100)
        # The residuals and Jacobian at the solution are the fit's own last evaluations
        # (trf ends on the point whose Jacobian it took): the same arrays, not made again.
        return FitResult(res.x, self.split_rows(res.fun), res.jac, self)

    def split_rows(self, resid: np.ndarray) -> list:
        """:meth:`residuals`' vector cut back into its years' rows."""
        return np.split(resid, np.cumsum(self.mask.sum(axis=1))[:-1])


@dataclass
class FitResult:
    """A solved :class:`JointFit`: ``x`` [n_params] (normalised), whitened residual rows,
    Jacobian [n_samples, n_params]."""

    x: np.ndarray
    rows: list
    J: np.ndarray
    problem: JointFit

    @property
    def chi2_rows(self) -> np.ndarray:
        return np.array([float(r @ r) for r in self.rows])

    def covariance(self) -> np.ndarray:
        """Linearised covariance of ``x`` ((J^T J)^-1, whitened residuals), [n_p, n_p]."""
        return np.linalg.pinv(self.J.T @ self.J)

    def leverage_rows(self) -> list:
        """Leverage h_i = diag(J (J^T J)^-1 J^T) per fitted year."""
        J = self.J
        h = np.einsum("ij,jk,ik->i", J, self.covariance(), J)
        out, i0 = [], 0
        for r in self.rows:
            out.append(np.clip(h[i0:i0 + r.size], 0.0, 0.99))
            i0 += r.size
        return out
