"""Fleet-sized artifacts and report: thinned, chunked, lazily read posterior and forecast; the
fleet overview of a report on 40 units.

A small real pipeline (FMU design, surrogate, three fabricated units over four years,
calibration) is run once; its posterior is then written again under 40 unit names (a healthy
unit, a pump fault and a motor fault, each about 13 times) and forecast for real, so the 40
forecasts differ by their Monte Carlo draws.
"""
from __future__ import annotations

import base64
import dataclasses
import json
import re
import time

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from twinmon import artifacts
from twinmon.calibrate import read_posterior, write_posterior
from twinmon.calibrate.posterior import thin_indices
from twinmon.config import load_config
from twinmon.errors import ArtifactError, ConfigError
from twinmon.forecast import read_forecast
from twinmon.observations import read_observations, write_observations
from twinmon.report import report

from ..conftest import CONFIGS, write_posterior_v1, write_yaml

N_UNITS = 40
DETAIL = 6


@pytest.fixture(scope="module")
def fleet(tmp_path_factory, fmu_path):
    """(cfg, cfg_path, folder, names): folder holds sur.h5, sims.h5, the 3-unit real run
    (obs3.h5, post3.h5) and the 40-unit fleet (obs.h5, post.h5, fc.h5)."""
    from twinmon.calibrate import calibrate
    from twinmon.fabricate import fabricate
    from twinmon.forecast import forecast
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    tmp = tmp_path_factory.mktemp("fleet_scale")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "fleet.yaml"),
        "simulate": {"train_size": 40, "test_size": 8, "executor": "serial"},
        "calibrate": {"chains": 2, "samples": 300, "burn_in": 150, "workers": 1,
                      "sampler": "openturns",  # a fixed draw count (the thinning test)
                      "ess_warn": 100.0, "max_extensions": 1},
        # Four years cannot show most faults: every healthy verdict would be unreliable
        # and at risk, and the report's choice of units is what is tested here.
        "forecast": {"samples": 100, "observed_samples": 20, "horizon": 5,
                     "detectable_multiple": 0},
        "report": {"detail_units": DETAIL},
        "fabricate": {"years": 4, "units": {
            "Park": {"trajectories": {"motor_damping": {"start": 9.5, "slope": 0.05},
                                      "pump_coef": {"start": 3.75, "slope": -0.02}}},
            "Colt": {"trajectories": {"motor_damping": {"start": 10.5, "slope": 0.05},
                                      "pump_coef": {"start": 3.2, "slope": -0.25}}},
            "Monk": {"trajectories": {"motor_damping": {"start": 12.0, "slope": 3.0},
                                      "pump_coef": {"start": 3.65, "slope": -0.02}}},
        }},
    })
    cfg = load_config(cfg_path)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    fabricate(cfg, tmp / "obs3.h5", tmp / "truth3.h5")
    calibrate(cfg, tmp / "sur.h5", tmp / "obs3.h5", tmp / "post3.h5")

    post3, obs3 = read_posterior(tmp / "post3.h5"), read_observations(tmp / "obs3.h5")
    bases = list(post3.units)
    names = [f"{bases[i % 3]}{i // 3:02d}" for i in range(N_UNITS)]
    origin = {n: bases[i % 3] for i, n in enumerate(names)}
    write_posterior(tmp / "post.h5", {n: post3.units[origin[n]] for n in names},
                    post3.input_names, cfg, [], surrogate_id=artifacts.read_provenance(
                        tmp / "post3.h5").get("surrogate_id", ""))
    write_observations(tmp / "obs.h5", dataclasses.replace(
        obs3, units={n: obs3.units[origin[n]] for n in names}))
    forecast(cfg, tmp / "post.h5", tmp / "sur.h5", tmp / "fc.h5")
    return cfg, cfg_path, tmp, names


def _damage(path, dataset):
    """Overwrite the middle of the first stored chunk of ``dataset`` (fletcher32 finds it)."""
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(0)
    data = bytearray(path.read_bytes())
    mid = info.byte_offset + info.size // 2 - 16
    data[mid:mid + 32] = bytes((i * 37 + 11) % 256 for i in range(32))
    path.write_bytes(bytes(data))


# ---------------------------------------------------------------------------------------
# Posterior
# ---------------------------------------------------------------------------------------
def test_thinning_keeps_the_statistics_of_every_draw(fleet, tmp_path):
    cfg, cfg_path, tmp, _ = fleet
    full = read_posterior(tmp / "post3.h5").units["Colt"]       # 2 chains x 300 draws
    n_draws = full.samples.shape[1]
    assert n_draws == 600
    small = load_config(cfg_path, ["calibrate.keep_draws=100"])
    write_posterior(tmp_path / "thin.h5", {"Colt": full}, small.model.input_names, small, [])
    back = read_posterior(tmp_path / "thin.h5").units["Colt"]
    idx = thin_indices(n_draws, 100)
    assert np.array_equal(back.samples, full.samples[:, idx, :])
    # Every chain gives the same share, spread from its start to its end.
    per_chain = np.bincount(idx // 300)
    assert list(per_chain) == [50, 50] and np.all(np.diff(idx) == 6)
    # The statistics are those of all 600 draws, not of the 100 stored.
    for name in ("mean", "median", "q05", "q95", "rhat", "ess"):
        assert np.array_equal(getattr(back, name), getattr(full, name)), name
    assert np.allclose(back.mean, full.samples.mean(axis=1))
    assert not np.allclose(back.mean, back.samples.mean(axis=1), rtol=0, atol=1e-9)
    with h5py.File(tmp_path / "thin.h5", "r") as f:
        ds = f["units/Colt/samples"]
        assert ds.chunks == (1, 100, 2) and ds.compression == "gzip"
        assert ds.shuffle and ds.fletcher32
        assert ds.attrs["draws_total"] == 600


def test_reading_one_unit_reads_no_other(fleet, tmp_path):
    _, _, tmp, names = fleet
    copy = tmp_path / "post.h5"
    copy.write_bytes((tmp / "post.h5").read_bytes())
    victim, other = names[7], names[21]
    _damage(copy, f"units/{victim}/samples")
    with h5py.File(copy, "a") as f:
        del f[f"units/{names[30]}/record"]
    post = read_posterior(copy)                 # neither damage is seen here
    assert len(post.units) == N_UNITS and list(post.units) == sorted(names)   # HDF5 order
    assert victim in post.units and "Nobody" not in post.units
    assert post.units[other].samples.shape[0] == 4
    with pytest.raises(ArtifactError, match=str(copy.name)):
        post.units[victim]
    with pytest.raises(ArtifactError, match=f"/units/{names[30]}/record is missing"):
        post.units[names[30]]
    with pytest.raises(KeyError):
        post.units["Nobody"]


def test_a_posterior_replaced_after_opening_is_refused(fleet, tmp_path):
    _, _, tmp, names = fleet
    copy = tmp_path / "post.h5"
    copy.write_bytes((tmp / "post.h5").read_bytes())
    post = read_posterior(copy)
    post.units[names[0]]
    (tmp_path / "new.h5").write_bytes((tmp / "post3.h5").read_bytes())
    (tmp_path / "new.h5").replace(copy)
    assert post.units[names[0]] is not None               # kept from before
    with pytest.raises(ArtifactError, match="replaced or removed since it was opened"):
        post.units[names[1]]


def test_a_posterior_of_the_old_layout_reads(fleet, tmp_path):
    """A ``twinmon.posterior/1`` file reads as it did (its units field by field), and
    ``run`` takes it for out of date (``calibrate --update`` continuing from one: in
    test_calibrate_vectorised)."""
    _, _, tmp, _ = fleet
    new = read_posterior(tmp / "post3.h5")
    old = tmp_path / "old.h5"
    write_posterior_v1(old, tmp / "post3.h5", {u: new.units[u] for u in new.units})
    back = read_posterior(old)
    for unit in ("Park", "Colt", "Monk"):
        a, b = back.units[unit], new.units[unit]
        for name in ("years", "samples", "mean", "q95", "ess", "acceptance", "var",
                     "chain_end", "digest"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert a.status.tolist() == b.status.tolist()
        assert np.array_equal(a.fit["converged"], b.fit["converged"])
    prov = artifacts.read_provenance(tmp / "post3.h5")
    made_from = [r["path"] for r in prov["inputs"]]
    assert artifacts.is_up_to_date(tmp / "post3.h5", "posterior", prov["config"], made_from)
    assert not artifacts.is_up_to_date(old, "posterior", prov["config"], made_from)


# ---------------------------------------------------------------------------------------
# Forecast
# ---------------------------------------------------------------------------------------
def test_forecast_artifact_is_chunked_per_year_and_read_lazily(fleet, tmp_path):
    _, _, tmp, names = fleet
    with h5py.File(tmp / "fc.h5", "r") as f:
        g = f[f"units/{names[0]}"]
        for name in ("samples", "indicator", "nonphysical", "source", "indicator_observed"):
            ds = g[name]
            assert ds.chunks[0] == 1 and ds.chunks[1:] == ds.shape[1:], name
            # No Fletcher-32 on these: each chunk's zlib stream has its checksum (the damaged
            # unit below is found by it).
            assert ds.compression == "gzip" and ds.shuffle, name
    copy = tmp_path / "fc.h5"
    copy.write_bytes((tmp / "fc.h5").read_bytes())
    _damage(copy, f"units/{names[3]}/indicator")
    fc = read_forecast(copy)
    assert list(fc.units) == sorted(names)
    u = fc.units[names[4]]
    assert u.samples.shape == (5, 100, 2) and u.indicator.shape == (5, 100)
    with pytest.raises(ArtifactError, match=copy.name):
        fc.units[names[3]]


# ---------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet_report(fleet):
    cfg, _, tmp, _ = fleet
    out = tmp / "report"
    start = time.perf_counter()
    s = report(cfg, out, observations=tmp / "obs.h5", posterior=tmp / "post.h5",
               forecast=tmp / "fc.h5")
    return s, out, time.perf_counter() - start


def test_a_large_fleet_opens_on_its_overview(fleet, fleet_report):
    cfg, _, tmp, names = fleet
    s, out, seconds = fleet_report
    text = (out / "index.html").read_text()
    fl = s.fleet
    assert fl is not None and sorted(fl["ranking"]) == sorted(names)
    # The overview comes first, and ranks every unit by its largest P(unsafe).
    assert text.index("Fleet overview") < text.index("Units drawn in detail") \
        < text.index('id="observations"')
    rows = re.findall(r"<tr><td class='num'>(\d+)</td><td class='unit'>(?:<a [^>]*>)?([^<]+)",
                      text)
    assert [u for _, u in rows] == fl["ranking"]
    p = [s.units[u].p_unsafe_max for u in fl["ranking"]]
    assert all(a >= b for a, b in zip(p, p[1:]))
    assert sum(fl["counts"].values()) == N_UNITS
    # Per-unit figures for the units at risk only, at most report.detail_units of them.
    assert 0 < len(fl["detail"]) <= DETAIL < len(fl["at_risk"])
    assert fl["detail"] == [u for u in fl["ranking"] if u in fl["at_risk"]][:DETAIL]
    drawn = {u for f in s.figures for u in names if re.search(rf"\b{u}\b", f["title"])}
    assert drawn == set(fl["detail"])
    assert {"fleet_failure", "fig6_estimates_1", "fig7_trends_2", "fig9_indicator_forecast_2",
            "fig2_last_transients"} <= {f["name"] for f in s.figures}
    assert "fig7_trends_3" not in {f["name"] for f in s.figures}
    # Every figure is embedded; the page is one file of modest size.
    pngs = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)
    assert len(pngs) == len(s.figures)
    assert all(base64.b64decode(b).startswith(b"\x89PNG") for b in pngs)
    data = json.loads((out / "summary.json").read_text())
    assert data["fleet"]["detail"] == fl["detail"] and len(data["units"]) == N_UNITS
    lines = s.terminal().splitlines()
    assert lines[0].startswith(f"fleet of {N_UNITS} units") and len(lines) < DETAIL + 5
    print(f"\nreport of {N_UNITS} units: {seconds:.1f} s, {len(s.figures)} figures, "
          f"index.html {len(text) / 1e6:.2f} MB")


def test_report_unit_draws_a_unit_on_request(fleet, tmp_path):
    cfg, cfg_path, tmp, names = fleet
    from twinmon.cli import main
    healthy, other = names[2], names[5]                 # Park00, Park01: not at risk
    res = CliRunner().invoke(main, [
        "report", "-c", str(cfg_path), "--posterior", str(tmp / "post.h5"),
        "--forecast", str(tmp / "fc.h5"), "-o", str(tmp_path / "r"), "--unit", healthy,
        "--unit", other, "--set", "report.detail_units=3", "--json"])
    assert res.exit_code == 0, res.output
    fl = json.loads(res.stdout)["fleet"]
    assert healthy not in fl["at_risk"] and fl["requested"] == [healthy, other]
    # The two asked for, and the first unit at risk to fill report.detail_units.
    assert set(fl["detail"]) == {healthy, other, next(iter(fl["at_risk"]))}
    text = (tmp_path / "r" / "index.html").read_text()
    assert f'id="unit-{healthy}"' in text and f'href="#unit-{healthy}"' in text
    res = CliRunner().invoke(main, [
        "report", "-c", str(cfg_path), "--forecast", str(tmp / "fc.h5"),
        "-o", str(tmp_path / "r2"), "--unit", "Nobody"])
    assert res.exit_code == ConfigError.exit_code
    assert "--unit Nobody: no such unit" in res.stderr and "Traceback" not in res.output
    assert not (tmp_path / "r2").exists()
