"""A fleet the benchmarks do not build: units new in service, parts replaced in the record's
last years (recorded or not), a step in the last year. ``twinmon run`` must forecast the
others, and say of these units what their records can and cannot show, with the real FMU."""
from __future__ import annotations

import json

import pytest

from ..conftest import CONFIGS, write_yaml

LINE = {"motor_damping": {"start": 10.0, "slope": 0.0, "jitter": 0.15},
        "pump_coef": {"start": 3.65, "slope": -0.02, "jitter": 0.01}}


def _unit(**kw):
    spec = {"trajectories": {n: dict(v) for n, v in LINE.items()}}
    for name, extra in kw.pop("trajectories", {}).items():
        spec["trajectories"][name].update(extra)
    spec.update(kw)
    return spec


@pytest.fixture(scope="module")
def odd_run(tmp_path_factory, fmu_path):
    from twinmon.cli import main
    from click.testing import CliRunner
    tmp = tmp_path_factory.mktemp("odd")
    cfg = write_yaml(tmp / "odd.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 64, "test_size": 16},
        "forecast": {"samples": 600, "observed_samples": 60},
        "fabricate": {"years": 10, "noise_std": 4.0, "seed": 99, "units": {
            "Steady": _unit(),
            "Young": _unit(last_year=2),
            "Infant": _unit(last_year=1),
            # A motor wearing fast, replaced in the last year; the plant did not record it.
            "Renewed": _unit(trajectories={"motor_damping": {"start": 10.2, "slope": 1.1}},
                             events=[{"year": 10, "component": "motor",
                                      "recorded": False}]),
            # A pump recorded as replaced in year 9 after fast wear.
            "Swapped": _unit(trajectories={"pump_coef": {"slope": -0.12}},
                             events=[{"year": 9, "component": "pump"}]),
            # A motor worn past the design box (its damping above 30 from year 9).
            "Beyond": _unit(trajectories={"motor_damping": {"slope": 2.5}}),
            # A motor fitted worn: past the limit from year 1, at a normal (flat) rate.
            "Fitted": _unit(trajectories={"motor_damping": {"start": 28.5}}),
            # The pump coefficient steps down 0.5 in the last year, then stays.
            "Stepped": _unit(trajectories={"pump_coef": {
                "changes": [{"year": 10, "size": -0.5}]}}),
        }}})
    obs, truth, work = tmp / "obs.h5", tmp / "truth.h5", tmp / "w"
    r = CliRunner().invoke(main, ["fabricate", "-c", str(cfg), "-o", str(obs),
                                  "--truth", str(truth)])
    assert r.exit_code == 0, r.output
    # Every unit's summary is the report's; its figures are drawn for two units (the fleet
    # overview's choice), not eight.
    r = CliRunner().invoke(main, ["run", "-c", str(cfg), "--set", "report.detail_units=2",
                                  "--observations", str(obs), "--truth", str(truth),
                                  "--workdir", str(work)])
    assert r.exit_code == 0, r.output
    return json.loads((work / "report" / "summary.json").read_text())["units"], work


def test_units_new_in_service_do_not_stop_the_fleet(odd_run):
    units, work = odd_run
    from twinmon.forecast import read_forecast
    fc = read_forecast(work / "forecast.h5")
    assert fc.too_few_years == {"Young": 2, "Infant": 1}
    assert set(fc.units) == {"Steady", "Renewed", "Swapped", "Beyond", "Stepped", "Fitted"}
    for u, k in (("Young", 2), ("Infant", 1)):
        assert units[u]["health"] == "not judged (too few years)"
        assert units[u]["action"].startswith(f"no prognosis yet: {k} calibrated year(s)")
    s = units["Steady"]
    assert s["root_cause"] == "healthy", s
    # Its trend may bend (the fleet's shapes learnt from these odd units): a failure year
    # from the bend alone is not a confident one.
    assert s["status"] == "ok" or (s["status"] == "unreliable" and s["status_reason"]
                                   .startswith("prognosis unreliable: no input wears")), s


def test_a_part_replaced_in_the_last_years_is_not_called_failing(odd_run):
    """The new motor (found) and the new pump (recorded) are extended at their
    predecessors' rates from their new levels: no failure within the horizon's first
    years, and the status says their rate is assumed."""
    units, _ = odd_run
    for u, part in (("Renewed", "motor_damping in year 10"), ("Swapped", "pump_coef in year 9")):
        s = units[u]
        assert s["status"] == "unreliable", s
        assert s["status_reason"].startswith("prognosis unreliable: the trend restarted after "
                                             f"a repair, of {part}")
        assert s["failure_year"] is None or s["failure_year"] > 12, s


def test_a_step_in_the_last_year_is_not_a_confident_failure(odd_run):
    units, _ = odd_run
    s = units["Stepped"]
    assert s["status"] == "unreliable", s
    # Named by the check of the latest year, or by the whole history's where year 10 is
    # the one missed (which fires depends on the fleet's pooled year-to-year sd).
    r = s["status_reason"]
    assert "the latest year, 10, is not where the trend" in r or \
        "the trend missed year(s) 10 one year ahead" in r, r


def test_a_part_worn_past_the_box_is_said_to_be_past_the_box(odd_run):
    """The twin misses the plant where the motor's estimates sit on the box's high edge: the
    box is named, and widening it is the action (not an effect diagnose fits in its place)."""
    units, _ = odd_run
    s = units["Beyond"]
    assert s["status"] == "withheld"
    assert "motor_damping sit on the design box's high edge" in s["status_reason"]
    assert "widen model.inputs.motor_damping.high and run again" in s["action"]
    # Its recorded transients are past the limit themselves (t90 above 30 s): no twin is
    # needed to say it is unsafe now, and the action says it first.
    since = s["measured_unsafe_since"]
    assert since is not None and since <= 10
    assert s["action"].startswith(f"unsafe as measured since year {since} (t90 ")
    assert s["time_to_failure"].endswith(f"; measured unsafe since year {since}")


def test_a_part_unsafe_at_its_level_is_named_though_it_does_not_drift(odd_run):
    """A motor past the limit from year 1 but wearing at a normal rate: no drift to detect,
    yet the unit is not called healthy; its motor's level is named as the cause."""
    units, work = odd_run
    s = units["Fitted"]
    assert s["root_cause"] == "motor", s
    assert s["health"] == "unsafe: motor (a level, not a drift)", s
    assert s["action"].endswith("inspect the motor now"), s
    assert s["plan"].startswith("Inspect/replace the motor now (already unsafe"), s
    assert "a level, not a drift -- motor_damping " in s["plan"]
    from twinmon.forecast import read_forecast
    lv = read_forecast(work / "forecast.h5").units["Fitted"].level_cause
    assert list(lv) == ["motor_damping"] and lv["motor_damping"]["safe"], lv
    assert lv["motor_damping"]["nominal"] == 10.0
    # The truth: unsafe since its first year, not in the first year after the record.
    assert s["true_failure_year"] == 1, s


def test_the_backtest_runs_on_a_fleet_with_units_new_in_service(odd_run, tmp_path):
    units, work = odd_run
    from click.testing import CliRunner

    from twinmon.cli import main
    cfg = work.parent / "odd.yaml"
    r = CliRunner().invoke(main, ["backtest", "-c", str(cfg), "--posterior",
                                  str(work / "posterior.h5"), "--surrogate",
                                  str(work / "surrogate.h5"), "--observations",
                                  str(work.parent / "obs.h5"), "-o", str(tmp_path / "bt.h5"),
                                  "--set", "backtest.min_years=8", "--json"])
    assert r.exit_code == 0, r.output
    bt = json.loads(r.stdout)
    assert set(bt["units"]) == {"Steady", "Renewed", "Swapped", "Beyond", "Stepped", "Fitted"}
    assert bt["units"]["Steady"]["cuts"] == [8, 9]
