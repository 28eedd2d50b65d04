"""The method and sampler interfaces (twinmon.calibrate.base) and the methods' registry
(twinmon.calibrate.methods): every ``calibrate.method`` the config accepts is a module with a
Method of that name, each has a sampler for every ``calibrate.sampler``, and a method is
found from its one file."""
from __future__ import annotations

import sys
import typing

import pytest

from twinmon.calibrate import methods
from twinmon.calibrate.base import Method, Sampler
from twinmon.calibrate.methods.sequential import SequentialMethod
from twinmon.config import CalibrateConfig
from twinmon.errors import ConfigError


def _choices(field: str) -> set[str]:
    return set(typing.get_args(typing.get_type_hints(CalibrateConfig)[field]))


def test_every_configured_method_is_a_module_with_a_sampler_per_choice():
    named = _choices("method") - {"auto"}
    assert set(methods.names()) == named
    for name in named:
        m = methods.method_named(name)
        assert isinstance(m, Method) and m.name == name
        assert set(m.samplers) == _choices("sampler")
        for s, sampler in m.samplers.items():
            assert isinstance(sampler, Sampler) and sampler.name == s


def test_update_continues_the_sequential_and_laplace_years_only():
    assert methods.method_named("sequential").continues_years
    assert not methods.method_named("joint").continues_years
    assert methods.method_named("laplace").continues_years


def test_unknown_names_are_refused_with_the_choices():
    with pytest.raises(ValueError, match="no calibration method 'nope' .*joint, laplace, sequential"):
        methods.method_named("nope")
    with pytest.raises(ConfigError, match="'gpu' cannot sample the joint method .*openturns"):
        methods.method_named("joint").sampler("gpu")


def test_a_method_is_one_file(tmp_path, monkeypatch):
    """A module dropped beside the methods' (here in a further folder of the package's
    search path) is found by its name, without any other file changed."""
    (tmp_path / "widened.py").write_text(
        "from twinmon.calibrate.methods.sequential import SequentialMethod\n\n\n"
        "class WidenedMethod(SequentialMethod):\n"
        "    name = 'widened'\n")
    monkeypatch.setattr(methods, "__path__", list(methods.__path__) + [str(tmp_path)])
    try:
        assert "widened" in methods.names()
        m = methods.method_named("widened")
        assert type(m).__name__ == "WidenedMethod" and isinstance(m, SequentialMethod)
        assert m.continues_years and set(m.samplers) == _choices("sampler")
    finally:
        sys.modules.pop(f"{methods.__name__}.widened", None)
