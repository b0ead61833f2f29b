"""The docstring examples of every installed module, run under the module's real name (fluorocal.*)."""

import doctest
import importlib
import pkgutil

import fluorocal
import pytest

MODULES = sorted(m.name for m in pkgutil.walk_packages(fluorocal.__path__, "fluorocal."))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
