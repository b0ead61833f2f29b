"""Structure limits of the code: no module over 600 lines, no function over 80.

Usage: ``python .ci/limits.py [DIR ...] [--exclude FILE ...]`` (default: pipeline stages). Prints each breach
and exits 1 if any. ``--exclude`` leaves out one file (repeatable); the Makefile's lint target says why for each.
"""

import argparse
import ast
import sys
from pathlib import Path

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def breaches(root: Path, excluded: frozenset[Path] = frozenset()):
    for path in sorted(root.rglob("*.py")):
        if path.resolve() in excluded:
            continue
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
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "dirs", nargs="*", default=["pipeline", "stages"], help="folders to check (default: pipeline stages)"
    )
    parser.add_argument("--exclude", action="append", default=[], metavar="FILE", help="a file to leave out")
    args = parser.parse_intermixed_args(argv)
    missing = [f for f in args.exclude if not Path(f).is_file()]
    if missing:
        parser.error(f"--exclude {missing[0]}: no such file (drop the exclusion if the file is gone)")
    excluded = frozenset(Path(f).resolve() for f in args.exclude)
    found = [b for d in args.dirs for b in breaches(Path(d), excluded)]
    print("\n".join(found) if found else "structure limits: ok")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
