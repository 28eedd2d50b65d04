"""Building FMUs from C sources, describing them, and running them fast, many times.

An FMU source folder holds ``modelDescription.xml`` and ``sources/*.c|*.h`` (FMI 2.0 or 3.0);
:func:`build_fmu` compiles it with the system C compiler into a ``.fmu`` cached under
``<src_dir>/.build/<hash>/`` (the hash covers the model description, the sources and the
build recipe), so an unchanged model is compiled once.  :func:`describe_fmu` reads what an
FMU offers (its parameters, outputs, types and units) for config checks and ``twinmon init``.
:class:`FMUModel` extracts an FMU once, keeps one instance and resets it between runs: an
FMI 2.0 or 3.0 Co-Simulation run costs a few dozen direct C calls. A crash in an FMU's native
code during a run ends the process with the one-line simulation error naming the FMU and the
run's inputs (:mod:`.guard`), not with a core dump.
"""
from __future__ import annotations

from .build import build_fmu, resolve_fmu, source_hash
from .common import FLOAT_TYPES, INTEGER_TYPES, NUMERIC_TYPES, closest_names  # noqa: F401
from .description import FMUInfo, VariableInfo, describe_fmu, why_not_settable
from .runner import FMUModel

__all__ = ["source_hash", "build_fmu", "resolve_fmu", "FMUModel", "VariableInfo", "FMUInfo",
           "describe_fmu", "closest_names", "why_not_settable"]
