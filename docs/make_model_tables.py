"""Figures and tables of docs/model.md, computed from the PumpCircuit FMU.

Usage::

    .venv/bin/python docs/make_model_tables.py           # print the markdown
    .venv/bin/python docs/make_model_tables.py --write   # replace the generated block in docs/model.md

Everything runs the Co-Simulation FMU through :class:`twinmon.fmu.FMUModel` on a 0.01 s grid.
"""
from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import brentq

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from twinmon.fmu import FMUModel, build_fmu  # noqa: E402

DT = 0.01                 # s, output grid for t90
HORIZON = 60.0            # s, simulated for the t90 table
OBS_END = 50.0            # s, end of the observation window (non-physical flag read there)
LONG = 400.0              # s, "steady state" for the nominal flow
D_VALUES = [5, 10, 15, 20, 25, 30]
B2_VALUES = [1.6, 2.0, 2.4, 2.8, 3.2, 3.61, 4.0]
BEGIN, END = "<!-- tables:begin -->", "<!-- tables:end -->"


def t90(times, flow, nominal):
    """First time (s) flow reaches 0.9*nominal, linearly interpolated; inf if never."""
    target = 0.9 * nominal
    i = int(np.argmax(flow >= target))
    if flow[i] < target:
        return float("inf")
    if i == 0:
        return float(times[0])
    t0, t1, f0, f1 = times[i - 1], times[i], flow[i - 1], flow[i]
    return float(t0 + (target - f0) * (t1 - t0) / (f1 - f0))


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="update docs/model.md in place")
    args = ap.parse_args(argv)

    fmu = build_fmu(ROOT / "fmus" / "PumpCircuit")
    grid = np.arange(DT, HORIZON + DT / 2, DT)
    i_obs = int(np.argmin(np.abs(grid - OBS_END)))
    lines = []

    with FMUModel(fmu, ["sensor.m_flow"], np.arange(1.0, LONG + 0.5, 1.0)) as m:
        nominal = float(m.run({})["sensor.m_flow"][-1])
    with FMUModel(fmu, ["sensor.m_flow", "motor.w", "pump.dp", "motor.I", "nonphysical"],
                  grid) as m:
        def run(**p):
            return m.run({k.replace("_", ".", 1): v for k, v in p.items()})

        healthy = run()
        t90_h = t90(grid, healthy["sensor.m_flow"], nominal)

        def t90_of(D, b2):
            return t90(grid, run(motor_D=D, pump_b2=b2)["sensor.m_flow"], nominal)

        def flag_of(D, b2):
            return run(motor_D=D, pump_b2=b2)["nonphysical"][i_obs]

        D30 = brentq(lambda D: t90_of(D, 3.61) - 30.0, 15.0, 40.0, xtol=1e-3)
        b230 = brentq(lambda b: t90_of(10.0, b) - 30.0, 2.05, 3.0, xtol=1e-4)

        def b2_threshold(D):
            lo, hi = 1.0, 3.61     # flag at lo, no flag at hi
            if flag_of(D, hi) or not flag_of(D, lo):
                return float("nan")
            for _ in range(30):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if flag_of(D, mid) else (lo, mid)
            return hi

        thresholds = {D: b2_threshold(D) for D in (0, 5, 10, 20, 30, 40)}

        table = {}
        for D in D_VALUES:
            for b2 in B2_VALUES:
                r = run(motor_D=D, pump_b2=b2)
                table[D, b2] = (t90(grid, r["sensor.m_flow"], nominal), r["nonphysical"][i_obs])

        n = 300
        params = [{"motor.D": d, "pump.b2": b} for d, b in
                  zip(np.linspace(5, 30, n), np.linspace(4.0, 2.2, n))]
    with FMUModel(fmu, ["sensor.m_flow", "pump.m_flow", "motor.w", "pump.dp", "motor.I",
                        "nonphysical"], np.arange(2.0, 50.5, 2.0)) as m:
        t0 = time.perf_counter()
        for p in params:
            m.run(p)
        rate = n / (time.perf_counter() - t0)

    lines.append(f"- Healthy unit (D = 10, b2 = 3.61): nominal flow (steady state, t = {LONG:.0f} s) "
                 f"**{nominal:.2f} kg/s**; t90 = **{t90_h:.2f} s**; at t = 50 s the flow is "
                 f"{healthy['sensor.m_flow'][i_obs]:.2f} kg/s, the speed "
                 f"{healthy['motor.w'][i_obs]:.2f} rad/s, the current {healthy['motor.I'][i_obs]:.0f} A, "
                 f"the pump pressure rise {healthy['pump.dp'][i_obs] / 1e5:.3f} bar.")
    lines.append(f"- t90 reaches 30 s at D = **{D30:.2f}** (b2 = 3.61) and at b2 = **{b230:.3f}** (D = 10).")
    thr = ", ".join(f"D = {D}: b2 < {v:.3f}" for D, v in thresholds.items())
    lines.append(f"- `nonphysical` is set by t = 50 s for {thr}.")
    lines.append(f"- FMUModel speed (Co-Simulation, 25 outputs times, 6 outputs, one core): "
                 f"about {rate:.0f} runs/s on the machine that generated this page.")
    lines.append("")
    lines.append(f"t90 (s) of `sensor.m_flow` to 90 % of {nominal:.1f} kg/s, 0.01 s grid; "
                 f"'>{HORIZON:.0f}' = not reached; **NP** = non-physical flag set by t = 50 s.")
    lines.append("")
    lines.append("| D \\ b2 | " + " | ".join(f"{b:g}" for b in B2_VALUES) + " |")
    lines.append("|---|" + "---|" * len(B2_VALUES))
    for D in D_VALUES:
        cells = []
        for b2 in B2_VALUES:
            t, flag = table[D, b2]
            s = f">{HORIZON:.0f}" if not np.isfinite(t) else f"{t:.2f}"
            if flag:
                s += " NP"
            cells.append(s)
        lines.append(f"| {D} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"

    if args.write:
        doc = ROOT / "docs" / "model.md"
        old = doc.read_text()
        new, k = re.subn(re.escape(BEGIN) + r".*?" + re.escape(END),
                         lambda _: f"{BEGIN}\n{text}{END}", old, flags=re.S)
        if k != 1:
            raise SystemExit(f"{doc}: markers {BEGIN} ... {END} not found")
        doc.write_text(new)
    print(text)
    return text


if __name__ == "__main__":
    main()
