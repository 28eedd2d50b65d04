"""The twin seen by ``diagnose``: one FMU instance, parameters in normalised units.

Degradation inputs and candidate effects go in (each mapped from [0, 1] over its fitting
range), the observed channels come out whitened (divided by their noise), so that every fit
and test downstream works on residuals of unit variance.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Sequence

import numpy as np

from ..config import Config

#: Effect values closer than this (fraction of the effect's range) to the baseline are run as
#: the baseline itself: a vanishing lag (sensor.tau -> 0) makes the FMU's equations stiff
#: (seconds per run) while its output equals the baseline's to far below the noise.
SNAP = 1e-3

#: FMU results a twin remembers, by exact parameter values. The fits of one unit come back
#: to the same points -- a candidate's fits from neighbouring onsets share their later years'
#: start, the screening's base run is the same for every candidate, least_squares ends on a
#: point whose Jacobian it has run -- about 15 % of the runs (1890 of 13050 on 4 units of
#: benchmarks/fleet_scale.py). The FMU is deterministic after a reset, so the result is the
#: same; 4096 runs of a few outputs are a few MB.
CACHE_RUNS = 4096


class Twin:
    """The FMU seen by ``diagnose``: degradation inputs + effects in, observed channels out.

    Parameters
    ----------
    cfg : Config
    fmu_path : path-like
        The ``.fmu`` file (already built).
    channels : sequence of str
        Observed channels: ``model.output.name`` (the config's output variable) and further
        channels named by their FMU variable.
    time : ndarray, shape [n_t]
        Sample times (s).
    sigma : dict of str to float
        Noise standard deviation per channel (channel units); residuals are divided by it.
    effects : sequence of str
        Candidate effect parameters; their fitting range is the config's ``[low, high]``.
    """

    def __init__(self, cfg: Config, fmu_path, channels: Sequence[str], time: np.ndarray,
                 sigma: dict, effects: Sequence[str]):
        from ..fmu import FMUModel
        self.cfg = cfg
        self.channels = list(channels)
        out = cfg.model.output
        self.var = {c: (out.variable if c == out.name else c) for c in self.channels}
        extra = [out.variable, cfg.indicator_variable] + list(cfg.model.channels)
        if cfg.model.nonphysical:
            extra.append(cfg.model.nonphysical)
        outputs = list(dict.fromkeys(list(self.var.values()) + extra))
        self.model = FMUModel(fmu_path, outputs, time, fmi_type=cfg.model.fmi_type,
                              start_values=dict(cfg.model.fixed))
        self.time = np.asarray(time, float)
        self.sigma = np.concatenate([np.full(self.time.size, float(sigma[c]))
                                     for c in self.channels])
        self.in_vars = [s.variable for s in cfg.model.inputs.values()]
        box = cfg.model.bounds
        width = box[:, 1] - box[:, 0]
        lo = box[:, 0] - cfg.diagnose.fit_margin * width
        # Damping-like inputs must stay positive for the physics to hold.
        self.in_lo = np.where(box[:, 0] > 0, np.maximum(lo, 0.05 * box[:, 0]), lo)
        self.in_hi = box[:, 1] + cfg.diagnose.fit_margin * width
        self.effects = {e: cfg.model.effects[e] for e in effects}
        #: FMU runs made (not those answered from the cache).
        self.runs = 0
        self._cache: OrderedDict = OrderedDict()

    # -- parameter maps ---------------------------------------------------------------
    def theta_of(self, u: np.ndarray) -> np.ndarray:
        """Normalised degradation inputs [..., d] in [0, 1] -> input units."""
        return self.in_lo + np.asarray(u) * (self.in_hi - self.in_lo)

    def u_of(self, theta: np.ndarray) -> np.ndarray:
        return (np.asarray(theta) - self.in_lo) / (self.in_hi - self.in_lo)

    def effect_of(self, name: str, u: float) -> float:
        e = self.effects[name]
        return e.low + float(u) * (e.high - e.low)

    def effect_u(self, name: str, value: float) -> float:
        e = self.effects[name]
        return (float(value) - e.low) / (e.high - e.low)

    # -- runs ---------------------------------------------------------------------------
    def run(self, theta: np.ndarray, effects: dict | None = None) -> dict:
        """All recorded outputs (each [n_t]) for inputs ``theta`` [d] (input units) and
        effect values ``{fmu parameter: value}``."""
        p = {v: float(x) for v, x in zip(self.in_vars, theta)}
        for k, v in (effects or {}).items():
            e = self.effects.get(k)
            if e is not None and abs(v - e.baseline) < SNAP * (e.high - e.low):
                v = e.baseline
            p[k] = float(v)
        # The values' bits, not their float equality (0.0 == -0.0).
        key = (tuple(p), np.array(list(p.values())).tobytes())
        out = self._cache.get(key)
        if out is None:
            self.runs += 1
            out = self.model.run(p)
            self._cache[key] = out
            if len(self._cache) > CACHE_RUNS:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        # Copies: a caller may work on the arrays in place.
        return {name: x.copy() for name, x in out.items()}

    def predict(self, theta: np.ndarray, effects: dict | None = None) -> np.ndarray:
        """Whitened prediction of the observed channels, shape [n_ch * n_t] (channel-major)."""
        out = self.run(theta, effects)
        return np.concatenate([out[self.var[c]] for c in self.channels]) / self.sigma

    def close(self) -> None:
        self.model.close()
