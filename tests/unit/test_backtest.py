"""backtest: the coverage of past forecasts judged against the intervals' confidence."""
from __future__ import annotations

import pytest

from twinmon.backtest import coverage_verdict


@pytest.mark.parametrize("coverage, pairs, flagged, word", [
    (0.90, 200, False, ""),          # on target
    (0.86, 200, False, ""),          # inside the band
    (0.59, 300, True, "too narrow"),  # the accelerating-wear case: loudly
    (0.70, 10, False, ""),           # outside the band, but 10 pairs cannot tell
    (0.99, 400, True, "wider"),      # intervals far too wide
])
def test_coverage_outside_the_band_is_flagged_beyond_its_sampling_error(coverage, pairs,
                                                                      flagged, word):
    in_band, message = coverage_verdict(coverage, pairs, 0.90, 0.05)
    assert in_band is not flagged
    assert (word in message) if flagged else message == ""
    if flagged:
        assert f"{coverage:.2f}" in message and f"{pairs} later observations" in message
        assert "0.85-0.95" in message


def test_no_pairs_is_not_a_verdict():
    assert coverage_verdict(float("nan"), 0, 0.9, 0.05) == (True, "")


def _unit(years, cuts, lo, hi, observed, horizon=3):
    import numpy as np

    from twinmon.backtest import UnitBacktest
    years = np.asarray(years)
    n_c = len(cuts)
    return UnitBacktest(years, np.asarray(observed, float), np.zeros(len(years), bool),
                        np.asarray(cuts), np.full((n_c, horizon), lo), np.zeros((n_c, horizon)),
                        np.full((n_c, horizon), hi), np.full(n_c, -1), None, horizon)


def test_coverage_is_also_judged_per_record_length():
    """Each later observation counts under the years recorded up to its cut (a missing year
    is not counted); a record length whose forecasts miss is flagged on its own, though the
    pooled coverage may hold, and the same numbers come back from the artifact's arrays."""
    from twinmon.backtest import coverage_by_record
    # Year 4 missing: the cut at year 5 has 4 recorded years, the cut at 6 has 5.
    years = [1, 2, 3, 5, 6, 7, 8, 9]
    # Every later observation at 1.0; the intervals [0, 2] hold it, [0, 0.5] do not.
    good = _unit(years, [6], 0.0, 2.0, [1.0] * 8)
    pairs = [(c, j, y) for c, j, y in good.pairs()]
    assert pairs == [(0, 0, 7), (0, 1, 8), (0, 2, 9)]
    assert [n for n, _ in good.scored()] == [5, 5, 5]
    bad = _unit(years, [5], 0.0, 0.5, [1.0] * 8)
    assert list(bad.scored()) == [(4, False)] * 3             # years 6, 7, 8
    units = {f"G{i}": _unit(years, [6], 0.0, 2.0, [1.0] * 8) for i in range(60)}
    units.update({f"B{i}": _unit(years, [5], 0.0, 0.5, [1.0] * 8) for i in range(60)})
    by, warnings = coverage_by_record(units, 0.9, 0.05)
    assert by[5] == {"coverage": 1.0, "pairs": 180, "in_band": False}      # too wide
    assert by[4] == {"coverage": 0.0, "pairs": 180, "in_band": False}
    assert len(warnings) == 2
    assert "made from 4 recorded year(s) covered 0.00 of 180 later observations" in warnings[0]
    assert "too narrow" in warnings[0] and "wider" in warnings[1]
    assert "below 0.85-0.95" in warnings[0] and "above 0.85-0.95" in warnings[1]
    # Few pairs: 2 of 3 inside is not a verdict.
    few = _unit(years, [5], 0.0, 2.0, [1.0] * 6 + [5.0, 1.0])
    by, warnings = coverage_by_record({"F": few}, 0.9, 0.05)
    assert by[4]["pairs"] == 3 and by[4]["coverage"] == pytest.approx(2 / 3)
    assert by[4]["in_band"] and warnings == []


def test_a_unit_unsafe_before_its_first_cut_is_named_not_hidden():
    """A unit unsafe from its first year has no forecast made before its end of life: no
    time-to-failure score, and the summary says so instead of "no unit reached unsafe"."""
    import numpy as np

    from twinmon.backtest import BacktestSummary
    years = [1, 2, 3, 4, 5, 6]
    early = _unit(years, [3, 4], 0.0, 2.0, [1.0] * 6)
    early.end_of_life = 1
    late = _unit(years, [3, 4], 0.0, 2.0, [1.0] * 6)
    s = BacktestSummary(units={"Early": early, "Fine": late}, coverage=1.0, n_pairs=0,
                        indicator_mae=float("nan"))
    assert s.unsafe_before_cuts == {"Early": 1}
    d = s.as_dict()
    assert d["units_reaching_unsafe"] == 0 and d["units_unsafe_before_cuts"] == {"Early": 1}
    assert list(early.pairs()) == []          # past its end of life: nothing to cover
    assert np.isnan(s.alpha_lambda)


def test_a_forecast_made_before_a_recorded_repair_is_not_scored_after_it():
    """The cut-5 forecast of a unit whose part was replaced in year 8 says nothing of the
    new part: its years 8 on are left out (counted apart), its years 6-7 kept."""
    import dataclasses
    b = _unit(range(1, 11), [5, 6, 8], 0.0, 1.0, [0.5] * 10)
    assert len(list(b.pairs())) == 3 + 3 + 2 and b.across_repairs() == 0
    r = dataclasses.replace(b, repairs=(8,))
    kept = [(int(b.cuts[c]), y) for c, _, y in r.pairs()]
    assert kept == [(5, 6), (5, 7), (6, 7), (8, 9), (8, 10)]
    assert r.across_repairs() == 3
