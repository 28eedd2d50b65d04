"""An FMU whose native code crashes for some inputs (abort() or a bad pointer, instead of an
error status): in the command's own process the crash becomes the one-line simulation
error naming the FMU and the input, exit 6, the files already there untouched and no
extracted FMU left behind; in a pool worker the parent says so in one line, as before."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from ..conftest import ROOT
from .conftest import Snapshot, assert_fails, twinmon

#: Parameter values at which the built variant aborts / writes through a null pointer.
ABORT_AT, FAULT_AT = 750.0, 850.0


@pytest.fixture(scope="module")
def crashing_fmu(tmp_path_factory):
    """The pump FMU built from its sources with two crashes added to fmi2SetReal: any
    parameter set to a value in [700, 800) aborts, in [800, 900) faults."""
    from twinmon.fmu import build_fmu
    src = tmp_path_factory.mktemp("crash") / "PumpCircuit"
    shutil.copytree(ROOT / "fmus" / "PumpCircuit", src, ignore=shutil.ignore_patterns(".build"))
    c = src / "sources" / "fmi2.c"
    text = c.read_text()
    anchor = "            if (is_param(v)) m->p[v] = value[k];"
    assert anchor in text
    text = "#include <stdlib.h>\n" + text.replace(anchor, (
        "            if (value[k] >= 700.0 && value[k] < 800.0) abort();\n"
        "            if (value[k] >= 800.0 && value[k] < 900.0) *(volatile int *)0 = 1;\n")
        + anchor)
    c.write_text(text)
    return build_fmu(src)


@pytest.mark.parametrize("value,signal", [(ABORT_AT, "SIGABRT"), (FAULT_AT, "SIGSEGV")])
@pytest.mark.parametrize("fmi_type", ["CoSimulation", "ModelExchange"])
def test_crash_in_this_process_is_one_line(crashing_fmu, tmp_path, value, signal, fmi_type):
    script = (
        "import numpy as np\n"
        "from twinmon.fmu import FMUModel\n"
        f"with FMUModel({str(crashing_fmu)!r}, ['sensor.m_flow'], np.arange(1, 26) * 2.0, "
        f"fmi_type={fmi_type!r}) as m:\n"
        "    print(m.run({'motor.D': 14.0})['sensor.m_flow'][-1], flush=True)\n"
        f"    m.run({{'motor.D': {value}}})\n")
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=120, env=env)
    assert float(r.stdout.split()[0]) > 0          # the runs before the crash were fine
    assert_fails(r, 6, "simulation error", str(crashing_fmu),
                 f"crashed ({signal}) running motor.D={value:g}")
    assert not list(tmp_path.glob("twinmon-fmu-*")), "the extracted FMU was left behind"


def test_crash_outside_an_fmu_call_is_not_the_fmus(crashing_fmu, tmp_path):
    # The handler gives a crash elsewhere back to the handler it replaced (the default).
    # That crash leaves the extracted FMU behind, as any process killed outright does: in
    # the test's own folder, not the machine's temporary one.
    script = (
        "import ctypes, numpy as np\n"
        "from twinmon.fmu import FMUModel\n"
        f"m = FMUModel({str(crashing_fmu)!r}, ['sensor.m_flow'], np.arange(1, 26) * 2.0)\n"
        "m.run({})\n"
        "ctypes.string_at(0)\n")
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=120, env=env)
    assert r.returncode == -11 and "the FMU" not in r.stderr, (r.returncode, r.stderr)


@pytest.mark.parametrize("executor", ["serial", "process"])
def test_simulate_with_a_crashing_fmu(work, crashing_fmu, executor):
    """The design reaches the crashing inputs: the line names the FMU and the input, whether
    the crash ends the command's process or a pool worker (which leaves its line for the
    parent); nothing there changes."""
    snap = Snapshot(work)
    r = twinmon("simulate", "-c", work / "small.yaml", "--set", f"model.fmu={crashing_fmu}",
                "--set", f"simulate.executor={executor}",
                "--set", "model.inputs.motor_damping.high=760", "-o", work / "sim.h5",
                cwd=work)
    assert_fails(r, 6, str(crashing_fmu), "crashed (SIGABRT) running motor.D=7")
    assert not (work / "sim.h5").exists()
    snap.check()


def _crash_in_worker(args, fmu=None):
    import numpy as np

    from twinmon.fmu import FMUModel
    with FMUModel(fmu, ["sensor.m_flow"], np.arange(1, 26) * 2.0) as m:
        m.run({"motor.D": ABORT_AT})


def test_diagnose_worker_crash_names_the_input(work, crashing_fmu, monkeypatch):
    """A stage's own pool (diagnose's): the worker that crashed in an FMU is named by its
    line, not by the stage's generic "a worker process died"."""
    import functools

    import twinmon.diagnose as dg
    from twinmon.config import load_config
    from twinmon.errors import SimulationError
    cfg = load_config(work / "small.yaml")
    snap = Snapshot(work)
    monkeypatch.setattr(dg, "_job", functools.partial(_crash_in_worker, fmu=crashing_fmu))
    with pytest.raises(SimulationError) as info:
        dg.diagnose(cfg, work / "fleet.h5", work / "gap_new.h5", workers=2)
    assert f"crashed (SIGABRT) running motor.D={ABORT_AT:g}" in str(info.value)
    assert str(crashing_fmu) in str(info.value) and "\n" not in str(info.value)
    assert not (work / "gap_new.h5").exists()
    snap.check()
