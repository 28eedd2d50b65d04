"""The health indicator: every kind on known transients, missing samples, failed runs."""
from __future__ import annotations

import numpy as np
import pytest

from twinmon.config import IndicatorSpec, SafetyConfig, UnsafeIf
from twinmon.safety import compute_indicator, failure_year, is_unsafe

T = np.arange(1.0, 11.0)                      # 1..10 s
RISE = 10.0 * T                               # 10, 20, ..., 100
FALL = 100.0 - 10.0 * T                       # 90, 80, ..., 0


@pytest.mark.parametrize("spec, values, expect", [
    (IndicatorSpec("time_to_reach", level=55.0), RISE, 5.5),
    (IndicatorSpec("time_to_reach", level=5.0, initial=0.0), RISE, 0.5),   # before 1st sample
    (IndicatorSpec("time_to_reach", level=5.0), RISE, 1.0),                # no t=0 value known
    (IndicatorSpec("time_to_reach", level=500.0), RISE, np.inf),           # never reached
    (IndicatorSpec("time_to_reach", level=45.0, direction="down"), FALL, 5.5),
    (IndicatorSpec("value_at", at=2.5), RISE, 25.0),
    (IndicatorSpec("max", window=(2.0, 4.0)), RISE, 40.0),
    (IndicatorSpec("min", window=(2.0, 4.0)), RISE, 20.0),
    (IndicatorSpec("mean", window=(2.0, 4.0)), RISE, 30.0),
    (IndicatorSpec("mean"), RISE, 55.0),
    (IndicatorSpec("final"), FALL, 0.0),
])
def test_every_kind_on_a_known_transient(spec, values, expect):
    got = compute_indicator(T, values[None, :], spec)
    assert got.shape == (1,) and got[0] == pytest.approx(expect)


def test_missing_samples_are_skipped_and_a_failed_run_has_no_indicator():
    spec = IndicatorSpec("time_to_reach", level=55.0, initial=0.0)
    x = np.vstack([RISE, RISE, np.full(10, np.nan)])
    x[1, 4:6] = np.nan                        # the crossing's samples are missing
    got = compute_indicator(T, x, spec)
    assert got[0] == pytest.approx(5.5) and got[1] == pytest.approx(5.5)
    assert np.isnan(got[2])                   # not 'reached at t = 0' from the initial value
    for kind in ("max", "mean", "final"):
        assert np.isnan(compute_indicator(T, x[2:], IndicatorSpec(kind))[0])
    assert compute_indicator(T, x[1:2], IndicatorSpec("final"))[0] == 100.0


def test_unsafe_above_or_below_and_the_failure_year():
    above = SafetyConfig(IndicatorSpec("final"), UnsafeIf(above=30.0))
    below = SafetyConfig(IndicatorSpec("final"), UnsafeIf(below=30.0))
    v = np.array([10.0, 30.0, 50.0, np.nan])
    assert list(is_unsafe(v, above)) == [False, False, True, False]
    assert list(is_unsafe(v, below)) == [True, False, False, False]
    assert list(is_unsafe(v, above, nonphysical=[1, 0, 0, 0])) == [True, False, True, False]
    assert failure_year(np.array([11, 12, 13]), np.array([0.01, 0.06, 0.5]), above) == 12
    assert failure_year(np.array([11, 12]), np.array([0.01, 0.05]), above) is None


def test_a_dimensionless_indicator_prints_no_unit(tmp_path):
    """Units "1" (a ratio, a per-unit value): "2.2", not "2.2 1"; the DC drive's speed as a
    fraction of its nominal, say."""
    from twinmon.config import load_config
    from twinmon.safety import Indicator, with_units
    from ..conftest import CONFIGS, write_yaml
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "safety": {"indicator": {"units": "1"}, "unsafe_if": {"below": 2.2}}}))
    ind = Indicator.from_config(cfg)
    assert ind.fmt(4.1) == "4.1" and ind.rule == "settled speed below 2.2"
    assert with_units("3", "rad/s") == "3 rad/s" and with_units("3", "") == "3"


def test_indicator_values_keep_the_limits_digits(tmp_path):
    """Beside a limit of 4335, 4339 (not 4.34e+03, which cannot be compared with it); three
    significant digits where the limit is small."""
    from twinmon.config import load_config
    from twinmon.safety import Indicator
    from ..conftest import CONFIGS, write_yaml
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"), "safety": {"unsafe_if": {"below": 4335.0}}}))
    ind = Indicator.from_config(cfg)
    assert ind.fmt(4339.2) == "4339 rad/s" and ind.fmt(12345.6) == "12346 rad/s"
    assert Indicator.from_config(load_config(CONFIGS / "pump.yaml")).fmt(14.53) == "14.5 s"
