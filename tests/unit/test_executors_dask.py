"""executor: dask on a LocalCluster: the process executor's arrays, bit for bit; a scheduler
out of reach fails in one line within its timeout; Ctrl-C exits 130; no worker outlives the
command."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest

from twinmon.calibrate import calibrate, read_posterior
from twinmon.config import load_config
from twinmon.errors import SimulationError
from twinmon.executors import ProcessExecutor, SimulationSpec
from twinmon.executors.dask import DaskExecutor
from twinmon.observations import Observations, UnitObservations, write_observations
from twinmon.reduce import read_surrogate, reduce
from twinmon.simulate import simulate

from ..conftest import CONFIGS, write_yaml

TIMES = np.arange(2.0, 50.0 + 1e-9, 2.0)
OUTPUTS = ("sensor.m_flow", "motor.w")


def _workers_alive() -> set[int]:
    return {p.pid for p in psutil.Process().children(recursive=True) if p.is_running()}


@pytest.fixture
def alarm():
    """Fail (instead of hanging the suite) if the block takes more than 90 s."""
    def on_alarm(*_):
        raise TimeoutError("executor hung")
    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(90)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def test_dask_batch_equals_process_and_leaves_no_worker(fmu_path, alarm):
    spec = SimulationSpec(fmu=fmu_path, outputs=OUTPUTS, times=TIMES)
    params = [(i, {"motor.D": 6.0 + 0.5 * i, "pump.b2": 3.0 + 0.05 * i}) for i in range(24)]
    want = {r.index: r.outputs for r in ProcessExecutor(2).map(spec, params)}
    before = _workers_alive()
    with DaskExecutor(2) as ex:
        # Two batches on one cluster: the second reuses each worker's FMU instance.
        got = {r.index: r.outputs for r in ex.map(spec, params[:10])}
        got.update({r.index: r.outputs for r in ex.map(spec, params[10:])})
        assert ex.workers == 2
        assert len(_workers_alive() - before) >= 2
    assert got.keys() == want.keys()
    for i in want:
        for o in OUTPUTS:
            assert np.array_equal(got[i][o], want[i][o]), (i, o)
    # The LocalCluster is closed with the executor: no worker process outlives it.
    deadline = time.monotonic() + 10
    while _workers_alive() - before and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _workers_alive() - before


def test_a_dask_worker_runs_blas_on_one_thread(alarm):
    from twinmon.executors.dask import open_dask_pool

    from .test_executors import blas_threads
    pool = open_dask_pool(2)
    try:
        assert pool.submit(blas_threads).result() == [1]
    finally:
        pool.shutdown()


def test_a_dask_worker_that_cannot_open_the_fmu_names_the_users_file(fmu_path, alarm):
    spec = SimulationSpec(fmu=fmu_path, outputs=("no.such.output",), times=TIMES)
    with pytest.raises(SimulationError, match="no.such.output") as exc:
        list(DaskExecutor(2).map(spec, [(i, {"motor.D": 10.0}) for i in range(8)]))
    assert str(fmu_path) in str(exc.value) and "\n" not in str(exc.value)


@pytest.fixture(scope="module")
def surrogate_setup(tmp_path_factory, fmu_path):
    """A real (small) surrogate: FMU runs and reduce."""
    tmp = tmp_path_factory.mktemp("dask_calibrate")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 32, "test_size": 4, "executor": "serial"},
        "calibrate": {"chains": 2, "samples": 200, "burn_in": 100, "noise_std": 4.0,
                      "ess_warn": 100, "max_extensions": 1}})
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    return cfg_path, tmp


def test_calibrate_on_dask_gives_the_process_pools_posterior(surrogate_setup, tmp_path, alarm):
    cfg_path, tmp = surrogate_setup
    sur = read_surrogate(tmp / "sur.h5")
    rng = np.random.default_rng(0)
    units = {}
    for name, X in {"A": [[10, 3.6], [10.5, 3.55]], "B": [[14, 3.3], [14.2, 3.2]]}.items():
        clean = sur.predict(np.atleast_2d(X))
        units[name] = UnitObservations(np.array([1, 2]),
                                       {"m_flow": clean + 4.0 * rng.standard_normal(clean.shape)})
    obs = tmp_path / "obs.h5"
    write_observations(obs, Observations(sur.time, units, obs))
    posts = {}
    for kind in ("process", "dask"):
        c = load_config(cfg_path, ["calibrate.workers=2", f"calibrate.executor={kind}"])
        calibrate(c, tmp / "sur.h5", obs, tmp_path / f"{kind}.h5")
        posts[kind] = read_posterior(tmp_path / f"{kind}.h5")
    for u in ("A", "B"):
        a, b = posts["process"].units[u], posts["dask"].units[u]
        assert np.array_equal(a.samples, b.samples) and np.array_equal(a.mean, b.mean)


def _cli(*args):
    return [sys.executable, "-m", "twinmon", *map(str, args)]


@pytest.fixture
def small_cfg(tmp_path, fmu_path):
    return write_yaml(tmp_path / "small.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 8, "test_size": 0}})


def test_a_scheduler_out_of_reach_fails_fast_in_one_line(small_cfg, tmp_path):
    address = "tcp://127.0.0.1:9"          # nothing listens there: connection refused
    t0 = time.monotonic()
    r = subprocess.run(_cli("simulate", "-c", small_cfg, "--set", "simulate.executor=dask",
                            "--set", f"dask.address={address}", "--set", "dask.timeout=2",
                            "-o", tmp_path / "s.h5"),
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert time.monotonic() - t0 < 30
    assert r.returncode == 3, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and address in lines[0] and "dask.address" in lines[0], r.stderr
    # Refused at once, and said so (it waited the timeout twice, then blamed a handshake).
    assert "Connection refused" in lines[0] and "handshake" not in lines[0]
    assert not list(tmp_path.glob("s.h5*"))         # no partial file left behind


@pytest.mark.parametrize("address", ["foo", "tcp://127.0.0.1", "inproc://x",
                                     "tls://127.0.0.1:1", "ucx://127.0.0.1:1"])
def test_an_address_that_is_no_tcp_scheduler_is_a_config_error(address):
    """Another transport or no port: one config line naming the key, not a traceback from
    inside Dask (tls, ucx) or a wait for the timeout twice."""
    from twinmon.config import load_config
    from twinmon.config.dask import scheduler_host_port
    from twinmon.errors import ConfigError
    assert scheduler_host_port(address) is None
    with pytest.raises(ConfigError, match=r"dask.address: expected a TCP scheduler address"):
        load_config(CONFIGS / "pump.yaml", [f"dask.address={address}"])
    assert scheduler_host_port("tcp://10.0.0.5:8786") == ("10.0.0.5", 8786)
    assert scheduler_host_port("[::1]:8786") == ("::1", 8786)


def test_ctrl_c_on_dask_exits_130_and_leaves_no_worker(small_cfg, tmp_path):
    scratch = tmp_path / "tmp"          # the command's $TMPDIR: where its workers' files go
    scratch.mkdir()
    # A design long enough to be interrupted mid-way: 400 Model Exchange runs take about 1 s
    # on 2 idle cores, 20 000 about a minute (Ctrl-C comes after a second).
    p = subprocess.Popen(_cli("simulate", "-c", small_cfg, "--set", "simulate.executor=dask",
                              "--set", "simulate.workers=2", "--set", "simulate.train_size=20000",
                              "--set", "model.fmi_type=ModelExchange", "-o", tmp_path / "s.h5"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         cwd=tmp_path, start_new_session=True,
                         env={**os.environ, "TMPDIR": str(scratch)})
    parent = psutil.Process(p.pid)
    deadline = time.monotonic() + 60
    workers: list = []
    while time.monotonic() < deadline and p.poll() is None:
        workers = parent.children(recursive=True)
        if len(workers) >= 2:
            break
        time.sleep(0.2)
    assert len(workers) >= 2, "the local Dask workers never started"
    time.sleep(1.0)                                   # some runs under way
    assert p.poll() is None, "simulate ended before it could be interrupted"
    os.killpg(p.pid, signal.SIGINT)                    # what a terminal's Ctrl-C does
    try:
        _, err = p.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        pytest.fail("still running 20 s after Ctrl-C")
    assert p.returncode == 130, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "resume" in lines[0], err
    assert not [w for w in workers if w.is_running() and w.status() != psutil.STATUS_ZOMBIE]
    assert not list(scratch.iterdir())



def test_a_worker_that_lacks_the_fmu_runs_the_copy_it_was_sent(fmu_path, tmp_path, alarm):
    """The FMU travels with the pool: a worker that cannot see the user's file (another
    machine) runs a copy keyed by content, and errors still name the user's file."""
    from twinmon.executors.dask import DaskConnection, DaskPool, _open_model, _work_chunk
    params = [(i, {"motor.D": 6.0 + i, "pump.b2": 3.2}) for i in range(4)]
    spec = SimulationSpec(fmu=fmu_path, outputs=OUTPUTS, times=TIMES)
    want = {r.index: r.outputs for r in ProcessExecutor(2).map(spec, params)}
    with DaskConnection(1) as conn:
        for outputs in (OUTPUTS, ("no.such.output",)):
            gone = tmp_path / outputs[0] / "PumpCircuit.fmu"
            gone.parent.mkdir()
            gone.write_bytes(fmu_path.read_bytes())
            pool = DaskPool(conn, _open_model,
                            (SimulationSpec(fmu=gone, outputs=outputs, times=TIMES),),
                            files=(gone,))
            gone.unlink()                      # read and sent; no longer here for the worker
            if outputs == OUTPUTS:
                got = [r for rs in pool.as_completed(_work_chunk, [params]) for r in rs]
                assert all(np.array_equal(r.outputs[o], want[r.index][o])
                           for r in got for o in OUTPUTS)
            else:
                with pytest.raises(SimulationError) as exc:
                    list(pool.as_completed(_work_chunk, [params]))
                assert str(gone) in str(exc.value) and "twinmon-dask-files" not in str(exc.value)
            pool.shutdown()


def test_forecast_on_dask_gives_the_process_pools_forecast(surrogate_setup, tmp_path, alarm):
    """forecast's units on a LocalCluster (simulate.executor: dask; the surrogate and the FMU
    spec sent once per worker) give the process pool's arrays, bit for bit."""
    from twinmon.forecast import forecast, read_forecast

    from .test_forecast import BOTH, HEALTHY, PUMP, write_synthetic_posterior
    cfg_path, tmp = surrogate_setup
    fc = {}
    for kind in ("process", "dask"):
        c = load_config(cfg_path, [f"simulate.executor={kind}", "forecast.samples=100",
                                   "forecast.observed_samples=20", "forecast.horizon=3"])
        post = write_synthetic_posterior(tmp_path / "post.h5", c,
                                         {"H": HEALTHY, "P": PUMP, "B": BOTH}, n_s=60)
        forecast(c, post, tmp / "sur.h5", tmp_path / f"{kind}.h5", workers=2)
        fc[kind] = read_forecast(tmp_path / f"{kind}.h5")
    for u in ("H", "P", "B"):
        a, b = fc["process"].units[u], fc["dask"].units[u]
        assert np.array_equal(a.samples, b.samples)
        assert np.array_equal(a.indicator, b.indicator, equal_nan=True)
        assert np.array_equal(a.source, b.source) and a.plan == b.plan
    assert (fc["process"].units["B"].source > 0).any()      # FMU runs on the workers too


def test_what_a_task_leaves_open_is_closed_with_its_pool():
    # On a Dask worker (a pool's token set) a closer registers once and runs when the pool
    # is forgotten; outside a Dask pool's task it is not kept.
    from twinmon.executors import dask as dx
    calls = []

    def close():
        calls.append(1)

    dx.close_with_pool(close)
    assert dx._state.closers == []
    dx._state.token = "pool"
    try:
        dx.close_with_pool(close)
        dx.close_with_pool(close)
        assert dx._state.closers == [close]
        dx._forget("pool")
        assert calls == [1] and dx._state.closers == [] and dx._state.token is None
    finally:
        dx._forget()
