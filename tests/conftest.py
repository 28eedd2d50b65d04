"""Shared fixtures: the real FMU (built once per test run) and small configs in tmp folders."""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture(scope="session")
def fmu_path() -> Path:
    """The real PumpCircuit FMU, built from its C sources (cached by hash)."""
    from twinmon.fmu import build_fmu
    return build_fmu(ROOT / "fmus" / "PumpCircuit")


def made_once(tmp_path_factory, name: str, make):
    """``make(folder)`` once per test run, its (picklable) result returned.

    Under pytest-xdist the first worker to ask makes it in a folder of the run's shared base
    temp folder while holding a lock; the others wait on the lock and read the pickled
    result (a pipeline fixture used by modules on both workers is made once, not once per
    worker). Without xdist, a plain session fixture's folder.
    """
    import fcntl
    import os
    import pickle
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        return make(tmp_path_factory.mktemp(name))
    shared = tmp_path_factory.getbasetemp().parent
    done = shared / f"{name}.pickle"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            folder = shared / name
            if folder.exists():          # a worker's attempt that failed
                import shutil
                shutil.rmtree(folder)
            folder.mkdir()
            result = make(folder)
            tmp = done.with_suffix(".tmp")
            tmp.write_bytes(pickle.dumps(result))
            tmp.replace(done)
        return pickle.loads(done.read_bytes())


def write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def first_years(src: Path, dst: Path, n: int, units=None) -> Path:
    """The observations of ``src`` cut to each unit's first ``n`` years, written to ``dst``
    (``units``: only these units), as a yearly update's earlier file."""
    import dataclasses

    import numpy as np

    from twinmon.observations import read_observations, write_observations
    obs = read_observations(src)
    out = {}
    for name, u in obs.units.items():
        if units is not None and name not in units:
            continue
        keep = np.asarray(u.years) <= n
        out[name] = dataclasses.replace(u, years=np.asarray(u.years)[keep],
                                        channels={c: v[keep] for c, v in u.channels.items()},
                                        events=[e for e in u.events if e.year <= n])
    write_observations(dst, dataclasses.replace(obs, units=out))
    return dst


@pytest.fixture
def small_config(tmp_path, fmu_path) -> Path:
    """The paper case with a small design (24 training + 8 test runs), serial executor."""
    return write_yaml(tmp_path / "small.yaml", {
        "extends": str(CONFIGS / "pump.yaml"),
        "simulate": {"train_size": 24, "test_size": 8, "executor": "serial"},
    })


@pytest.fixture
def small_fleet_config(tmp_path, fmu_path) -> Path:
    """The shipped fleet shortened to 4 years."""
    return write_yaml(tmp_path / "fleet_small.yaml", {
        "extends": str(CONFIGS / "fleet.yaml"),
        "fabricate": {"years": 4},
    })


@pytest.fixture(scope="session")
def calibrated_fleet(tmp_path_factory, fmu_path):
    """The shipped fleet through the real stages once per test run: simulate, reduce,
    fabricate (configs/fleet.yaml) and calibrate with the truth check.

    Returns (cfg, folder, calibrate summary); the folder holds sims.h5, sur.h5, fleet.h5,
    truth.h5 and post.h5.
    """
    return made_once(tmp_path_factory, "calibrated_fleet", _calibrate_fleet)


def _calibrate_fleet(tmp: Path):
    import time

    from twinmon.calibrate import calibrate
    from twinmon.config import load_config
    from twinmon.fabricate import fabricate
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    cfg = load_config(CONFIGS / "fleet.yaml")
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    fabricate(cfg, tmp / "fleet.h5", tmp / "truth.h5")
    start = time.perf_counter()
    summary = calibrate(cfg, tmp / "sur.h5", tmp / "fleet.h5", tmp / "post.h5",
                        truth_path=tmp / "truth.h5")
    print(f"\ncalibrate wall time {time.perf_counter() - start:.2f} s")
    return cfg, tmp, summary


def write_posterior_v1(path, src_path, post) -> None:
    """``post`` (unit -> UnitPosterior) in the first posterior layout
    (``twinmon.posterior/1``): a dataset per field and unit, every draw uncompressed, HDF5's
    earliest format, as twinmon wrote it before the per-unit record; root attributes copied
    from ``src_path``."""
    from twinmon import artifacts
    with h5py.File(src_path, "r") as src, h5py.File(path, "w") as dst:
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        dst.attrs["schema"] = "twinmon.posterior/1"
        for unit, p in post.items():
            g = dst.create_group(f"units/{unit}")
            for name in ("years", "samples", "mean", "median", "q05", "q95", "rhat", "ess",
                         "acceptance", "noise_std", "surrogate_var_ratio", "var", "chain_end"):
                ds = artifacts.put(g, name, np.asarray(getattr(p, name)), "u", "d")
                assert ds.compression is None
            artifacts.put(g, "digest", [str(v) for v in p.digest], "1", "d")
            for key, v in p.fit.items():
                v = np.asarray(v)
                if key == "status":
                    v = np.array([str(x) for x in v], dtype=h5py.string_dtype())
                elif v.dtype == bool:
                    v = v.astype(np.int8)
                artifacts.put(g, f"fit/{key}", v, "1", "d")
            g.attrs["noise_source"] = p.noise_source
