"""Structure limits of the installed code: no module over 600 lines, no function over 80.

Usage: ``python .ci/limits.py [DIR ...]`` (default: pipeline stages). Prints each breach and exits 1 if any.
"""

import ast
import sys
from pathlib import Path

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def breaches(root: Path):
    for path in sorted(root.rglob("*.py")):
        text = path.read_text()
        n_lines = text.count("\n")
        if n_lines > MAX_MODULE_LINES:
            yield f"{path}: {n_lines} lines (limit {MAX_MODULE_LINES})"
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    yield f"{path}:{node.lineno}: function {node.name} has {length} lines (limit {MAX_FUNCTION_LINES})"


def main(argv: list[str]) -> int:
    found = [b for d in (argv or ["pipeline", "stages"]) for b in breaches(Path(d))]
    print("\n".join(found) if found else "structure limits: ok")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
