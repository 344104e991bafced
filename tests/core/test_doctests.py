"""The examples in the numpy core's docstrings run (doctest), so they stay true."""

import doctest
import importlib

import pytest

CORE = ["dolfinx_lopinf.core.basis", "dolfinx_lopinf.core.ddt", "dolfinx_lopinf.core.fit", "dolfinx_lopinf.core.inference",
        "dolfinx_lopinf.core.io_atomic"]


@pytest.mark.parametrize("name", CORE)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0, f"{name} has no examples to run"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
