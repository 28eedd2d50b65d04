"""Blind cases of ``diagnose``: an effect is withheld in fabricated data, and the diagnosis,
which reads only the observations, must name it.

Each case is one unit, 6 years, degradation drifting, the effect on from year 3, flow noise
1 % of nominal (4 kg/s). Every magnitude is chosen so that the effect's gap -- RMS of (flow
with the effect - the same unit's flow without it), in noise standard deviations, over its
worst config window -- is at least 3; ``test_magnitudes_give_a_3_sigma_gap`` checks it on the
twin. The scorer (this file) knows the truth from the case table; ``diagnose`` never sees it.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from twinmon.config import config_from_mapping, load_config
from twinmon.diagnose import diagnose
from twinmon.fabricate import fabricate
from twinmon.fmu import FMUModel, resolve_fmu

ROOT = Path(__file__).resolve().parents[2]
PUMP = ROOT / "configs" / "pump.yaml"
YEARS, ONSET, SIGMA = 6, 3, 4.0
TRAJ = {"motor_damping": {"start": 10.0, "slope": 0.4}, "pump_coef": {"start": 3.7, "slope": -0.03}}

#: One case per candidate effect: (FMU parameter, value). Gaps (sigma, worst window, year 3):
#: tau 0.8 s ~9, gain 1.05 ~5, opening 8 s ~8, fouling 0.2 ~6, leak 1e-4 ~4.3,
#: start delay 1 s ~12, supply 0.95 ~5 (computed by test_magnitudes_give_a_3_sigma_gap).
EFFECTS = {
    "sensor.tau": 0.8,
    "sensor.gain": 1.05,
    "valve.opening_time": 8.0,
    "pipe.fouling": 0.2,
    "pump.leak": 1.0e-4,
    "motor.start_delay": 1.0,
    "motor.supply_ratio": 0.95,
}
#: Transient-type effects: their flow signatures differ, so the first-ranked must be right.
FLOW_SEPARABLE = {"sensor.tau", "valve.opening_time", "motor.start_delay"}
CASES = {f"E{i}": name for i, name in enumerate(EFFECTS)}


def _units():
    units = {u: {"trajectories": TRAJ, "effects": {n: {"value": EFFECTS[n], "onset": ONSET}}}
             for u, n in CASES.items()}
    units["NULL"] = {"trajectories": TRAJ}
    # Out of the candidate list: a pulsation added to the measured flow (amplitude 5 sigma,
    # RMS 3.5 sigma over every window).
    units["OUT"] = {"trajectories": TRAJ, "disturbance": {"amplitude": 20.0, "period": 7.0,
                                                          "onset": ONSET, "shape": "sine"}}
    return units


def _cfg(units, seed=101, **fab):
    raw = copy.deepcopy(dict(load_config(PUMP).raw))
    raw["fabricate"] = {"years": YEARS, "noise_std": SIGMA, "seed": seed, "units": units,
                        **fab}
    return config_from_mapping(raw, PUMP)


def _diagnosed(cfg, folder, workers=1) -> dict:
    """The config's fleet fabricated in ``folder`` and diagnosed from its observations alone
    (the truth file stays unread): unit -> gap result; gap.h5 is in ``folder``."""
    fabricate(cfg, folder / "obs.h5", folder / "truth.h5")
    return diagnose(cfg, folder / "obs.h5", folder / "gap.h5", workers=workers).units


@pytest.fixture(scope="module")
def blind(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("blind")
    cfg = _cfg(_units())
    return _diagnosed(cfg, tmp, workers=2)


def test_magnitudes_give_a_3_sigma_gap():
    cfg = load_config(PUMP)
    t = cfg.model.output.times.times
    theta = {"motor.D": 10.0 + 0.4 * (ONSET - 1), "pump.b2": 3.7 - 0.03 * (ONSET - 1)}
    with FMUModel(resolve_fmu(cfg.model.fmu), ["sensor.m_flow"], t) as m:
        base = m.run(theta)["sensor.m_flow"]
        for name, value in EFFECTS.items():
            d = (m.run({**theta, name: value})["sensor.m_flow"] - base) / SIGMA
            gap = max(np.sqrt(np.mean(d[(t >= w.start) & (t < w.stop)] ** 2))
                      for w in cfg.diagnose_windows().values())
            assert gap >= 3.0, (name, gap)


@pytest.mark.parametrize("unit", list(CASES))
def test_withheld_effect_is_found(blind, unit):
    name = CASES[unit]
    g = blind[unit]
    assert g.verdict == "effect", (name, g.verdict, g.candidates[:3])
    assert name in g.effects, (name, g.effects)
    if name in FLOW_SEPARABLE:
        assert g.effects[0] == name
    assert abs(g.onset - ONSET) <= 1
    assert g.closed_percent >= 90.0
    e = load_config(PUMP).model.effects[name]
    mean, q05, q95 = g.estimate[name]
    assert abs(mean - EFFECTS[name]) <= 0.2 * (e.high - e.low)
    assert q05 <= mean <= q95
    # The effect biased the base twin's estimates; adding it brings them back.
    assert set(g.where_years) == set(range(g.onset, YEARS + 1))


def test_null_case_has_no_gap(blind):
    g = blind["NULL"]
    assert g.verdict == "none"
    assert g.effects == [] and g.closed_percent == 0.0
    assert 0.7 < g.rms_before < 1.3


def test_out_of_list_disturbance_is_unexplained(blind):
    # Honest expectation: the gap is seen and located (from about its onset), and no
    # candidate is accepted as its cause.
    g = blind["OUT"]
    assert g.verdict == "unexplained", (g.verdict, g.effects, g.closed_percent)
    assert g.effects == []
    assert abs(g.onset - ONSET) <= 1
    assert g.rms_before > 2.0


def test_extra_channels_separate_plateau_effects(tmp_path):
    # Fouling and a flowmeter gain look alike on the flow alone; with the pump pressure,
    # speed and current recorded, the first-ranked effect must be the true one.
    units = {"F": {"trajectories": TRAJ, "effects": {"pipe.fouling": {"value": 0.2,
                                                                      "onset": ONSET}}},
             "G": {"trajectories": TRAJ, "effects": {"sensor.gain": {"value": 1.05,
                                                                     "onset": ONSET}}}}
    cfg = _cfg(units, seed=7, record_channels=True)
    res = _diagnosed(cfg, tmp_path, workers=2)
    assert res["F"].verdict == "effect" and res["F"].effects[0] == "pipe.fouling"
    assert res["G"].verdict == "effect" and res["G"].effects[0] == "sensor.gain"


def test_two_effects_are_both_found(tmp_path):
    units = {"T": {"trajectories": TRAJ, "effects": {
        "motor.start_delay": {"value": 1.0, "onset": 2},
        "pipe.fouling": {"value": 0.25, "onset": 4}}}}
    cfg = _cfg(units, seed=5)
    g = _diagnosed(cfg, tmp_path)["T"]
    assert g.verdict == "effect"
    assert g.effects[0] == "motor.start_delay"
    # The second, plateau-type effect can only be named up to its flow-alike group.
    assert len(g.effect_onsets) == 2
    second = [e for e in g.effect_onsets if e != "motor.start_delay"][0]
    assert second in {"pipe.fouling", "sensor.gain", "pump.leak", "motor.supply_ratio"}
    assert abs(g.effect_onsets[second] - 4) <= 1 and abs(g.effect_onsets["motor.start_delay"] - 2) <= 1
    assert abs(g.estimate["motor.start_delay"][0] - 1.0) < 0.2
    assert g.closed_percent >= 90.0


def test_pair_gets_a_group_per_effect(tmp_path):
    # A lagging flowmeter and fouling from the same year: the lag is named alone, the
    # fouling only up to the plateau-type effects the flow cannot tell apart beside it.
    # Each effect gets its group; the JSON, gap.h5 and the per-member consequences carry it.
    from twinmon.diagnose import read_gap
    units = {"P": {"trajectories": TRAJ, "effects": {
        "sensor.tau": {"value": 1.5, "onset": ONSET},
        "pipe.fouling": {"value": 0.25, "onset": ONSET}}}}
    cfg = _cfg(units, seed=5)
    g = _diagnosed(cfg, tmp_path)["P"]
    assert g.verdict == "effect"
    assert len(g.groups) == 2
    members = [[m["effect"] for m in grp["members"]] for grp in g.groups]
    assert ["sensor.tau"] in members
    plateau = next(m for m in members if m != ["sensor.tau"])
    assert "pipe.fouling" in plateau and len(plateau) > 1
    assert set(plateau) <= {"pipe.fouling", "sensor.gain", "pump.leak", "motor.supply_ratio"}
    assert g.group == members[0]
    horizon_end = YEARS + load_config(PUMP).forecast.horizon
    for grp in g.groups:
        ws = [m["weight"] for m in grp["members"]]
        assert abs(sum(ws) - 1.0) < 1e-9
        # The named effect and its alternatives alone, by evidence; then any member that
        # explains the gap together with the named one.
        alone = [m["weight"] for m in grp["members"] if not m["together_with"]]
        assert alone == sorted(alone, reverse=True)
        assert grp["effect"] == grp["members"][0]["effect"]
        assert abs(grp["onset"] - ONSET) <= 1
        for m in grp["members"]:
            if m["together_with"]:
                assert m["together_with"] == [grp["effect"]]
            else:
                assert 0 <= m["delta_bic"] <= load_config(PUMP).diagnose.group_bic
            assert m["closed_percent"] >= 90.0
            assert m["q05"] <= m["value"] <= m["q95"]
            assert m["failure_year"] is None or 1 <= m["failure_year"] <= horizon_end
        fys = [horizon_end + 1 if m["failure_year"] is None else m["failure_year"]
               for m in grp["members"]]
        assert grp["failure_year_spread"] == (max(fys) - min(fys) > 1)
        lo, hi = grp["failure_year_range"]
        assert (lo or horizon_end + 1) == min(fys) and (hi or horizon_end + 1) == max(fys)
    sep = next(grp for grp in g.groups if len(grp["members"]) > 1)
    assert sep["separating_channel"] in load_config(PUMP).model.channels
    fouling = next(m for m in sep["members"] if m["effect"] == "pipe.fouling")
    assert abs(fouling["value"] - 0.25) < 0.05
    # What --json prints and what gap.h5 holds.
    js = g.as_dict()["groups"]
    assert [[m["effect"] for m in grp["members"]] for grp in js] == members
    back = read_gap(tmp_path / "gap.h5").units["P"]
    assert [[m["effect"] for m in grp["members"]] for grp in back.groups] == members
    assert back.groups[0]["failure_year_range"] == g.groups[0]["failure_year_range"]
    # What the command prints: both named effects on the unit's line, then the plateau
    # group on a line of its own, each member with its share, and the separating channel.
    from twinmon.diagnose.text import INDENT, summary_line, weight_text
    first, *rest = summary_line("P", g).splitlines()
    assert "sensor.tau = " in first and " + " in first
    assert f"{sep['effect']} = " in first and f"(group of {len(plateau)})" in first
    assert len(rest) == 1                  # one group of several; nothing hidden on the pump
    line = rest[0]
    assert line.startswith(f"{INDENT}{sep['effect']}'s group")
    for m in sep["members"]:
        assert m["effect"] in line and weight_text(m["weight"]) in line
    assert f"recording {sep['separating_channel']} would separate them" in line


def test_plateau_shifts_from_two_years_are_both_found(tmp_path):
    # Fouling from year 3, a flowmeter reading low from year 5: two plateau shifts the flow
    # shows alike. The second is screened with the first re-adjusted by one value shared
    # over its years (year by year, the first took the second shift up and nothing was
    # added). Each effect must sit in its own place's group.
    units = {"S": {"trajectories": TRAJ, "effects": {
        "pipe.fouling": {"value": 0.15, "onset": 3},
        "sensor.gain": {"value": 0.955, "onset": 5}}}}
    cfg = _cfg(units, seed=5, years=7)
    g = _diagnosed(cfg, tmp_path)["S"]
    assert g.verdict == "effect" and len(g.groups) == 2, (g.verdict, g.groups)
    by_onset = {grp["onset"]: {m["effect"] for m in grp["members"]} for grp in g.groups}
    assert set(by_onset) == {3, 5}, by_onset
    assert "pipe.fouling" in by_onset[3] and "sensor.gain" in by_onset[5]
    assert g.closed_percent >= 90.0


def test_same_year_plateau_shifts_are_one_group(tmp_path):
    # Fouling and a weak supply from the same year: the flow sees one shift, their sum.
    # Fouling alone cannot reach it within its range; it is in the group *together with*
    # the named effect, with the BIC weight of a two-effect explanation.
    units = {"W": {"trajectories": TRAJ, "effects": {
        "pipe.fouling": {"value": 0.3, "onset": ONSET},
        "motor.supply_ratio": {"value": 0.925, "onset": ONSET}}}}
    cfg = _cfg(units, seed=9)
    g = _diagnosed(cfg, tmp_path)["W"]
    assert g.verdict == "effect" and len(g.groups) == 1, (g.verdict, g.groups)
    grp = g.groups[0]
    members = {m["effect"]: m for m in grp["members"]}
    assert {"pipe.fouling", "motor.supply_ratio"} <= set(members), list(members)
    assert len(members) <= len(FLOW_ALIKE)
    assert set(members) <= FLOW_ALIKE
    assert grp["members"][0]["together_with"] == []
    together = [m for m in grp["members"] if m["together_with"]]
    assert together, "a member explains the shift only together with the named effect"
    for m in together:
        assert m["together_with"] == [grp["effect"]]
        assert m["q05"] <= m["value"] <= m["q95"]
    assert abs(sum(m["weight"] for m in grp["members"]) - 1.0) < 1e-9
    assert g.effects == [m["effect"] for m in grp["members"]]
    assert g.closed_percent >= 90.0
    assert g.hidden == {}      # the pump's candidates all show on the flow
    # A weak supply makes the twin unsafe at once; the plant had it from its onset only, so
    # no projected failure year comes before it (the healthy years before stay healthy).
    assert g.failure_year_after is not None and g.failure_year_after >= g.onset
    assert all(m["failure_year"] is None or m["failure_year"] >= grp["onset"]
               for m in grp["members"])
    # What a user sees: the command's lines, and the report's terminal, table and summary.
    from twinmon.diagnose.text import INDENT, summary_line, weight_text
    from twinmon.report import report
    first, line = summary_line("W", g).splitlines()
    assert first.startswith(f"W: {grp['effect']} = ") and f"(group of {len(members)})" in first
    assert line.startswith(f"{INDENT}{grp['effect']}'s group")
    for m in grp["members"][1:]:
        said = (f"{grp['effect']} with " if m["together_with"] else "") + f"{m['effect']} = "
        assert said in line and weight_text(m["weight"]) in line, (said, line)
    assert f"recording {grp['separating_channel']} would separate them" in line
    assert ("across the group" in line) == grp["failure_year_spread"]
    s = report(cfg, tmp_path / "report", observations=tmp_path / "obs.h5",
               gap=tmp_path / "gap.h5")
    assert line in s.terminal().splitlines()
    assert s.units["W"].diagnose["groups"] == json.loads(json.dumps(g.groups))
    html = (tmp_path / "report" / "index.html").read_text()
    table = html[html.index("Its group (posterior weight)"):]
    table = table[:table.index("</table>")]
    for m in grp["members"]:
        assert f"<code>{m['effect']}</code> = " in table
        assert f"<b>{weight_text(m['weight'])}</b>" in table
    assert f"<code>{grp['separating_channel']}</code>" in table
    if grp["failure_year_spread"]:
        assert "differs across the group" in table
        assert all(f"(failure year {m['failure_year']})" in table for m in grp["members"]
                   if m["failure_year"] is not None)


#: The pump's plateau-type effects: alike on the flow alone.
FLOW_ALIKE = {"pipe.fouling", "sensor.gain", "pump.leak", "motor.supply_ratio"}


def test_effects_the_speed_cannot_see_are_stated_with_the_channel(tmp_path):
    # The DC drive's extra load torque is taken up by the bearing friction on the speed
    # alone: diagnose cannot name it, and says so for every unit, with the channel that
    # would show it. With the armature current recorded it is seen and named.
    dc = ROOT / "configs" / "dcdrive.yaml"
    raw = copy.deepcopy(dict(load_config(dc).raw))
    traj = {"bearing_friction": {"start": 0.001, "slope": 2.0e-5},
            "winding_resistance": {"start": 1.0, "slope": 0.003}}
    units = {"L": {"trajectories": traj, "effects": {"load.extra": {"value": 0.3, "onset": 3}}},
             "C": {"trajectories": traj}}
    for record in (False, True):
        raw["fabricate"] = {"years": YEARS, "noise_std": 3.0, "seed": 13, "units": units,
                            "record_channels": record}
        cfg = config_from_mapping(copy.deepcopy(raw), dc)
        obs = tmp_path / f"obs{int(record)}.h5"
        fabricate(cfg, obs, tmp_path / "truth.h5")
        res = diagnose(cfg, obs, tmp_path / f"gap{int(record)}.h5", workers=2).units
        if not record:
            assert res["L"].verdict == "none" and res["C"].verdict == "none"
            for g in res.values():
                h = g.hidden["load.extra"]
                assert h["gap"] >= 3.0 and h["visible"] < 1.0
                assert h["channel"] in {"armature.i", "shaft.torque"}
            assert "tacho.tau" not in res["C"].hidden and "supply.delay" not in res["C"].hidden
            # What --json prints and gap.h5 holds.
            from twinmon.diagnose import read_gap
            back = read_gap(tmp_path / "gap0.h5").units["L"]
            assert back.hidden == json.loads(json.dumps(res["L"].hidden))
            assert res["L"].as_dict()["hidden"]["load.extra"]["channel"] == back.hidden["load.extra"]["channel"]
        else:
            assert res["L"].verdict == "effect" and res["L"].effects[0] == "load.extra"
            assert res["C"].verdict == "none"
            assert res["L"].hidden == {} and res["C"].hidden == {}
