"""The digest of the code that produces an artifact, for the cache key.

A stage's artifact depends on its own module and on every project module that
module imports, directly or not (the learning stage runs the adjustment's
code). :func:`code_digest` follows the imports statically — it parses the
source files and never runs them — and hashes the syntax tree of each module
reached, so any change to what a stage executes changes its key, while a
change of comments or layout does not. No hand-kept version number can go
stale.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
from functools import lru_cache
from pathlib import Path


def code_digest(modules) -> str:
    """sha256 over the syntax trees of ``modules`` and of every module of the same packages they import.

    Parameters
    ----------
    modules : iterable of str
        Dotted module names (``"fluorocal.stages.learn"``). Imports are followed
        only into modules whose top-level package is that of one of these names.

    Returns
    -------
    str
        Hex digest; it changes when the code of any module reached changes.
    """
    roots = sorted(set(modules))
    scope = {name.split(".")[0] for name in roots}
    seen: dict[str, str] = {}
    todo = list(roots)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        source = _module_source(name)
        if source is None:
            continue
        seen[name], imported = _analyse(name, *source)
        todo.extend(m for m in imported if m.split(".")[0] in scope and m not in seen)
    h = hashlib.sha256()
    for name in sorted(seen):
        h.update(f"{name}:{seen[name]}\n".encode())
    return h.hexdigest()


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
def _analyse(name: str, path: Path, text: str) -> tuple[str, tuple[str, ...]]:
    """The digest of a module's syntax tree and the dotted names of the modules it imports.

    Cached by the source text itself, so the stages' shared modules are parsed once per process and an
    edited file is parsed anew. Imports anywhere in the body count (function-level ones included).
    """
    tree = ast.parse(text, filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node.module or "", node.level, package)
            # ``from a.b import c``: c may be a submodule of a.b or a name defined in it
            found += [base] + [f"{base}.{alias.name}" for alias in node.names if alias.name != "*"]
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest(), tuple(found)


def _absolute(module: str, level: int, package: str) -> str:
    if not level:
        return module
    parts = package.split(".")
    base = ".".join(parts[: len(parts) - level + 1])
    return f"{base}.{module}" if module else base
