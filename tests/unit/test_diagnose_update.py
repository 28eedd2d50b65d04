"""``diagnose --update``: a gap.h5 of the first years, updated with the years added since,
equals a full run's gap.h5 dataset for dataset (the real FMU, a few small units); a unit whose
data changed is redone; another config or FMU, or a gap.h5 without the per-year records, is
refused; the DC drive (a second model) updates like the pump."""
from __future__ import annotations

import copy
import dataclasses
import json
import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from twinmon.artifacts import file_sha256
from twinmon.config import config_from_mapping, load_config
from twinmon.diagnose import SECTIONS, diagnose, read_gap
from twinmon.diagnose.artifact import gap_differences
from twinmon.diagnose.update import check_update
from twinmon.errors import ArtifactError
from twinmon.fabricate import fabricate
from twinmon.fmu import resolve_fmu
from twinmon.observations import read_observations, write_observations

from ..conftest import CONFIGS, first_years

PUMP = CONFIGS / "pump.yaml"
HEALTHY = {"trajectories": {"motor_damping": {"start": 10.0, "slope": 0.1},
                            "pump_coef": {"start": 3.7, "slope": -0.02}}}


def fleet_cfg(base, units: dict, years: int, **fab):
    raw = copy.deepcopy(dict(load_config(base).raw))
    raw["fabricate"] = {**raw.get("fabricate", {}), "years": years, "seed": 11,
                        "units": units, **fab}
    return config_from_mapping(raw, base)


def differences(a_path, b_path) -> list:
    """Fields of two gap.h5 that differ (bits; NaN equal to NaN), the units' own cost left
    out (``gap_differences``)."""
    return gap_differences(a_path, b_path)


@pytest.fixture(scope="module")
def pump(tmp_path_factory):
    """Three pump units over 4 years (noise recorded): A and C healthy, B with a start
    delay from year 2; the full run's gap.h5; the first 2 years of A and B diagnosed."""
    tmp = tmp_path_factory.mktemp("diag_update")
    cfg = fleet_cfg(PUMP, {"A": HEALTHY, "C": HEALTHY,
                           "B": {**HEALTHY, "effects": {"motor.start_delay":
                                                        {"value": 1.5, "onset": 2}}}},
                    years=4, noise_std=4.0)
    fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
    full = diagnose(cfg, tmp / "obs.h5", tmp / "full.h5", workers=1)
    first_years(tmp / "obs.h5", tmp / "obs2.h5", 2, units=("A", "B"))
    diagnose(cfg, tmp / "obs2.h5", tmp / "gap2.h5", workers=1)
    return cfg, tmp, full


def test_update_equals_a_full_run(pump, tmp_path):
    """Years 1-2 of A and B, then years 1-4 and a new unit C on two workers: gap.h5 equals
    the full run's, the per-year records included; only the new years were fitted."""
    cfg, tmp, full = pump
    out = tmp_path / "gap.h5"
    shutil.copy(tmp / "gap2.h5", out)
    s = diagnose(cfg, tmp / "obs.h5", out, workers=2, update=True)
    assert s.update == {"from": str(out), "kept_years": 4, "new_years": 8, "new_units": ["C"],
                        "redone_units": [], "dropped_units": []}
    assert differences(tmp / "full.h5", out) == []
    assert s.units["B"].verdict == full.units["B"].verdict == "effect"
    # The kept years' base fit and screening were not run again.
    assert s.units["A"].fmu_runs < full.units["A"].fmu_runs
    assert s.units["C"].fmu_runs == full.units["C"].fmu_runs
    assert s.as_dict()["update"]["kept_years"] == 4

    # Nothing new: every year kept, the rest recomputed, the same file again.
    again = diagnose(cfg, tmp / "obs.h5", out, workers=1, update=True)
    assert again.update["kept_years"] == 12 and again.update["new_years"] == 0
    assert differences(tmp / "full.h5", out) == []

    # A unit gone from the observations is left out, as a full run would.
    first_years(tmp / "obs.h5", tmp_path / "ab.h5", 4, units=("A", "B"))
    s = diagnose(cfg, tmp_path / "ab.h5", out, workers=1, update=True)
    assert s.update["dropped_units"] == ["C"] and sorted(read_gap(out).units) == ["A", "B"]


def test_a_unit_whose_data_changed_is_redone(pump, tmp_path):
    cfg, tmp, full = pump
    obs = read_observations(tmp / "obs.h5")
    a = obs.units["A"]
    flow = a.channels["m_flow"].copy()
    flow[0, 5] += 1.0                      # a corrected sample of year 1
    units = {**obs.units, "A": dataclasses.replace(a, channels={"m_flow": flow})}
    write_observations(tmp_path / "fixed.h5", dataclasses.replace(obs, units=units))
    out = tmp_path / "gap.h5"
    shutil.copy(tmp / "gap2.h5", out)
    s = diagnose(cfg, tmp_path / "fixed.h5", out, workers=1, update=True)
    assert s.update["redone_units"] == ["A"] and s.update["kept_years"] == 2
    diagnose(cfg, tmp_path / "fixed.h5", tmp_path / "fixed_full.h5", workers=1)
    assert differences(tmp_path / "fixed_full.h5", out) == []


def test_another_config_fmu_or_version_or_an_older_gap_is_refused(pump, tmp_path):
    cfg, tmp, _ = pump
    out = tmp_path / "gap.h5"
    shutil.copy(tmp / "gap2.h5", out)
    before = file_sha256(out)
    raw = copy.deepcopy(dict(cfg.raw))
    raw["diagnose"] = {**raw.get("diagnose", {}), "bic_gain": 12.0}
    other = config_from_mapping(raw, PUMP)
    with pytest.raises(ArtifactError, match=r"gap\.h5: made with another config "
                                            r"\(diagnose\.bic_gain 10\.0 -> 12\.0\)") as e:
        diagnose(other, tmp / "obs.h5", out, workers=1, update=True)
    assert "\n" not in str(e.value) and "without --update" in str(e.value)
    assert file_sha256(out) == before
    # Settings that cannot change a result are no part of it.
    raw["diagnose"]["bic_gain"] = cfg.diagnose.bic_gain
    raw["diagnose"]["workers"] = 2
    check_update(config_from_mapping(raw, PUMP), resolve_fmu(cfg.model.fmu), out, SECTIONS)

    fmu2 = tmp_path / "other.fmu"
    fmu2.write_bytes(resolve_fmu(cfg.model.fmu).read_bytes() + b"\0")
    with pytest.raises(ArtifactError, match=r"gap\.h5: made through another FMU.*other\.fmu"):
        check_update(cfg, fmu2, out, SECTIONS)

    # Another twinmon's gap.h5: its per-year fits may come from other code (another fit
    # tolerance), so a continued run would be neither version's full run.
    old = tmp_path / "old.h5"
    shutil.copy(out, old)
    with h5py.File(old, "r+") as f:
        f.attrs["twinmon_version"] = "0.0.9"
    before = file_sha256(old)
    with pytest.raises(ArtifactError, match=r"old\.h5: made by twinmon 0\.0\.9, this is "
                                            r"twinmon .*re-run diagnose without --update"):
        diagnose(cfg, tmp / "obs.h5", old, workers=1, update=True)
    assert file_sha256(old) == before

    # A gap.h5 of a twinmon without the per-year records: refused, still read by the report.
    with h5py.File(out, "r+") as f:
        del f["units/B/cache"], f["units/B/cache_gains"]
    with pytest.raises(ArtifactError, match=r"/units/B lacks the per-year records"):
        diagnose(cfg, tmp / "obs.h5", out, workers=1, update=True)
    g = read_gap(out, cache=True)
    assert g.units["B"].cache is None and g.units["A"].cache.n_years == 2


def test_a_gap_of_the_first_layout_reads_and_is_not_updated(pump, tmp_path):
    """``twinmon.gap/1`` (a dataset per array, an attribute per value, -1 for none): the
    report still reads it, field for field; --update refuses it in one line."""
    from twinmon import artifacts
    from twinmon.diagnose.artifact import _ARRAYS, _ATTRS, _JSON_ATTRS
    cfg, tmp, _ = pump
    new = read_gap(tmp / "full.h5")
    old = tmp_path / "gap.h5"
    with h5py.File(tmp / "full.h5", "r") as src, h5py.File(old, "w") as f:
        for k, v in src.attrs.items():
            f.attrs[k] = v
        f.attrs["schema"] = "twinmon.gap/1"
        for k in ("time", "windows"):
            src.copy(src[k], f, k)
        for unit, g in new.units.items():
            grp = f.create_group(f"units/{unit}")
            for name in _ARRAYS:
                data = np.asarray(getattr(g, name))
                artifacts.put(grp, name, data.astype(np.int8) if data.dtype == bool else data,
                              "1", "d")
            for name in _ATTRS:
                grp.attrs[name] = -1 if getattr(g, name) is None else getattr(g, name)
            for name in _JSON_ATTRS:
                grp.attrs[name] = artifacts.json_attr(getattr(g, name))
    # Every field equal but the records an update continues from, which it never had.
    assert differences(tmp / "full.h5", old) == [".schema"] + [f"/units/{u}: cache"
                                                              for u in new.units]
    with pytest.raises(ArtifactError, match=r"gap\.h5: written by an older twinmon, without "
                                            r"the per-year records .*without --update$"):
        diagnose(cfg, tmp / "obs.h5", old, workers=1, update=True)


def test_no_gap_yet_is_a_full_run_and_the_cli_says_what_it_kept(pump, tmp_path):
    from twinmon.cli import main
    cfg, tmp, _ = pump
    cfg_path = tmp_path / "c.yaml"
    cfg_path.write_text(json.dumps({"extends": str(PUMP), "fabricate": cfg.raw["fabricate"]}))
    args = ["diagnose", "-c", str(cfg_path), "-o", str(tmp_path / "gap.h5"), "-j", "1",
            "--update"]
    r = CliRunner().invoke(main, args + ["--observations", str(tmp / "obs2.h5"), "--json"])
    assert r.exit_code == 0, r.output
    u = json.loads(r.stdout)["update"]
    assert u["from"] is None and u["new_years"] == 4 and u["new_units"] == ["A", "B"]
    r = CliRunner().invoke(main, args + ["--observations", str(tmp / "obs.h5")])
    assert r.exit_code == 0, r.output
    assert ("diagnose --update: 4 unit-year(s) of base fits and screening kept from "
            f"{tmp_path / 'gap.h5'}, 8 run") in r.stderr
    assert "new units: C" in r.stderr


def test_the_dc_drive_updates_like_the_pump(tmp_path):
    """The second model (fmus/DCDrive, its gap fleet: a tachometer lag from year 5 on one
    unit): 4 years updated to 5 equal the 5-year run."""
    cfg = fleet_cfg(CONFIGS / "dcdrive_gap.yaml",
                    load_config(CONFIGS / "dcdrive_gap.yaml").raw["fabricate"]["units"],
                    years=5)
    fabricate(cfg, tmp_path / "obs.h5", tmp_path / "truth.h5")
    full = diagnose(cfg, tmp_path / "obs.h5", tmp_path / "full.h5", workers=1)
    first_years(tmp_path / "obs.h5", tmp_path / "obs4.h5", 4)
    diagnose(cfg, tmp_path / "obs4.h5", tmp_path / "gap.h5", workers=1)
    s = diagnose(cfg, tmp_path / "obs.h5", tmp_path / "gap.h5", workers=1, update=True)
    assert s.update["kept_years"] == 4 * len(full.units) and not s.update["redone_units"]
    assert differences(tmp_path / "full.h5", tmp_path / "gap.h5") == []
    assert sum(g.fmu_runs for g in s.units.values()) < sum(g.fmu_runs for g in full.units.values())
