"""Inputs that used to end in a traceback: out-of-range seeds, non-UTF-8 text, absurd years,
malformed noise attributes, a one-sample time grid, damaged HDF5 artifacts."""
from __future__ import annotations

import json

from pathlib import Path

import h5py
import pytest

from .conftest import Snapshot, assert_fails, assert_ok, twinmon, twinmon_many


def test_bad_seeds_and_grid_exit_3(work):
    cfg = work / "small.yaml"
    latin = work / "latin1.yaml"
    latin.write_bytes(b"extends: " + str(cfg).encode() + b"\n# pompe \xe0 eau\nseed: 3\n")
    snap = Snapshot(work)
    sim = ["simulate", "-c", cfg, "-o", work / "s.h5"]
    r_neg, r_big, r_latin, r_grid = twinmon_many(
        [*sim, "--set", "seed=-1"],
        [*sim, "--set", "seed=1180591620717411303424"],
        ["simulate", "-c", latin, "-o", work / "s.h5"],
        [*sim, "--set", "model.output.times.stop=2"],
        cwd=work)
    assert_fails(r_neg, 3, "seed", "-1")
    assert_fails(r_big, 3, "seed", "1180591620717411303424")
    assert_fails(r_latin, 3, "latin1.yaml", "line 2", "UTF-8")
    assert_fails(r_grid, 3, "model.output.times")
    assert not (work / "s.h5").exists()
    snap.check()


def test_bad_csv_exit_4(work, repo_root):
    pump = repo_root / "configs" / "pump.yaml"
    latin = work / "latin1.csv"
    latin.write_bytes(b"unit,year,time,m_flow\nPomp\xe9,1,2,10\nPomp\xe9,1,4,12\n")
    year = work / "year.csv"
    year.write_text("unit,year,time,m_flow\nA,9223372036854775808,2,10\n"
                    "A,9223372036854775808,4,12\n")
    snap = Snapshot(work)
    r_latin, r_year = twinmon_many(
        ["import-csv", latin, "-c", pump, "-o", work / "o1.h5"],
        ["import-csv", year, "-c", pump, "-o", work / "o2.h5"], cwd=work)
    assert_fails(r_latin, 4, "latin1.csv", "line 2", "UTF-8")
    assert_fails(r_year, 4, "year.csv", "line 2", "9223372036854775808")
    assert not (work / "o1.h5").exists() and not (work / "o2.h5").exists()
    snap.check()


def _one_unit_year(src, dst, noise_std):
    """Park's first year only (a fast calibrate), with the given noise_std attribute."""
    dst.write_bytes(src.read_bytes())
    with h5py.File(dst, "a") as f:
        for unit in list(f["units"]):
            if unit != "Park":
                del f[f"units/{unit}"]
        g = f["units/Park"]
        for name in ("years", "m_flow"):
            ds = g[name]
            data, attrs = ds[()][:1], dict(ds.attrs)
            del g[name]
            g[name] = data
            g[name].attrs.update(attrs)
        g.attrs["noise_std"] = noise_std


def test_noise_std_attribute(work):
    """A bare number is the output's noise (accepted and used); a list or text is refused."""
    paths = {}
    for name, value in (("number", 5.5), ("list", "[4.0, 4.0]"), ("text", "four kg/s")):
        paths[name] = work / f"noise_{name}.h5"
        _one_unit_year(work / "fleet.h5", paths[name], value)
    snap = Snapshot(work)

    def cal(name):
        return ["calibrate", "-c", work / "small.yaml", "--surrogate", work / "surrogate.h5",
                "--observations", paths[name], "-o", work / f"post_{name}.h5", "--json"]
    r_num, r_list, r_text = twinmon_many(cal("number"), cal("list"), cal("text"), cwd=work)
    assert_ok(r_num)
    assert json.loads(r_num.stdout)["noise"]["Park"] == {"std": 5.5, "source": "file"}
    assert_fails(r_list, 4, "noise_list.h5", "noise_std")
    assert_fails(r_text, 4, "noise_text.h5", "noise_std")
    assert not (work / "post_list.h5").exists() and not (work / "post_text.h5").exists()
    snap.check()


def _overwrite_middle(path, dataset):
    """64 bytes of a fixed pattern in the middle of the stored bytes of ``dataset`` (the
    middle of the whole file may be metadata or free space no stage reads: overwriting it
    damages nothing, and exit 0 is then right)."""
    with h5py.File(path, "r") as f:
        ds = f[dataset].id
        info = ds.get_chunk_info(0) if f[dataset].chunks else None
        offset, size = ((info.byte_offset, info.size) if info is not None
                        else (ds.get_offset(), ds.get_storage_size()))
    data = bytearray(path.read_bytes())
    mid = offset + size // 2 - 32
    data[mid:mid + 64] = bytes((i * 37 + 11) % 256 for i in range(64))
    path.write_bytes(bytes(data))


def _stage_reading(work, kind, path):
    """The command that reads a damaged ``kind`` artifact at ``path`` (others intact)."""
    cfg = work / "small.yaml"
    # One output per damaged file: commands run side by side into one output would stop at
    # its lock (exit 8) instead of reading their input.
    out = work / f"out_{Path(path).stem}.h5"
    if kind == "simulations":
        return ["reduce", "-c", cfg, "--simulations", path, "-o", out]
    if kind == "surrogate-calibrate":
        return ["calibrate", "-c", cfg, "--surrogate", path, "--observations",
                work / "fleet.h5", "-o", out]
    if kind == "surrogate-forecast":
        return ["forecast", "-c", cfg, "--posterior", work / "posterior.h5", "--surrogate",
                path, "-o", out]
    return ["forecast", "-c", cfg, "--posterior", path, "--surrogate", work / "surrogate.h5",
            "-o", out]


CASES = {"simulations": "simulations.h5", "surrogate-calibrate": "surrogate.h5",
         "surrogate-forecast": "surrogate.h5", "posterior": "posterior.h5"}


@pytest.mark.parametrize("kind", list(CASES))
def test_overwritten_bytes_artifact_exit_5(work, kind):
    """reduce (simulations), calibrate and forecast (surrogate), forecast (posterior) on a
    copy with bytes overwritten inside a dataset the stage reads."""
    damaged = work / f"damaged_{CASES[kind]}"
    damaged.write_bytes((work / CASES[kind]).read_bytes())
    _overwrite_middle(damaged, REMOVALS[kind][1])
    snap = Snapshot(work)
    r = twinmon(*_stage_reading(work, kind, damaged), cwd=work)
    assert_fails(r, 5, str(damaged))
    assert not any(work.glob("out*.h5"))
    snap.check()


REMOVALS = {
    "simulations": ("simulations.h5", "train/Y", "input_names"),
    "surrogate-calibrate": ("surrogate.h5", "basis", "input_names"),
    "surrogate-forecast": ("surrogate.h5", "xi_train", "transform"),
    "posterior": ("posterior.h5", "units/Monk/samples", "input_names"),
}


def test_missing_dataset_or_attribute_exit_5(work):
    """For each artifact: a copy without a required dataset, one without a required root
    attribute (deleted with h5py)."""
    calls, expect = [], []
    for kind, (name, dataset, attr) in REMOVALS.items():
        for what, remove in (("dataset", dataset), ("attribute", attr)):
            copy = work / f"no_{what}_{kind}.h5"
            copy.write_bytes((work / name).read_bytes())
            with h5py.File(copy, "a") as f:
                if what == "dataset":
                    del f[remove]
                else:
                    del f.attrs[remove]
            calls.append(_stage_reading(work, kind, copy))
            expect.append(copy)
    snap = Snapshot(work)
    results = twinmon_many(*calls, cwd=work)
    for r, copy in zip(results, expect):
        assert_fails(r, 5, str(copy))
    assert not any(work.glob("out*.h5"))
    snap.check()


def test_forecast_with_failed_twin_runs_no_traceback(work):
    """forecast.samples=100 on the shared posterior: some Monte Carlo draws fall where the FMU
    fails; forecast must answer (failed runs count as unsafe), never end in a traceback.
    (Found while building this suite: the health indicator of a failed run -- all NaN, plus
    the known value at t = 0 of ``initial`` -- is an IndexError in safety._time_to_reach.)"""
    snap = Snapshot(work)
    r = twinmon("forecast", "-c", work / "small.yaml", "--set", "forecast.samples=100",
                "--posterior", work / "posterior.h5", "--surrogate", work / "surrogate.h5",
                "-o", work / "out.h5", cwd=work)
    assert "Traceback" not in r.stderr, r.stderr
    assert_ok(r)
    snap.check()
