"""twinmon is not tied to the pump: its names live in configs/ and fmus/, not in the library."""
from __future__ import annotations

import re

from ..conftest import ROOT

#: Strings of the pump model (FMU variables, its channel name, units and safety constants).
PUMP_WORDS = re.compile(r"pump\.|motor\.|m_flow|kg/s|nominal_flow")


def test_no_pump_names_in_the_library():
    hits = []
    for path in sorted((ROOT / "twinmon").rglob("*.py")):
        for lineno, line in enumerate(path.read_text().splitlines(), 1):
            if PUMP_WORDS.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{lineno}: {line.strip()}")
    assert not hits, "pump names in twinmon/:\n" + "\n".join(hits)
