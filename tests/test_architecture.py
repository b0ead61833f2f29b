"""The shape of the package, read from its source.

No import cycle, no private name borrowed, packages in layers, and the calibration scheme decoded in one place.

Imports are read from the syntax trees of ``pipeline/`` (the package ``fluorocal``) and ``stages/``
(``fluorocal.stages``), function-level (lazy) ones included. Importing ``a.b.c`` runs the ``__init__`` of
``a.b`` too, so it counts as importing that package as well. Imports under ``if TYPE_CHECKING:`` never run
(they name types for annotations) and are left out.
"""

from __future__ import annotations

import ast
from pathlib import Path

import fluorocal

PIPELINE = Path(fluorocal.__file__).parent
STAGES = PIPELINE.parent / "stages"


def _modules() -> dict[str, Path]:
    found = {}
    for folder, package in ((PIPELINE, "fluorocal"), (STAGES, "fluorocal.stages")):
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            found[".".join((package, *parts))] = path
    return found


MODULES = _modules()


def _executed(tree):
    """The nodes of ``tree`` but those inside ``if TYPE_CHECKING:`` (its ``else`` kept)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        test = getattr(node, "test", None) if isinstance(node, ast.If) else None
        if isinstance(test, (ast.Name, ast.Attribute)) and getattr(test, "id", getattr(test, "attr", "")) == (
            "TYPE_CHECKING"
        ):
            todo += node.orelse
        else:
            todo += ast.iter_child_nodes(node)


def _imports(name: str) -> list[tuple[str, str | None]]:
    """``(project module imported, name taken from it or None)`` of every import statement of module ``name``."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in _executed(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names if alias.name in MODULES]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join([*parts[: len(parts) - node.level + 1], *([base] if base else [])])
            for alias in node.names:
                if f"{base}.{alias.name}" in MODULES:
                    found.append((f"{base}.{alias.name}", None))
                elif base in MODULES:
                    found.append((base, alias.name))
    return found


def _edges() -> dict[str, set[str]]:
    """Module -> the project modules importing it runs (the imported ones and their packages' ``__init__``)."""
    edges = {}
    for name in MODULES:
        targets = set()
        for target, _ in _imports(name):
            parts = target.split(".")
            packages = {".".join(parts[:i]) for i in range(1, len(parts) + 1)}
            # the importer's own packages are running already: importing from them runs nothing new
            own = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 2)}
            targets |= {p for p in packages - own if p in MODULES}
        edges[name] = targets
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan, iteratively)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_cycle():
    """The finder itself, on a known graph: a -> b -> c -> a is one cycle, d stands apart."""
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}
    assert _cycles(edges) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_package_is_read_whole():
    assert {"fluorocal.stages.learn.loop", "fluorocal.export", "fluorocal.stages"} <= set(MODULES)
    assert "fluorocal.stages.learn" in _edges()["fluorocal.stages.plate.solve"]  # the package's __init__ counts


def test_every_package_is_installed():
    """Every folder of ``pipeline/`` and ``stages/`` with an ``__init__.py`` is in pyproject's ``packages``.

    setuptools installs only the packages listed: one left out is missing from a wheel (not from an editable
    install, which the tests use), and the installed tool fails on importing it.
    """
    import tomllib

    setuptools = tomllib.loads((PIPELINE.parent / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    assert setuptools["package-dir"] == {"fluorocal": "pipeline", "fluorocal.stages": "stages"}
    found = {
        ".".join((package, *init.parent.relative_to(folder).parts))
        for folder, package in ((PIPELINE, "fluorocal"), (STAGES, "fluorocal.stages"))
        for init in folder.rglob("__init__.py")
    }
    assert {"fluorocal.kinds", "fluorocal.stages.kinds", "fluorocal.stages.plate"} <= found  # not vacuous
    assert sorted(found) == sorted(setuptools["packages"])


def test_no_import_cycle_lazy_ones_included():
    assert _cycles(_edges()) == []


def test_no_private_name_is_imported_from_another_module():
    borrowed = [
        f"{name}: {target}.{taken}"
        for name in MODULES
        for target, taken in _imports(name)
        if taken and taken.startswith("_") and not taken.startswith("__")
    ]
    assert borrowed == []


def _layer(module: str) -> str:
    """``pipeline`` for the package ``fluorocal``'s own modules; a stage package or module by its name."""
    if not module.startswith("fluorocal.stages"):
        return "pipeline"
    return ".".join(module.split(".")[:3])


def test_packages_are_layers():
    """Between packages the imports go one way: no package imports from one that imports from it, directly or not.

    So the packages sort into layers, each importing only from those below; the stages never import the pipeline.
    """
    layers: dict[str, set[str]] = {}
    for name, targets in _edges().items():
        layers.setdefault(_layer(name), set()).update(_layer(t) for t in targets if _layer(t) != _layer(name))
    assert _cycles(layers) == []
    assert not any("pipeline" in targets for layer, targets in layers.items() if layer != "pipeline")


def _names(node) -> str:
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else ""


def _literals(node) -> list[str]:
    elements = node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
    return [e.value for e in elements if isinstance(e, ast.Constant) and isinstance(e.value, str)]


#: the values spelled in the project file that the code reads as enumerations: the scheme, the learning's switches
#: (:data:`~fluorocal.stages.learn.params.SWITCHES`) and what responds to the joint step
SPELLED = ("scheme", "acceleration", "refine", "training", "field_gauge", "respond")


def _scheme_spellings(text: str, words: tuple[str, ...] = ("scheme",)) -> list[int]:
    """Lines where ``text`` decodes a spelling: compares a value named after a word of ``words`` with a literal.

    Or splits it, or asks whether it starts or ends with a text. ``words`` default to the scheme alone.
    """
    found = []

    def named(node) -> bool:
        return any(word in _names(node).lower() for word in words)

    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(named(s) for s in sides) and any(_literals(s) for s in sides):
                found.append(node.lineno)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if node.func.attr in ("startswith", "endswith", "split") and named(node.func.value):
                found.append(node.lineno)
    return sorted(found)


def test_the_scheme_and_the_switches_are_decoded_in_one_place():
    """Only their enumerations (:mod:`fluorocal.stages.learn.params`) read the scheme's and the switches' spellings.

    The rest compares members or asks the value what it does.
    """
    home = STAGES / "learn" / "params.py"
    found = {
        name: lines
        for name, path in MODULES.items()
        if path != home and (lines := _scheme_spellings(path.read_text(encoding="utf-8"), SPELLED))
    }
    assert found == {}


def test_the_scheme_check_sees_the_decodings_the_issue_names():
    """The four decodings issue 29 lists (one a line) are seen; asking the parsed value is not."""
    decodings = (
        'a = set(scheme.split("+"))\n'
        'if scheme == "polynomial": pass\n'
        'b = setup.scheme != "none"\n'
        'c = project_scheme if project_scheme.startswith("knn") else None\n'
        "d = scheme.polynomial or setup.scheme.corrects or phase == 'knn'\n"
    )
    assert _scheme_spellings(decodings) == [1, 2, 3, 4]
    switches = (
        'if params.refine != "none": pass\nlocal = plan.params.training == "local"\nx = params.refine is Refine.NONE\n'
    )
    assert _scheme_spellings(switches, SPELLED) == [1, 2]


#: builtins whose argument a branch decides by as if it were the test itself
TRUTH_TESTS = ("bool", "len", "any", "all")
#: the home of the phantom kinds (issue 29): the only place that may decide anything by a phantom's ``lattice``
KINDS_HOME = (STAGES / "kinds",)


def _lattice_branches(text: str) -> list[int]:
    """Lines where ``text`` branches on a ``.lattice`` attribute.

    That is: an ``if``/``while``/``assert`` or conditional test, a comprehension's condition, or an operand of
    ``and``/``or``/``not`` or of a comparison, holding it.

    A call's arguments (but a truth or size test's: ``bool``, ``len``) and a subscript's key are not searched:
    passing the value on (the lattice geometry takes it as data) or looking it up in a table is not a decision by it.
    """

    def holds(node) -> bool:
        todo = [node]
        while todo:
            node = todo.pop()
            if isinstance(node, ast.Attribute) and node.attr == "lattice":
                return True
            if isinstance(node, ast.Call) and not (isinstance(node.func, ast.Name) and node.func.id in TRUTH_TESTS):
                todo.append(node.func)
            elif isinstance(node, ast.Subscript):
                todo.append(node.value)
            elif not isinstance(node, (ast.Lambda, ast.FunctionDef)):
                todo += ast.iter_child_nodes(node)
        return False

    found = set()
    for node in ast.walk(ast.parse(text)):
        tests = []
        if isinstance(node, (ast.If, ast.While, ast.IfExp, ast.Assert)):
            tests.append(node.test)
        elif isinstance(node, ast.comprehension):
            tests += node.ifs
        elif isinstance(node, ast.BoolOp):
            tests += node.values
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
            tests.append(node.operand)
        elif isinstance(node, ast.Compare):
            tests += [node.left, *node.comparators]
        elif isinstance(node, ast.Match):
            tests.append(node.subject)
        found.update(t.lineno for t in tests if holds(t))
    return sorted(found)


def test_only_the_kinds_branch_on_the_lattice():
    """Outside the kinds' home no module decides by ``phantom.lattice``: callers ask the phantom's kind."""
    found = {
        name: lines
        for name, path in MODULES.items()
        if not any(path.is_relative_to(home) for home in KINDS_HOME)
        and (lines := _lattice_branches(path.read_text(encoding="utf-8")))
    }
    assert found == {}


def test_the_lattice_check_sees_the_branches_the_issue_names():
    """Each way today's code decided by the lattice (one a line) is seen; passing it on or a table lookup is not."""
    branches = (
        "if phantom.lattice: pass\n"
        "alone = {} if phantom.lattice else {'search_around': False}\n"
        "if len(systems) < 2 or config.phantom.lattice: pass\n"
        "if plate != bool(config.phantom.lattice): pass\n"
        "ok = [s for s in systems if not s.phantom.lattice]\n"
        "unused = 'learn' if config.phantom.lattice else 'plate'\n"
    )
    assert _lattice_branches(branches) == [1, 2, 3, 4, 5, 6]
    data = "xyz = lattice_xyz_mm(ij, phantom.lattice, phantom.pitch_mm)\nkind = KINDS[phantom.lattice]\n"
    assert _lattice_branches(data + "if kind.pairs_frames: pass\n") == []
