"""Step 1, **locate**: where the twin misses the plant.

The base twin (the FMU, degradation inputs fitted by maximum likelihood year by year,
warm-started from the previous year) is compared with the observations:

- :func:`fit_base`: the per-year fits, their residuals, Jacobians, leverages;
- :func:`detect`: per-year chi-square of the whitened residual and a Ljung-Box test of its
  structure, pooled tests from every possible onset year, at a Bonferroni-corrected level;
  the onset year;
- :func:`residual_maps`: standardised output residuals [n_y, n_t] (against the base twin or
  the calibrated posterior predictive) and their RMS per year and time window;
- :func:`where`: the significant windows over the affected years;
- :func:`absorbed_share`: how much of the identified effect's signature the degradation inputs
  absorb (its share in the span of their sensitivities).

Every function takes the unit's :class:`~twinmon.diagnose.state.UnitState` ``s``;
:func:`fit_base` and :func:`detect` fill in its base-twin attributes.
"""
from __future__ import annotations

import numpy as np

from ..errors import SimulationError
from .fit import JointFit
from .state import UnitState
from .stats import ljung_box, pooled_onset_pvalues


# -- the base twin -----------------------------------------------------------------------------
def fit_base(s: UnitState) -> None:
    """Fit the degradation inputs of each year alone (no effect), warm-started from the
    previous year; sets ``s.base_*``, ``s.chi2_base``, ``s.n_rows``, ``s.dof``.

    The years of ``s.kept`` (``diagnose --update``) are taken as stored: year ``k``'s fit
    depends only on years ``<= k``, so fitting them again would give the same bits."""
    u_prev = s.twin.u_of([p.nominal for p in s.cfg.model.inputs.values()])
    s.base_u = np.zeros((s.n_y, s.d))
    s.base_rows, s.base_J, s.base_lev = [], [], []
    n_kept = s.kept.n_years if s.kept is not None else 0
    for k in range(n_kept):
        u, row, J, lev = s.kept.year(k, np.isfinite(s.Y[k]))
        s.base_u[k] = u
        s.base_rows.append(row)
        s.base_J.append(J)
        s.base_lev.append(lev)
        u_prev = u
    for k in range(n_kept, s.n_y):
        prob = JointFit(s.twin, s.Y[k:k + 1], s.years[k:k + 1])
        fit = prob.solve(u_prev)
        if k == 0 and fit.chi2_rows[0] > 3 * fit.rows[0].size:
            # A poor first year may sit in a local minimum: retry from the box centre.
            alt = prob.solve(np.full(s.d, 0.5))
            if alt.chi2_rows[0] < fit.chi2_rows[0]:
                fit = alt
        s.base_u[k] = fit.x
        s.base_rows.append(fit.rows[0])
        s.base_J.append(fit.J)
        s.base_lev.append(fit.leverage_rows()[0])
        u_prev = fit.x
    s.chi2_base = np.array([float(r @ r) for r in s.base_rows])
    s.n_rows = np.array([r.size for r in s.base_rows])
    s.dof = np.maximum(s.n_rows - s.d, 1)
    # Orthonormal bases of the span of the degradation sensitivities, per year.
    s.base_Q = [np.linalg.qr(J)[0] for J in s.base_J]


# -- tests ---------------------------------------------------------------------------------------
def year_tests(s: UnitState, rows, lev, n_par):
    """Per-year chi-square, its dof, its p-value and the Ljung-Box p-value of the output
    residual (leverage-corrected), each [n_y], for residual rows fitted with ``n_par``
    parameters per year."""
    chi2 = np.array([float(r @ r) for r in rows])
    dof = np.maximum(np.array([r.size for r in rows]) - n_par, 1)
    p_chi2 = s.p_excess(chi2, s.channel_counts, dof)
    p_lb = np.array([ljung_box(output_part(s, r / np.sqrt(1 + h), k), s.dc.ljung_box_lags)
                     for k, (r, h) in enumerate(zip(rows, lev))])
    return chi2, dof, p_chi2, p_lb


def output_part(s: UnitState, r_masked: np.ndarray, k: int) -> np.ndarray:
    """The output channel of a masked residual row, back on the time grid [n_t] (NaN gaps)."""
    full = np.full(s.m, np.nan)
    full[np.isfinite(s.Y[k])] = r_masked
    return full[:s.n_t]


def detect(s: UnitState) -> None:
    """Tests of the base twin; sets ``s.p_chi2_before``, ``s.p_lb_before``,
    ``s.significant_years``, ``s.detected_onset`` and ``s.p_omnibus``."""
    a = s.dc.alpha
    chi2, dof, p_chi2, p_lb = year_tests(s, s.base_rows, s.base_lev, s.d)
    s.p_chi2_before, s.p_lb_before = p_chi2, p_lb
    p_year = np.minimum(1.0, 2 * s.n_y * np.minimum(p_chi2, p_lb))
    s.significant_years = p_year < a
    p_pool = np.minimum(1.0, s.n_y * pooled_onset_pvalues(chi2, dof, s.channel_counts,
                                                          s.p_excess))
    s.detected_onset = int(s.years[int(np.argmin(p_pool))])
    # Bonferroni over the two families (per-year tests, pooled-from-onset tests).
    s.p_omnibus = float(min(1.0, 2 * min(p_year.min(), p_pool.min())))


# -- residual maps -------------------------------------------------------------------------------
def residual_maps(s: UnitState, after_rows, after_lev) -> tuple:
    """``(z_before, z_after, window_rms_before, window_rms_after)``: the standardised output
    residuals [n_y, n_t] of the base twin (against the posterior predictive if the unit has a
    posterior) and of the final twin (rows ``after_rows``, leverages ``after_lev``), and
    their RMS per year and window [n_y, n_w]."""
    z_before = (posterior_zmap(s) if s.posterior is not None
                else zmap(s, s.base_rows, s.base_lev))
    z_after = zmap(s, after_rows, after_lev)
    return z_before, z_after, window_rms(s, z_before), window_rms(s, z_after)


def zmap(s: UnitState, rows, lev) -> np.ndarray:
    """Standardised output residuals [n_y, n_t]: whitened residual over
    sqrt(1 + h) (noise plus the twin's posterior variance J Sigma J^T, linearised)."""
    return np.array([output_part(s, r / np.sqrt(1.0 + h), k)
                     for k, (r, h) in enumerate(zip(rows, lev))])


def posterior_zmap(s: UnitState) -> np.ndarray:
    """Standardised output residuals against the calibrated posterior predictive:
    (y - f(posterior mean)) / sqrt(noise^2 + diag(J Sigma_post J^T)), J the FMU's
    sensitivities at the base fit, Sigma_post the covariance of the posterior draws."""
    mean, cov = s.posterior
    width = s.twin.in_hi - s.twin.in_lo
    out = np.full((s.n_y, s.n_t), np.nan)
    for k in range(s.n_y):
        mask = np.isfinite(s.Y[k])
        try:
            f = s.twin.predict(mean[k])
        except SimulationError:
            continue
        J = s.base_J[k] / width                      # d residual / d theta
        var = 1.0 + np.einsum("ij,jk,ik->i", J, cov[k], J)
        full = np.full(s.m, np.nan)
        full[mask] = (s.Y[k] - f)[mask] / np.sqrt(var)
        out[k] = full[:s.n_t]
    return out


def window_rms(s: UnitState, z: np.ndarray) -> np.ndarray:
    """RMS of a residual map ``z`` [n_y, n_t] per year and window, [n_y, n_w] (NaN ignored)."""
    out = np.full((s.n_y, len(s.win_masks)), np.nan)
    for j, w in enumerate(s.win_masks):
        if w.any():
            with np.errstate(invalid="ignore"):
                out[:, j] = np.sqrt(np.nanmean(z[:, w] ** 2, axis=1))
    return out


def where(s: UnitState, z_before: np.ndarray, aff: np.ndarray) -> tuple:
    """``(windows, years)``: the windows whose pooled chi-square of ``z_before`` over the
    affected years ``aff`` [n_y] bool is significant (Bonferroni over windows), and those
    years."""
    where_w = []
    where_y = [int(y) for y in s.years[aff]]
    for j, name in enumerate(s.win_names):
        z = z_before[aff][:, s.win_masks[j]]
        z = z[np.isfinite(z)]
        # The output channel's samples alone (its noise level may be an estimate).
        counts = np.zeros((1, len(s.noise_dof)))
        counts[0, 0] = z.size
        if z.size and s.p_excess(float(z @ z), counts, z.size) * len(s.win_names) < s.dc.alpha:
            where_w.append(name)
    return where_w, where_y


# -- absorbed share ------------------------------------------------------------------------------
def absorbed_share(s: UnitState, main: str, after_u: np.ndarray, eff_year: list,
                   aff: np.ndarray) -> float:
    """Share of effect ``main``'s signature (twin with - without it, at the final inputs
    ``after_u`` [n_y, d] and effects ``eff_year``, over the affected years) that lies in the
    span of the degradation sensitivities: the part silently turned into biased estimates."""
    num = den = 0.0
    for k in np.flatnonzero(aff):
        theta = s.twin.theta_of(after_u[k])
        mask = np.isfinite(s.Y[k])
        eff = eff_year[k]
        rest = {n: v for n, v in eff.items() if n != main}
        delta = (s.twin.predict(theta, eff) - s.twin.predict(theta, rest))[mask]
        Q = s.base_Q[k]
        inside = Q @ (Q.T @ delta)
        num += float(inside @ inside)
        den += float(delta @ delta)
    return num / den if den > 0 else float("nan")
