"""The digest of the code that produces an artifact, for the cache key.

A stage's artifact depends on its own module and on every project module that
module imports, directly or not (the learning stage runs the adjustment's
code). :func:`code_digest` follows the imports statically — it parses the
source files and never runs them — and hashes the syntax tree of each module
reached, so any change to what a stage executes changes its key. What it
follows is what Python executes: the imports of the module body and of every
function body (lazy ones included), and the ``__init__`` of every package a
module reached lives in; an ``if TYPE_CHECKING:`` block is never executed and
is not followed. Comments, layout and docstrings are not code: changing them
changes no key. No hand-kept version number can go stale.

The versions of the numerical libraries the code reached imports
(:data:`LIBRARIES`: NumPy, SciPy, OpenCV, scikit-image and the frame decoders
OpenImageIO, pydicom, tifffile) are in the digest too,
with those of the libraries they are built on: a new SciPy recomputes the
stages that call SciPy, and only them.

Parsing the modules is most of the cost (about a second for the pipeline's
stages). An :class:`AnalysisMemo` keeps each module's analysis in a file between
runs, under a key that is a hash of the module's source text itself (with its
name, this module's own source and Python's version): every source file is still
read and hashed on each call, never trusted by its size or time, so an edited
module is analysed anew whatever its metadata say.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import json
import logging
import re
import sys
from functools import lru_cache
from pathlib import Path

from fluorocal.compute import no_collection

log = logging.getLogger(__name__)

#: the libraries whose version is in the digest of the code importing them -> the ones they run in turn
LIBRARIES = {
    "numpy": (),
    "scipy": ("numpy",),
    "cv2": ("numpy",),
    "skimage": ("numpy", "scipy"),
    # the frame decoders: a new release may decode the same file to other pixels
    "OpenImageIO": ("numpy",),
    "pydicom": ("numpy",),
    "tifffile": ("numpy",),
}


def code_digest(modules, memo: AnalysisMemo | None = None) -> str:
    """sha256 over the syntax trees of ``modules``, of every module of the same packages they import, and the versions.

    Parameters
    ----------
    modules : iterable of str
        Dotted module names (``"fluorocal.stages.learn"``). Imports are followed
        only into modules whose top-level package is that of one of these names.
    memo : AnalysisMemo, optional
        Analyses kept from earlier runs (the same digest, without parsing the unchanged modules).

    Returns
    -------
    str
        Hex digest; it changes when the code of any module reached changes, or the version
        of one of the :data:`LIBRARIES` that code imports.
    """
    seen, libraries = reach(modules, memo)
    h = hashlib.sha256()
    for name in sorted(seen):
        h.update(f"{name}:{seen[name]}\n".encode())
    for library in sorted(libraries):
        h.update(f"{library}=={_library_version(library)}\n".encode())
    return h.hexdigest()


def reach(modules, memo: AnalysisMemo | None = None) -> tuple[dict[str, str], set[str]]:
    """The modules ``modules`` execute (name -> digest of its syntax tree) and the :data:`LIBRARIES` they run.

    A package reached only as the parent of a module runs its body alone: its functions' imports are
    followed once the package itself is imported.
    """
    roots = sorted(set(modules))
    scope = {name.split(".")[0] for name in roots}
    seen: dict[str, str] = {}
    whole: set[str] = set()  # the modules imported (not only run as a parent): every import of theirs followed
    libraries: set[str] = set()
    todo = [(name, True) for name in roots]
    while todo:
        name, imported = todo.pop()
        if name in whole or (name in seen and not imported):
            continue
        source = _module_source(name)
        if source is None:
            continue
        seen[name], body, functions = memo.analyse(name, *source) if memo is not None else _analyse(name, *source)
        whole |= {name} if imported else set()
        for module in body + functions * imported:
            top = module.split(".")[0]
            if top in LIBRARIES:
                libraries |= {top, *LIBRARIES[top]}
            elif top in scope and module not in whole:
                todo.append((module, True))
        todo += [(parent, False) for parent in _parents(name) if parent not in seen]
    return seen, libraries


def _parents(name: str) -> list[str]:
    """The packages whose ``__init__`` runs before module ``name``: ``a``, ``a.b`` for ``a.b.c``."""
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


@lru_cache(maxsize=None)
def _library_version(name: str) -> str:
    return importlib.import_module(name).__version__


def _module_path(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):  # a parent that is not a package, or a name that is not a module
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def _module_source(name: str) -> tuple[Path, str] | None:
    path = _module_path(name)
    return None if path is None else (path, path.read_text(encoding="utf-8"))


@lru_cache(maxsize=512)
def _analyse(name: str, path: Path, text: str) -> tuple[str, tuple[str, ...], tuple[str, ...]]:
    """The digest of a module's syntax tree (docstrings left out) and the modules its body and its functions import.

    Cached by the source text itself, so the stages' shared modules are parsed once per process and an
    edited file is parsed anew. The imports of an ``if TYPE_CHECKING:`` block are never run and not listed.
    """
    with no_collection():  # a syntax tree holds no reference cycles
        tree = ast.parse(text, filename=str(path))
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        statements = list(_executed(tree))
        body = _imports((node for node, in_function in statements if not in_function), package)
        functions = [m for m in _imports((node for node, _ in statements), package) if m not in body]
        _drop_docstrings(tree)
        return hashlib.sha256(ast.dump(tree).encode()).hexdigest(), tuple(body), tuple(functions)


#: a memo's key and an analysis' digest: sha256 hex
_HEX = re.compile(r"[0-9a-f]{64}")


class AnalysisMemo:
    """Module analyses kept in a JSON file between runs (the cache's), each under a key of its source text.

    The key (:meth:`key`) is the sha256 of this module's own source, Python's version, the module's
    name, whether it is a package's ``__init__`` and its source text: the analysis of the same text by the
    same code, so a hit is what :func:`_analyse` would return. The file is data, never trusted to steer
    imports: an entry is used only if it fits the source it is kept for (:func:`_fits`). An unreadable file,
    or entry, is ignored (the module is parsed again); the file is written atomically, and runs writing it
    at once lose at most each other's additions. It holds the entries of the last run and, up to
    :data:`MAX_ENTRIES`, older ones.
    """

    #: entries kept from earlier runs besides this run's
    MAX_ENTRIES = 2000

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.entries = self._load()
        self.used: set[str] = set()
        self.added = False

    def analyse(self, name: str, path: Path, text: str) -> tuple[str, tuple[str, ...], tuple[str, ...]]:
        """:func:`_analyse` of the module, from the memo when it holds the same text's."""
        key = self.key(name, path, text)
        if key in self.used:  # fitted to this very text, or made from it, earlier in this process
            return self.entries[key]
        self.used.add(key)
        kept = self.entries.get(key)
        if kept is None or not _fits(kept, name, path, text):
            if kept is not None:
                log.debug("code analysis of %s in %s does not fit its source: parsed again", name, self.path)
            self.entries[key] = _analyse(name, path, text)
            self.added |= self.entries[key] != kept
        return self.entries[key]

    @staticmethod
    def key(name: str, path: Path, text: str) -> str:
        h = hashlib.sha256(_own_source())
        for part in (sys.version, name, str(path.name == "__init__.py"), text):
            h.update(hashlib.sha256(part.encode("utf-8", "surrogatepass")).digest())
        return h.hexdigest()

    def save(self) -> None:
        """Write the memo if this run analysed a module it did not hold; a failure only loses the memo."""
        if not self.added:
            return
        from fluorocal.stages.io import atomic_write

        if self._linked():
            return
        kept = self.entries if len(self.entries) <= self.MAX_ENTRIES else {k: self.entries[k] for k in self.used}
        text = json.dumps({k: [d, list(b), list(f)] for k, (d, b, f) in sorted(kept.items())})
        try:
            atomic_write(self.path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
            self.added = False
        except OSError as exc:
            log.debug("code analyses not kept in %s: %s", self.path, exc)

    def _linked(self) -> bool:
        """Whether the memo's file or folder is a symlink (which may lead out of the cache): then it is ignored."""
        linked = self.path.is_symlink() or self.path.parent.is_symlink()
        if linked:
            log.debug("code analyses in %s not used: a symlink", self.path)
        return linked

    def _load(self) -> dict[str, tuple[str, tuple[str, ...], tuple[str, ...]]]:
        if self._linked():
            return {}
        try:
            raw = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError):  # RecursionError: nested too deep to decode
            return {}
        entries = {}
        for key, value in raw.items() if isinstance(raw, dict) else ():
            if _valid_entry(key, value):
                entries[key] = (value[0], tuple(value[1]), tuple(value[2]))
        return entries


def _valid_entry(key, value) -> bool:
    return (
        isinstance(key, str)
        and _HEX.fullmatch(key) is not None
        and isinstance(value, list)
        and len(value) == 3
        and isinstance(value[0], str)
        and _HEX.fullmatch(value[0]) is not None
        and all(isinstance(v, list) and all(isinstance(m, str) for m in v) for v in value[1:])
    )


#: an import statement at a line's start: ``from <module> import <names>`` or ``import <names>``
_STATED = re.compile(
    r"^[ \t]*(?:from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n;#]*)|import[ \t]+([^\n;#]*))", re.M
)
_WORD = re.compile(r"[A-Za-z_]\w*")


def _fits(analysis, name: str, path: Path, text: str) -> bool:
    """Whether a memo's ``analysis`` can be the one of ``text``; the memo is data, never trusted to steer imports.

    Each module it lists must be a dotted name whose parts are words of the text (past the part it shares
    with the module's own package, which a relative import leaves out), and each module an import at a
    line's start names must be listed (but in an ``if TYPE_CHECKING:`` block). Not fitting, the module is
    parsed again: a text with an import statement in a docstring is, on every run, correctly if more slowly.
    """
    package = (name if path.name == "__init__.py" else name.rpartition(".")[0]).split(".")
    listed = {*analysis[1], *analysis[2]}
    words = set(_WORD.findall(text))
    for module in listed:
        parts = module.split(".")
        if not all(part.isidentifier() for part in parts):
            return False
        shared = next((i for i, (a, b) in enumerate(zip(parts, package)) if a != b), min(len(parts), len(package)))
        if not set(parts[shared:]) <= words:
            return False
    return _stated_imports(_without_type_checking(text), ".".join(package)) <= listed


_TYPE_CHECKING = re.compile(r"([ \t]*)if[ \t]+(?:\w+\.)?TYPE_CHECKING[ \t]*:[ \t]*(?:#.*)?")


def _without_type_checking(text: str) -> str:
    """``text`` without the lines of its ``if TYPE_CHECKING:`` blocks (as laid out: the block's lines indented more)."""
    if "TYPE_CHECKING" not in text:
        return text
    kept, block = [], None  # block: the indent of the ``if`` being skipped
    for line in text.splitlines():
        rest = line.lstrip()
        if block is not None and (not rest or len(line) - len(rest) > block):
            continue
        m = _TYPE_CHECKING.fullmatch(line)
        block = None if m is None else len(m.group(1))
        kept += [] if m else [line]
    return "\n".join(kept)


def _stated_imports(text: str, package: str) -> set[str]:
    """The modules the import statements at the start of a line of ``text`` name (as :func:`_imports` lists them)."""
    found = set()
    for source, names, plain in _STATED.findall(text):
        if plain:
            found |= {item.split()[0] for item in plain.split(",") if item.split()}
            continue
        level = len(source) - len(source.lstrip("."))
        base = _absolute(source[level:], level, package)
        items = re.sub(r"#[^\n]*", "", names.strip().strip("()")).split(",")
        found |= {base} | {f"{base}.{i.split()[0]}" for i in items if i.split() and i.split()[0] != "*"}
    return {m for m in found if all(part.isidentifier() for part in m.split("."))}


@lru_cache(maxsize=1)
def _own_source() -> bytes:
    """The source of :mod:`fluorocal.codehash`: a change to how modules are analysed invalidates every memo entry."""
    return Path(__file__).read_bytes()


def _imports(nodes, package: str) -> list[str]:
    found = []
    for node in nodes:
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node.module or "", node.level, package)
            # ``from a.b import c``: c may be a submodule of a.b or a name defined in it
            found += [base] + [f"{base}.{alias.name}" for alias in node.names if alias.name != "*"]
    return found


#: the nodes that hold statements: an import, a class or a function is a statement, never inside an expression
_HOLDS_STATEMENTS = (ast.mod, ast.stmt, ast.excepthandler, ast.match_case)


def _statements(node: ast.AST) -> list[ast.AST]:
    """The children of ``node`` that are or hold statements (its expressions, arguments, aliases... hold none)."""
    return [child for child in ast.iter_child_nodes(node) if isinstance(child, _HOLDS_STATEMENTS)]


def _executed(tree: ast.AST):
    """``(node, in a function)`` of each statement of ``tree`` that runs (not ``if TYPE_CHECKING:``, but its else)."""
    todo = [(tree, False)]
    while todo:
        node, in_function = todo.pop()
        yield node, in_function
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            todo += [(child, in_function) for child in node.orelse]
        else:
            inner = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
            todo += [(child, inner) for child in _statements(node)]


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _drop_docstrings(tree: ast.AST) -> None:
    """Remove the docstring of the module and of every class and function (a body left empty becomes ``pass``)."""
    todo = [tree]
    while todo:
        node = todo.pop()
        todo += _statements(node)
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            ):
                node.body = node.body[1:] or [ast.Pass()]


def _absolute(module: str, level: int, package: str) -> str:
    if not level:
        return module
    parts = package.split(".")
    base = ".".join(parts[: len(parts) - level + 1])
    return f"{base}.{module}" if module else base
