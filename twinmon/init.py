"""A starter config for a new FMU: what ``twinmon init MODEL.fmu -o my.yaml`` writes.

The starter lists, from the FMU's model description, every tunable parameter as a candidate
degradation input (and as a candidate unmodelled effect), every recordable variable for the
observed output and the further channels, and the health indicator's keys. Everything that
only the user can decide (which inputs, their design box, the output, the indicator and its
limit) is left commented or marked ``<fill in>``, so that loading the file fails, naming the
first missing key, until it is filled in: a starter never runs by accident on guessed values.
"""
from __future__ import annotations

import json
import math
import os
import re
import tempfile
from pathlib import Path

from .config import PLACEHOLDER
from .errors import ConfigError
from .fmu import FMUInfo, VariableInfo, describe_fmu

__all__ = ["starter_config", "write_starter_config", "FILL"]

#: The placeholder for every value only the user can give (the loader refuses it anywhere).
FILL = PLACEHOLDER

_PLAIN_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_.()\-]*$")


def _key(name: str) -> str:
    """A YAML mapping key for an FMU variable name (quoted unless plainly safe)."""
    return name if _PLAIN_KEY.match(name) else json.dumps(name)


def _str(text: str) -> str:
    """A YAML scalar for free text: a JSON string is valid YAML."""
    return json.dumps(text, ensure_ascii=False)


def _num(value: float | None) -> str:
    """A YAML float (PyYAML needs a dot in the mantissa to read 7e-06 as a number)."""
    if value is None or not math.isfinite(value):
        return FILL
    s = repr(float(value))
    if "e" in s and "." not in s.split("e")[0]:
        mant, exp = s.split("e")
        s = f"{mant}.0e{exp}"
    return s


def _input_key(name: str, taken: set[str]) -> str:
    key = re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_").lower() or "input"
    if key[0].isdigit():
        key = "p_" + key
    base, k = key, 2
    while key in taken:
        key, k = f"{base}_{k}", k + 1
    taken.add(key)
    return key


def _component(name: str) -> str:
    return name.split(".")[0] if "." in name else FILL


def _describe_line(v: VariableInfo, width: int) -> str:
    unit = v.unit or "-"
    what = v.description or ""
    return f"{v.name:<{width}}  {v.type:<8} {unit:<12} {v.causality:<7} {what}".rstrip()


def _fmu_ref(fmu_path: Path, base_dir: Path | None) -> str:
    p = Path(fmu_path).resolve()
    if base_dir is None:
        return str(p)
    base = Path(base_dir).resolve()
    try:
        if os.path.commonpath([p, base]) == p.anchor:   # nothing in common but the root
            return str(p)
        return os.path.relpath(p, base)
    except ValueError:          # another drive (Windows): keep it absolute
        return str(p)


def starter_config(fmu_path, base_dir=None) -> str:
    """The starter YAML for an FMU, as text.

    Parameters
    ----------
    fmu_path : Path or str
        A ``.fmu`` file or an FMU source folder (built and cached to be read).
    base_dir : Path or str, optional
        Folder the YAML will live in: ``model.fmu`` is written relative to it (the config
        schema resolves paths against the YAML file). None: an absolute path.

    Returns
    -------
    str
        YAML that parses, names every tunable parameter and recordable variable of the FMU
        (commented), and fails :func:`twinmon.config.load_config` until its ``<fill in>``
        values and commented required keys are filled in.

    Raises
    ------
    SimulationError
        The FMU cannot be read (one line naming the file).
    """
    info: FMUInfo = describe_fmu(fmu_path)
    params = info.tunable_parameters()
    recordable = info.recordable()
    outputs = [v for v in recordable if v.causality == "output"]
    flags = [v for v in outputs if v.type not in ("Real", "Float64", "Float32")
             or v.variability == "discrete"]
    first_float_out = next((v for v in outputs if v.is_float), None)
    kinds = [k for k, ok in (("CoSimulation", info.co_simulation),
                             ("ModelExchange", info.model_exchange)) if ok]
    fmi_type = "CoSimulation" if info.co_simulation else "ModelExchange"
    width = max([len(v.name) for v in params + recordable] + [8])
    L: list[str] = []
    add = L.append

    add(f"# twinmon starter config for {info.model_name or Path(info.path).stem} "
        f"(FMI {info.fmi_version}; {', '.join(kinds) or 'no interface'}),")
    add(f"# written by `twinmon init` from {Path(fmu_path)}.")
    if info.description:
        add(f"# FMU: {info.description}")
    add("#")
    add("# Fill in every <fill in>, uncomment the entries you use, delete the rest. Until then")
    add("# loading this file fails on purpose, naming the first key still missing. Other sections")
    add("# (simulate, reduce, calibrate, forecast, diagnose) have defaults; the worked examples")
    add("# in twinmon's configs/ folder are complete configs. Paths are relative to this file.")
    add("seed: 1")
    add("")
    add("model:")
    add(f"  fmu: {_str(_fmu_ref(Path(fmu_path), base_dir))}")
    other = [k for k in kinds if k != fmi_type]
    add(f"  fmi_type: {fmi_type}" + (f"             # this FMU also supports {other[0]}"
                                      if other else ""))
    add("")
    add("  # Calibrated degradation inputs (required): uncomment `inputs:` and at least one")
    add("  # candidate (the FMU's tunable parameters, start value as nominal); give its design box")
    add("  # (low <= nominal <= high), the component it belongs to (the verdicts' words) and its")
    add("  # normal yearly drift.")
    add("  # inputs:")
    if not params:
        add("  #   (this FMU declares no float parameter or input that can be set)")
    taken: set[str] = set()
    for v in params:
        key = _input_key(v.name, taken)
        add(f"  #   {key}:")
        add(f"  #     variable: {_key(v.name)}")
        add(f"  #     low: {FILL}")
        add(f"  #     high: {FILL}")
        add(f"  #     nominal: {_num(v.start)}")
        add(f"  #     units: {_str(v.unit or '1')}")
        add(f"  #     component: {_component(v.name)}")
        if v.description:
            add(f"  #     description: {_str(v.description)}")
        add("  #     normal_rate: 0.0            # yearly drift normal ageing allows")
        add(f"  #     normal_rate_tolerance: {FILL}")
        add("  #     # degrading: up             # up | down (omit: inferred from the twin)")
    add("")
    add("  output:")
    add(f"    # variable: {FILL}        # the observed FMU variable (required), one of:")
    for v in recordable:
        add(f"    #   {_describe_line(v, width)}")
    add(f"    # name: {FILL}            # its channel name in observation files (default: the variable)")
    add(f"    # label: {FILL}           # words for the report (default: the name)")
    unit = first_float_out.unit if first_float_out is not None else ""
    add(f"    units: {_str(unit or FILL)}")
    start, stop, step = info.step_size, info.stop_time, info.step_size
    if start and stop and step and stop > start:
        add(f"    times: {{start: {_num(start)}, stop: {_num(stop)}, step: {_num(step)}}}"
            "   # s, from the FMU's DefaultExperiment: set your plant's sampling")
    else:
        add(f"    times: {{start: {FILL}, stop: {FILL}, step: {FILL}}}   # s, the plant's sampling")
    add("")
    add("  # Further FMU variables recorded as observation channels (optional; any recordable")
    add("  # variable listed above):")
    add("  # channels:")
    for v in outputs:
        if first_float_out is not None and v.name == first_float_out.name:
            continue
        if v in flags:
            continue
        label = _str(v.description) if v.description else _str(v.name)
        add(f"  #   {_key(v.name)}: {{units: {_str(v.unit or '1')}, label: {label}}}")
    add("")
    hint = f"; candidates: {', '.join(v.name for v in flags)}" if flags else ""
    add("  # FMU output that is 1 when the twin left its physical domain (\"\" for none)" + hint)
    add("  nonphysical: \"\"")
    add("")
    add("  # FMU parameters held at another value than the FMU's default ({name: value}):")
    add("  fixed: {}")
    add("")
    add("  # Candidate unmodelled effects screened by `diagnose` (optional): a parameter whose")
    add("  # baseline value gives exactly the model you calibrate; measurement_only: true for a")
    add("  # sensor effect (left out when the twin judges safety). A state's start value (initial")
    add("  # exact) is a candidate too: the machine not starting from rest.")
    add("  # effects:")
    for v in params + info.start_values():
        desc = f", description: {_str(v.description)}" if v.description else ""
        add(f"  #   {_key(v.name)}: {{baseline: {_num(v.start)}, low: {FILL}, high: {FILL}, "
            f"units: {_str(v.unit or '1')}{desc}}}")
    add("")
    add("safety:")
    rows = [
        ("  indicator:", "the health indicator: one number per transient"),
        (f"    # kind: {FILL}", "required: time_to_reach | value_at | max | min | mean | final"),
        ('    variable: ""', "FMU variable (default: model.output.variable)"),
        (f"    # window: [{FILL}, {FILL}]", "s, for max | min | mean (default: the record)"),
        (f"    # level: {FILL}", "time_to_reach: the level to cross"),
        ("    # direction: up", "time_to_reach: up | down"),
        ("    # initial: 0.0", "time_to_reach: the value at t = 0 (a start from rest)"),
        (f"    # at: {FILL}", "value_at: the time (s)"),
        ('    name: ""', "short name (default: from the kind)"),
        ('    label: ""', "words for the report"),
        ('    units: ""', "default: the variable's (s for time_to_reach)"),
        (f"  # unsafe_if: {{below: {FILL}}}", f"required: {{below: limit}} or {{above: limit}}"),
        ("  failure_probability: 0.05", "fails in the first year P(unsafe) exceeds this"),
    ]
    for code, comment in rows:
        add(f"{code:<35} # {comment}")
    return "\n".join(L) + "\n"


def write_starter_config(fmu_path, output, force: bool = False) -> Path:
    """Write :func:`starter_config` for ``fmu_path`` to ``output`` (atomically).

    Parameters
    ----------
    fmu_path : Path or str
        A ``.fmu`` file or an FMU source folder.
    output : Path or str
        The YAML file to write; ``model.fmu`` in it is relative to its folder.
    force : bool
        Overwrite an existing file.

    Returns
    -------
    Path
        ``output``.

    Raises
    ------
    ConfigError
        ``output`` exists and ``force`` is false.
    SimulationError
        The FMU cannot be read.
    """
    out = Path(output)
    if out.exists() and not force:
        raise ConfigError(f"{out}: already exists; use --force to overwrite it")
    text = starter_config(fmu_path, base_dir=out.parent if str(out.parent) else Path("."))
    folder = out.parent if str(out.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return out
