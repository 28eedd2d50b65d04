"""twinmon's command line: a thin click shell over the library, one module per command group.

Every command reads a config (``-c``), applies ``--set`` overrides, calls one library function
and prints a short human summary, or a machine-readable one with ``--json``. Errors of the
:class:`~twinmon.errors.TwinmonError` family become one line on stderr and the family's exit
code; the traceback is shown only with ``--verbose``.
"""
from __future__ import annotations

import sys

from .app import main

__all__ = ["main"]


def _register() -> None:
    # Each module attaches its commands to main as it is imported.
    from . import (backtest_cmd, calibrate_cmd, check_cmd, data, diagnose_cmd,  # noqa: F401
                   forecast_cmd, init_cmd, pipeline, report_cmd)


_register()

if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
