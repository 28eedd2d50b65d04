"""Tails and quantiles of Student's t, chi-square and F from ``scipy.special``.

``scipy.stats``' own methods call these very functions, so the values are the same; importing
``scipy.stats`` costs 0.5-0.6 s at every start of a stage that needs one of them (forecast,
calibrate's goodness of fit, diagnose, the report drawing the trends). Arguments are
broadcast as numpy arrays; a scalar in gives a numpy scalar out.
"""
from __future__ import annotations

import numpy as np
from scipy import special


def t_sf(x, dof):
    """Student's t upper tail, ``scipy.stats.t.sf(x, dof)``."""
    return special.stdtr(dof, -np.asarray(x, float))


def t_ppf(q, dof):
    """Student's t quantile, ``scipy.stats.t.ppf(q, dof)``."""
    return special.stdtrit(dof, q)


def t_isf(q, dof):
    """Student's t upper quantile, ``scipy.stats.t.isf(q, dof)``."""
    return -special.stdtrit(dof, q)


def chi2_sf(x, dof):
    """Chi-square upper tail, ``scipy.stats.chi2.sf(x, dof)``."""
    return special.chdtrc(dof, x)


def f_sf(x, dfn, dfd):
    """F upper tail, ``scipy.stats.f.sf(x, dfn, dfd)``."""
    return special.fdtrc(dfn, dfd, x)
