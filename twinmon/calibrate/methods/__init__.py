"""The calibration methods, one module each (``calibrate.method``): :mod:`.sequential` (the
paper's, year by year) and :mod:`.joint` (a unit's whole history with its trend).

A module here defines one :class:`~twinmon.calibrate.base.Method` subclass whose ``name`` is
the module's own; :func:`method_named` finds it by that name, so a method is added as one
file (and its name in the config's ``calibrate.method`` choices).
"""
from __future__ import annotations

import importlib
import pkgutil

from ..base import Method


def names() -> list[str]:
    """The methods' names (their modules')."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__))


def method_named(name: str) -> Method:
    """An instance of the method ``name``.

    Raises
    ------
    ValueError
        No method module of that name, or it defines no ``Method`` of that name.
    """
    if name not in names():
        raise ValueError(f"no calibration method {name!r} (there are {', '.join(names())})")
    module = importlib.import_module(f"{__name__}.{name}")
    for obj in vars(module).values():
        if isinstance(obj, type) and issubclass(obj, Method) and obj.__module__ == module.__name__ \
                and getattr(obj, "name", None) == name:
            return obj()
    raise ValueError(f"{module.__name__} defines no Method named {name!r}")
