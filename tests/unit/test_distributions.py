"""The tails and quantiles taken from scipy.special are scipy.stats' values, bit for bit."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from twinmon import distributions as D


@pytest.mark.parametrize("dof", [1, 2, 3.5, 8, 40, 1e6])
def test_the_values_are_scipy_stats_own(dof):
    rng = np.random.default_rng(1)
    x, q = rng.normal(0, 3, 200), rng.uniform(0.001, 0.999, 200)
    assert np.array_equal(D.t_sf(x, dof), stats.t.sf(x, dof))
    assert np.array_equal(D.t_ppf(q, dof), stats.t.ppf(q, dof))
    assert np.array_equal(D.t_isf(q, dof), stats.t.isf(q, dof))
    assert D.t_ppf(0.95, dof) == stats.t.ppf(0.95, dof)
    x2 = 3 * np.abs(x)
    assert np.array_equal(D.chi2_sf(x2, dof), stats.chi2.sf(x2, dof))
    for dfn in (1, 2, 5):
        assert np.array_equal(D.f_sf(x2, dfn, dof), stats.f.sf(x2, dfn, dof))

