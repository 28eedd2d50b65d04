"""The whole configuration: :class:`Config` holds every section, checks what spans
sections, and writes the provenance YAML that artifacts record.

``EXECUTION_ONLY`` lists, per section, the keys that only spread the work over processes;
they are left out of that YAML.
"""
from __future__ import annotations

import difflib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Optional

import numpy as np
import yaml

from .calibrate import CalibrateConfig
from .dask import DaskConfig
from .diagnose import DiagnoseConfig, WindowSpec
from .fabricate import FabricateConfig
from .forecast import BacktestConfig, ForecastConfig
from .model import ModelConfig
from .reduce import ReduceConfig
from .report import ReportConfig
from .safety import SafetyConfig
from .schema import to_plain
from .simulate import SimulateConfig


@dataclass(frozen=True)
class Config:
    """A whole resolved twinmon configuration."""

    model: ModelConfig
    #: The safety criterion (health indicator and its limit).
    safety: SafetyConfig
    seed: int = 0
    simulate: SimulateConfig = SimulateConfig()
    reduce: ReduceConfig = ReduceConfig()
    calibrate: CalibrateConfig = CalibrateConfig()
    forecast: ForecastConfig = ForecastConfig()
    backtest: BacktestConfig = BacktestConfig()
    diagnose: DiagnoseConfig = DiagnoseConfig()
    fabricate: Optional[FabricateConfig] = None
    #: The Dask cluster of ``executor: dask`` (never changes a result).
    dask: DaskConfig = DaskConfig()
    report: ReportConfig = ReportConfig()
    #: Where this config came from (not a YAML key).
    source: Path = field(default=Path("<memory>"), compare=False)
    #: The merged mapping after overrides (not a YAML key): a base for derived configs.
    raw: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def indicator_variable(self) -> str:
        """The FMU variable the health indicator is computed from."""
        return self.safety.indicator.variable or self.model.output.variable

    def for_workers(self) -> "Config":
        """This config without what only the main process reads: ``fabricate`` (a
        fabricated fleet's trajectories) and ``raw``. What a stage hands to each task of
        its workers: a task pickles the config it carries, and a fabricated fleet of 1000
        units makes that 0.43 MB to pickle and 87 ms to unpickle (4 kB and 2 ms without)."""
        return replace(self, fabricate=None, raw={})

    def diagnose_windows(self) -> dict[str, "WindowSpec"]:
        """The named windows of ``diagnose``: the config's, or the record in thirds."""
        if self.diagnose.windows:
            return dict(self.diagnose.windows)
        t = self.model.output.times.times
        # Cut half-way between samples so every sample falls in exactly one window.
        edges = np.quantile(np.concatenate([[0.0], t]), [1 / 3, 2 / 3])
        return {"early": WindowSpec(0.0, float(edges[0])),
                "middle": WindowSpec(float(edges[0]), float(edges[1])),
                "late": WindowSpec(float(edges[1]), float(t[-1]) + 1.0)}

    def _check(self):
        if not 0 <= self.seed < 2 ** 32:
            yield "seed", "must lie in [0, 2**32 - 1] (OpenTURNS and numpy seeds)", self.seed
        for section in ("reduce", "calibrate"):
            for i, ch in enumerate(getattr(self, section).channels or ()):
                if ch not in self.model.channels:
                    yield f"{section}.channels.{i}", "not a key of model.channels (channels: " \
                        f"{', '.join(self.model.channels) or 'none'})", ch
        times = self.model.output.times.times
        for name, w in self.diagnose.windows.items():
            if not np.any((times >= w.start) & (times < w.stop)):
                yield f"diagnose.windows.{name}", "holds no sample of the record " \
                    f"(model.output.times: {times[0]:g} to {times[-1]:g} s)", [w.start, w.stop]
        comps = self.model.components
        inputs = list(self.model.inputs)
        for unit, spec in (self.fabricate.units if self.fabricate else {}).items():
            # A misspelt input first (its closest name), then one left out.
            for key in spec.trajectories:
                if key not in self.model.inputs:
                    near = difflib.get_close_matches(key, inputs, n=1, cutoff=0.5)
                    yield f"fabricate.units.{unit}.trajectories.{key}", \
                        "not an input of the model" + (f" (did you mean {near[0]}?)" if near
                                                       else f" (inputs: {', '.join(inputs)})"), \
                        key
            for name in inputs:
                if name not in spec.trajectories:
                    yield f"fabricate.units.{unit}.trajectories.{name}", \
                        "missing: every input needs a trajectory (given for)", \
                        sorted(spec.trajectories)
            for i, ev in enumerate(spec.events):
                if ev.component not in comps:
                    yield f"fabricate.units.{unit}.events.{i}.component", \
                        f"not a component of model.inputs (components: {', '.join(comps)})", \
                        ev.component

    def section_yaml(self, *names: str) -> str:
        """The resolved YAML of the named sections, recorded in artifacts as provenance.

        Settings that decide how the work is spread over processes but cannot change a
        result (``EXECUTION_ONLY``) are left out, so changing them does not make ``twinmon
        run`` redo a stage."""
        out = {n: to_plain(getattr(self, n)) for n in names}
        if "calibrate" in out and self.calibrate.method == "auto":
            # auto picks the method by forecast's pooling settings, so they decide calibrate's
            # result: recorded with it (changing them re-runs calibrate, refuses --update).
            out["calibrate"]["auto_by"] = {"forecast.pool_sigma": self.forecast.pool_sigma,
                                           "forecast.pool_min_units":
                                               self.forecast.pool_min_units}
        if "calibrate" in out and self.calibrate.method != "sequential":
            # The joint method starts a trend segment at each unrecorded repair it finds, at
            # forecast's level: it decides the posterior too.
            out["calibrate"]["repairs_by"] = {"forecast.repair_alpha": self.forecast.repair_alpha}
        if "calibrate" in out:
            # Each year's goodness of fit (calibrate/fit.py) is judged on diagnose's windows
            # and Ljung-Box lags: they decide the posterior's fit records too (an update
            # that kept years fitted on other windows stored their indices, out of range).
            out["calibrate"]["fit_by"] = {
                # A list: the records store a window's index, so the order is part of it.
                "diagnose.windows": [[n, w.start, w.stop]
                                     for n, w in self.diagnose_windows().items()],
                "diagnose.ljung_box_lags": self.diagnose.ljung_box_lags}
        for section, keys in EXECUTION_ONLY.items():
            if isinstance(out.get(section), dict):
                for k in keys:
                    out[section].pop(k, None)
        return yaml.safe_dump(out, sort_keys=True)


#: Per section, the keys that spread the work over processes without changing any result.
EXECUTION_ONLY = {"simulate": ("workers", "executor", "chunk_size"),
                  "calibrate": ("workers", "executor"), "diagnose": ("workers", "executor"),
                  "report": ("workers",),
                  "dask": ("address", "timeout")}
