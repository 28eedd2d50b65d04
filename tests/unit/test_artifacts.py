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


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    out = tmp_path / "a.h5"
    stale = tmp_path / ".a.h5.999999999.tmp"             # no such process
    stale.write_bytes(b"half")
    with artifacts.write_artifact(out, "gap") as f:
        artifacts.put(f, "v", [1.0], "1", "first")
    assert not stale.exists()
