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

#: The FMU instance of the last twin closed in this process, by what it was opened with: the
#: next unit's twin takes it over instead of extracting and instantiating the FMU again
#: (10 ms a unit, 6 % of a diagnose --update of 120 units). Every run resets the instance
#: and sets all its parameters, so a run gives the same bits on any instance.
_SPARE: dict = {}


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
        #: The FMU variables each run records, in the order of :meth:`run`'s dict.
        self.outputs = list(dict.fromkeys(list(self.var.values()) + extra))
        self.time = np.asarray(time, float)
        fixed = dict(cfg.model.fixed)
        self._model_key = (str(fmu_path), tuple(self.outputs), self.time.tobytes(),
                           cfg.model.fmi_type, tuple(sorted(fixed.items())))
        self.model = _SPARE.pop(self._model_key, None)
        if self.model is None:
            self.model = FMUModel(fmu_path, self.outputs, time, fmi_type=cfg.model.fmi_type,
                                  start_values=fixed)
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
    def _key(self, theta: np.ndarray, effects: dict | None) -> tuple:
        """The FMU parameters of a run ``{variable: value}`` and its key in the run cache."""
        p = {v: float(x) for v, x in zip(self.in_vars, theta)}
        for k, v in (effects or {}).items():
            e = self.effects.get(k)
            if e is not None and abs(v - e.baseline) < SNAP * (e.high - e.low):
                v = e.baseline
            p[k] = float(v)
        # The values' bits, not their float equality (0.0 == -0.0).
        return p, (tuple(p), np.array(list(p.values())).tobytes())

    def run(self, theta: np.ndarray, effects: dict | None = None) -> dict:
        """All recorded outputs (each [n_t]) for inputs ``theta`` [d] (input units) and
        effect values ``{fmu parameter: value}``."""
        # Copies: a caller may work on the arrays in place.
        return {name: x.copy() for name, x in self._run(theta, effects).items()}

    def _run(self, theta: np.ndarray, effects: dict | None) -> dict:
        """:meth:`run`'s outputs as the run cache holds them: not to be modified."""
        p, key = self._key(theta, effects)
        out = self._cache.get(key)
        if out is None:
            self.runs += 1
            out = self.model.run(p)
            self._remember(key, out)
        else:
            self._cache.move_to_end(key)
        return out

    def _remember(self, key: tuple, out: dict) -> None:
        self._cache[key] = out
        if len(self._cache) > CACHE_RUNS:
            self._cache.popitem(last=False)

    def predict(self, theta: np.ndarray, effects: dict | None = None) -> np.ndarray:
        """Whitened prediction of the observed channels, shape [n_ch * n_t] (channel-major)."""
        # concatenate makes a new array: the cached outputs need no copy first.
        out = self._run(theta, effects)
        return np.concatenate([out[self.var[c]] for c in self.channels]) / self.sigma

    def close(self) -> None:
        """Done with this twin: its FMU instance is kept for the next twin of the process
        (:func:`release_spare` frees it)."""
        if self.model is None:
            return
        release_spare()
        _SPARE[self._model_key] = self.model
        self.model = None
        # A Dask worker outlives the stage: the pool's end frees the spare (and removes its
        # extracted FMU), as it closes what the pool's set-up opened (docs/cluster.md).
        from ..executors.dask import close_with_pool
        close_with_pool(release_spare)


def release_spare() -> None:
    """Free the FMU instance kept by the last twin closed in this process (and remove its
    extracted FMU)."""
    # popitem, not a test then a pop: Dask workers run one task at a time, but a library
    # caller may close twins from threads.
    while True:
        try:
            _, model = _SPARE.popitem()
        except KeyError:
            return
        model.close()
