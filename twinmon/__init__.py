"""twinmon: health monitoring of industrial machines through calibrated digital twins.

The library is organised one module per pipeline stage (``simulate``, ``fabricate``,
``reduce``, ``calibrate``, ``forecast``, ``diagnose``, ``report``), each a function taking a
typed :class:`~twinmon.config.Config` and paths; ``twinmon.cli`` is a thin shell over them.
"""
__version__ = "0.2.0"
