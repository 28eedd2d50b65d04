"""Artifacts: atomic writes, provenance attributes, schema checks, up-to-date test."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from twinmon import artifacts
from twinmon.errors import ArtifactError


def test_write_records_provenance_and_units(tmp_path):
    src = tmp_path / "in.txt"
    src.write_text("hello")
    out = tmp_path / "sub" / "a.h5"
    with artifacts.write_artifact(out, "gap", config="x: 1\n", inputs=[src], seed=3) as f:
        artifacts.put(f, "v", np.arange(3.0), "kg/s", "a vector")
    prov = artifacts.read_provenance(out)
    assert prov["schema"] == artifacts.schema_name("gap") and prov["seed"] == 3
    assert prov["config"] == "x: 1\n"
    assert prov["inputs"] == [{"path": str(src), "sha256": artifacts.file_sha256(src)}]
    assert prov["created"].endswith("+00:00")
    with artifacts.open_artifact(out, "gap") as f:
        assert f["v"].attrs["units"] == "kg/s" and f["v"].attrs["description"] == "a vector"


def test_failed_write_keeps_the_previous_artifact(tmp_path):
    out = tmp_path / "a.h5"
    with artifacts.write_artifact(out, "gap") as f:
        artifacts.put(f, "v", [1.0], "1", "first")
    with pytest.raises(RuntimeError):
        with artifacts.write_artifact(out, "gap") as f:
            artifacts.put(f, "v", [2.0], "1", "second")
            raise RuntimeError("crash mid-write")
    with h5py.File(out) as f:
        assert f["v"][0] == 1.0
    assert [p.name for p in tmp_path.iterdir()] == ["a.h5"]  # no temp file left


def test_a_swallowed_ctrl_c_keeps_the_previous_artifact(tmp_path):
    """A KeyboardInterrupt raised where Python drops it (a weak-reference callback, a
    ``__del__``) is recorded by the handler: the artifact being written is not made final."""
    from twinmon import interrupts
    out = tmp_path / "a.h5"
    with artifacts.write_artifact(out, "gap") as f:
        artifacts.put(f, "v", [1.0], "1", "first")
    interrupts.reset()
    try:
        with pytest.raises(KeyboardInterrupt):
            with artifacts.write_artifact(out, "gap") as f:
                artifacts.put(f, "v", [2.0], "1", "second")
                try:
                    interrupts.on_sigint(2, None)
                except KeyboardInterrupt:
                    pass                       # swallowed, as "Exception ignored in ..."
        assert interrupts.pending()
    finally:
        interrupts.reset()
    with h5py.File(out) as f:
        assert f["v"][0] == 1.0
    assert [p.name for p in tmp_path.iterdir()] == ["a.h5"]


def test_open_checks_schema_and_content(tmp_path):
    p = tmp_path / "notes.h5"
    p.write_text("not hdf5")
    with pytest.raises(ArtifactError, match="notes.h5: not a readable HDF5 file"):
        artifacts.open_artifact(p, "gap")
    q = tmp_path / "q.h5"
    with artifacts.write_artifact(q, "forecast") as f:
        pass
    with pytest.raises(ArtifactError, match="schema is 'twinmon.forecast/1', expected 'twinmon.gap/2'"):
        artifacts.open_artifact(q, "gap")
    with artifacts.open_artifact(q, "forecast") as f:
        with pytest.raises(ArtifactError, match=r"q.h5: dataset /missing is missing"):
            artifacts.get(f, "missing")


def test_up_to_date_follows_config_and_input_hashes(tmp_path):
    src = tmp_path / "in.txt"
    src.write_text("a")
    out = tmp_path / "o.h5"
    assert not artifacts.is_up_to_date(out, "gap", "c", [src])
    with artifacts.write_artifact(out, "gap", config="c", inputs=[src]):
        pass
    assert artifacts.is_up_to_date(out, "gap", "c", [src])
    assert not artifacts.is_up_to_date(out, "gap", "other", [src])
    src.write_text("b")
    assert not artifacts.is_up_to_date(out, "gap", "c", [src])


def test_an_artifact_of_another_twinmon_version_is_not_up_to_date(tmp_path):
    import h5py
    src = tmp_path / "in.txt"
    src.write_text("a")
    out = tmp_path / "o.h5"
    with artifacts.write_artifact(out, "gap", config="c", inputs=[src]):
        pass
    assert artifacts.is_up_to_date(out, "gap", "c", [src])
    with h5py.File(out, "r+") as f:
        f.attrs["twinmon_version"] = "0.0.1"
    assert not artifacts.is_up_to_date(out, "gap", "c", [src])


def _hold_lock(path, ready, release):
    with artifacts.output_lock(path, "twinmon test"):
        ready.set()
        release.wait(30)


def test_a_second_writer_is_refused_and_a_killed_holder_leaves_no_lock(tmp_path):
    import multiprocessing as mp
    import os
    import signal

    from twinmon.errors import OutputBusyError
    out = tmp_path / "a.h5"
    with artifacts.write_artifact(out, "gap") as f:
        artifacts.put(f, "v", [1.0], "1", "first")
    before = artifacts.file_sha256(out)
    ctx = mp.get_context("fork")
    ready, release = ctx.Event(), ctx.Event()
    holder = ctx.Process(target=_hold_lock, args=(out, ready, release))
    holder.start()
    assert ready.wait(30)
    with pytest.raises(OutputBusyError, match=rf"a.h5 is being written by .*pid {holder.pid}"):
        with artifacts.write_artifact(out, "gap") as f:
            artifacts.put(f, "v", [2.0], "1", "second")
    assert artifacts.file_sha256(out) == before         # nothing touched
    os.kill(holder.pid, signal.SIGKILL)                  # the kernel drops a dead holder's lock
    holder.join()
    with artifacts.write_artifact(out, "gap") as f:
        artifacts.put(f, "v", [3.0], "1", "third")
    assert [p.name for p in tmp_path.iterdir()] == ["a.h5"]


def test_a_folder_named_by_dot_is_locked_as_that_folder(tmp_path, monkeypatch):
    """``run --workdir .`` (or ``out/..``): the lock is the folder's own, beside it, whichever
    way the folder is named; a second writer of it is refused."""
    import multiprocessing as mp

    from twinmon.errors import OutputBusyError
    work = tmp_path / "work"
    (work / "out").mkdir(parents=True)
    monkeypatch.chdir(work)
    assert artifacts.lock_path(".") == tmp_path / ".work.lock"
    assert artifacts.lock_path("out/..") == tmp_path / ".work.lock"
    ctx = mp.get_context("fork")
    ready, release = ctx.Event(), ctx.Event()
    holder = ctx.Process(target=_hold_lock, args=(".", ready, release))
    holder.start()
    try:
        assert ready.wait(30)
        with pytest.raises(OutputBusyError, match="is being written by"):
            with artifacts.output_lock(work, "twinmon run"):
                pass
    finally:
        release.set()
        holder.join()
    with artifacts.output_lock("out/..", "twinmon run"):
        pass


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    out = tmp_path / "a.h5"
    stale = tmp_path / ".a.h5.999999999.tmp"             # no such process
    stale.write_bytes(b"half")
    with artifacts.write_artifact(out, "gap") as f:
        artifacts.put(f, "v", [1.0], "1", "first")
    assert not stale.exists()


def test_lazy_units_read_a_run_of_units_in_one_opening(tmp_path):
    out = tmp_path / "g.h5"
    with artifacts.write_artifact(out, "gap") as f:
        for u in ("A", "B", "C"):
            artifacts.put(f, f"units/{u}/v", [float(ord(u))], "1", "value")
    units = artifacts.LazyUnits(out, "gap", ["A", "B", "C"],
                                lambda f, unit, p: float(f[f"units/{unit}/v"][0]))
    assert list(units.each()) == [("A", 65.0), ("B", 66.0), ("C", 67.0)]
    assert list(units.each(["C", "A"])) == [("C", 67.0), ("A", 65.0)]
    with pytest.raises(KeyError):
        list(units.each(["A", "D"]))


def _stored(obj) -> dict:
    """Each attribute's stored type and value."""
    return {k: (obj.attrs.get_id(k).dtype, obj.attrs.get_id(k).shape, obj.attrs[k])
            for k in obj.attrs}


def test_fast_writes_store_what_h5py_stores(tmp_path):
    """put and set_attrs take the low-level path for numbers and strings: the file must
    hold what h5py's own create_dataset / attrs[...] = would (types, shapes, chunks,
    filters, values), and read back alike through get."""
    values = {"text": "débit", "empty": "", "real": 1.5, "whole": 3, "flag": True,
              "np_flag": np.bool_(False), "np_int": np.int64(-4), "np_real": np.float32(2.5),
              "vector": np.array([1.0, np.nan]), "ints": np.arange(3), "json": '{"a": 1}',
              "nested": [1, 2]}
    arrays = {"f": np.linspace(0, 1, 7), "i": np.arange(5, dtype=np.int64),
              "i8": np.zeros((3, 4), np.int8), "b": np.array([True, False]),
              "big": np.random.default_rng(0).normal(size=(40, 3000)),
              "scalar": np.float64(2.0), "strings": ["a", "bc"], "none": np.zeros(0)}
    path = tmp_path / "a.h5"
    with h5py.File(path, "w") as f:
        fast, slow = f.create_group("fast"), f.create_group("slow")
        artifacts.set_attrs(fast, values)
        for k, v in values.items():
            slow.attrs[k] = v
        for k, v in arrays.items():
            artifacts.put(fast, k, v, "m", f"{k} data")
            kw = {"fletcher32": True} if np.ndim(v) and np.size(v) and \
                np.asarray(v).dtype.kind in "fiub" else {}
            data = np.array(v, dtype=h5py.string_dtype()) if k == "strings" else v
            ds = slow.create_dataset(k, data=data, **kw)
            ds.attrs["units"], ds.attrs["description"] = "m", f"{k} data"
        # Overwriting an attribute replaces it, as attrs[...] = does.
        artifacts.set_attrs(fast, {"whole": 4})
        slow.attrs["whole"] = 4
    with h5py.File(path, "r") as f:
        a, b = _stored(f["fast"]), _stored(f["slow"])
        assert a.keys() == b.keys()
        for k in a:
            assert a[k][:2] == b[k][:2], k
            assert type(a[k][2]) is type(b[k][2]) and np.array_equal(
                a[k][2], b[k][2], equal_nan=isinstance(a[k][2], np.ndarray)
                and a[k][2].dtype.kind == "f"), k
        for k in arrays:
            x, y = f["fast"][k], f["slow"][k]
            assert (x.dtype, x.shape, x.chunks, x.compression, x.fletcher32) == \
                (y.dtype, y.shape, y.chunks, y.compression, y.fletcher32), k
            assert _stored(x).keys() == _stored(y).keys()
            got, want = artifacts.get(f["fast"], k), artifacts.get(f["slow"], k)
            assert type(got) is type(want) and np.array_equal(got, want), k
            assert np.array_equal(got, y[()] if k != "strings" else ["a", "bc"]), k
        with pytest.raises(ArtifactError, match="dataset /fast/missing is missing"):
            artifacts.get(f["fast"], "missing")
