"""The examples in the numpy core's docstrings run (doctest), so they stay true."""

import doctest
import importlib

import pytest

CORE = ["basis", "ddt", "fit", "inference", "io_atomic"]


@pytest.mark.parametrize("name", CORE)
def test_docstring_examples_run(name):
    module = importlib.import_module(f"dolfinx_lopinf.{name}")
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no examples to run"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
