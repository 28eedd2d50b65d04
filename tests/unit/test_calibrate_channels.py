"""Several recorded channels in the likelihood: simulate records them, reduce learns them,
calibrate stacks the observed ones (real FMU, real OpenTURNS surrogates, real HDF5)."""
from __future__ import annotations

import copy
import dataclasses
import json

import h5py
import numpy as np
import pytest

from twinmon.calibrate import calibrate, read_posterior, year_fit
from twinmon.calibrate.channels import StackedSurrogate, channel_noise, load_surrogate
from twinmon.config import config_from_mapping, load_config
from twinmon.errors import ArtifactError, ConfigError, InputDataError
from twinmon.fabricate import fabricate
from twinmon.observations import Observations, read_observations, write_observations
from twinmon.reduce import read_channel_surrogates, read_surrogate, reduce
from twinmon.simulate import read_simulations, simulate

from ..conftest import CONFIGS

SPEED = "motor.w"


def _config(tmp, **calibrate_keys):
    """The shipped fleet cut to its motor-fault unit and 3 years, every channel recorded,
    a small design, motor speed the only channel reduced, fast sampling."""
    raw = copy.deepcopy(dict(load_config(CONFIGS / "fleet.yaml").raw))
    raw["simulate"].update(train_size=48, test_size=8, executor="serial")
    raw["reduce"]["channels"] = [SPEED]
    fab = raw["fabricate"]
    fab.update(years=3, record_channels=True, units={"Monk": fab["units"]["Monk"]})
    raw["calibrate"].update({"chains": 4, "samples": 400, "burn_in": 100, "workers": 1,
                             "ess_warn": 100, "max_extensions": 1, **calibrate_keys})
    return config_from_mapping(raw, tmp / "channels.yaml")


@pytest.fixture(scope="module")
def built(tmp_path_factory, fmu_path):
    tmp = tmp_path_factory.mktemp("channels")
    cfg = _config(tmp)
    simulate(cfg, tmp / "sims.h5")
    reduce(cfg, tmp / "sims.h5", tmp / "sur.h5")
    fabricate(cfg, tmp / "obs.h5", tmp / "truth.h5")
    both = calibrate(cfg, tmp / "sur.h5", tmp / "obs.h5", tmp / "both.h5")
    flow = calibrate(_config(tmp, channels=[]), tmp / "sur.h5", tmp / "obs.h5", tmp / "flow.h5")
    return cfg, tmp, both, flow


def _strip(obs: Observations, keep: list[str], path, years=None) -> None:
    """Write ``obs`` with only the ``keep`` channels (and the first ``years`` years)."""
    units = {}
    for name, u in obs.units.items():
        sl = slice(None, years)
        units[name] = dataclasses.replace(
            u, years=u.years[sl], channels={c: u.channels[c][sl] for c in keep},
            noise_std={c: s for c, s in u.noise_std.items() if c in keep})
    write_observations(path, Observations(obs.time, units, path, obs.output))


def test_simulate_records_every_channel_and_reduce_learns_the_chosen_one(built):
    cfg, tmp, _, _ = built
    sims = read_simulations(tmp / "sims.h5")
    ok = sims.ok["train"]
    assert sorted(sims.channels["train"]) == sorted(cfg.model.channels)
    assert np.all(np.isfinite(sims.channels["train"][SPEED][ok]))
    sur = read_surrogate(tmp / "sur.h5")
    assert sur.channel_names == [SPEED]
    speed = read_channel_surrogates(tmp / "sur.h5")[SPEED]
    Y = sims.channels["test"][SPEED][sims.ok["test"]]
    rel = np.abs(speed.predict(sims.X["test"][sims.ok["test"]]) / Y - 1)
    assert rel.max() < 0.01
    with pytest.raises(ArtifactError, match="no surrogate of channel 'pump.dp'.*re-run"):
        read_channel_surrogates(tmp / "sur.h5", ["pump.dp"])


def test_stacked_surrogate_puts_channels_side_by_side(built):
    cfg, tmp, _, _ = built
    stack = load_surrogate(tmp / "sur.h5", cfg.model.output.name, [SPEED])
    assert isinstance(stack, StackedSurrogate) and stack.names == ["m_flow", SPEED]
    X = np.array([[10.0, 3.6], [20.0, 3.0]])
    flow, speed = read_surrogate(tmp / "sur.h5"), read_channel_surrogates(tmp / "sur.h5")[SPEED]
    assert np.array_equal(stack.predict(X), np.hstack([flow.predict(X), speed.predict(X)]))
    n_t = flow.time.size
    assert stack.time.shape == (2 * n_t,) and np.array_equal(stack.time[n_t:], flow.time)
    assert np.array_equal(stack.noise_var([2.0, 0.5]), np.r_[np.full(n_t, 4.0),
                                                             np.full(n_t, 0.25)])
    assert load_surrogate(tmp / "sur.h5", "m_flow", []).fingerprint() == flow.fingerprint()


def test_motor_speed_enters_the_likelihood_and_narrows_the_posterior(built):
    cfg, tmp, both, flow = built
    assert both.channels == ["m_flow", SPEED] and flow.channels == ["m_flow"]
    # The other recorded channels have no surrogate (reduce.channels): said, not used.
    assert any("pump.dp" in w and "motor.I" in w and "left out" in w for w in both.warnings)
    pb, pf = both.posterior["Monk"], flow.posterior["Monk"]
    assert list(pb.channels) == ["m_flow", SPEED]
    assert pb.channels[SPEED]["source"] == "file" and pb.channels[SPEED]["std"] > 0
    assert pf.channels == {}
    width_b, width_f = pb.q95 - pb.q05, pf.q95 - pf.q05          # [year, input]
    ratio = width_b.mean(axis=0) / width_f.mean(axis=0)
    print("90 % interval width, flow + speed / flow only, per input:", ratio)
    assert np.all(ratio < 0.85), ratio
    # Fit per channel, at the noise level for both.
    assert pb.fit["channel_rms"].shape == (3, 2)
    assert np.all(pb.fit["channel_rms"] < 1.5) and list(pb.status) == ["ok"] * 3
    # The artifact and --json say which channels were used.
    post = read_posterior(tmp / "both.h5")
    assert list(post.units["Monk"].channels) == ["m_flow", SPEED]
    assert np.array_equal(post.units["Monk"].fit["channel_rms"], pb.fit["channel_rms"])
    with h5py.File(tmp / "both.h5") as f:
        assert json.loads(f.attrs["channels"]) == ["m_flow", SPEED]
    with h5py.File(tmp / "flow.h5") as f:
        assert json.loads(f.attrs["channels"]) == ["m_flow"]
    d = both.as_dict()
    assert d["channels"] == ["m_flow", SPEED]
    assert set(d["noise"]["Monk"]["channels"]) == {"m_flow", SPEED}
    assert set(d["units"]["Monk"]["fit"]["channel_rms"]) == {"m_flow", SPEED}


def test_output_alone_gives_the_single_channel_result(built):
    """A file with the output only, and calibrate.channels: [] on a file with more channels,
    give the same posterior, bit for bit."""
    cfg, tmp, _, flow = built
    _strip(read_observations(tmp / "obs.h5"), ["m_flow"], tmp / "obs_flow.h5")
    alone = calibrate(cfg, tmp / "sur.h5", tmp / "obs_flow.h5", tmp / "alone.h5")
    assert alone.channels == ["m_flow"] and alone.warnings == flow.warnings
    a, b = alone.posterior["Monk"], flow.posterior["Monk"]
    for key in ("mean", "q05", "q95", "rhat", "ess", "acceptance", "noise_std"):
        assert np.array_equal(getattr(a, key), getattr(b, key)), key


def test_parallel_workers_give_the_serial_result(built, tmp_path):
    cfg, tmp, _, _ = built
    _strip(read_observations(tmp / "obs.h5"), ["m_flow", SPEED], tmp_path / "one.h5", years=1)
    serial = calibrate(cfg, tmp / "sur.h5", tmp_path / "one.h5", tmp_path / "s.h5")
    par = calibrate(_config(tmp, workers=2), tmp / "sur.h5", tmp_path / "one.h5",
                    tmp_path / "p.h5")
    assert par.channels == ["m_flow", SPEED]
    assert serial.method == par.method
    assert np.array_equal(read_posterior(tmp_path / "s.h5").units["Monk"].samples,
                          read_posterior(tmp_path / "p.h5").units["Monk"].samples)
    # A spawned worker rebuilds the stack from the file.
    from twinmon.calibrate.shared import init_worker, worker
    init_worker(None, str(tmp / "sur.h5"), "m_flow", (SPEED,))
    assert worker["surrogate"].names == ["m_flow", SPEED]


def test_channel_noise_is_estimated_when_the_file_has_none(built):
    cfg, tmp, _, _ = built
    u = read_observations(tmp / "obs.h5").units["Monk"]
    recorded = u.noise_std[SPEED]
    stack = load_surrogate(tmp / "sur.h5", "m_flow", [SPEED])
    std, info = channel_noise(cfg, dataclasses.replace(u, noise_std={"m_flow": 4.0}), stack,
                              4.0, "file")
    assert info[SPEED]["source"] == "estimated" and info["m_flow"]["source"] == "file"
    # 3 years x 25 samples, 2 inputs fitted per year: ~10 % standard deviation.
    assert std[1] == pytest.approx(recorded, rel=0.35), (std, recorded)


def test_year_fit_tells_which_channel_misses(built):
    """A speed sensor off by 10 noise sd: the stacked fit is a misfit, the speed's RMS
    says where."""
    cfg, tmp, _, _ = built
    stack = load_surrogate(tmp / "sur.h5", "m_flow", [SPEED])
    x = np.array([12.0, 3.6])
    sd = np.array([4.0, 1.0])
    rng = np.random.default_rng(0)
    y = stack.predict(x[None])[0] + np.repeat(sd, stack.n_t) * rng.standard_normal(2 * stack.n_t)
    y[stack.n_t:] += 10 * sd[1]
    fit = year_fit(stack, cfg, y, stack.noise_var(sd), np.tile(x, (50, 1)), cfg.model.bounds)
    assert fit["status"] == "misfit"
    assert fit["channel_rms"][0] < 1.5 and fit["channel_rms"][1] > 8


def test_bad_channel_settings_and_data_are_clear_errors(built, tmp_path):
    cfg, tmp, _, _ = built
    with pytest.raises(ArtifactError, match=r"sur.h5: no surrogate of channel 'motor.I'"):
        calibrate(_config(tmp, channels=["motor.I"]), tmp / "sur.h5", tmp / "obs.h5",
                  tmp_path / "x.h5")
    obs = read_observations(tmp / "obs.h5")
    _strip(obs, ["m_flow"], tmp_path / "flow.h5")
    with pytest.raises(InputDataError, match=r"flow.h5: /units/Monk/motor.w is missing"):
        calibrate(_config(tmp, channels=[SPEED]), tmp / "sur.h5", tmp_path / "flow.h5",
                  tmp_path / "x.h5")
    # Speed recorded in rpm instead of rad/s: far outside what the design produced.
    u = obs.units["Monk"]
    u.channels[SPEED] = u.channels[SPEED] * 60 / (2 * np.pi) * 10
    write_observations(tmp_path / "rpm.h5", obs)
    with pytest.raises(InputDataError, match=r"rpm.h5: /units/Monk/motor.w year 1 .* rad/s"):
        calibrate(cfg, tmp / "sur.h5", tmp_path / "rpm.h5", tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()
    raw = copy.deepcopy(dict(cfg.raw))
    raw["reduce"]["channels"] = ["motor.speed"]
    with pytest.raises(ConfigError, match=r"reduce.channels.0: not a key of model.channels"):
        config_from_mapping(raw, tmp / "bad.yaml")


def test_a_surrogate_without_channels_still_calibrates_the_output(built, tmp_path):
    """A surrogate.h5 written before channels were reduced (reduce.channels: [] writes the
    same layout) is read as it was; recorded channels are left out with a warning."""
    cfg, tmp, _, flow = built
    raw = copy.deepcopy(dict(cfg.raw))
    raw["reduce"]["channels"] = []
    old = config_from_mapping(raw, tmp / "old.yaml")
    reduce(old, tmp / "sims.h5", tmp_path / "old.h5")
    assert read_surrogate(tmp_path / "old.h5").channel_names == []
    _strip(read_observations(tmp / "obs.h5"), ["m_flow", SPEED], tmp_path / "obs.h5", years=1)
    s = calibrate(old, tmp_path / "old.h5", tmp_path / "obs.h5", tmp_path / "p.h5")
    assert s.channels == ["m_flow"]
    assert any(SPEED in w and "does not model" in w for w in s.warnings)
