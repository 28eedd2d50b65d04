"""Indicator settings the record cannot answer: a config error (exit 3) naming the key and
the value. Before, a mean window after the record made every indicator NaN (and still gave
failure years), and a max window between two samples or value_at outside the record (1e6
silently clamped to the last sample, -5) passed."""
from __future__ import annotations

import pytest

from .conftest import assert_fails, assert_ok, twinmon

CASES = {
    "mean window after the record": ("{kind: mean, window: [60, 80]}", "safety.indicator.window"),
    "max window between samples": ("{kind: max, window: [3.0, 3.5]}", "safety.indicator.window"),
    "value_at 1e6": ("{kind: value_at, at: 1.0e6}", "safety.indicator.at"),
    "value_at -5": ("{kind: value_at, at: -5}", "safety.indicator.at"),
}


def _report(work, indicator):
    return twinmon("report", "-c", work / "small.yaml", "--set", f"safety.indicator={indicator}",
                   "--observations", work / "fleet.h5", "-o", work / "rep", cwd=work)


@pytest.mark.parametrize("case", list(CASES))
def test_indicator_outside_the_record(work, case):
    indicator, key = CASES[case]
    assert_fails(_report(work, indicator), 3, key, "small.yaml")
    assert not (work / "rep").exists()


def test_indicator_within_the_record_is_accepted(work):
    assert_ok(_report(work, "{kind: mean, window: [10, 20]}"))
