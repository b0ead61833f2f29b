"""The cache key covers the code: a one-line change in a helper recomputes exactly the stages that import it."""

from __future__ import annotations

import importlib
import sys
import textwrap

import pytest
from fluorocal.cache import ArtifactCache
from fluorocal.codehash import code_digest
from fluorocal.config import load_config
from fluorocal.graph import Stage
from fluorocal.run import Runner

from tests.pipeline.toy import MeanParams, ScaleParams, gather, make_project

PACKAGE = "codehash_toy"

FILES = {
    "__init__.py": "",
    "_helper.py": "def twice(x):\n    return 2 * x\n",
    "first.py": """
        from tests.pipeline.toy import Value

        def mean(radiograph, params) -> Value:
            return Value([radiograph.image.mean() + params.offset])
    """,
    "second.py": """
        from . import _helper
        from tests.pipeline.toy import Value

        def scale(value, params) -> Value:
            # the helper is imported lazily elsewhere too; both forms are followed
            from codehash_toy._helper import twice

            return Value(twice(value.value) * params.factor)
    """,
}


@pytest.fixture()
def package(tmp_path, monkeypatch):
    root = tmp_path / "code"
    (root / PACKAGE).mkdir(parents=True)
    for name, text in FILES.items():
        (root / PACKAGE / name).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(root))
    yield root / PACKAGE
    for name in [m for m in sys.modules if m.split(".")[0] == PACKAGE]:
        del sys.modules[name]


def _stages():
    first = importlib.import_module(f"{PACKAGE}.first")
    second = importlib.import_module(f"{PACKAGE}.second")
    return [
        Stage("mean", first.mean, MeanParams, ("frame",)),
        Stage("scale", second.scale, ScaleParams, ("mean",), per_frame=False, gather=gather),
    ]


def _run(cfg):
    stages = _stages()
    config = load_config(cfg, stage_params_allowed={s.name: s.params_cls for s in stages})
    return Runner(config, stages, ArtifactCache(config.cache_dir), progress=False).run()


def test_a_changed_helper_recomputes_the_stages_that_import_it(package, tmp_path):
    cfg = make_project(tmp_path / "project")
    assert _run(cfg).computed == {"mean": 3, "scale": 1}
    assert _run(cfg).total_computed == 0
    helper = package / "_helper.py"
    helper.write_text(helper.read_text().replace("2 * x", "3 * x"))
    # the stage importing the helper (and all downstream of it) recomputes; the one that does not is served
    assert _run(cfg).computed == {"mean": 0, "scale": 1}


def test_comments_and_layout_do_not_change_the_digest(package):
    before = code_digest([f"{PACKAGE}.second"])
    helper = package / "_helper.py"
    helper.write_text("# a comment\n\n\ndef twice(x):\n    return 2 * x  # why\n")
    assert code_digest([f"{PACKAGE}.second"]) == before
    helper.write_text("def twice(x):\n    return 2 * x + 0\n")
    assert code_digest([f"{PACKAGE}.second"]) != before


def test_the_learning_stage_digest_covers_the_adjustment(monkeypatch):
    """The learning stage runs the adjustment: its digest must reach the adjustment's modules."""
    from fluorocal import codehash

    reached = []
    real = codehash._module_source
    monkeypatch.setattr(codehash, "_module_source", lambda name: reached.append(name) or real(name))
    code_digest(["fluorocal.stages.learn"])
    assert any(name.startswith("fluorocal.stages.adjust") for name in reached), sorted(set(reached))
