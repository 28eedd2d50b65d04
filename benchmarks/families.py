"""Fleet families for ``benchmarks/prognosis.py --family``: wear that is not a straight line.

Every family has the linear fleet's healthy units (rates uniform in the normal band: the
false-alarm rate is measured on them) and faulty units whose *mean* excess rate over the ten
recorded years is the given multiple of the tolerance, as the linear fleet's are, so a
family differs from the linear one by the shape of its wear only (``rate_change`` excepted,
below):

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
  time, as sliding wear under rising contact stress does): faster early than a quadratic,
  slower late than an exponential;
* ``power_spread``: the same with each faulty input's own exponent, uniform in 1.15-1.95
  (mostly between the laplace method's power forms, 1.25, 1.5 and 1.75);
* ``mixed``: each faulty unit's wear takes one of the shapes above at random (linear,
  quadratic, exponential, step, power): a fleet whose units do not share one mechanism;
* ``rate_change``: normal ageing, then from year 4-7 the faulty rate, with no step: a
  part whose wear rate jumps late (a seal that starts leaking, a bearing whose lubricant
  gives out). Unlike the other families, the multiple is the excess rate *from the change
  on*, the rate the unit wears at now: over the record the mean excess is only (10 -
  year) / 9 of it (2/3 from year 4, 1/3 from year 7), and the rate at the end is 1.5-3
  times the record's mean rate.

Seeds: the same seed gives the same fleet in every family (same starts, same multiples).

The model (:class:`FleetModel`) is any config's: ``FleetModel.from_config(cfg)`` reads each
of ``model.inputs``:

* the tolerance is its ``normal_rate_tolerance``, the healthy units' band around
  ``normal_rate`` (a healthy unit's rate is uniform in normal +- tolerance);
* the degrading sign from ``degrading`` (``up`` +1, ``down`` -1; required: a fault has to
  move the input one way), the fault's label from ``component``;
* a fault of ``m`` tolerances ages at ``normal + sign * tolerance * m``.

The pump's inputs (``configs/pump.yaml``, or a config extending it with the same inputs) keep
the numbers the benchmark was built with, :data:`PUMP`, so its fleets are bit for bit what
they were. For any other model the rest is derived, by rules the pump's numbers follow
where they can:

* **starting values**: uniform in ``nominal +- 2`` tolerances, clipped to the design box
  (the motor's 9.5-10.5 is 10 +- 2 x 0.25; the pump coefficient's 3.55-3.75 is not
  centred on its 3.61);
* **year-to-year jitter**: half the tolerance (the pump's are 0.6 and 0.33 of theirs);
* **fault multiples**: the motor's ladder 1.25, 1.5, 2, 2, 2.5, 3, 3.5, 4, 4.5, 5, 6, 7,
  its part above 2 compressed linearly to end at ``m_max`` when the box allows less than 7:
  ``m_max`` is the largest multiple whose straight line, started at the start band's
  degrading edge, stays inside the box ``low``..``high`` through the first year after the
  record (year 11). Every shape of wear reaches the line's excess at the end of the record
  and none goes beyond it before, so every recorded year of a fault stays in the box,
  where calibration's prior lives. That is where the pump's largest faults sit: its pump
  coefficient at 3.75 tolerances from 3.55 stays above the box's 2.2 through year 11, the
  motor's 7 from 10.5 below its 30 through year 12. Over the whole 20-year span the faster
  faults leave the box, as the pump's do: the forecast then runs the FMU itself there. (A
  straight line inside the box over 20 years would allow the pump coefficient no fault
  beyond 1.7 tolerances.) ``m_max`` under 2.5 is refused: the box leaves no room for the
  faults the benchmark scores. The other side of the normal band is the config's: an input
  ageing against its degrading direction may reach the box's other bound (the DC drive's
  bearing friction, nominal 0.001 and low 0.0005, may fall by 5e-5 a year: from the start
  band's low edge, 0.0009, it comes within 2 % of the box's range of the bound in year 7
  and reaches the bound in year 9);
* **faults of both parts**: each input's multiple uniform in 1.5 .. min(4, m_max) (the
  motor's range; the pump coefficient's is 1.5-3);
* **decimals** written to the fleet: starts to ``ceil(log10(300 / tolerance))`` decimals,
  straight-line rates to one more (the pump's 4 and 5);
* **unit names**: ``H`` healthy, ``B`` both, each component's shortest capitalised prefix
  that no other name uses (the pump's ``P`` and ``M``; the DC drive's ``Be`` and ``W``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

YEARS = 10
FAMILIES = ("linear", "quadratic", "exponential", "step", "repair", "repair_hidden",
            "irregular", "reversing", "power", "power_spread", "mixed", "rate_change")
#: The shapes a ``mixed`` fleet's faulty units draw from.
MIXED = ("linear", "quadratic", "exponential", "step", "power")
#: Exponent of the ``power`` family's wear, and the range the ``power_spread`` family's
#: exponents are drawn from (a unit's own, uniform).
POWER = 1.5
POWER_SPREAD = (1.15, 1.95)
#: Years of service the trajectories are written out to: the record and the forecast's
#: horizon after it (fabricate extends a trajectory's last rate beyond its last change).
SPAN = 20


#: The motor's ladder of fault multiples: a generic model's, compressed above 2 to its box.
LADDER = (1.25, 1.5, 2.0, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 7.0)
#: Half-width of the starting values' band, in tolerances, around ``nominal``.
START_TOLS = 2.0
#: Year-to-year jitter, as a share of the tolerance.
JITTER_SHARE = 0.5
#: The last service year a straight-line fault must stay inside the design box (the first
#: year after the record).
BOX_YEAR = YEARS + 1
#: Smallest ``m_max`` accepted: below it the box has no room for the faults scored
#: (detection counts faults of at least 2 tolerances).
MIN_MAX_MULT = 2.5
#: Upper end of a fault of both parts' multiples (the motor's).
BOTH_MULT = (1.5, 4.0)


@dataclass(frozen=True)
class FleetModel:
    """What a fleet needs to know of the model: per input (config order) its normal band,
    its degrading direction and component, and the fleet's draws.

    Attributes
    ----------
    tol, normal, sign, component, jitter : dict input -> value
        ``normal_rate_tolerance``, ``normal_rate``, +1 (``up``) / -1 (``down``), the
        component word, the year-to-year jitter of the true path.
    mult : dict input -> tuple of float
        Excess rates, in tolerances, of its single-part faults; the dict's order is the order
        the fault groups are drawn in.
    start, both : dict input -> (low, high)
        Uniform ranges of the starting values and of a both-parts fault's multiples.
    decimals : dict input -> int
        Decimals of the starting values written out (straight-line rates: one more).
    prefix : dict component -> str
        First letters of its faulty units' names.
    """

    tol: dict
    normal: dict
    sign: dict
    component: dict
    jitter: dict
    mult: dict
    start: dict
    both: dict
    decimals: dict
    prefix: dict

    @property
    def inputs(self) -> list[str]:
        return list(self.tol)

    @property
    def components(self) -> list[str]:
        """The fault groups' components, in the order their units are drawn."""
        return list(dict.fromkeys(self.component[n] for n in self.mult))

    @classmethod
    def from_config(cls, cfg) -> "FleetModel":
        """The fleet model of a loaded twinmon config: :data:`PUMP` for the pump's inputs,
        else derived from ``model.inputs`` by the rules of the module's docstring."""
        spec = cfg.model.inputs
        if {n: _identity(s) for n, s in spec.items()} == PUMP_INPUTS:
            return PUMP
        if len(spec) < 2:
            raise SystemExit(f"{cfg.source}: the fleets need two inputs or more (faults of "
                             f"one part and of several); model.inputs has {len(spec)}")
        tol, normal, sign, component, start, mult, both, dec = {}, {}, {}, {}, {}, {}, {}, {}
        for n, s in spec.items():
            if s.degrading not in ("up", "down"):
                raise SystemExit(f"{cfg.source}: model.inputs.{n}.degrading: up or down "
                                 "needed (the fleet's faults move the input that way)")
            if s.normal_rate_tolerance <= 0:
                raise SystemExit(f"{cfg.source}: model.inputs.{n}.normal_rate_tolerance: "
                                 "must be > 0 (the faults are multiples of it)")
            t, sg = float(s.normal_rate_tolerance), 1 if s.degrading == "up" else -1
            tol[n], normal[n], sign[n] = t, float(s.normal_rate), sg
            component[n] = s.component or n
            start[n] = (max(s.low, s.nominal - START_TOLS * t),
                        min(s.high, s.nominal + START_TOLS * t))
            # The straight line from the band's degrading edge meets the box's edge at the
            # end of service year BOX_YEAR (age BOX_YEAR - 1).
            edge = start[n][1] if sg > 0 else start[n][0]
            room = (s.high - edge) if sg > 0 else (edge - s.low)
            m_max = min(LADDER[-1], (room / (BOX_YEAR - 1) - sg * normal[n]) / t)
            if m_max < MIN_MAX_MULT:
                raise SystemExit(f"{cfg.source}: model.inputs.{n}: the design box allows "
                                 f"faults of {m_max:.2f} tolerances at most through year "
                                 f"{BOX_YEAR} (at least {MIN_MAX_MULT} needed)")
            mult[n] = tuple(m if m <= 2 else round(2 + (m - 2) * (m_max - 2) / (LADDER[-1] - 2), 4)
                            for m in LADDER)
            both[n] = (BOTH_MULT[0], min(BOTH_MULT[1], m_max))
            dec[n] = math.ceil(math.log10(300 / t))
        comps = list(dict.fromkeys(component.values()))
        return cls(tol=tol, normal=normal, sign=sign, component=component,
                   jitter={n: JITTER_SHARE * t for n, t in tol.items()}, mult=mult,
                   start=start, both=both, decimals=dec, prefix=_prefixes(comps))


def _identity(s) -> tuple:
    """What makes an input the pump's: its box, nominal, band, direction and component."""
    return (s.low, s.high, s.nominal, s.normal_rate, s.normal_rate_tolerance, s.degrading,
            s.component)


def _prefixes(components: list[str]) -> dict:
    """Each component's shortest capitalised prefix that no other name uses (``H`` and
    ``B`` are the healthy and both-parts units')."""
    taken, out = {"H", "B"}, {}
    for c in components:
        for k in range(1, len(c) + 1):
            p = c[:k].capitalize()
            if p not in taken and not any(o.startswith(p) or p.startswith(o)
                                          for o in out.values()):
                break
        else:
            p = c.capitalize() + "_"
        taken.add(p)
        out[c] = p
    return out


#: The pump (configs/pump.yaml): the numbers the benchmark was built with.
PUMP_INPUTS = {"motor_damping": (4.0, 30.0, 10.0, 0.0, 0.25, "up", "motor"),
               "pump_coef": (2.2, 4.0, 3.61, -0.02, 0.03, "down", "pump")}
PUMP = FleetModel(
    tol={"motor_damping": 0.25, "pump_coef": 0.03},
    normal={"motor_damping": 0.0, "pump_coef": -0.02},
    sign={"motor_damping": 1, "pump_coef": -1},
    component={"motor_damping": "motor", "pump_coef": "pump"},
    jitter={"motor_damping": 0.15, "pump_coef": 0.01},
    # Excess rates, in tolerances, of the single-component faults (the pump's box allows
    # less); the pump's faults are drawn first.
    mult={"pump_coef": (1.25, 1.5, 2.0, 2.0, 2.25, 2.5, 2.75, 3.0, 3.0, 3.25, 3.5, 3.75),
          "motor_damping": (1.25, 1.5, 2.0, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 6.0, 7.0)},
    start={"motor_damping": (9.5, 10.5), "pump_coef": (3.55, 3.75)},
    both={"motor_damping": (1.5, 4.0), "pump_coef": (1.5, 3.0)},
    decimals={"motor_damping": 4, "pump_coef": 4},
    prefix={"pump": "P", "motor": "M"})


def shaped(family: str, start: float, rate: float, normal: float,
           rng: np.random.Generator, decimals: int = 4) -> tuple[dict, dict]:
    """The trajectory of a faulty input whose mean rate over the record is ``rate``, and
    the unit's other options (events, record) the family adds. ``normal`` is the input's
    normal ageing rate (a step family's rate before and, for half, after its step);
    ``decimals`` those of the start written out."""
    ages = YEARS - 1
    tr = {"start": round(start, decimals)}
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
    elif family == "rate_change":
        year = int(rng.integers(4, 8))
        # normal up to ``year``, then the fault's rate: no step.
        tr.update(slope=normal, changes=[{"year": year, "size": 0.0, "slope": float(rate)}])
    elif family in ("power", "power_spread"):
        # c a^p has mean rate c 9^(p-1) over the record; the trajectory is written as its
        # yearly increments (a change of rate each year), exact at every service year.
        p = POWER if family == "power" else float(rng.uniform(*POWER_SPREAD))
        c = rate / ages ** (p - 1)
        inc = c * np.diff(np.arange(SPAN) ** p)
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
          faulty: bool = True, model: FleetModel | None = None) -> tuple[dict, dict]:
    """Fabricate specs of a family's fleet and each unit's (kind, excess multiple).

    ``model`` is the model's :class:`FleetModel` (default :data:`PUMP`); a unit's kind is
    ``healthy``, a component or ``both``."""
    if family not in FAMILIES:
        raise SystemExit(f"--family {family!r}: one of {', '.join(FAMILIES)}")
    m = PUMP if model is None else model
    rng = np.random.default_rng(seed)
    # The family's own draws come from their own stream: the starts, multiples and the
    # healthy units are the linear fleet's.
    frng = np.random.default_rng([seed, FAMILIES.index(family)])
    units, kinds = {}, {}

    def add(name, kind, rates, excess, faulty_inputs=()):
        start = {n: rng.uniform(*m.start[n]) for n in m.inputs}
        spec, extra = {}, {}
        # A mixed fleet's faulty unit draws its wear's shape (its own stream: the other
        # families' draws are unchanged).
        shape = (MIXED[np.random.default_rng([seed, 99, len(units)]).integers(len(MIXED))]
                 if family == "mixed" and faulty_inputs else family)
        for n in m.inputs:
            if n in faulty_inputs and shape != "linear":
                tr, more = shaped(shape, float(start[n]), float(rates[n]), m.normal[n], frng,
                                  m.decimals[n])
                extra.update(more)
                if "repair_year" in more:
                    extra.setdefault("repaired", []).append(m.component[n])
            else:
                tr = {"start": round(float(start[n]), m.decimals[n]),
                      "slope": round(float(rates[n]), m.decimals[n] + 1)}
            tr["jitter"] = m.jitter[n]
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
        return m.normal[n] + m.tol[n] * rng.uniform(-1, 1)

    for i in range(n_healthy):
        add(f"H{i:02d}", "healthy", {n: normal(n) for n in m.inputs}, 0.0)
    if not faulty:
        return units, kinds
    for inp, mults in m.mult.items():
        comp = m.component[inp]
        for i, x in enumerate(mults):
            rates = {n: normal(n) for n in m.inputs if n != inp}
            rates[inp] = m.normal[inp] + m.sign[inp] * m.tol[inp] * x
            add(f"{m.prefix[comp]}{i:02d}", comp, rates, x, faulty_inputs=(inp,))
    for i in range(n_both):
        x = {n: rng.uniform(*m.both[n]) for n in m.inputs}
        add(f"B{i:02d}", "both", {n: m.normal[n] + m.sign[n] * m.tol[n] * x[n]
                                  for n in m.inputs},
            min(x.values()), faulty_inputs=tuple(m.inputs))
    return units, kinds


if __name__ == "__main__":
    # What each family's units look like (seed 11): the faulty units' shapes and options,
    # for the config given (default the pump).
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from twinmon.config import load_config
    cfg = load_config(sys.argv[1] if len(sys.argv) > 1 else
                      Path(__file__).resolve().parents[1] / "configs" / "pump.yaml")
    model = FleetModel.from_config(cfg)
    print(model)
    for fam in FAMILIES:
        units, kinds = fleet(11, fam, model=model)
        shaped_units = {u: s for u, s in units.items() if kinds[u][0] != "healthy"}
        u, spec = next(iter(shaped_units.items()))
        print(f"{fam:14s} {len(units)} units ({len(shaped_units)} faulty); e.g. {u}: {spec}")
