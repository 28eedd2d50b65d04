"""Stage ``diagnose``: where the twin misses the plant, what causes it, and how far it shrinks.

A calibrated twin never matches a plant exactly. An unmodelled effect (a lagging flowmeter, a
valve that opens slowly, fouling, a leak, a weak supply, ...) leaves a structured residual and,
worse, is partly absorbed into the degradation estimates and so into the time to failure. For
each unit this module

1. **locates** the gap: the twin (the real FMU, degradation inputs fitted by maximum likelihood
   year by year, warm-started) is compared with the observations; standardised residuals by
   year, channel and time window; per-year chi-square of the whitened residual and a
   Ljung-Box test of structure, pooled tests from every possible onset year, all at a
   Bonferroni-corrected level; the onset year; how much of the effect's signature the
   degradation inputs absorb (its share in the span of their sensitivities);
2. **identifies** the cause: every candidate effect (an FMU parameter of ``model.effects``) is
   screened by how much of the residual its signature explains once the degradation inputs
   are linearly re-adjusted (a grid over the effect's range and every onset year: cheap), then
   confirmed by the augmented fit through the FMU (per-year degradation inputs plus the effect,
   one value per unit from its onset) and compared by BIC; candidates within ``group_bic``
   of the best are reported as one group, with the FMU channel that would separate them;
   further effects are added only while the BIC gain stays above ``bic_gain``;
3. **measures the shrink**: residual RMS over noise before and after, percentage of the excess
   gap closed, the BIC gain, the effect estimate with a 90 % interval, and how the degradation
   estimates and the projected failure year move once the effect is in the twin.

The diagnosing side reads only observations (and optionally a posterior); never a truth file.
The artifact is ``gap.h5`` (``twinmon.gap/1``, layout in :func:`write_gap`).
"""
from __future__ import annotations

import json
import math
import os
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError, ConfigError, InputDataError, SimulationError
from ..observations import read_observations

#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "diagnose", "safety")

VERDICTS = ("none", "effect", "unexplained")
#: Forward-difference step of the Jacobians, in units of each parameter's fitting range.
#: The FMU integrates with rtol 1e-10, so this is far above its numerical noise.
FD_STEP = 1e-5
#: Whitened residual returned for a parameter set the FMU cannot simulate: large and
#: constant, so the trust-region step is rejected and the fit moves back.
_FAIL_RESIDUAL = 1e3
#: Effect values closer than this (fraction of the effect's range) to the baseline are run as
#: the baseline itself: a vanishing lag (sensor.tau -> 0) makes the FMU's equations stiff
#: (seconds per run) while its output equals the baseline's to far below the noise.
SNAP = 1e-3


# ---------------------------------------------------------------------------------------
# The twin: one FMU instance, parameters in normalised units
# ---------------------------------------------------------------------------------------
class Twin:
    """The FMU seen by ``diagnose``: degradation inputs + effects in, observed channels out.

    Parameters
    ----------
    cfg : Config
    fmu_path : path-like
        The ``.fmu`` file (already built).
    channels : sequence of str
        Observed channels: ``model.output.name`` (the config's output variable) and further
        channels named by their FMU variable.
    time : ndarray, shape [n_t]
        Sample times (s).
    sigma : dict of str to float
        Noise standard deviation per channel (channel units); residuals are divided by it.
    effects : sequence of str
        Candidate effect parameters; their fitting range is the config's ``[low, high]``.
    """

    def __init__(self, cfg: Config, fmu_path, channels: Sequence[str], time: np.ndarray,
                 sigma: dict, effects: Sequence[str]):
        from ..fmu import FMUModel
        self.cfg = cfg
        self.channels = list(channels)
        out = cfg.model.output
        self.var = {c: (out.variable if c == out.name else c) for c in self.channels}
        extra = [out.variable, cfg.indicator_variable] + list(cfg.model.channels)
        if cfg.model.nonphysical:
            extra.append(cfg.model.nonphysical)
        outputs = list(dict.fromkeys(list(self.var.values()) + extra))
        self.model = FMUModel(fmu_path, outputs, time, fmi_type=cfg.model.fmi_type,
                              start_values=dict(cfg.model.fixed))
        self.time = np.asarray(time, float)
        self.sigma = np.concatenate([np.full(self.time.size, float(sigma[c]))
                                     for c in self.channels])
        self.in_vars = [s.variable for s in cfg.model.inputs.values()]
        box = cfg.model.bounds
        width = box[:, 1] - box[:, 0]
        lo = box[:, 0] - cfg.diagnose.fit_margin * width
        # Damping-like inputs must stay positive for the physics to hold.
        self.in_lo = np.where(box[:, 0] > 0, np.maximum(lo, 0.05 * box[:, 0]), lo)
        self.in_hi = box[:, 1] + cfg.diagnose.fit_margin * width
        self.effects = {e: cfg.model.effects[e] for e in effects}
        self.runs = 0

    # -- parameter maps ---------------------------------------------------------------
    def theta_of(self, u: np.ndarray) -> np.ndarray:
        """Normalised degradation inputs [..., d] in [0, 1] -> input units."""
        return self.in_lo + np.asarray(u) * (self.in_hi - self.in_lo)

    def u_of(self, theta: np.ndarray) -> np.ndarray:
        return (np.asarray(theta) - self.in_lo) / (self.in_hi - self.in_lo)

    def effect_of(self, name: str, u: float) -> float:
        e = self.effects[name]
        return e.low + float(u) * (e.high - e.low)

    def effect_u(self, name: str, value: float) -> float:
        e = self.effects[name]
        return (float(value) - e.low) / (e.high - e.low)

    # -- runs ---------------------------------------------------------------------------
    def run(self, theta: np.ndarray, effects: dict | None = None) -> dict:
        """All recorded outputs (each [n_t]) for inputs ``theta`` [d] (input units) and
        effect values ``{fmu parameter: value}``."""
        p = {v: float(x) for v, x in zip(self.in_vars, theta)}
        for k, v in (effects or {}).items():
            e = self.effects.get(k)
            if e is not None and abs(v - e.baseline) < SNAP * (e.high - e.low):
                v = e.baseline
            p[k] = float(v)
        self.runs += 1
        return self.model.run(p)

    def predict(self, theta: np.ndarray, effects: dict | None = None) -> np.ndarray:
        """Whitened prediction of the observed channels, shape [n_ch * n_t] (channel-major)."""
        out = self.run(theta, effects)
        return np.concatenate([out[self.var[c]] for c in self.channels]) / self.sigma

    def close(self) -> None:
        self.model.close()


# ---------------------------------------------------------------------------------------
# Joint fits: per-year degradation inputs, effects shared over the years from their onset
# ---------------------------------------------------------------------------------------
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
        res = least_squares(self.residuals, x0, jac=self.jacobian, bounds=(0.0, 1.0),
                            method="trf", x_scale="jac", ftol=1e-10, xtol=1e-10, gtol=1e-10,
                            max_nfev=100)
        rows = self._resid_rows(res.x)
        J = self.jacobian(res.x)
        return FitResult(res.x, rows, J, self)


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


# ---------------------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------------------
def ljung_box(z: np.ndarray, lags: int) -> float:
    """Ljung-Box p-value of a residual sequence (NaN dropped) for ``lags`` lags."""
    z = np.asarray(z, float)
    z = z[np.isfinite(z)]
    n = z.size
    lags = min(lags, n - 2)
    if lags < 1:
        return 1.0
    z = z - z.mean()
    c0 = float(z @ z)
    if c0 <= 0:
        return 1.0
    rho = np.array([float(z[k:] @ z[:-k]) / c0 for k in range(1, lags + 1)])
    q = n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, lags + 1)))
    return float(stats.chi2.sf(q, lags))


def pooled_onset_pvalues(chi2: np.ndarray, dof: np.ndarray) -> np.ndarray:
    """p-value of the pooled chi-square of the years from each possible onset on, [n_y]."""
    c = np.cumsum(chi2[::-1])[::-1]
    d = np.cumsum(dof[::-1])[::-1]
    return stats.chi2.sf(c, np.maximum(d, 1))


# ---------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------
@dataclass
class UnitGap:
    """Diagnosis of one unit. Arrays are per year [n_y] and per time step [n_t] of the output.

    Attributes
    ----------
    verdict : str
        ``"none"``, ``"effect"`` or ``"unexplained"``.
    effects : list of str
        The effect, or the group of indistinguishable effects (best first), then any further
        effect added; empty unless the verdict is ``"effect"``.
    group : list of str
        The first effect's group (candidates within ``group_bic`` of the best).
    residual_before, residual_after : ndarray, shape [n_y, n_t]
        Standardised output residuals of the base and the final twin.
    window_rms_before, window_rms_after : ndarray, shape [n_y, n_w]
        RMS of the standardised output residual per year and window.
    predicted_before, predicted_after, observed : ndarray, shape [n_y, n_t]
        Output (its units).
    inputs_before, inputs_after, inputs_sd_before, inputs_sd_after : ndarray, shape [n_y, d]
        Degradation input estimates and their linearised standard deviations.
    candidates : list of str
        Candidate effects, in ranking order (best BIC first).
    screen_score : ndarray, shape [n_c]
        Screening chi-square reduction.
    delta_bic : ndarray, shape [n_c]
        BIC of the base twin minus BIC of the twin with that candidate (higher = better).
    """

    unit: str
    years: np.ndarray
    verdict: str
    effects: list
    group: list
    onset: Optional[int]
    where_windows: list
    where_years: list
    rms_before: float
    rms_after: float
    closed_percent: float
    delta_bic_final: float
    estimate: dict
    separating_channel: str
    separation_scores: dict
    absorbed_share: float
    p_gap: float
    noise_std: float
    residual_before: np.ndarray
    residual_after: np.ndarray
    chi2_before: np.ndarray
    chi2_after: np.ndarray
    dof: np.ndarray
    p_chi2_before: np.ndarray
    p_ljung_box_before: np.ndarray
    p_chi2_after: np.ndarray
    significant_years: np.ndarray
    window_rms_before: np.ndarray
    window_rms_after: np.ndarray
    observed: np.ndarray
    predicted_before: np.ndarray
    predicted_after: np.ndarray
    inputs_before: np.ndarray
    inputs_after: np.ndarray
    inputs_sd_before: np.ndarray
    inputs_sd_after: np.ndarray
    candidates: list
    screen_score: np.ndarray
    screen_onset: np.ndarray
    fit_onset: np.ndarray
    fit_value: np.ndarray
    fit_sd: np.ndarray
    delta_bic: np.ndarray
    failure_year_before: Optional[int]
    failure_year_after: Optional[int]
    #: Onset year of each effect in the final twin ({fmu parameter: year}).
    effect_onsets: dict = field(default_factory=dict)
    fmu_runs: int = 0
    wall_time: float = 0.0

    def as_dict(self) -> dict:
        """The ``--json`` entry of this unit (issue 4's schema, plus a few extra keys)."""
        return {
            "verdict": self.verdict,
            "effects": list(self.effects),
            "where": {"windows": list(self.where_windows), "years": [int(y) for y in self.where_years]},
            "shrink": {"rms_before": _num(self.rms_before), "rms_after": _num(self.rms_after),
                       "closed_percent": _num(self.closed_percent)},
            "estimate": {k: {"mean": _num(v[0]), "q05": _num(v[1]), "q95": _num(v[2])}
                         for k, v in self.estimate.items()},
            "onset": self.onset,
            "onsets": dict(self.effect_onsets),
            "group": list(self.group),
            "separating_channel": self.separating_channel or None,
            "bic_gain": _num(self.delta_bic_final),
            "absorbed_share": _num(self.absorbed_share),
            "p_gap": _num(self.p_gap),
            "failure_year": {"before": self.failure_year_before,
                             "after": self.failure_year_after},
            "ranking": [{"effect": c, "delta_bic": _num(b), "screen": _num(s)}
                        for c, b, s in zip(self.candidates, self.delta_bic, self.screen_score)],
        }


def _num(x) -> Optional[float]:
    x = float(x)
    return round(x, 6) if math.isfinite(x) else None


@dataclass
class DiagnoseSummary:
    units: dict
    output: str
    wall_time: float
    workers: int

    def as_dict(self) -> dict:
        return {"units": {u: g.as_dict() for u, g in self.units.items()},
                "output": self.output, "wall_time": round(self.wall_time, 3),
                "workers": self.workers}


# ---------------------------------------------------------------------------------------
# One unit
# ---------------------------------------------------------------------------------------
def estimate_noise(y: np.ndarray, time: np.ndarray, start: float) -> float:
    """Noise standard deviation from second differences of samples after ``start`` (s),
    where the transient is nearly flat: std(d2 y) = sqrt(6) sigma; median absolute
    deviation for robustness. ``y`` [n_y, n_t]."""
    sel = np.asarray(time) >= start
    if sel.sum() < 4:
        sel = np.ones(len(time), bool)
    d2 = np.diff(y[:, sel], n=2, axis=1).ravel()
    d2 = d2[np.isfinite(d2)]
    if d2.size < 3:
        raise InputDataError("too few samples to estimate the noise; record noise_std")
    s = 1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0)
    if not s > 0:
        raise InputDataError("cannot estimate the noise (flat record); record noise_std")
    return float(s)


class _UnitDiagnosis:
    """Carries the state of one unit's diagnosis through its steps (see module doc)."""

    def __init__(self, twin: Twin, cfg: Config, unit: str, years: np.ndarray,
                 Y: np.ndarray, posterior=None):
        self.twin, self.cfg, self.dc = twin, cfg, cfg.diagnose
        self.unit = unit
        self.years = np.asarray(years)
        self.Y = Y                                   # [n_y, m] whitened, NaN = missing
        self.n_y, self.m = Y.shape
        self.n_t = twin.time.size
        self.d = len(twin.in_vars)
        self.n_obs = int(np.isfinite(Y).sum())
        self.ln_n = math.log(max(self.n_obs, 2))
        self.posterior = posterior
        windows = cfg.diagnose_windows()
        self.win_names = list(windows)
        t = twin.time
        self.win_masks = [(t >= w.start) & (t < w.stop) for w in windows.values()]

    # -- step 1: the base twin ---------------------------------------------------------
    def fit_base(self):
        u_prev = self.twin.u_of([s.nominal for s in self.cfg.model.inputs.values()])
        self.base_u = np.zeros((self.n_y, self.d))
        self.base_rows, self.base_J, self.base_lev = [], [], []
        for k in range(self.n_y):
            prob = JointFit(self.twin, self.Y[k:k + 1], self.years[k:k + 1])
            fit = prob.solve(u_prev)
            if k == 0 and fit.chi2_rows[0] > 3 * fit.rows[0].size:
                # A poor first year may sit in a local minimum: retry from the box centre.
                alt = prob.solve(np.full(self.d, 0.5))
                if alt.chi2_rows[0] < fit.chi2_rows[0]:
                    fit = alt
            self.base_u[k] = fit.x
            self.base_rows.append(fit.rows[0])
            self.base_J.append(fit.J)
            self.base_lev.append(fit.leverage_rows()[0])
            u_prev = fit.x
        self.chi2_base = np.array([float(r @ r) for r in self.base_rows])
        self.n_rows = np.array([r.size for r in self.base_rows])
        self.dof = np.maximum(self.n_rows - self.d, 1)
        # Orthonormal bases of the span of the degradation sensitivities, per year.
        self.base_Q = [np.linalg.qr(J)[0] for J in self.base_J]

    def year_tests(self, rows, lev, n_par):
        chi2 = np.array([float(r @ r) for r in rows])
        dof = np.maximum(np.array([r.size for r in rows]) - n_par, 1)
        p_chi2 = stats.chi2.sf(chi2, dof)
        p_lb = np.array([ljung_box(self._output_part(r / np.sqrt(1 + h), k), self.dc.ljung_box_lags)
                         for k, (r, h) in enumerate(zip(rows, lev))])
        return chi2, dof, p_chi2, p_lb

    def _output_part(self, r_masked: np.ndarray, k: int) -> np.ndarray:
        """The output channel of a masked residual row, back on the time grid [n_t] (NaN gaps)."""
        full = np.full(self.m, np.nan)
        full[np.isfinite(self.Y[k])] = r_masked
        return full[:self.n_t]

    # -- step 2: detection ---------------------------------------------------------------
    def detect(self):
        a = self.dc.alpha
        chi2, dof, p_chi2, p_lb = self.year_tests(self.base_rows, self.base_lev, self.d)
        self.p_chi2_before, self.p_lb_before = p_chi2, p_lb
        p_year = np.minimum(1.0, 2 * self.n_y * np.minimum(p_chi2, p_lb))
        self.significant_years = p_year < a
        p_pool = np.minimum(1.0, self.n_y * pooled_onset_pvalues(chi2, dof))
        self.detected_onset = int(self.years[int(np.argmin(p_pool))])
        # Bonferroni over the two families (per-year tests, pooled-from-onset tests).
        self.p_omnibus = float(min(1.0, 2 * min(p_year.min(), p_pool.min())))

    # -- step 3: screening ---------------------------------------------------------------
    def _grid(self, name: str) -> np.ndarray:
        e = self.twin.effects[name]
        n = self.dc.screen_points
        fr = np.arange(1, n + 1) / n
        vals = []
        if e.high > e.baseline:
            vals += list(e.baseline + fr * (e.high - e.baseline))
        if e.low < e.baseline:
            vals += list(e.baseline - fr * (e.baseline - e.low))
        return np.array(vals)

    def screen(self, name: str, u_inputs, rows, Qs, fixed: dict) -> tuple:
        """Chi-square reduction of adding effect ``name`` (value on a grid, onset any year),
        the degradation inputs re-adjusted linearly.

        Returns ``(score, value, onset, gain [n_v, n_y])``; ``fixed`` maps years index ->
        effects already in the twin."""
        grid = self._grid(name)
        gains = np.zeros((grid.size, self.n_y))
        for k in range(self.n_y):
            theta = self.twin.theta_of(u_inputs[k])
            eff0 = fixed.get(k, {})
            mask = np.isfinite(self.Y[k])
            try:
                f0 = self.twin.predict(theta, eff0)[mask]
            except SimulationError:
                continue
            Q = Qs[k]
            r = rows[k]
            rp = r - Q @ (Q.T @ r)
            base = float(rp @ rp)
            for i, v in enumerate(grid):
                try:
                    f = self.twin.predict(theta, {**eff0, name: v})[mask]
                except SimulationError:
                    gains[i, k] = -np.inf
                    continue
                r2 = r - (f - f0)
                r2 = r2 - Q @ (Q.T @ r2)
                gains[i, k] = base - float(r2 @ r2)
        cum = np.cumsum(gains[:, ::-1], axis=1)[:, ::-1]      # [n_v, onset index]
        i, o = np.unravel_index(int(np.argmax(cum)), cum.shape)
        return float(cum[i, o]), float(grid[i]), int(self.years[o]), gains

    # -- step 4: confirmation by the augmented fit -------------------------------------
    def fit_with(self, effects: list, values: list, u_start: np.ndarray):
        """Fit the twin with ``effects`` [(name, onset)] from start values; years before the
        earliest onset keep the base fit. Returns ``(chi2 total, FitResult, first row)``."""
        first = min(on for _, on in effects)
        k0 = int(np.searchsorted(self.years, first))
        if k0 >= self.n_y:
            return np.inf, None, k0
        prob = JointFit(self.twin, self.Y[k0:], self.years[k0:], effects)
        x0 = np.concatenate([[self.twin.effect_u(n, v) for (n, _), v in zip(effects, values)],
                             np.asarray(u_start)[k0:].ravel()])
        fit = prob.solve(x0)
        chi2 = float(self.chi2_base[:k0].sum() + fit.chi2_rows.sum())
        return chi2, fit, k0

    def bic(self, chi2: float, n_effects: int) -> float:
        # Each effect costs its value and its onset year.
        return chi2 + (self.d * self.n_y + 2 * n_effects) * self.ln_n

    def confirm(self, name: str, value: float, onset: int, fixed_fit=None):
        """Best augmented fit of candidate ``name`` over onsets ``onset +- onset_search``."""
        best = None
        for on in range(onset - self.dc.onset_search, onset + self.dc.onset_search + 1):
            if on < self.years[0] or on > self.years[-1]:
                continue
            u0 = self._readjusted_start(name, value, on)
            chi2, fit, k0 = self.fit_with([(name, on)], [value], u0)
            if fit is not None and (best is None or chi2 < best[0]):
                best = (chi2, fit, k0, on)
        return best

    def _readjusted_start(self, name, value, onset):
        """Base inputs moved by one linear step to make room for the effect."""
        u = self.base_u.copy()
        for k in range(self.n_y):
            if self.years[k] < onset:
                continue
            mask = np.isfinite(self.Y[k])
            theta = self.twin.theta_of(u[k])
            try:
                df = (self.twin.predict(theta, {name: value}) - self.twin.predict(theta))[mask]
            except SimulationError:
                continue
            J = -self.base_J[k]                        # d f / d u
            step = np.linalg.lstsq(J, self.base_rows[k] - df, rcond=None)[0]
            u[k] = np.clip(u[k] + step, 0.0, 1.0)
        return u

    # -- whole unit ----------------------------------------------------------------------
    def run(self, candidates: list) -> UnitGap:
        t0 = _time.perf_counter()
        runs0 = self.twin.runs
        self.fit_base()
        self.detect()
        bic_base = self.bic(float(self.chi2_base.sum()), 0)

        # Screening, then confirmation of every candidate (cheap with the FMU at ~0.1 ms/run).
        screened = {}
        for name in candidates:
            screened[name] = self.screen(name, self.base_u, self.base_rows, self.base_Q, {})
        confirmed = {}
        for name in candidates:
            score, v, on, _ = screened[name]
            confirmed[name] = self.confirm(name, v, on)
        dbic = {n: (bic_base - self.bic(c[0], 1)) if c else -np.inf for n, c in confirmed.items()}
        order = sorted(candidates, key=lambda n: -dbic[n])
        best = order[0] if order else None

        significant = self.p_omnibus < self.dc.alpha or (
            best is not None and dbic[best] > self.dc.bic_gain)
        p_gap = self.p_omnibus
        if best is not None and dbic[best] > 0:
            # Likelihood-ratio p-value of the best candidate, Bonferroni over candidates and
            # onsets (value and onset both free: 2 degrees of freedom).
            lr = float(self.chi2_base.sum() - confirmed[best][0])
            p_lr = min(1.0, stats.chi2.sf(lr, 2) * len(candidates) * self.n_y)
            p_gap = min(p_gap, p_lr)

        # The final model: effects added while the BIC gain stays above bic_gain.
        model_effects, model_values, final = [], [], None
        group = []
        if significant and best is not None and dbic[best] > self.dc.bic_gain:
            chi2_b, fit_b, k0_b, on_b = confirmed[best]
            ue, _ = fit_b.problem.unpack(fit_b.x)
            model_effects = [(best, on_b)]
            model_values = [self.twin.effect_of(best, ue[0])]
            final = (chi2_b, fit_b, k0_b)
            group = [n for n in order if dbic[n] > self.dc.bic_gain
                     and dbic[best] - dbic[n] <= self.dc.group_bic]
            while len(model_effects) < self.dc.max_effects:
                nxt = self._further(final, model_effects, model_values, candidates)
                if nxt is None:
                    break
                final, model_effects, model_values = nxt

        # Before / after on the affected years.
        after_u = self.base_u.copy()
        after_rows = list(self.base_rows)
        after_lev = list(self.base_lev)
        after_cov = None
        if final is not None:
            _, fit, k0 = final
            _, ut = fit.problem.unpack(fit.x)
            after_u[k0:] = ut
            lev = fit.leverage_rows()
            for j in range(len(ut)):
                after_rows[k0 + j] = fit.rows[j]
                after_lev[k0 + j] = lev[j]
            after_cov = fit.covariance()
        onset = (min(on for _, on in model_effects) if model_effects
                 else (self.detected_onset if significant else None))
        aff = (self.years >= onset) if onset is not None else np.ones(self.n_y, bool)
        n_eff = len(model_effects)
        rss_b = float(self.chi2_base[aff].sum())
        rss_a = float(sum(float(after_rows[k] @ after_rows[k]) for k in np.flatnonzero(aff)))
        n_aff = int(self.n_rows[aff].sum())
        dof_b = max(n_aff - self.d * int(aff.sum()), 1)
        dof_a = max(dof_b - n_eff, 1)
        rms_before = math.sqrt(rss_b / dof_b)
        rms_after = math.sqrt(rss_a / dof_a)
        # If the gap was significant but nothing was accepted, show what the best candidate
        # would have done (so an "unexplained" verdict still says how far the best one got).
        if final is None and significant and best is not None and confirmed[best]:
            _, fit_x, k0_x, _ = confirmed[best]
            rows_x = list(self.base_rows[:k0_x]) + list(fit_x.rows)
            rss_x = float(sum(float(rows_x[k] @ rows_x[k]) for k in np.flatnonzero(aff)))
            rms_after = math.sqrt(rss_x / max(dof_b - 1, 1))
        ex_b = rms_before ** 2 - 1.0
        ex_a = max(rms_after ** 2 - 1.0, 0.0)
        closed = 100.0 * (1.0 - ex_a / ex_b) if ex_b > 0 else 0.0
        closed = float(np.clip(closed, 0.0, 100.0)) if significant else 0.0

        # Is what remains consistent with noise? (same battery of tests, affected years)
        chi2_a, dof_a_y, p_chi2_a, p_lb_a = self.year_tests(after_rows, after_lev, self.d)
        k_aff = np.flatnonzero(aff)
        p_rem_year = min(1.0, 2 * len(k_aff) * float(np.minimum(p_chi2_a, p_lb_a)[k_aff].min()))
        p_rem_pool = float(stats.chi2.sf(chi2_a[k_aff].sum(), max(dof_a, 1)))
        remaining = min(p_rem_year, p_rem_pool) < self.dc.alpha

        if not significant:
            verdict = "none"
        elif final is not None and closed >= self.dc.min_closed and (
                not remaining or closed >= self.dc.explained_closed):
            # A large gap closed almost entirely is explained even if the remainder fails the
            # noise tests (an unlucky noise draw, or the test's power on many years).
            verdict = "effect"
        else:
            verdict = "unexplained"
        if verdict != "effect":
            # The twin is left as it was: nothing is added that the data do not support.
            after_u = self.base_u.copy()
            after_rows, after_lev = list(self.base_rows), list(self.base_lev)
            chi2_a, p_chi2_a = self.chi2_base.copy(), self.p_chi2_before.copy()
            if verdict == "none":
                rms_after = rms_before
            after_cov = None

        effects_out, estimate = [], {}
        if verdict == "effect":
            effects_out = list(group) + [n for n, _ in model_effects[1:] if n not in group]
            cov = after_cov
            for j, (n, _) in enumerate(model_effects):
                sd_u = math.sqrt(max(cov[j, j], 0.0))
                estimate[n] = self._interval(n, model_values[j], sd_u)
            for n in group[1:]:
                if n in estimate:
                    continue
                c = confirmed[n]
                ue, _ = c[1].problem.unpack(c[1].x)
                sd_u = math.sqrt(max(c[1].covariance()[0, 0], 0.0))
                estimate[n] = self._interval(n, self.twin.effect_of(n, ue[0]), sd_u)

        # Where: significant windows in the affected years.
        z_before = (self._posterior_zmap() if self.posterior is not None
                    else self._zmap(self.base_rows, self.base_lev))
        z_after = self._zmap(after_rows, after_lev)
        w_before, w_after = self._window_rms(z_before), self._window_rms(z_after)
        where_w, where_y = [], []
        if verdict != "none":
            where_y = [int(y) for y in self.years[aff]]
            for j, name in enumerate(self.win_names):
                z = z_before[aff][:, self.win_masks[j]]
                z = z[np.isfinite(z)]
                if z.size and stats.chi2.sf(float(z @ z), z.size) * len(self.win_names) < self.dc.alpha:
                    where_w.append(name)

        # Predictions, inputs and their standard deviations.
        pred_b = np.array([self._output_pred(self.base_u[k], {}) for k in range(self.n_y)])
        eff_year = [{n: v for (n, on), v in zip(model_effects, model_values) if self.years[k] >= on}
                    if verdict == "effect" else {} for k in range(self.n_y)]
        pred_a = np.array([self._output_pred(after_u[k], eff_year[k]) for k in range(self.n_y)])
        width = self.twin.in_hi - self.twin.in_lo
        sd_b = np.array([np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)), 0, None)) * width
                         for J in self.base_J])
        sd_a = sd_b.copy()
        if verdict == "effect":
            k0 = final[2]
            var = np.clip(np.diag(after_cov), 0, None)[n_eff:].reshape(-1, self.d)
            sd_a[k0:] = np.sqrt(var) * width

        # Absorbed share of the effect's signature (in the span of the degradation inputs).
        absorbed = float("nan")
        if verdict == "effect":
            num = den = 0.0
            for k in np.flatnonzero(aff):
                theta = self.twin.theta_of(after_u[k])
                mask = np.isfinite(self.Y[k])
                eff = eff_year[k]
                main = model_effects[0][0]
                rest = {n: v for n, v in eff.items() if n != main}
                delta = (self.twin.predict(theta, eff) - self.twin.predict(theta, rest))[mask]
                Q = self.base_Q[k]
                inside = Q @ (Q.T @ delta)
                num += float(inside @ inside)
                den += float(delta @ delta)
            absorbed = num / den if den > 0 else float("nan")

        sep_channel, sep_scores = "", {}
        if verdict == "effect" and len(group) > 1:
            sep_channel, sep_scores = self._separation(group, confirmed)

        fy_b = self._failure_year(self.twin.theta_of(self.base_u), {})
        fy_a = (self._failure_year(self.twin.theta_of(after_u), eff_year[-1])
                if verdict == "effect" else fy_b)

        ranking = order
        fit_on, fit_val, fit_sd = [], [], []
        for n in ranking:
            c = confirmed[n]
            if c is None:
                fit_on.append(-1), fit_val.append(np.nan), fit_sd.append(np.nan)
                continue
            ue, _ = c[1].problem.unpack(c[1].x)
            e = self.twin.effects[n]
            fit_on.append(c[3])
            fit_val.append(self.twin.effect_of(n, ue[0]))
            fit_sd.append(math.sqrt(max(c[1].covariance()[0, 0], 0.0)) * (e.high - e.low))
        delta_final = (bic_base - self.bic(final[0], n_eff)) if verdict == "effect" else (
            dbic[best] if best is not None else 0.0)
        return UnitGap(
            unit=self.unit, years=self.years, verdict=verdict, effects=effects_out,
            group=group if verdict == "effect" else [], onset=onset,
            where_windows=where_w, where_years=where_y, rms_before=rms_before,
            rms_after=rms_after, closed_percent=closed, delta_bic_final=float(delta_final),
            estimate=estimate, separating_channel=sep_channel, separation_scores=sep_scores,
            absorbed_share=absorbed, p_gap=float(p_gap), noise_std=float(self.twin.sigma[0]),
            residual_before=z_before, residual_after=z_after,
            chi2_before=self.chi2_base, chi2_after=np.asarray(chi2_a, float), dof=self.dof,
            p_chi2_before=self.p_chi2_before, p_ljung_box_before=self.p_lb_before,
            p_chi2_after=np.asarray(p_chi2_a, float), significant_years=self.significant_years,
            window_rms_before=w_before, window_rms_after=w_after,
            observed=self.Y[:, :self.n_t] * self.twin.sigma[0],
            predicted_before=pred_b, predicted_after=pred_a,
            inputs_before=self.twin.theta_of(self.base_u), inputs_after=self.twin.theta_of(after_u),
            inputs_sd_before=sd_b, inputs_sd_after=sd_a,
            candidates=ranking,
            screen_score=np.array([screened[n][0] for n in ranking]),
            screen_onset=np.array([screened[n][2] for n in ranking]),
            fit_onset=np.array(fit_on), fit_value=np.array(fit_val), fit_sd=np.array(fit_sd),
            delta_bic=np.array([dbic[n] for n in ranking]),
            failure_year_before=fy_b, failure_year_after=fy_a,
            effect_onsets=({n: int(on) for n, on in model_effects} if verdict == "effect" else {}),
            fmu_runs=self.twin.runs - runs0, wall_time=_time.perf_counter() - t0)

    def _further(self, final, model_effects, model_values, candidates):
        """Try one more effect on top of the current model; None unless the BIC gain is
        above ``bic_gain``."""
        chi2_cur, fit, k0 = final
        _, ut = fit.problem.unpack(fit.x)
        u_now = self.base_u.copy()
        u_now[k0:] = ut
        rows = list(self.base_rows[:k0]) + list(fit.rows)
        fixed = {k: {n: v for (n, on), v in zip(model_effects, model_values) if self.years[k] >= on}
                 for k in range(self.n_y)}
        Qs = []
        for k in range(self.n_y):
            prob = JointFit(self.twin, self.Y[k:k + 1], self.years[k:k + 1],
                            [(n, on) for n, on in model_effects])
            # Sensitivities of this year's inputs at the current model (effects held).
            x = np.concatenate([[self.twin.effect_u(n, v) for (n, _), v in
                                 zip(model_effects, model_values)], u_now[k]])
            J = prob.jacobian(x)[:, len(model_effects):]
            Qs.append(np.linalg.qr(J)[0])
        used = {n for n, _ in model_effects}
        scores = []
        for name in candidates:
            if name in used:
                continue
            s, v, on, _ = self.screen(name, u_now, rows, Qs, fixed)
            scores.append((s, name, v, on))
        scores.sort(reverse=True)
        best = None
        for s, name, v, on in scores[:self.dc.confirm_further]:
            effs = model_effects + [(name, on)]
            vals = model_values + [v]
            chi2, fit2, k02 = self.fit_with(effs, vals, u_now)
            if fit2 is not None and (best is None or chi2 < best[0][0]):
                ue, _ = fit2.problem.unpack(fit2.x)
                best = ((chi2, fit2, k02), effs,
                        [self.twin.effect_of(n, ue[j]) for j, (n, _) in enumerate(effs)])
        if best is None:
            return None
        gain = self.bic(chi2_cur, len(model_effects)) - self.bic(best[0][0], len(best[1]))
        return best if gain > self.dc.bic_gain else None

    def _interval(self, name: str, value: float, sd_u: float) -> tuple:
        e = self.twin.effects[name]
        sd = sd_u * (e.high - e.low)
        z = stats.norm.ppf(0.95)
        return (float(value), float(max(e.low, value - z * sd)), float(min(e.high, value + z * sd)))

    def _zmap(self, rows, lev) -> np.ndarray:
        """Standardised output residuals [n_y, n_t]: whitened residual over
        sqrt(1 + h) (noise plus the twin's posterior variance J Sigma J^T, linearised)."""
        return np.array([self._output_part(r / np.sqrt(1.0 + h), k)
                         for k, (r, h) in enumerate(zip(rows, lev))])

    def _posterior_zmap(self) -> np.ndarray:
        """Standardised output residuals against the calibrated posterior predictive:
        (y - f(posterior mean)) / sqrt(noise^2 + diag(J Sigma_post J^T)), J the FMU's
        sensitivities at the base fit, Sigma_post the covariance of the posterior draws."""
        mean, cov = self.posterior
        width = self.twin.in_hi - self.twin.in_lo
        out = np.full((self.n_y, self.n_t), np.nan)
        for k in range(self.n_y):
            mask = np.isfinite(self.Y[k])
            try:
                f = self.twin.predict(mean[k])
            except SimulationError:
                continue
            J = self.base_J[k] / width                      # d residual / d theta
            var = 1.0 + np.einsum("ij,jk,ik->i", J, cov[k], J)
            full = np.full(self.m, np.nan)
            full[mask] = (self.Y[k] - f)[mask] / np.sqrt(var)
            out[k] = full[:self.n_t]
        return out

    def _window_rms(self, z: np.ndarray) -> np.ndarray:
        out = np.full((self.n_y, len(self.win_masks)), np.nan)
        for j, w in enumerate(self.win_masks):
            if w.any():
                with np.errstate(invalid="ignore"):
                    out[:, j] = np.sqrt(np.nanmean(z[:, w] ** 2, axis=1))
        return out

    def _output_pred(self, u: np.ndarray, effects: dict) -> np.ndarray:
        return self.twin.run(self.twin.theta_of(u), effects)[self.cfg.model.output.variable]

    def _separation(self, group: list, confirmed: dict) -> tuple:
        """The unobserved FMU channel on which the group's fitted twins differ most,
        relative to its noise (``channel_noise_fraction`` of its healthy plateau, or of its
        range for a channel that ends near 0)."""
        chans = [c for c in self.cfg.model.channels if c not in self.twin.channels]
        if not chans:
            return "", {}
        healthy = self.twin.run(np.array([s.nominal for s in self.cfg.model.inputs.values()]))

        def scale(x: np.ndarray) -> float:
            final, span = abs(float(x[-1])), float(x.max() - x.min())
            return max(final if final > 0.1 * span else span, 1e-12)

        noise = {c: self.dc.channel_noise_fraction * scale(healthy[c]) for c in chans}
        sims = []
        for n in group:
            chi2, fit, k0, on = confirmed[n]
            ue, ut = fit.problem.unpack(fit.x)
            sims.append(self.twin.run(self.twin.theta_of(ut[-1]),
                                      {n: self.twin.effect_of(n, ue[0])}))
        scores = {}
        for c in chans:
            best = 0.0
            for i in range(len(sims)):
                for j in range(i + 1, len(sims)):
                    diff = (sims[i][c] - sims[j][c]) / noise[c]
                    best = max(best, float(np.sqrt(np.mean(diff ** 2))))
            scores[c] = best
        return max(scores, key=scores.get), scores

    def _failure_year(self, thetas: np.ndarray, effects: dict) -> Optional[int]:
        """First year (observed or projected over ``forecast.horizon`` years by a straight
        line through the yearly estimates) in which the twin fails the safety criterion;
        None if none within the horizon. Effects that alter only the measurement
        (``measurement_only``) are left out: a lagging sensor does not make the machine
        unsafe."""
        from ..safety import Indicator
        ind = Indicator.from_config(self.cfg)
        effects = {k: v for k, v in (effects or {}).items()
                   if not self.cfg.model.effects[k].measurement_only}
        yrs = self.years.astype(float)
        if len(yrs) >= 2:
            coef = np.polyfit(yrs, thetas, 1)                   # [2, d]
        else:
            coef = np.vstack([np.zeros(self.d), thetas[0]])
        future = np.arange(self.years[-1] + 1, self.years[-1] + 1 + self.cfg.forecast.horizon)
        cand = np.concatenate([self.years, future])
        np_var = self.cfg.model.nonphysical
        for i, yr in enumerate(cand):
            theta = thetas[i] if i < self.n_y else coef[0] * yr + coef[1]
            theta = np.clip(theta, self.twin.in_lo, self.twin.in_hi)
            try:
                out = self.twin.run(theta, effects)
            except SimulationError:
                return int(yr)
            value = ind(self.twin.time, out[ind.variable])
            nonphys = bool(out[np_var].max() > 0.5) if np_var else None
            if bool(ind.unsafe(np.array(value), nonphys)):
                return int(yr)
        return None


# ---------------------------------------------------------------------------------------
# The stage
# ---------------------------------------------------------------------------------------
def candidate_names(cfg: Config) -> list:
    """The candidate effects: ``diagnose.candidates`` or every ``model.effects`` entry."""
    names = list(cfg.diagnose.candidates) or list(cfg.model.effects)
    for n in names:
        if n not in cfg.model.effects:
            raise ConfigError(f"{cfg.source}: diagnose.candidates: {n!r} is not in model.effects "
                              f"(known: {', '.join(cfg.model.effects) or 'none'})")
    return names


def _unit_sigma(cfg: Config, uo, time: np.ndarray) -> dict:
    # Noise not recorded: estimated where the transient is calmest, the last window.
    plateau = list(cfg.diagnose_windows().values())[-1].start
    sig = {}
    for ch, arr in uo.channels.items():
        s = uo.noise_std.get(ch)
        if s is None and ch == cfg.model.output.name and cfg.calibrate.noise_std is not None:
            s = cfg.calibrate.noise_std
        sig[ch] = float(s) if s is not None else estimate_noise(arr, time, plateau)
    return sig


def diagnose_unit(cfg: Config, fmu_path, unit: str, time: np.ndarray, years: np.ndarray,
                  channels: dict, noise_std: dict, twin: Twin | None = None,
                  posterior: tuple | None = None) -> UnitGap:
    """Diagnose one unit.

    Parameters
    ----------
    cfg : Config
    fmu_path : path-like
        The built ``.fmu``.
    unit : str
    time : ndarray, shape [n_t]
        Sample times (s).
    years : ndarray of int, shape [n_y]
    channels : dict of str to ndarray, each [n_y, n_t]
        The output (under ``model.output.name``) and any further observed FMU channel, each
        in its units; NaN = missing.
    noise_std : dict of str to float
        Noise standard deviation per channel (channel units).
    twin : Twin, optional
        Reused if given (must have the same channels and noise).
    posterior : (ndarray [n_y, d], ndarray [n_y, d, d]), optional
        Posterior mean and covariance of the degradation inputs per year (input units); if
        given, the standardised residual map is taken against this posterior predictive
        instead of the maximum-likelihood twin (the tests and fits are unchanged).
    """
    out = cfg.model.output.name
    chans = [out] + sorted(c for c in channels if c != out and c in cfg.model.channels)
    names = candidate_names(cfg)
    own = twin is None
    if own:
        twin = Twin(cfg, fmu_path, chans, time, noise_std, names)
    try:
        Y = np.concatenate([np.asarray(channels[c], float) / noise_std[c] for c in chans], axis=1)
        return _UnitDiagnosis(twin, cfg, unit, years, Y, posterior).run(names)
    finally:
        if own:
            twin.close()


def _job(args):
    return diagnose_unit(*args)


def _posterior_for(posterior_path, post, cfg: Config, unit: str, years: np.ndarray):
    if post is None:
        return None
    up = post.units.get(unit)
    if up is None:
        raise ArtifactError(f"{posterior_path}: no posterior for unit {unit!r}")
    if list(post.input_names) != cfg.model.input_names:
        raise ArtifactError(f"{posterior_path}: inputs {post.input_names} differ from the "
                            f"config's {cfg.model.input_names}")
    if not np.array_equal(np.asarray(up.years), np.asarray(years)):
        raise ArtifactError(f"{posterior_path}: /units/{unit}/years {list(up.years)} differ "
                            f"from the observations' {list(years)}")
    cov = np.array([np.atleast_2d(np.cov(s, rowvar=False)) for s in up.samples])
    return np.asarray(up.mean, float), cov


def diagnose(cfg: Config, observations: str | os.PathLike, output: str | os.PathLike,
             workers: int | None = None, progress=None,
             posterior: str | os.PathLike | None = None) -> DiagnoseSummary:
    """Run ``diagnose`` on every unit of an observations file and write ``gap.h5``.

    Parameters
    ----------
    cfg : Config
    observations : path-like
        ``twinmon.observations/1`` file (truth files are never read).
    output : path-like
        ``gap.h5`` to write.
    workers : int, optional
        Processes over units (default ``diagnose.workers``; 0 = one per core).
    progress : callable, optional
        Called with the number of units done.
    posterior : path-like, optional
        ``posterior.h5`` of ``calibrate``: the residual map is then standardised against
        the calibrated twin's posterior predictive.
    """
    from concurrent.futures import ProcessPoolExecutor
    from ..fmu import resolve_fmu

    t0 = _time.perf_counter()
    from ..simulate import check_model
    check_model(cfg)
    obs = read_observations(observations, cfg.model.output.name)
    candidate_names(cfg)
    expected = cfg.model.output.times.times
    if obs.time.shape != expected.shape or not np.allclose(obs.time, expected):
        raise InputDataError(f"{observations}: /time does not match the config's output grid "
                             f"({expected[0]:g}..{expected[-1]:g} s, {expected.size} samples)")
    fmu = resolve_fmu(cfg.model.fmu)
    post = None
    if posterior is not None:
        from ..calibrate import read_posterior
        post = read_posterior(posterior)
    jobs = [(cfg, fmu, u, obs.time, uo.years, uo.channels, _unit_sigma(cfg, uo, obs.time),
             None, _posterior_for(posterior, post, cfg, u, uo.years))
            for u, uo in obs.units.items()]
    n_workers = workers if workers is not None else cfg.diagnose.workers
    n_workers = min(n_workers or os.cpu_count() or 1, len(jobs))
    results = {}
    if n_workers <= 1:
        for i, j in enumerate(jobs, 1):
            results[j[2]] = _job(j)
            if progress:
                progress(i)
    else:
        with ProcessPoolExecutor(n_workers) as ex:
            for i, (j, g) in enumerate(zip(jobs, ex.map(_job, jobs)), 1):
                results[j[2]] = g
                if progress:
                    progress(i)
    write_gap(output, results, cfg, obs.time,
              [observations, fmu] + ([posterior] if posterior is not None else []))
    return DiagnoseSummary(results, str(output), _time.perf_counter() - t0, n_workers)


# ---------------------------------------------------------------------------------------
# gap.h5
# ---------------------------------------------------------------------------------------
_ARRAYS = {
    # name: (units, description)
    "years": ("year", "year of service"),
    "residual_before": ("1", "standardised output residual of the base twin [year, time]"),
    "residual_after": ("1", "standardised output residual of the twin with the effect(s) "
                       "[year, time]"),
    "chi2_before": ("1", "chi-square of the whitened residual, base twin [year]"),
    "chi2_after": ("1", "chi-square of the whitened residual, final twin [year]"),
    "dof": ("1", "degrees of freedom of the per-year chi-square [year]"),
    "p_chi2_before": ("1", "p-value of the per-year chi-square, base twin [year]"),
    "p_ljung_box_before": ("1", "Ljung-Box p-value of the output residual, base twin [year]"),
    "p_chi2_after": ("1", "p-value of the per-year chi-square, final twin [year]"),
    "significant_years": ("1", "1 where the year's gap is significant (Bonferroni) [year]"),
    "window_rms_before": ("1", "RMS of the standardised output residual [year, window], base"),
    "window_rms_after": ("1", "RMS of the standardised output residual [year, window], final"),
    "observed": ("output units", "observed output [year, time]"),
    "predicted_before": ("output units", "output of the base twin [year, time]"),
    "predicted_after": ("output units", "output of the final twin [year, time]"),
    "inputs_before": ("input units", "degradation inputs, base twin [year, input]"),
    "inputs_after": ("input units", "degradation inputs, final twin [year, input]"),
    "inputs_sd_before": ("input units", "linearised standard deviation [year, input], base"),
    "inputs_sd_after": ("input units", "linearised standard deviation [year, input], final"),
    "screen_score": ("1", "screening chi-square reduction [candidate] (ranking order)"),
    "screen_onset": ("year", "onset year found by screening [candidate]"),
    "fit_onset": ("year", "onset year of the confirmed fit [candidate]"),
    "fit_value": ("effect units", "fitted effect value [candidate]"),
    "fit_sd": ("effect units", "linearised standard deviation of the effect [candidate]"),
    "delta_bic": ("1", "BIC(base) - BIC(base + candidate) [candidate]; > bic_gain accepted"),
}
_ATTRS = ("verdict", "onset", "rms_before", "rms_after", "closed_percent", "delta_bic_final",
          "separating_channel", "absorbed_share", "p_gap", "noise_std", "failure_year_before",
          "failure_year_after", "fmu_runs", "wall_time")
_JSON_ATTRS = ("effects", "group", "where_windows", "where_years", "estimate",
               "separation_scores", "candidates", "effect_onsets")


def write_gap(path, results: dict, cfg: Config, time: np.ndarray, inputs) -> None:
    """Write ``gap.h5`` (``twinmon.gap/1``)::

        /time                          [n_t]  s
        /windows/names [n_w], /windows/bounds [n_w, 2] s
        attrs input_names (JSON)
        /units/<U>/<array>             see _ARRAYS (per year, [year, time], [year, window],
                                       [year, input] or [candidate] in ranking order)
        /units/<U>.attrs verdict, onset (-1: none), rms_before, rms_after, closed_percent,
                         delta_bic_final, separating_channel, absorbed_share, p_gap,
                         noise_std, failure_year_before/after (-1: none within the horizon),
                         and JSON: effects, group, where_windows, where_years, estimate
                         ({name: [mean, q05, q95]}), separation_scores, candidates,
                         effect_onsets ({name: onset year})
    """
    wins = cfg.diagnose_windows()
    with artifacts.write_artifact(path, "gap", config=cfg.section_yaml(*SECTIONS),
                                  inputs=inputs, seed=cfg.seed) as f:
        artifacts.put(f, "time", np.asarray(time), "s", "sample times")
        artifacts.put(f, "windows/names", list(wins), "", "time windows of the transient")
        artifacts.put(f, "windows/bounds", np.array([[w.start, w.stop] for w in wins.values()]),
                      "s", "start and stop of each window")
        f.attrs["input_names"] = json.dumps(cfg.model.input_names)
        for unit, g in results.items():
            grp = f.create_group(f"units/{unit}")
            for name, (units, desc) in _ARRAYS.items():
                units = cfg.model.output.units if units == "output units" else units
                data = np.asarray(getattr(g, name))
                if data.dtype == bool:
                    data = data.astype(np.int8)
                artifacts.put(grp, name, data, units, desc)
            for name in _ATTRS:
                v = getattr(g, name)
                grp.attrs[name] = -1 if v is None else v
            for name in _JSON_ATTRS:
                grp.attrs[name] = artifacts.json_attr(getattr(g, name))


@dataclass
class GapFile:
    """A loaded ``gap.h5``: time [n_t], window names and bounds [n_w, 2], units {name: UnitGap}."""

    time: np.ndarray
    windows: list
    window_bounds: np.ndarray
    input_names: list
    units: dict = field(default_factory=dict)


def read_gap(path: str | os.PathLike) -> GapFile:
    """Load ``gap.h5`` (schema checked) into :class:`UnitGap` records."""
    path = Path(path)
    with artifacts.open_artifact(path, "gap") as f:
        time = artifacts.get(f, "time", path)
        names = list(artifacts.get(f, "windows/names", path))
        bounds = artifacts.get(f, "windows/bounds", path)
        units = {}
        if "units" not in f:
            raise ArtifactError(f"{path}: group /units is missing")
        for unit, g in f["units"].items():
            kw = {n: artifacts.get(g, n, path) for n in _ARRAYS}
            kw["significant_years"] = kw["significant_years"].astype(bool)
            for n in _ATTRS:
                if n not in g.attrs:
                    raise ArtifactError(f"{path}: attribute /units/{unit}.{n} is missing")
                v = g.attrs[n]
                v = v.decode() if isinstance(v, bytes) else v
                v = v.item() if isinstance(v, np.generic) else v
                if n in ("onset", "failure_year_before", "failure_year_after") and v == -1:
                    v = None
                kw[n] = v
            for n in _JSON_ATTRS:
                kw[n] = json.loads(g.attrs[n])
            kw["estimate"] = {k: tuple(v) for k, v in kw["estimate"].items()}
            units[unit] = UnitGap(unit=unit, **kw)
        return GapFile(time, names, bounds, json.loads(f.attrs["input_names"]), units)
