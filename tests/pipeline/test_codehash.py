"""The cache key covers the code: a one-line change in a helper recomputes exactly the stages that import it."""

from __future__ import annotations

import importlib
import itertools
import json
import logging
import os
import pathlib
import re
import sys
import textwrap

import pytest
from fluorocal.cache import ArtifactCache
from fluorocal.codehash import AnalysisMemo, code_digest
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


def test_docstrings_do_not_change_the_digest(package):
    """Docstrings are not code: editing one recomputes nothing (the issue's docstring in learn/params.py)."""
    helper = package / "_helper.py"
    before = code_digest([f"{PACKAGE}.second"])
    helper.write_text('"""Helpers."""\n\n\ndef twice(x):\n    """Twice ``x``."""\n    return 2 * x\n')
    assert code_digest([f"{PACKAGE}.second"]) == before


# --- the analyses kept between runs ----------------------------------------------------------------------------


def _fresh_process():
    """Forget the analyses this process made (as a new run starts without them)."""
    from fluorocal import codehash

    codehash._analyse.cache_clear()


def test_the_memo_gives_the_same_digest_without_parsing(package, tmp_path, monkeypatch):
    from fluorocal import codehash

    expected = code_digest([f"{PACKAGE}.second"])
    memo = AnalysisMemo(tmp_path / "analyses.json")
    assert code_digest([f"{PACKAGE}.second"], memo) == expected
    memo.save()
    _fresh_process()

    def no_parsing(*args, **kwargs):
        raise AssertionError("a module the memo holds was parsed")

    monkeypatch.setattr(codehash.ast, "parse", no_parsing)
    assert code_digest([f"{PACKAGE}.second"], AnalysisMemo(tmp_path / "analyses.json")) == expected


def test_an_edited_module_changes_the_digest_whatever_its_size_and_time(package, tmp_path):
    """The memo is keyed by each module's text: an edit of the same size with the file's time put back still counts."""
    memo = AnalysisMemo(tmp_path / "analyses.json")
    before = code_digest([f"{PACKAGE}.second"], memo)
    memo.save()
    helper = package / "_helper.py"
    stat = helper.stat()
    helper.write_text(helper.read_text().replace("2 * x", "3 * x"))
    os.utime(helper, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert (helper.stat().st_size, helper.stat().st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)
    _fresh_process()
    edited = code_digest([f"{PACKAGE}.second"], AnalysisMemo(tmp_path / "analyses.json"))
    assert edited != before
    _fresh_process()
    assert code_digest([f"{PACKAGE}.second"]) == edited  # what parsing the edited module gives


def test_a_kept_memo_sees_a_module_edited_while_the_process_runs(package, tmp_path):
    """One memo kept by a long-lived process (a notebook, a server): an edit between two digests is seen."""
    memo = AnalysisMemo(tmp_path / "analyses.json")
    before = code_digest([f"{PACKAGE}.second"], memo)
    helper = package / "_helper.py"
    helper.write_text(helper.read_text().replace("2 * x", "3 * x"))
    edited = code_digest([f"{PACKAGE}.second"], memo)
    assert edited != before
    _fresh_process()
    assert code_digest([f"{PACKAGE}.second"]) == edited  # what parsing the edited module gives
    helper.write_text(helper.read_text().replace("3 * x", "2 * x"))
    assert code_digest([f"{PACKAGE}.second"], memo) == before


@pytest.mark.parametrize("enabled", [True, False])
def test_the_cycle_collector_is_left_as_it_was_even_by_a_syntax_error(package, enabled):
    import gc

    (package / "_helper.py").write_text("def twice(x):\n    return 2 *\n")
    _fresh_process()
    gc.enable() if enabled else gc.disable()
    try:
        with pytest.raises(SyntaxError):
            code_digest([f"{PACKAGE}.second"])
        assert gc.isenabled() == enabled
    finally:
        gc.enable()


def test_an_unreadable_memo_or_entry_is_ignored(package, tmp_path):
    expected = code_digest([f"{PACKAGE}.second"])
    path = tmp_path / "analyses.json"
    path.write_text("{not json")
    assert code_digest([f"{PACKAGE}.second"], AnalysisMemo(path)) == expected
    path.write_text("[" * 200_000)  # nested too deep for the decoder
    assert code_digest([f"{PACKAGE}.second"], AnalysisMemo(path)) == expected
    memo = AnalysisMemo(path)
    code_digest([f"{PACKAGE}.second"], memo)
    memo.save()
    entries = json.loads(path.read_text())
    key = next(iter(entries))
    entries[key] = ["not a digest", [], []]
    path.write_text(json.dumps(entries))
    assert key not in AnalysisMemo(path).entries
    _fresh_process()
    assert code_digest([f"{PACKAGE}.second"], AnalysisMemo(path)) == expected


@pytest.mark.parametrize(
    "tamper",
    [
        lambda body, functions: (body + ["codehash_toy.extra"], functions),  # a module the source never names
        lambda body, functions: (body, functions + ["codehash_toy.extra"]),
        lambda body, functions: ([], []),  # its imports dropped: the helper would leave the digest
        lambda body, functions: ([m for m in body if "_helper" not in m], functions),
        lambda body, functions: (body + ["os.system('x')"], functions),  # not a module name
    ],
)
def test_a_memo_entry_not_fitting_its_source_is_ignored(package, tmp_path, tamper, caplog):
    """The memo is data: an entry listing what the source does not import, or not what it does, is not used."""
    (package / "extra.py").write_text("VALUE = 1\n")  # importable, imported by no module
    expected = code_digest([f"{PACKAGE}.second"])
    path = tmp_path / "analyses.json"
    memo = AnalysisMemo(path)
    code_digest([f"{PACKAGE}.second"], memo)
    memo.save()
    second = package / "second.py"
    key = AnalysisMemo.key(f"{PACKAGE}.second", second, second.read_text())
    entries = json.loads(path.read_text())
    body, functions = tamper(*entries[key][1:])
    assert (body, functions) != tuple(entries[key][1:])
    entries[key] = [entries[key][0], body, functions]
    path.write_text(json.dumps(entries))
    _fresh_process()
    with caplog.at_level(logging.DEBUG, logger="fluorocal.codehash"):
        assert code_digest([f"{PACKAGE}.second"], AnalysisMemo(path)) == expected
    assert "does not fit its source" in caplog.text


# --- the project's own stages, on a copy of the package ----------------------------------------------

#: run in a fresh interpreter on the copy: import the stage's modules, then run, in each project module
#: imported, every import statement of its functions (as calling them would), until nothing new loads.
#: Python's own import system decides what that executes; the modules and libraries loaded are printed.
#: A package only loaded as the parent of a module runs its body, not its functions: those of modules
#: named by an import statement are run.
ORACLE = """
import ast, builtins, json, sys, importlib
named = set(sys.argv[1:])
real_import = builtins.__import__
def recording(name, globals=None, locals=None, fromlist=(), level=0):
    base = importlib.util.resolve_name("." * level + name, (globals or {}).get("__package__")) if level else name
    named.update([base, *(f"{base}.{item}" for item in fromlist or ())])
    return real_import(name, globals, locals, fromlist, level)
builtins.__import__ = recording
for root in sys.argv[1:]:
    importlib.import_module(root)
done = set()
while True:
    todo = [n for n in list(sys.modules) if n.split(".")[0] == "fluorocal" and n in named and n not in done]
    if not todo:
        break
    for name in todo:
        done.add(name)
        module = sys.modules[name]
        tree = ast.parse(open(module.__file__, encoding="utf-8").read())
        for function in ast.walk(tree):
            if isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for node in ast.walk(function):
                    if isinstance(node, (ast.Import, ast.ImportFrom)):
                        code = compile(ast.Module([node], []), module.__file__, "exec")
                        exec(code, dict(module.__dict__))
files = {n: m.__file__ for n, m in sys.modules.items() if n.split(".")[0] == "fluorocal"}
libraries = sorted(set(importlib.import_module("fluorocal.codehash").LIBRARIES) & set(sys.modules))
print(json.dumps({"files": files, "libraries": libraries}))
"""

#: run once on the copy: each module in turn gets a line of code appended, and the stages' digests are
#: compared with the unedited ones; then each library's version is changed in turn
EDITS = """
import json, sys, pathlib
from fluorocal import codehash
roots, top = json.loads(sys.argv[1]), pathlib.Path(sys.argv[2])
digests = lambda: {stage: codehash.code_digest(modules) for stage, modules in roots.items()}
base = digests()
changed = {}
for path in [pathlib.Path(a) for a in sys.argv[3:]] or sorted(top.rglob("*.py")):
    text = path.read_text(encoding="utf-8")
    path.write_text(text + "\\n_CODEHASH_PROBE = 1\\n", encoding="utf-8")
    now = digests()
    path.write_text(text, encoding="utf-8")
    changed[str(path)] = sorted(s for s in roots if now[s] != base[s])
libraries = {}
real = codehash._library_version
for library in codehash.LIBRARIES:
    codehash._library_version = lambda name, library=library: "0+test" if name == library else real(name)
    now = digests()
    libraries[library] = sorted(s for s in roots if now[s] != base[s])
print(json.dumps({"modules": changed, "libraries": libraries}))
"""


def _python(code: str, root, *args) -> dict:
    import json
    import os
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(root), "PYTHONDONTWRITEBYTECODE": "1"}  # a throwaway copy
    done = subprocess.run([sys.executable, "-c", code, *args], cwd=root, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.splitlines()[-1])


def _package_copy(root):
    """The package copied into ``root`` (``pipeline/`` as ``fluorocal``, ``stages/`` in it); each stage's modules."""
    import shutil
    from pathlib import Path

    import fluorocal
    from fluorocal.graph import default_stages

    source = Path(fluorocal.__file__).parent
    ignore = shutil.ignore_patterns("__pycache__")
    shutil.copytree(source, root / "fluorocal", ignore=ignore)
    shutil.copytree(source.parent / "stages", root / "fluorocal" / "stages", ignore=ignore, dirs_exist_ok=True)
    return {stage.name: list(stage.code_modules()) for stage in default_stages()}


@pytest.fixture(scope="module")
def project_copy(tmp_path_factory):
    """The package copied, what each stage runs, and the stages whose key each module's edit changes."""
    import json

    root = tmp_path_factory.mktemp("copy")
    roots = _package_copy(root)
    runs = {stage: _python(ORACLE, root, *modules) for stage, modules in roots.items()}
    edits = _python(EDITS, root, json.dumps(roots), str(root / "fluorocal"))
    return root, runs, edits


@pytest.mark.check  # every module in turn, in a copy of the package: make test keeps the issue's own cases
def test_each_module_changes_the_key_of_exactly_the_stages_that_run_it(project_copy):
    root, runs, edits = project_copy
    for stage, run in runs.items():  # the copy was run, not the installed package
        assert all(path.startswith(str(root)) for path in run["files"].values()), stage
    assert len(edits["modules"]) > 100  # every module of the package, pipeline and stages
    for path, changed in edits["modules"].items():
        running = sorted(stage for stage, run in runs.items() if path in run["files"].values())
        assert changed == running, path


def test_the_issue_cases(tmp_path):
    """A kNN learning-loop edit or a parameter docstring of the learning no longer recomputes the detection.

    The issue's four modules edited in a copy of the package (every module in turn: `make check`).
    """
    import json

    roots = _package_copy(tmp_path)
    stages = tmp_path / "fluorocal" / "stages"
    probed = [stages / "learn" / "loop.py", stages / "detect.py", tmp_path / "fluorocal" / "gather.py"]
    probed.append(tmp_path / "fluorocal" / "graph.py")
    # the kinds' entries: the plate's solver is the learning's alone, the labelling's dispatch the label stage's
    probed += [stages / "plate" / "solve.py", stages / "kinds" / "labelling.py", stages / "kinds" / "learning.py"]
    edits = _python(EDITS, tmp_path, json.dumps(roots), str(tmp_path / "fluorocal"), *map(str, probed))
    assert sorted(edits["modules"]) == sorted(map(str, probed))
    assert edits["modules"][str(stages / "learn" / "loop.py")] == ["label", "learn"]  # label imports learn.grid
    assert edits["modules"][str(stages / "detect.py")] == ["centroid", "detect"]  # centroid imports detect's helpers
    assert edits["modules"][str(tmp_path / "fluorocal" / "gather.py")] == ["learn"]
    assert edits["modules"][str(tmp_path / "fluorocal" / "graph.py")] == []  # the hooks' values are in the key
    assert edits["modules"][str(stages / "plate" / "solve.py")] == ["learn"]
    assert edits["modules"][str(stages / "kinds" / "labelling.py")] == ["label"]
    assert edits["modules"][str(stages / "kinds" / "learning.py")] == ["learn"]


@pytest.mark.check  # every module in turn, in a copy of the package: make test keeps the issue's own cases
def test_a_library_version_changes_the_key_of_exactly_the_stages_that_call_it(project_copy):
    _, runs, edits = project_copy
    for library, changed in edits["libraries"].items():
        assert changed == sorted(stage for stage, run in runs.items() if library in run["libraries"]), library
    assert edits["libraries"]["scipy"]  # not vacuous: some stage calls SciPy


NESTED = """
import a
try:
    import b
except ImportError:
    import c
else:
    from . import d
finally:
    import e
with open(x) as fh:
    import f
match x:
    case 1:
        import g
class K:
    import h

    def method(self):
        import i
if TYPE_CHECKING:
    import j
else:
    import k
for _ in ():
    if y:
        def late():
            try:
                pass
            except* ValueError:
                import m
            return lambda: __import__("n")
while z:
    import o
async def coro():
    async with x:
        import p
    async for _ in y:
        import q
    class Local:
        import r

        def method(self):
            import s
    if typing.TYPE_CHECKING:
        import t
    else:
        import u
@decorate
class Outer:
    if TYPE_CHECKING:
        import v
    elif w:
        import w
"""


def test_imports_in_every_kind_of_block_are_followed():
    """Only statements hold imports and functions: each block's are found, a function's apart from the body's."""
    from fluorocal.codehash import _analyse

    _, body, functions = _analyse("pkg.mod", pathlib.Path("mod.py"), NESTED)
    assert sorted(body) == ["a", "b", "c", "e", "f", "g", "h", "k", "o", "pkg", "pkg.d", "w"]
    assert sorted(functions) == ["i", "m", "p", "q", "r", "s", "u"]  # a class in a function runs with it


#: ``<C>`` where code is, in every kind of block; ``<D>`` in the docstrings of the module, classes and functions
BLOCKS = '''
"""Module <D>."""
import a
x = <C>
"a string statement that is not a docstring <C>"
@decorate(<C>)
class K(Base, key=<C>):
    """Class <D>."""

    y: int = <C>

    @staticmethod
    def method(z=<C>, *, w: "<C>" = None) -> "<C>":
        """Method <D>."""
        "a second string <C>"
        return [lambda v=<C>: v + <C> for _ in range(<C>) if _ > <C>], {k: <C> for k in ()}
async def coro():
    """Coroutine <D>."""
    async with a(<C>) as b:
        <C>
    async for _ in b:
        await b(<C>)
    def inner():
        class Local:
            """Local <D>."""

            w = <C>
        return Local
    return inner
if TYPE_CHECKING:
    "the first statement of a block <C>"
    T = <C>
else:
    T = <C>
try:
    "the first statement of a try <C>"
except* ValueError:
    x = <C>
else:
    x = <C>
finally:
    x = <C>
match x:
    case {"k": <C>} if x > <C>:
        x = <C>
    case [<C>, *rest]:
        pass
while x:
    "the first statement of a loop <C>"
else:
    del x, y[<C>]
for x in ():
    pass
else:
    with a(<C>):
        assert x, <C>
'''


def _variant(text: str, edited: int | None) -> str:
    """``text`` with every marker ``0`` but the ``edited``-th, ``1``."""
    count = itertools.count()
    return re.sub(r"<[CD]>", lambda m: "1" if next(count) == edited else "0", text)


def test_a_change_in_any_block_changes_the_digest_and_one_in_a_docstring_none():
    """Only docstrings are left out: a change anywhere else gives its own digest (a cache entry never served stale)."""
    from fluorocal.codehash import _analyse

    markers = re.findall(r"<[CD]>", BLOCKS)
    variants = [_variant(BLOCKS, i) for i in [None, *range(len(markers))]]
    base, *edited = [_analyse("pkg.mod", pathlib.Path("mod.py"), text)[0] for text in variants]
    code = [digest for digest, marker in zip(edited, markers) if marker == "<C>"]
    assert len(set(code)) == len(code) == 33 and base not in code
    assert [digest for digest, marker in zip(edited, markers) if marker == "<D>"] == [base] * 5
