"""The docstring examples of every installed module, run under the module's real name (fluorocal.*)."""

import doctest
import importlib
import pkgutil

import fluorocal
import fluorocal.stages
import pytest

# fluorocal.stages lives in a folder of its own (stages/), so it is walked on its own
MODULES = sorted(
    {"fluorocal", "fluorocal.stages"}
    | {m.name for m in pkgutil.walk_packages(fluorocal.__path__, "fluorocal.")}
    | {m.name for m in pkgutil.walk_packages(fluorocal.stages.__path__, "fluorocal.stages.")}
)


def test_every_stage_module_is_collected():
    assert {"fluorocal.stages.adjust", "fluorocal.stages.learn", "fluorocal.calibration"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
