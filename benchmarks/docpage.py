"""A benchmark's own result page for the documentation site: ``--write-docs``.

A benchmark run with ``--write-docs`` prints as usual and also writes what it printed to
``docs/benchmarks/<name>.md``, with the command, the date, the commit and the machine's load, so
the site's figures are never copied by hand. Each script ends with::

    if __name__ == "__main__":
        import docpage

        sys.exit(docpage.run(__file__, main))
"""

from __future__ import annotations

import contextlib
import datetime
import io
import os
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = ROOT / "docs" / "benchmarks"


def run(script: str, main):
    """Run a benchmark's ``main()``; with ``--write-docs`` among the arguments, record its page as well.

    ``--write-docs`` is taken out of ``sys.argv`` before ``main`` parses it.
    """
    enabled = "--write-docs" in sys.argv[1:]
    argv = [a for a in sys.argv[1:] if a != "--write-docs"]
    sys.argv[1:] = argv
    with recorded(script, enabled):
        return main()


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, text: str) -> int:
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self) -> None:
        for s in self.streams:
            s.flush()


@contextlib.contextmanager
def recorded(script: str, enabled: bool):
    """Print as usual; with ``enabled``, write the page ``docs/benchmarks/<script's stem>.md`` at the end.

    Nothing is written when the benchmark raises: a page always holds a complete run.
    """
    if not enabled:
        yield
        return
    buffer = io.StringIO()
    load_before = os.getloadavg()[0]
    started = datetime.datetime.now(datetime.timezone.utc)
    with contextlib.redirect_stdout(_Tee(sys.stdout, buffer)):
        yield
    write_page(Path(script), buffer.getvalue(), started, (load_before, os.getloadavg()[0]))


def write_page(script: Path, output: str, started: datetime.datetime, load: tuple[float, float]) -> Path:
    """Write ``docs/benchmarks/<script's stem>.md`` holding ``output`` and how it was made; return its path."""
    name = script.stem
    command = shlex.join(["python", f"benchmarks/{script.name}", *sys.argv[1:], "--write-docs"])
    title = _title(script)
    text = (
        f"# {name}\n\n{title}\n\n"
        "This page was written by the benchmark itself (`--write-docs`); do not edit it by hand.\n\n"
        f"- command: `{command}`\n"
        f"- date: {started:%Y-%m-%d %H:%M} UTC\n"
        f"- commit: `{_commit()}`\n"
        f"- machine: {os.cpu_count()} CPU(s), load {load[0]:.1f} at the start and {load[1]:.1f} at the end\n\n"
        f"```text\n{output.rstrip()}\n```\n"
    )
    PAGES.mkdir(parents=True, exist_ok=True)
    path = PAGES / f"{name}.md"
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def _title(script: Path) -> str:
    import ast

    doc = ast.get_docstring(ast.parse(script.read_text(encoding="utf-8"))) or ""
    return doc.split("\n\n")[0].replace("\n", " ")


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out + (" with uncommitted changes" if dirty else "")
