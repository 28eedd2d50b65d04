"""Maintenance events: stored per unit in observations (and truth), checked against the unit's
years and the config's components, imported from CSV, added in place, fabricated."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from twinmon.artifacts import file_sha256, read_provenance
from twinmon.cli import main
from twinmon.config import config_from_mapping, load_config
from twinmon.errors import ConfigError, InputDataError
from twinmon.fabricate import fabricate, read_truth
from twinmon.observations import (Event, Observations, UnitObservations, add_events,
                                  check_events, import_csv, read_observations,
                                  write_observations)

from ..conftest import CONFIGS, write_yaml

COMPONENTS = ["bearing", "winding"]          # configs/dcdrive.yaml's


def _obs(events=(), years=(1, 2, 3, 4)):
    u = UnitObservations(np.array(years), {"speed": np.ones((len(years), 3))}, {"speed": 3.0},
                         list(events))
    v = UnitObservations(np.array(years), {"speed": np.ones((len(years), 3))}, {"speed": 3.0})
    return Observations(np.array([0.1, 0.2, 0.3]), {"A": u, "B": v}, output="speed")


def _one_line(res) -> str:
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    return lines[0]


# ---------------------------------------------------------------------------------------
# The file
# ---------------------------------------------------------------------------------------
def test_round_trip_sorted_and_old_files_read_as_none(tmp_path):
    events = [Event(3, "bearing", note="WO 4711"), Event(4, "winding", "rewound")]
    write_observations(tmp_path / "o.h5", _obs(events))
    back = read_observations(tmp_path / "o.h5")
    assert back.units["A"].events == events
    assert back.units["B"].events == []                  # no dataset written for B
    with h5py.File(tmp_path / "o.h5") as f:
        assert "events" not in f["units/B"]
        assert f["units/A/events"]["year"].tolist() == [3, 4]
    # A file written before events existed (no dataset at all) reads as no events.
    with h5py.File(tmp_path / "o.h5", "a") as f:
        del f["units/A/events"]
    assert read_observations(tmp_path / "o.h5").units["A"].events == []


def test_hand_written_events_need_only_year_and_component(tmp_path):
    write_observations(tmp_path / "o.h5", _obs())
    dt = np.dtype([("year", "<i4"), ("component", h5py.string_dtype())])
    with h5py.File(tmp_path / "o.h5", "a") as f:
        f["units/A"].create_dataset("events", data=np.array([(4, "winding"), (2, "bearing")],
                                                            dtype=dt))
    ev = read_observations(tmp_path / "o.h5").units["A"].events
    assert ev == [Event(2, "bearing"), Event(4, "winding")]   # sorted, action "replaced"


@pytest.mark.parametrize("events, message", [
    ([Event(1, "bearing")], r"/units/A/events: year 1 \(bearing replaced\) is not after the "
                            r"first recorded year 1"),
    ([Event(5, "bearing")], r"year 5 \(bearing replaced\) is after the last recorded year 4"),
    ([Event(3, "bearing"), Event(2, "winding")], r"comes after year 3 \(events must be sorted"),
    ([Event(3, "bearing"), Event(3, "bearing", "repaired")], r"a second event for 'bearing'"),
    ([Event(3, "")], r"year 3: component is ''"),
])
def test_bad_events_are_never_written(tmp_path, events, message):
    out = tmp_path / "o.h5"
    with pytest.raises(InputDataError, match=message) as exc:
        write_observations(out, _obs(events))
    assert "\n" not in str(exc.value) and not out.exists()


def test_year_is_checked_on_reading_a_hand_edited_file(tmp_path):
    out = tmp_path / "o.h5"
    write_observations(out, _obs([Event(3, "bearing")]))
    with h5py.File(out, "a") as f:
        f["units/A/events"][0] = (0, "bearing", "replaced", "")
    with pytest.raises(InputDataError, match=r"o.h5: /units/A/events: year 0 \(bearing "
                                             r"replaced\) is not after the first recorded year"):
        read_observations(out)


def test_check_events_names_file_unit_year_component_and_the_valid_ones(tmp_path):
    cfg = load_config(CONFIGS / "dcdrive.yaml")
    assert cfg.model.components == {"bearing": ("bearing_friction",),
                                     "winding": ("winding_resistance",)}
    write_observations(tmp_path / "o.h5", _obs([Event(3, "bearing")]))
    check_events(cfg, read_observations(tmp_path / "o.h5"))          # fine
    write_observations(tmp_path / "o.h5", _obs([Event(3, "bearing"), Event(3, "pump")]))
    with pytest.raises(InputDataError, match=r"o.h5: /units/A/events: year 3: component "
                                             r"'pump' is not a component of the config's "
                                             r"model.inputs \(components: bearing, winding\)"):
        check_events(cfg, read_observations(tmp_path / "o.h5"))


def test_an_input_without_component_is_named_by_its_own_name():
    raw = load_config(CONFIGS / "dcdrive.yaml").raw
    raw["model"]["inputs"]["winding_resistance"].pop("component")
    assert list(config_from_mapping(raw).model.components) == ["bearing", "winding_resistance"]


# ---------------------------------------------------------------------------------------
# Adding to an existing file
# ---------------------------------------------------------------------------------------
def test_add_events_keeps_the_files_permissions(tmp_path):
    """The edit replaces the file by a copy: the copy has the original's mode (plant data
    kept private stays private), and a read-only file is refused (for a user it binds)."""
    import os
    p = tmp_path / "o.h5"
    write_observations(p, _obs())
    os.chmod(p, 0o600)
    add_events(p, {"A": [Event(3, "bearing")]}, COMPONENTS)
    assert oct(os.stat(p).st_mode & 0o777) == oct(0o600)
    os.chmod(p, 0o400)
    if os.access(p, os.W_OK):
        pytest.skip("root writes a file whatever its mode")
    with pytest.raises(OSError, match="read-only"):
        add_events(p, {"A": [Event(4, "winding")]}, COMPONENTS)


def test_add_events_in_place_keeps_everything_else(tmp_path):
    out = tmp_path / "o.h5"
    write_observations(out, _obs([Event(4, "winding")]), config="x: 1", seed=7)
    before = read_provenance(out)
    obs = add_events(out, {"A": [Event(2, "bearing", note="WO 1")]}, COMPONENTS)
    assert obs.units["A"].events == [Event(2, "bearing", note="WO 1"), Event(4, "winding")]
    back = read_observations(out)
    assert back.units["A"].events == obs.units["A"].events
    assert np.array_equal(back.output_of("A"), np.ones((4, 3)))
    after = read_provenance(out)
    assert {k: after[k] for k in ("config", "seed", "created")} == \
        {k: before[k] for k in ("config", "seed", "created")}
    assert '"command": "events add"' in after["edits"] and '"WO 1"' in after["edits"]
    assert [p.name for p in tmp_path.iterdir()] == ["o.h5"]       # no temporary left


@pytest.mark.parametrize("unit, event, message", [
    ("C", Event(2, "bearing"), r"o.h5: no unit 'C' \(units: A, B\)"),
    ("A", Event(2, "pump"), r"year 2: component 'pump' is not a component"),
    ("A", Event(4, "winding"), r"year 4: an event for 'winding' is already recorded"),
    ("A", Event(1, "bearing"), r"is not after the first recorded year 1"),
    ("B", Event(9, "bearing"), r"/units/B/events: year 9 .* after the last recorded year 4"),
])
def test_add_events_on_error_leaves_the_file_untouched(tmp_path, unit, event, message):
    out = tmp_path / "o.h5"
    write_observations(out, _obs([Event(4, "winding")]))
    digest = file_sha256(out)
    with pytest.raises(InputDataError, match=message):
        add_events(out, {unit: [event]}, COMPONENTS)
    assert file_sha256(out) == digest
    assert [p.name for p in tmp_path.iterdir()] == ["o.h5"]


# ---------------------------------------------------------------------------------------
# import-csv --events
# ---------------------------------------------------------------------------------------
DATA = "unit,year,time,speed\n" + "".join(
    f"{u},{y},{t},{100 + t}\n" for u in ("P-1", "P-2") for y in (1, 2, 3, 4) for t in (0.1, 0.2))


def _files(tmp_path, events: str):
    (tmp_path / "d.csv").write_text(DATA)
    (tmp_path / "ev.csv").write_text(events)
    return tmp_path / "d.csv", tmp_path / "ev.csv"


def test_import_csv_with_events(tmp_path):
    data, ev = _files(tmp_path, "unit,year,component,action,note\n"
                                "P-1,4,winding,rewound,\"WO 12, brushes\"\n"
                                "P-1,3,bearing,,\n")
    obs = import_csv(data, tmp_path / "o.h5", "speed", events=ev, components=COMPONENTS)
    expect = [Event(3, "bearing"), Event(4, "winding", "rewound", "WO 12, brushes")]
    assert obs.units["P-1"].events == expect
    back = read_observations(tmp_path / "o.h5")
    assert back.units["P-1"].events == expect and back.units["P-2"].events == []
    assert [r["path"] for r in read_provenance(tmp_path / "o.h5")["inputs"]] == \
        [str(data), str(ev)]


@pytest.mark.parametrize("events, message", [
    ("unit,year,component\nP-3,2,bearing\n", r"ev.csv: line 2: unit 'P-3' has no measurements "
                                             r"in .*d.csv \(units: P-1, P-2\)"),
    ("unit,year,component\nP-1,2,bearing\nP-1,1,winding\n",
     r"ev.csv: line 3: year 1 of unit 'P-1' is outside its measured years \(1, 4\]"),
    ("unit,year,component\nP-1,5,bearing\n", r"ev.csv: line 2: year 5 .* outside"),
    ("unit,year,component\nP-1,2,pump\n", r"ev.csv: line 2: component 'pump' is not a "
                                          r"component of the config's model.inputs "
                                          r"\(components: bearing, winding\)"),
    ("unit,year,component\nP-1,two,bearing\n", r"line 2: column 'year' is 'two', expected an "
                                               r"integer"),
    ("unit,year,component\nP-1,2,\n", r"line 2: column 'component' is empty"),
    ("unit,year,part\nP-1,2,bearing\n", r"line 1: missing column 'component'"),
    ("unit,year,component,cost\nP-1,2,bearing,300\n", r"line 1: unknown column 'cost'"),
    ("unit,year,component\nP-1,2,bearing\nP-1,2,bearing\n",
     r"line 3: a second event for 'bearing' of unit 'P-1' in year 2 \(first on line 2\)"),
])
def test_import_csv_event_errors_name_the_line(tmp_path, events, message):
    data, ev = _files(tmp_path, events)
    with pytest.raises(InputDataError, match=message) as exc:
        import_csv(data, tmp_path / "o.h5", "speed", events=ev, components=COMPONENTS)
    assert "\n" not in str(exc.value) and not (tmp_path / "o.h5").exists()


# ---------------------------------------------------------------------------------------
# The CLI: exit codes and one line
# ---------------------------------------------------------------------------------------
def test_cli_import_add_and_list(tmp_path):
    cfg = CONFIGS / "dcdrive.yaml"
    data, ev = _files(tmp_path, "unit,year,component\nP-1,3,bearing\n")
    out = tmp_path / "o.h5"
    res = CliRunner().invoke(main, ["import-csv", str(data), "-c", str(cfg), "-o", str(out),
                                    "--events", str(ev)])
    assert res.exit_code == 0, res.output
    assert "1 event -> " in res.stderr
    res = CliRunner().invoke(main, ["events", "add", str(out), "-c", str(cfg), "--unit", "P-2",
                                    "--year", "2", "--component", "winding", "--note", "WO 9"])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["events", "list", str(out)])
    assert res.stdout.splitlines() == ["P-1: year 3: bearing replaced",
                                       "P-2: year 2: winding replaced (WO 9)"]
    digest = file_sha256(out)
    res = CliRunner().invoke(main, ["events", "add", str(out), "-c", str(cfg), "--unit", "P-2",
                                    "--year", "3", "--component", "gearbox"])
    assert res.exit_code == 4
    assert _one_line(res) == (f"twinmon: input error: {out}: /units/P-2/events: year 3: "
                              "component 'gearbox' is not a component of the config's "
                              "model.inputs (components: bearing, winding)")
    assert file_sha256(out) == digest


def test_cli_import_bad_event_exit_4(tmp_path):
    data, ev = _files(tmp_path, "unit,year,component\nP-1,1,bearing\n")
    res = CliRunner().invoke(main, ["import-csv", str(data), "-c", str(CONFIGS / "dcdrive.yaml"),
                                    "-o", str(tmp_path / "o.h5"), "--events", str(ev)])
    assert res.exit_code == 4
    assert "ev.csv: line 2: year 1 of unit 'P-1' is outside" in _one_line(res)
    assert not (tmp_path / "o.h5").exists()


# ---------------------------------------------------------------------------------------
# fabricate
# ---------------------------------------------------------------------------------------
def _fleet(tmp_path, events_a) -> object:
    trajectories = {"bearing_friction": {"start": 0.001, "slope": 4.0e-4},
                    "winding_resistance": {"start": 1.0, "slope": 0.05, "jitter": 0.01}}
    return write_yaml(tmp_path / "fab.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "fabricate": {"years": 4, "noise_std": 3.0, "truth_variables": ["shaft.w"], "units": {
            "A": {"trajectories": trajectories, "events": events_a},
            "B": {"trajectories": trajectories}}}})


def test_fabricated_replacement_resets_the_truth_at_the_event(tmp_path):
    cfg = load_config(_fleet(tmp_path, [{"year": 3, "component": "bearing", "note": "WO 1"}]))
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    truth = read_truth(tmp_path / "t.h5")
    a, b = truth.inputs["A"], truth.inputs["B"]
    # The bearing is new in year 3: back to start, then the same slope.
    assert np.allclose(a["bearing_friction"], [0.001, 0.0014, 0.001, 0.0014])
    assert np.allclose(b["bearing_friction"], [0.001, 0.0014, 0.0018, 0.0022])
    # The winding is untouched: its jitter draws are those of a fleet without events.
    plain = load_config(_fleet(tmp_path, []))
    fabricate(plain, tmp_path / "o0.h5", tmp_path / "t0.h5")
    t0 = read_truth(tmp_path / "t0.h5")
    assert np.array_equal(a["winding_resistance"], t0.inputs["A"]["winding_resistance"])
    assert np.array_equal(b["bearing_friction"], t0.inputs["B"]["bearing_friction"])
    # The FMU sees it: less friction after the replacement, a faster settled speed.
    with h5py.File(tmp_path / "t.h5") as f, h5py.File(tmp_path / "t0.h5") as g:
        new, old = f["units/A/speed_clean"][()], g["units/A/speed_clean"][()]
    assert np.array_equal(new[:2], old[:2]) and np.all(new[2:, -1] > old[2:, -1] + 1.0)
    # Both files record the event; the plant's file holds nothing more of the truth.
    ev = [Event(3, "bearing", "replaced", "WO 1")]
    assert truth.events == {"A": ev, "B": []}
    obs = read_observations(tmp_path / "o.h5")
    assert obs.units["A"].events == ev and obs.units["B"].events == []
    check_events(cfg, obs)


@pytest.mark.parametrize("events, message", [
    ([{"year": 3, "component": "pump"}], r"fabricate.units.A.events.0.component: not a "
                                         r"component of model.inputs \(components: bearing, "
                                         r"winding\), got 'pump'"),
    ([{"year": 1, "component": "bearing"}], r"fabricate.units.A.events.0.year: must lie in "
                                            r"\[2, 4\]"),
    ([{"year": 5, "component": "bearing"}], r"fabricate.units.A.events.0.year: must lie in "
                                            r"\[2, 4\]"),
    ([{"year": 3, "component": "bearing", "action": "inspected"}],
     r"fabricate.units.A.events.0.action: expected one of replaced, got 'inspected'"),
    ([{"year": 3, "component": "bearing", "when": 3}],
     r"fabricate.units.A.events.0.when: unknown key"),
])
def test_fabricate_events_are_validated_on_load(tmp_path, events, message):
    with pytest.raises(ConfigError, match=r"fab.yaml: " + message):
        load_config(_fleet(tmp_path, events))


def test_cli_fabricate_bad_event_exit_3(tmp_path):
    res = CliRunner().invoke(main, ["fabricate", "-c", str(_fleet(tmp_path, [])), "-o",
                                    str(tmp_path / "o.h5"), "--set",
                                    "fabricate.units.B.events=[{year: 2, component: gear}]"])
    assert res.exit_code == 3
    assert "fabricate.units.B.events.0.component: not a component" in _one_line(res)
    assert not (tmp_path / "o.h5").exists()


def test_calibrate_rejects_an_event_of_an_unknown_component(tmp_path):
    from twinmon.calibrate import calibrate
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    cfg = load_config(_fleet(tmp_path, [{"year": 3, "component": "bearing"}]), [
        "simulate.train_size=16", "simulate.test_size=4", "simulate.executor=serial"])
    fabricate(cfg, tmp_path / "o.h5", tmp_path / "t.h5")
    simulate(cfg, tmp_path / "s.h5")
    reduce(cfg, tmp_path / "s.h5", tmp_path / "r.h5")
    with h5py.File(tmp_path / "o.h5", "a") as f:          # a file from another machine's config
        f["units/A/events"][0] = (3, "pump", "replaced", "")
    with pytest.raises(InputDataError, match=r"o.h5: /units/A/events: year 3: component 'pump' "
                                             r"is not a component"):
        calibrate(cfg, tmp_path / "r.h5", tmp_path / "o.h5", tmp_path / "p.h5")
    assert not (tmp_path / "p.h5").exists()


def test_remove_an_event_recorded_by_mistake(tmp_path):
    """events remove takes one event out in place (the rest of the file kept, the removal
    recorded in edits); an event that is not there is refused with the unit's events, the
    file unchanged; the unit's last event gone leaves no dataset, as files without any."""
    import json
    from twinmon.observations import remove_events
    out = tmp_path / "o.h5"
    write_observations(out, _obs([Event(3, "bearing", note="WO 1"), Event(4, "winding")]))
    obs = remove_events(out, "A", 3, "bearing")
    assert obs.units["A"].events == [Event(4, "winding")]
    assert read_observations(out).units["A"].events == [Event(4, "winding")]
    with h5py.File(out) as f:
        edits = json.loads(f.attrs["edits"])
    assert edits[-1]["command"] == "events remove"
    assert edits[-1]["events"] == {"A": [{"year": 3, "component": "bearing",
                                          "action": "replaced", "note": "WO 1"}]}
    digest = file_sha256(out)
    with pytest.raises(InputDataError, match=r"/units/A/events: no event for 'bearing' in "
                                             r"year 3 \(the unit's events: year 4 winding\)"):
        remove_events(out, "A", 3, "bearing")
    with pytest.raises(InputDataError, match=r"no unit 'Z'"):
        remove_events(out, "Z", 4, "winding")
    assert file_sha256(out) == digest
    remove_events(out, "A", 4, "winding")
    with h5py.File(out) as f:
        assert "events" not in f["units/A"]
    res = CliRunner().invoke(main, ["events", "remove", str(out), "--unit", "A", "--year", "4",
                                    "--component", "winding"])
    assert res.exit_code == 4 and "no event for 'winding' in year 4" in res.output
