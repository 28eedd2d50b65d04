"""Goodness of fit of a calibrated year: is the residual at the posterior mean the size and
shape of the noise, and do the draws stay off the design box's edge."""
from __future__ import annotations

import numpy as np

from ..config import Config

#: Per-year verdicts of the fit, in order of precedence.
STATUS_OK, STATUS_MISFIT, STATUS_EDGE, STATUS_UNCONVERGED = "ok", "misfit", "edge", "unconverged"

#: Per-year goodness-of-fit fields: (units, description). ``window`` indexes the
#: config's diagnose windows (recorded as the posterior's ``fit_windows`` attribute).
FIT_FIELDS = {
    "rms": ("1", "RMS of the standardised residual at the posterior mean, in noise sd [year]"),
    "p_chi2": ("1", "p-value of the residual's chi-square (n - d dof) [year]"),
    "p_ljung_box": ("1", "Ljung-Box p-value of the residual (structure) [year]"),
    "window": ("1", "index of the window where the residual RMS is largest [year]"),
    "window_rms": ("1", "residual RMS in that window, in noise sd [year]"),
    "edge_share": ("1", "share of draws within edge_margin of a box bound [year, input]"),
    "extensions": ("1", "times the year's chains were lengthened for convergence [year]"),
    "converged": ("1", "1 when R-hat and ESS met calibrate.rhat_warn/ess_warn [year]"),
    "status": ("1", "ok | misfit | edge | unconverged [year]"),
}


def year_fit(surrogate, cfg: Config, y: np.ndarray, total_var: np.ndarray,
             draws: np.ndarray, bounds: np.ndarray) -> dict:
    """Goodness of fit of one calibrated year.

    The residual of the observation against the twin at the posterior mean, standardised
    by the likelihood's own variance (noise + surrogate), is tested for size (chi-square,
    n - d degrees of freedom) and for structure (Ljung-Box, ``diagnose.ljung_box_lags``);
    its RMS per diagnose window says where the twin misses. The draws' share near a box
    bound says whether the plant needs inputs outside the twin's box.

    With a stacked surrogate (several channels side by side, see
    :class:`~twinmon.calibrate.channels.StackedSurrogate`) ``y`` and ``total_var`` are
    stacked the same way; the windows hold every channel's samples in them, the Ljung-Box
    test runs per channel, and ``channel_rms`` gives each channel's RMS.

    Parameters
    ----------
    y : ndarray, shape [n_t] (or [n_ch * n_t])
        The observation (output units); NaN = missing.
    total_var : ndarray, shape [n_t] (or [n_ch * n_t])
        Likelihood variance per time step (output units squared).
    draws : ndarray, shape [n_s, d]
        Posterior draws (input units).
    bounds : ndarray, shape [d, 2]
        The design box.

    Returns
    -------
    dict
        The fields of :data:`FIT_FIELDS` but ``extensions``/``converged``; ``status`` is
        ``misfit``, ``edge`` or ``ok``.
    """
    from ..diagnose.stats import chi2_sf, ljung_box
    cc = cfg.calibrate
    d = draws.shape[1]
    pred = surrogate.predict(draws.mean(axis=0)[None, :])[0]
    z = (np.asarray(y, float) - pred) / np.sqrt(total_var)
    ok = np.isfinite(z)
    n = int(ok.sum())
    chi2 = float(np.sum(z[ok] ** 2))
    rms = float(np.sqrt(chi2 / max(n, 1)))
    p_chi2 = float(chi2_sf(chi2, max(n - d, 1)))
    blocks = getattr(surrogate, "blocks", None)
    if blocks:
        # Several channels side by side: one Ljung-Box test per channel (a residual's
        # structure runs along one channel, not across), Bonferroni over channels.
        p_lb = min(1.0, len(blocks) * min(ljung_box(z[sl], cfg.diagnose.ljung_box_lags)
                                          for _, sl in blocks))
    else:
        p_lb = ljung_box(z, cfg.diagnose.ljung_box_lags)
    # A stacked surrogate's time repeats the grid per channel: a window holds every
    # channel's samples in it.
    t = surrogate.time
    wins = list(cfg.diagnose_windows().values())
    w_rms = np.array([np.sqrt(np.mean(z[(t >= w.start) & (t < w.stop) & ok] ** 2))
                      if np.any((t >= w.start) & (t < w.stop) & ok) else 0.0 for w in wins])
    width = bounds[:, 1] - bounds[:, 0]
    near = (draws <= bounds[:, 0] + cc.edge_margin * width) | \
           (draws >= bounds[:, 1] - cc.edge_margin * width)
    edge = near.mean(axis=0)
    misfit = rms > cc.fit_min_rms and min(p_chi2, p_lb) < cc.fit_alpha
    status = STATUS_MISFIT if misfit else STATUS_EDGE if edge.max() > cc.edge_share \
        else STATUS_OK
    out = {"rms": rms, "p_chi2": p_chi2, "p_ljung_box": p_lb,
           "window": int(np.argmax(w_rms)), "window_rms": float(w_rms.max()),
           "edge_share": edge, "status": status}
    if blocks:
        out["channel_rms"] = np.array([np.sqrt(np.mean(z[sl][ok[sl]] ** 2))
                                       if ok[sl].any() else np.nan for _, sl in blocks])
    return out


def years_fit(surrogate, cfg: Config, flows: np.ndarray, total_var: np.ndarray,
              draws: np.ndarray, extensions: int, converged) -> dict:
    """:func:`year_fit` of each year of a unit whose years were drawn together (a joint
    posterior), as the posterior stores it: each field of :data:`FIT_FIELDS` [year] (and
    ``channel_rms`` [year, channel] with several channels). A year that did not converge
    and fits is ``unconverged``.

    Parameters
    ----------
    flows, total_var : ndarray, shape [K, n_out]
    draws : ndarray, shape [K, n_s, d]
    extensions : int
        Times the unit's draws were lengthened.
    converged : bool or array of bool, shape [K]
    """
    K = len(flows)
    converged = np.broadcast_to(np.asarray(converged, bool), (K,))
    fits = []
    for k in range(K):
        fit = year_fit(surrogate, cfg, flows[k], total_var[k], draws[k], cfg.model.bounds)
        fit.update(extensions=extensions, converged=bool(converged[k]))
        if fit["status"] == STATUS_OK and not converged[k]:
            fit["status"] = STATUS_UNCONVERGED
        fits.append(fit)
    out = {key: np.array([f[key] for f in fits]) for key in FIT_FIELDS}
    if fits and "channel_rms" in fits[0]:
        out["channel_rms"] = np.array([f["channel_rms"] for f in fits])
    return out
