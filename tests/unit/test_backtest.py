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
