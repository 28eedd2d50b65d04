"""Observations format and the CSV importer: validation and one-line errors naming the line."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from twinmon.errors import ArtifactError, InputDataError
from twinmon.observations import (Observations, UnitObservations, import_csv,
                                  read_observations, write_observations)


def _csv(tmp_path, text, name="m.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


# The output is named by the config: "speed" here, not the pump's flow.
GOOD = """unit,year,time,speed,drive.i
A,1,2,10.5,50
A,1,4,20.5,80
A,2,2,9.5,49
A,2,4,19.0,
B,1,2,11.0,51
B,1,4,21.0,82
"""


def test_import_csv_round_trip(tmp_path):
    obs = import_csv(_csv(tmp_path, GOOD), tmp_path / "o.h5", "speed", noise_std=4.0,
                     units={"speed": "rad/s", "drive.i": "A"})
    back = read_observations(tmp_path / "o.h5")
    assert back.output == "speed"                       # recorded in the file
    assert np.array_equal(back.time, [2.0, 4.0])
    assert list(back.units) == ["A", "B"]
    assert np.array_equal(back.units["A"].years, [1, 2])
    assert np.array_equal(back.output_of("A"), [[10.5, 20.5], [9.5, 19.0]])
    assert np.isnan(back.units["A"].channels["drive.i"][1, 1])  # empty cell = missing
    assert back.units["B"].noise_std == {"speed": 4.0}
    assert obs.output_of("B").shape == (1, 2)
    with h5py.File(tmp_path / "o.h5") as f:
        assert f["units/A/speed"].attrs["units"] == "rad/s"


def test_import_csv_strips_a_bom_and_rejects_latin1_and_foreign_columns(tmp_path):
    p = tmp_path / "bom.csv"
    p.write_bytes(b"\xef\xbb\xbf" + GOOD.encode())
    assert list(import_csv(p, tmp_path / "o.h5", "speed").units) == ["A", "B"]
    p.write_bytes(GOOD.replace("A,1,2", "\xc9,1,2", 1).encode("latin-1"))
    with pytest.raises(InputDataError, match=r"bom.csv: line 2: not UTF-8"):
        import_csv(p, tmp_path / "o2.h5", "speed")
    with pytest.raises(InputDataError, match=r"line 1: column 'drive.i' is not a channel of the "
                                             r"config \(allowed: shaft.w, speed\)"):
        import_csv(_csv(tmp_path, GOOD), tmp_path / "o3.h5", "speed", channels=["shaft.w"])
    big = "unit,year,time,speed\nA,9223372036854775808,2,1\n"
    with pytest.raises(InputDataError, match=r"line 2: column 'year' is 9223372036854775808"):
        import_csv(_csv(tmp_path, big), tmp_path / "o4.h5", "speed")
    for out in ("o2.h5", "o3.h5", "o4.h5"):
        assert not (tmp_path / out).exists()


@pytest.mark.parametrize("text, message", [
    ("unit,year,m_flow\nA,1,3\n", r"line 1: missing column 'time'"),
    ("unit,year,time,flow\nA,1,3,1\n", r"line 1: missing column 'm_flow'"),
    ("unit,year,time,m_flow\nA,1,2,abc\n", r"line 2: column 'm_flow' is 'abc', expected a number"),
    ("unit,year,time,m_flow\nA,x,2,1\n", r"line 2: column 'year' is 'x', expected an integer"),
    ("unit,year,time,m_flow\nA,1,2,1\nA,1,2,2\n", r"line 3: duplicate row for unit 'A' year 1 "
                                                   r"time 2 \(first on line 2\)"),
    ("unit,year,time,m_flow\nA,1,2,1\nA,1,4,1\nA,2,2,1\nA,2,6,1\n",
     r"lines 4-5: unit 'A' year 2 has no row at time 4, which unit 'A' year 1 has \(line 3; "),
    ("unit,year,time,m_flow\nA,1,2,1\nA,1,4,1\nA,2,2,1\nA,2,4,1\nA,2,6,1\n",
     r"line 6: unit 'A' year 2 has a row at time 6 that unit 'A' year 1 has not"),
    ("unit,year,time,m_flow\nA,1,2\n", r"line 2: 3 fields, expected 4"),
    ("unit,year,time,m_flow\nA,1,inf,1\n", r"line 2: column 'time' is 'inf', expected a finite"),
    ("", r"line 1: file is empty"),
    ("unit;year;time;m_flow\nA;1;2;1\n", r"missing column 'unit' .*; the file is separated "
                                         r"by semicolons"),
    ("unit,year,time [s],m_flow\nA,1,2,1\n", r"missing column 'time' .*; write the bare "
                                              r"names"),
    # A calendar year: refused here as every reader refuses it, with what to write instead.
    ("unit,year,time,m_flow\nA,2014,2,1\n", r"line 2: column 'year' is 2014, expected a year "
                                             r"of service from 1 to 1000 \(a calendar year\?"),
])
def test_import_csv_errors_name_the_line(tmp_path, text, message):
    """(A time written with an export's float noise is the same time: see below.)"""
    out = tmp_path / "o.h5"
    with pytest.raises(InputDataError, match=message) as exc:
        import_csv(_csv(tmp_path, text), out, "m_flow")
    assert "m.csv" in str(exc.value) and not out.exists()


def test_import_csv_missing_file(tmp_path):
    with pytest.raises(InputDataError, match="nope.csv: file not found"):
        import_csv(tmp_path / "nope.csv", tmp_path / "o.h5", "m_flow")


def _obs(**over):
    u = UnitObservations(np.array([1, 2]), {"m_flow": np.ones((2, 3))}, {"m_flow": 1.0})
    for k, v in over.items():
        setattr(u, k, v)
    return Observations(np.array([2.0, 4.0, 6.0]), {"A": u}, output="m_flow")


@pytest.mark.parametrize("over, message", [
    ({"channels": {"m_flow": np.ones((2, 4))}}, r"/units/A/m_flow has shape \(2, 4\), expected \(2, 3\)"),
    ({"channels": {"m_flow": np.array([[1, np.inf, 1], [1, 1, 1.0]])}}, r"m_flow\[0, 1\] is inf"),
    ({"years": np.array([2, 1])}, r"years\[1\] = 1 is not after 2"),
    ({"noise_std": {"m_flow": -1.0}}, r"noise_std\['m_flow'\] is -1.0"),
    ({"channels": {"m_flow": np.array([[np.nan] * 3, [1, 1, 1.0]])}}, r"year 1 has no sample"),
])
def test_bad_observations_are_never_written(tmp_path, over, message):
    out = tmp_path / "o.h5"
    with pytest.raises(InputDataError, match=message):
        write_observations(out, _obs(**over))
    assert not out.exists()


def test_read_rejects_wrong_schema_and_missing_flow(tmp_path):
    out = tmp_path / "o.h5"
    write_observations(out, _obs())
    with h5py.File(out, "a") as f:
        del f["units/A/m_flow"]
    with pytest.raises(ArtifactError, match=r"o.h5: dataset /units/A/m_flow \(the config.s "
                                            r"model.output.name\) is missing"):
        read_observations(out)
    with h5py.File(out, "a") as f:
        f.attrs["schema"] = "twinmon.observations/0"
    with pytest.raises(ArtifactError, match="expected 'twinmon.observations/1'"):
        read_observations(out)


@pytest.mark.parametrize("raw, expect", [
    (2.5, {"m_flow": 2.5}),                      # a bare number by hand: the output's noise
    ('{"m_flow": 3.0}', {"m_flow": 3.0}),
    ("2.5", {"m_flow": 2.5}),
])
def test_noise_std_attribute_written_by_hand(tmp_path, raw, expect):
    out = tmp_path / "o.h5"
    write_observations(out, _obs())
    with h5py.File(out, "a") as f:
        f["units/A"].attrs["noise_std"] = raw
    assert read_observations(out, "m_flow").units["A"].noise_std == expect


@pytest.mark.parametrize("raw", ["loud", [1.0, 2.0], "[1, 2]", -1.0])
def test_bad_noise_std_attribute_is_one_line(tmp_path, raw):
    out = tmp_path / "o.h5"
    write_observations(out, _obs())
    with h5py.File(out, "a") as f:
        f["units/A"].attrs["noise_std"] = raw
    with pytest.raises(InputDataError, match=r"o.h5: /units/A attribute noise_std") as exc:
        read_observations(out, "m_flow")
    assert "\n" not in str(exc.value)


def test_import_csv_reads_an_exports_float_noise_as_the_same_time(tmp_path):
    text = ("unit,year,time,m_flow\nA,1,0.1,1\nA,1,0.3,2\n"
            "B,1,0.1,1\nB,1,0.30000000000000004,2\n")
    obs = import_csv(_csv(tmp_path, text), tmp_path / "o.h5", "m_flow")
    assert obs.time.tolist() == [0.1, 0.3]
