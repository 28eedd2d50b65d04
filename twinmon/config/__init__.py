"""Typed, frozen, validated configuration.

A config is one YAML file (optionally ``extends:`` another, merged key by key) holding the
sections below. It is loaded once, ``--set a.b=v`` overrides are applied to the raw mapping,
and only then is it validated: every unknown key is rejected and every error names the file,
the YAML path and the value received, so a typo never silently falls back to a default.

The sections are plain frozen dataclasses, one module per section group, each holding its
schema, defaults and checks (``_check``) together:

- ``model``: :class:`ModelConfig` and its parts (model.py);
- ``safety``: the health indicator and its limit (safety.py);
- ``simulate``, ``fabricate``, ``reduce``, ``calibrate``, ``diagnose``, ``report``,
  ``dask``: one module each; ``forecast`` and ``backtest``: forecast.py;
- :class:`Config`, the whole, and ``EXECUTION_ONLY`` (top.py);
- mapping to dataclass and back, :func:`to_plain` (schema.py); reading the YAML,
  ``extends:`` and overrides, :func:`load_config` (load.py).

Adding a key to a section is a one-line change in that section's module.
"""
from .calibrate import CalibrateConfig
from .dask import DaskConfig
from .diagnose import DiagnoseConfig, WindowSpec
from .fabricate import (Disturbance, FabricateConfig, FabricateEvent, InjectedEffect,
                        TrajectoryChange, TrajectorySpec, UnitSpec)
from .forecast import BacktestConfig, ForecastConfig
from .load import (PLACEHOLDER, DuplicateKeyError, StrictLoader, config_from_mapping,
                   load_config)
from .model import ChannelSpec, EffectSpec, InputSpec, ModelConfig, OutputSpec, TimeGrid
from .reduce import ReduceConfig
from .report import ReportConfig
from .safety import INDICATOR_KINDS, IndicatorSpec, SafetyConfig, UnsafeIf
from .schema import to_plain
from .simulate import SimulateConfig
from .top import EXECUTION_ONLY, Config

__all__ = [
    "BacktestConfig", "CalibrateConfig", "ChannelSpec", "Config", "DaskConfig", "DiagnoseConfig",
    "Disturbance", "DuplicateKeyError", "EXECUTION_ONLY", "EffectSpec", "FabricateConfig",
    "FabricateEvent", "ForecastConfig", "INDICATOR_KINDS", "IndicatorSpec", "InjectedEffect",
    "InputSpec", "ModelConfig", "OutputSpec", "PLACEHOLDER", "ReduceConfig", "ReportConfig", "SafetyConfig",
    "SimulateConfig", "StrictLoader", "TimeGrid", "TrajectoryChange", "TrajectorySpec", "UnitSpec", "UnsafeIf",
    "WindowSpec", "config_from_mapping", "load_config", "to_plain",
]
