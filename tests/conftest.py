"""Shared fixtures: the real FMU (built once per session) and small configs in tmp folders."""
from __future__ import annotations

from pathlib import Path

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


def write_yaml(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


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
