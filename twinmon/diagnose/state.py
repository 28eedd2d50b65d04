"""The state of one unit's diagnosis, carried through the three steps.

:class:`UnitState` is built from the unit's whitened observations. Step 1
(:func:`~twinmon.diagnose.locate.fit_base`, :func:`~twinmon.diagnose.locate.detect`) fills in
the base twin and the detection below; steps 2 and 3 only read the state and hand back their
own records (:class:`~twinmon.diagnose.identify.Identification`,
:class:`~twinmon.diagnose.shrink.Shrink`). :func:`~twinmon.diagnose.unit.run_unit` runs the
steps in order.
"""
from __future__ import annotations

import math

import numpy as np

from ..config import Config
from .stats import chi2_sf, noise_sf
from .twin import Twin


class UnitState:
    """One unit's data, its twin, and the base twin once step 1 has fitted it.

    Parameters
    ----------
    twin : Twin
        Observed channels and noise as in ``Y``.
    cfg : Config
    unit : str
    years : ndarray of int, shape [n_y]
    Y : ndarray, shape [n_y, m]
        Whitened observations, channel-major (``m = n_ch * n_t``, the output first); NaN =
        missing.
    posterior : (ndarray [n_y, d], ndarray [n_y, d, d]), optional
        Posterior mean and covariance of the degradation inputs per year (input units).
    kept : YearCache, optional
        Per-year records of the unit's first years from an earlier ``gap.h5``
        (``diagnose --update``): their base fit and initial screening are taken from it.
    noise_dof : sequence of float, optional
        Per channel (the order of ``twin.channels``), the degrees of freedom of its noise
        level: ``inf`` (the default) where it is known, finite where it was estimated.
    """

    # -- filled by locate.fit_base: the base twin (degradation inputs only, year by year) ----
    #: Normalised degradation inputs per year, [n_y, d].
    base_u: np.ndarray
    #: Whitened residual of each year over its non-missing samples, list of [n_k].
    base_rows: list
    #: Jacobian of each year's residual w.r.t. its normalised inputs, list of [n_k, d].
    base_J: list
    #: Leverage of each year's samples, list of [n_k].
    base_lev: list
    #: Orthonormal basis of the span of each year's degradation sensitivities, list of [n_k, d].
    base_Q: list
    #: Chi-square per year [n_y], non-missing samples per year [n_y], and its dof [n_y].
    chi2_base: np.ndarray
    n_rows: np.ndarray
    dof: np.ndarray

    # -- filled by locate.detect: the tests of the base twin -----------------------------------
    #: Per-year chi-square and Ljung-Box p-values, [n_y].
    p_chi2_before: np.ndarray
    p_lb_before: np.ndarray
    #: Years whose gap is significant (Bonferroni over years and the two tests), [n_y] bool.
    significant_years: np.ndarray
    #: Year whose pooled test (from it on) is most significant.
    detected_onset: int
    #: Omnibus p-value (Bonferroni over the per-year and the pooled families).
    p_omnibus: float

    def __init__(self, twin: Twin, cfg: Config, unit: str, years: np.ndarray,
                 Y: np.ndarray, posterior=None, kept=None, noise_dof=None):
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
        self.kept = kept
        windows = cfg.diagnose_windows()
        self.win_names = list(windows)
        t = twin.time
        self.win_masks = [(t >= w.start) & (t < w.stop) for w in windows.values()]
        n_ch = len(twin.channels)
        self.noise_dof = (np.full(n_ch, np.inf) if noise_dof is None
                          else np.asarray(noise_dof, float))
        #: Non-missing samples per year and channel, [n_y, n_ch].
        self.channel_counts = np.isfinite(Y).reshape(self.n_y, n_ch, -1).sum(axis=2)

    def p_excess(self, stat, counts, dof) -> np.ndarray:
        """p-values of sums of squared whitened residuals ``stat`` [k] with ``dof`` [k]
        degrees of freedom, over samples ``counts`` [k, n_ch] per channel: the chi-square
        test, or where a channel's noise level was estimated the test that counts the
        estimate's degrees of freedom (:func:`~.stats.noise_sf`)."""
        stat = np.asarray(stat, float)
        if not np.isfinite(self.noise_dof).any():
            return chi2_sf(stat, dof)
        counts = np.atleast_2d(np.asarray(counts, float))
        total = np.maximum(counts.sum(axis=1, keepdims=True), 1.0)
        shared = counts * (np.atleast_1d(np.asarray(dof, float))[:, None] / total)
        return noise_sf(np.atleast_1d(stat), shared, self.noise_dof).reshape(stat.shape)
