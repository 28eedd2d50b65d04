"""Executors fail fast: a worker that cannot open the FMU ends the batch with its reason."""
from __future__ import annotations

import signal

import numpy as np
import pytest

from twinmon.errors import ConfigError, SimulationError
from twinmon.executors import (ProcessExecutor, SerialExecutor, SimulationSpec, make_executor,
                               one_blas_thread, start_pool)
from twinmon.executors.local import shutdown_pool

TIMES = np.arange(2.0, 50.0 + 1e-9, 2.0)


@pytest.fixture
def alarm():
    """Fail (instead of hanging the suite) if the block takes more than 60 s."""
    def on_alarm(*_):
        raise TimeoutError("executor hung")
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(60)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


@pytest.mark.parametrize("executor", [SerialExecutor(), ProcessExecutor(2)],
                         ids=["serial", "process"])
def test_a_worker_that_cannot_open_the_fmu_ends_the_batch(fmu_path, executor, alarm):
    spec = SimulationSpec(fmu=fmu_path, outputs=("no.such.output",), times=TIMES)
    params = [(i, {"motor.D": 10.0}) for i in range(16)]
    with pytest.raises(SimulationError, match=r"no.such.output") as exc:
        list(executor.map(spec, params))
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("executor", [SerialExecutor(), ProcessExecutor(2)],
                         ids=["serial", "process"])
def test_a_corrupt_fmu_ends_the_batch(tmp_path, executor, alarm):
    bad = tmp_path / "truncated.fmu"
    bad.write_bytes(b"PK\x03\x04" + b"\0" * 40)
    spec = SimulationSpec(fmu=bad, outputs=("y",), times=TIMES)
    with pytest.raises(SimulationError, match=r"truncated.fmu"):
        list(executor.map(spec, [(i, {}) for i in range(16)]))


def test_process_results_equal_serial(fmu_path, alarm):
    spec = SimulationSpec(fmu=fmu_path, outputs=("sensor.m_flow",), times=TIMES)
    params = [(i, {"motor.D": 5.0 + i, "pump.b2": 3.0}) for i in range(12)]
    a = {r.index: r.outputs["sensor.m_flow"] for r in SerialExecutor().map(spec, params)}
    b = {r.index: r.outputs["sensor.m_flow"] for r in ProcessExecutor(2).map(spec, params)}
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def blas_threads() -> list:
    """The thread counts of this process's BLAS libraries (numpy's and scipy's OpenBLAS)."""
    import scipy.linalg  # noqa: F401 -- loads scipy's own OpenBLAS
    from threadpoolctl import threadpool_info
    return sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})


def test_a_pool_worker_runs_blas_on_one_thread(alarm):
    pool = start_pool(2)
    try:
        assert pool.submit(blas_threads).result() == [1]
    finally:
        shutdown_pool(pool)


def test_one_blas_thread_as_a_block_gives_the_threads_back():
    before = blas_threads()
    with one_blas_thread():
        assert blas_threads() == [1]
    assert blas_threads() == before


def test_negative_worker_count_is_a_config_error():
    with pytest.raises(ConfigError, match="got -5"):
        make_executor("process", -5)


def _worker_tmp() -> tuple:
    """(pid, the folder a worker's extracted FMU lives in)."""
    import os

    from twinmon.executors import local
    return os.getpid(), str(local._worker_model._tmpdir)


def test_a_killed_worker_leaves_no_extracted_fmu_behind(fmu_path, alarm):
    """A worker killed with SIGKILL cannot remove its extracted FMU; it lives in the pool's
    folder, which goes with the pool."""
    import gc
    import os
    from pathlib import Path

    from twinmon.executors.local import _init_worker, start_pool
    spec = SimulationSpec(fmu=fmu_path, outputs=("sensor.m_flow",), times=TIMES)
    pool = start_pool(1, _init_worker, (spec,))
    pid, extracted = pool.submit(_worker_tmp).result()
    extracted = Path(extracted)
    assert extracted.is_dir() and extracted.parent.name.startswith("twinmon-pool-")
    os.kill(pid, signal.SIGKILL)
    pool.shutdown(wait=True)
    del pool
    gc.collect()
    assert not extracted.exists() and not extracted.parent.exists()
