"""Fleet families for ``benchmarks/prognosis.py --family``: wear that is not a straight line.

Every family has the linear fleet's healthy units (rates uniform in the normal band: the
false-alarm rate is measured on them) and faulty units whose *mean* excess rate over the ten
recorded years is the given multiple of the tolerance, as the linear fleet's are, so a
family differs from the linear one by the shape of its wear only:

* ``linear``: the straight lines of the original benchmark;
* ``quadratic``: ``start + b a + c a^2``, a share ``q`` (0.5-1) of the mean rate from the
  curvature, so the rate at the end of the record is ``1 + q`` times the mean;
* ``exponential``: ``start + s (exp(g a) - 1) / g``, growth ``g`` 0.15-0.35 a year;
* ``step``: normal ageing, then in year 5-8 a step whose size carries the whole excess; half
  the units age normally after it (a sudden fault that stays put), half at the faulty rate;
* ``repair`` / ``repair_hidden``: the faulty part is replaced in year 4-7 and wears again as
  the first did; the replacement is recorded in the observations, or not;
* ``reversing``: wear no trend shape follows: the faulty part's excess over normal ageing
  swings at twice the multiple's rate, up until year 3-4, back for three years with no
  repair (a deposit washed off, a setting drifting back), then up again; its mean excess
  is about two thirds of the multiple's;
* ``irregular``: 3-4 years of history, or ten with two years missing; 5-10 % of the samples
  lost (NaN); otherwise the linear fleet's units;
* ``power``: power-law wear ``start + c a^1.5`` (wear growing as a power of the running
  time, as sliding wear under rising contact stress does), none of the trend shapes'
  forms: faster early than a quadratic, slower late than an exponential;
* ``mixed``: each faulty unit's wear takes one of the shapes above at random (linear,
  quadratic, exponential, step, power): a fleet whose units do not share one mechanism.

Seeds: the same seed gives the same fleet in every family (same starts, same multiples).
"""
from __future__ import annotations

import numpy as np

TOL = {"motor_damping": 0.25, "pump_coef": 0.03}
NORMAL = {"motor_damping": 0.0, "pump_coef": -0.02}
SIGN = {"motor_damping": 1, "pump_coef": -1}
COMPONENT = {"motor_damping": "motor", "pump_coef": "pump"}
#: Excess rates, in tolerances, of the single-component faults (the pump's box allows less).
MULT = {"pump_coef": [1.25, 1.5, 2.0, 2.0, 2.25, 2.5, 2.75, 3.0, 3.0, 3.25, 3.5, 3.75],
        "motor_damping": [1.25, 1.5, 2.0, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 7.0]}
JITTER = {"motor_damping": 0.15, "pump_coef": 0.01}
YEARS = 10
FAMILIES = ("linear", "quadratic", "exponential", "step", "repair", "repair_hidden",
            "irregular", "reversing", "power", "mixed")
#: The shapes a ``mixed`` fleet's faulty units draw from.
MIXED = ("linear", "quadratic", "exponential", "step", "power")
#: Exponent of the ``power`` family's wear.
POWER = 1.5
#: Years of service the trajectories are written out to: the record and the forecast's
#: horizon after it (fabricate extends a trajectory's last rate beyond its last change).
SPAN = 20


def shaped(family: str, start: float, rate: float, normal: float,
           rng: np.random.Generator) -> tuple[dict, dict]:
    """The trajectory of a faulty input whose mean rate over the record is ``rate``, and
    the unit's other options (events, record) the family adds. ``normal`` is the input's
    normal ageing rate (a step family's rate before and, for half, after its step)."""
    ages = YEARS - 1
    tr = {"start": round(start, 4)}
    unit = {}
    if family == "quadratic":
        q = rng.uniform(0.5, 1.0)
        tr.update(slope=float(rate * (1 - q)), curvature=float(rate * q / ages))
    elif family == "exponential":
        g = rng.uniform(0.15, 0.35)
        tr.update(slope=float(rate * g * ages / np.expm1(g * ages)), growth=float(g))
    elif family == "step":
        year = int(rng.integers(5, 9))
        after = normal if rng.random() < 0.5 else rate
        # normal before, ``after`` from the step: the step makes up the mean rate.
        size = rate * ages - normal * (year - 1) - after * (YEARS - year)
        tr.update(slope=normal, changes=[{"year": year, "size": float(size),
                                          "slope": float(after)}])
    elif family == "power":
        # c a^p has mean rate c 9^(p-1) over the record; the trajectory is written as its
        # yearly increments (a change of rate each year), exact at every service year.
        c = rate / ages ** (POWER - 1)
        inc = c * np.diff(np.arange(SPAN) ** POWER)
        tr.update(slope=float(inc[0]), changes=[
            {"year": a + 1, "size": 0.0, "slope": float(inc[a])} for a in range(1, SPAN - 1)])
    elif family == "reversing":
        turn = int(rng.integers(3, 5))
        up, down = normal + 2 * (rate - normal), normal - 2 * (rate - normal)
        # The excess over normal ageing swings up, back and up again: a zigzag.
        tr.update(slope=float(up), changes=[
            {"year": turn, "size": 0.0, "slope": float(down)},
            {"year": turn + 3, "size": 0.0, "slope": float(up)}])
    else:
        tr["slope"] = rate
    if family in ("repair", "repair_hidden"):
        unit["repair_year"] = int(rng.integers(4, 8))
    return tr, unit


def fleet(seed: int, family: str = "linear", n_healthy: int = 12, n_both: int = 8,
          faulty: bool = True) -> tuple[dict, dict]:
    """Fabricate specs of a family's fleet and each unit's (kind, excess multiple)."""
    if family not in FAMILIES:
        raise SystemExit(f"--family {family!r}: one of {', '.join(FAMILIES)}")
    rng = np.random.default_rng(seed)
    # The family's own draws come from their own stream: the starts, multiples and the
    # healthy units are the linear fleet's.
    frng = np.random.default_rng([seed, FAMILIES.index(family)])
    units, kinds = {}, {}

    def add(name, kind, rates, excess, faulty_inputs=()):
        start = {"motor_damping": rng.uniform(9.5, 10.5), "pump_coef": rng.uniform(3.55, 3.75)}
        spec, extra = {}, {}
        # A mixed fleet's faulty unit draws its wear's shape (its own stream: the other
        # families' draws are unchanged).
        shape = (MIXED[np.random.default_rng([seed, 99, len(units)]).integers(len(MIXED))]
                 if family == "mixed" and faulty_inputs else family)
        for n in TOL:
            if n in faulty_inputs and shape != "linear":
                tr, more = shaped(shape, float(start[n]), float(rates[n]), NORMAL[n], frng)
                extra.update(more)
                if "repair_year" in more:
                    extra.setdefault("repaired", []).append(COMPONENT[n])
            else:
                tr = {"start": round(float(start[n]), 4), "slope": round(float(rates[n]), 5)}
            tr["jitter"] = JITTER[n]
            spec[n] = tr
        u = {"trajectories": spec}
        if "repair_year" in extra:
            u["events"] = [{"year": extra["repair_year"], "component": c,
                            "recorded": family == "repair"} for c in extra["repaired"]]
        if family == "irregular":
            pick = frng.random()
            if pick < 0.5:
                u["last_year"] = int(frng.integers(3, 5))
            else:
                u["missing_years"] = sorted(int(y) for y in
                                            frng.choice(np.arange(2, YEARS), 2, replace=False))
            u["nan_fraction"] = float(frng.uniform(0.05, 0.10))
        units[name] = u
        kinds[name] = (kind, float(excess))

    def normal(n):
        return NORMAL[n] + TOL[n] * rng.uniform(-1, 1)

    for i in range(n_healthy):
        add(f"H{i:02d}", "healthy", {n: normal(n) for n in TOL}, 0.0)
    if not faulty:
        return units, kinds
    for inp, mults in MULT.items():
        other = next(n for n in TOL if n != inp)
        for i, m in enumerate(mults):
            add(f"{COMPONENT[inp][0].upper()}{i:02d}", COMPONENT[inp],
                {other: normal(other), inp: NORMAL[inp] + SIGN[inp] * TOL[inp] * m}, m,
                faulty_inputs=(inp,))
    for i in range(n_both):
        mm, mp = rng.uniform(1.5, 4.0), rng.uniform(1.5, 3.0)
        add(f"B{i:02d}", "both", {"motor_damping": TOL["motor_damping"] * mm,
                                  "pump_coef": NORMAL["pump_coef"] - TOL["pump_coef"] * mp},
            min(mm, mp), faulty_inputs=tuple(TOL))
    return units, kinds


if __name__ == "__main__":
    # What each family's units look like (seed 11): the faulty units' shapes and options.
    for fam in FAMILIES:
        units, kinds = fleet(11, fam)
        shaped_units = {u: s for u, s in units.items() if kinds[u][0] != "healthy"}
        u, spec = next(iter(shaped_units.items()))
        print(f"{fam:14s} {len(units)} units ({len(shaped_units)} faulty); e.g. {u}: {spec}")
