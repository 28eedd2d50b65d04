"""Every --json output is strict JSON: an output that comes near 0 has no relative error
(NaN inside), which must print as null, not NaN."""
from __future__ import annotations

from ..conftest import CONFIGS, write_yaml
from ..unit.test_jsontext import strict_loads
from .test_cli_errors import twinmon


def test_reduce_json_is_strict_when_the_relative_error_is_undefined(tmp_path):
    # The supply switched on at 0.35 s: the speed is exactly 0 for the first samples, so
    # the relative error is undefined (NaN) and the log transform impossible.
    cfg = write_yaml(tmp_path / "dc.yaml", {
        "extends": str(CONFIGS / "dcdrive.yaml"),
        "model": {"fixed": {"supply.delay": 0.35}, "channels": {},
                  "effects": {"supply.delay": None}},
        "simulate": {"train_size": 16, "test_size": 4, "executor": "serial"},
        "reduce": {"transform": "none", "max_modes": 3}})
    r = twinmon("simulate", "-c", cfg, "-o", tmp_path / "sims.h5", "--json")
    assert r.returncode == 0, r.stderr
    strict_loads(r.stdout)
    r = twinmon("reduce", "-c", cfg, "--simulations", tmp_path / "sims.h5",
                "-o", tmp_path / "sur.h5", "--json")
    assert r.returncode == 0, r.stderr
    out = strict_loads(r.stdout)
    assert out["test"]["max_rel_error"] is None and out["test"]["max_range_error"] > 0
