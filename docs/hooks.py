"""MkDocs hook: pages generated from the code at build time.

A page holding ``<!-- fluorocal:config-reference -->`` gets the project file's keys, read from
the config loader's own schema (``fluorocal.config_schema.SCHEMA``) and the stage tables' ``Params``
dataclasses (``fluorocal.graph.stage_params_classes``); ``<!-- fluorocal:cli-reference -->`` gets
every command and option, walked from ``fluorocal.cli.build_parser()``. Nothing here is kept by
hand, so a key or an option added to the code appears in the documentation.
``tests/test_docs.py`` imports this file to check that.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import enum
import json
import re
import typing
from pathlib import Path

try:  # run before mkdocstrings reads its paths; without MkDocs (tests/test_docs.py imports this file) a no-op
    from mkdocs.plugins import event_priority

    _first = event_priority(100)
except ImportError:

    def _first(f):
        return f


CONFIG_MARKER = "<!-- fluorocal:config-reference -->"
CLI_MARKER = "<!-- fluorocal:cli-reference -->"
BENCHMARKS_MARKER = "<!-- fluorocal:benchmarks -->"
ROOT = Path(__file__).resolve().parents[1]


@_first
def on_config(config, **kwargs):
    """Lay out the installed namespace for mkdocstrings: ``build/api/fluorocal`` of links into the sources.

    Installed, ``pipeline/`` is ``fluorocal`` and ``stages/`` is ``fluorocal.stages``; griffe reads
    packages from folders, so it is given a folder shaped like the installed package.
    """
    package = ROOT / "build" / "api" / "fluorocal"
    package.mkdir(parents=True, exist_ok=True)
    wanted = {p.name: p for p in (ROOT / "pipeline").iterdir() if p.name != "__pycache__"}
    wanted["stages"] = ROOT / "stages"
    for link in package.iterdir():
        if link.is_symlink() and link.name not in wanted:
            link.unlink()
    for name, target in wanted.items():
        link = package / name
        if not link.is_symlink():
            link.symlink_to(target)
    config["nav"] = with_benchmark_pages(config["nav"])
    return config


def with_benchmark_pages(nav: list) -> list:
    """``nav`` with every page a benchmark has written (``docs/benchmarks/*.md``) under "Benchmarks", by name.

    The pages are written by the benchmarks themselves (``--write-docs``), so none is listed by hand.
    """
    pages = (ROOT / "docs" / "benchmarks").glob("*.md")
    written = sorted(f"benchmarks/{p.name}" for p in pages if p.name != "index.md")
    return [
        {"Benchmarks": ["benchmarks/index.md", *written]} if isinstance(e, dict) and "Benchmarks" in e else e
        for e in nav
    ]


def on_page_markdown(markdown: str, **kwargs) -> str:
    """Replace the markers by the generated references (MkDocs ``on_page_markdown`` event)."""
    if CONFIG_MARKER in markdown:
        markdown = markdown.replace(CONFIG_MARKER, config_reference())
    if CLI_MARKER in markdown:
        markdown = markdown.replace(CLI_MARKER, cli_reference())
    if BENCHMARKS_MARKER in markdown:
        markdown = markdown.replace(BENCHMARKS_MARKER, benchmark_list())
    return markdown


def on_page_content(html: str, **kwargs) -> str:
    """Drop the Sphinx roles (``:func:`` ...) the docstrings use; mkdocstrings shows the name as code after them."""
    return re.sub(r":(?:func|class|meth|data|attr|mod|exc):(?=<code>)", "", html)


def benchmark_list() -> str:
    """Every script in ``benchmarks/``: what it measures, its command and its result page where one was written."""
    rows = ["| benchmark | what it measures | result page |", "|---|---|---|"]
    for script in sorted((ROOT / "benchmarks").glob("*.py")):
        tree = ast.parse(script.read_text(encoding="utf-8"))
        if not _runs_as_script(tree):  # a helper the benchmarks import (docpage.py, graph_run.py)
            continue
        doc = ast.get_docstring(tree) or ""
        page = ROOT / "docs" / "benchmarks" / f"{script.stem}.md"
        link = f"[{script.stem}]({script.stem}.md)" if page.is_file() else "not written yet"
        summary = _cell(doc.split("\n\n")[0])
        rows.append(f"| `python benchmarks/{script.name}` | {summary} | {link} |")
    return "\n".join(rows)


def _runs_as_script(tree: ast.Module) -> bool:
    """Whether a module has a top-level ``if __name__ == "__main__":`` block."""
    return any(isinstance(node, ast.If) and "__name__" in ast.unparse(node.test) for node in tree.body)


def _cell(text) -> str:
    """Text for a table cell: reST roles and double backquotes as Markdown code, no bar or newline."""
    text = re.sub(r":(?:func|class|data|attr|meth|mod):`~?([^`]+)`", r"`\1`", str(text)).replace("``", "`")
    parts = text.split("`")  # brackets outside code spans would read as Markdown links
    parts[::2] = [re.sub(r"([\[\]])", r"\\\1", p) for p in parts[::2]]
    return "`".join(parts).replace("|", "\\|").replace("\n", " ")


def _code(value) -> str:
    """A default as it would be written in TOML (``"auto"``, ``[3]``, ``true``); ``-`` for none."""
    if value is None:
        return "-"
    if isinstance(value, (str, bool, tuple, list)):
        text = json.dumps(list(value) if isinstance(value, tuple) else value)
    else:
        text = str(value)
    return f"`{text}`"


def config_reference() -> str:
    """The project file's keys as Markdown: one heading and one table per TOML table."""
    from fluorocal.config import OWNED_ELSEWHERE
    from fluorocal.config_schema import SCHEMA
    from fluorocal.graph import stage_params_classes

    out = []
    for section in dict.fromkeys(k.section for k in SCHEMA):
        title = "[[systems]] orientations = [...]" if section == "systems.orientations" else f"[{section}]"
        if section == "systems":
            title = "[[systems]]"
        out += [f"### `{title}`", "", "| key | type | default | meaning |", "|---|---|---|---|"]
        for k in (k for k in SCHEMA if k.section == section):
            default = "required" if k.required else _code(k.default)
            out.append(f"| `{k.name}` | {_cell(k.type)} | {default} | {_cell(k.help)} |")
        out.append("")
    for section, classes in stage_params_classes().items():
        classes = classes if isinstance(classes, tuple) else (classes,)
        names = ", ".join(f"`{c.__module__}.{c.__name__}`" for c in classes)
        out += [f"### `[{section}]`", "", f"Fields of {names}; none is needed.", ""]
        out += ["| key | type | default | meaning |", "|---|---|---|---|"]
        for cls in classes:
            helps = attribute_help(cls)
            hints = typing.get_type_hints(cls)
            for f in dataclasses.fields(cls):
                owner = OWNED_ELSEWHERE.get((section, f.name))
                meaning = f"not here: set by {owner}" if owner else helps.get(f.name, "")
                out.append(
                    f"| `{f.name}` | {_cell(_type_name(hints[f.name]))} | {_cell(_code(_default(f)))} | "
                    f"{_cell(meaning)} |"
                )
        out.append("")
    return "\n".join(out)


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _type_name(hint) -> str:
    switches = [a for a in typing.get_args(hint) or (hint,) if isinstance(a, type) and issubclass(a, enum.Enum)]
    if switches:  # an enumeration is written as one of its spellings
        return "string: " + ", ".join(f'`"{m.value}"`' for m in switches[0])
    text = getattr(hint, "__name__", None) if not typing.get_args(hint) else None
    return text or str(hint).replace("typing.", "")


def attribute_help(cls) -> dict[str, str]:
    """Field name -> its description in the numpydoc ``Attributes`` section of ``cls``'s docstring."""
    doc = (cls.__doc__ or "").expandtabs()
    lines = doc.splitlines()
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == "Attributes")
    except StopIteration:
        return {}
    helps: dict[str, str] = {}
    names: list[str] = []
    for line in lines[start + 2 :]:
        stripped = line.strip()
        if stripped and set(stripped) == {"-"}:  # the next section's underline: the previous line was its title
            names = []
            break
        match = re.match(r"^ {4}([A-Za-z_][\w, ]*?)\s*:\s*(.*)$", line)
        if match:
            names = [n.strip() for n in match.group(1).split(",")]
            for n in names:
                helps[n] = ""
        elif names and stripped:
            for n in names:
                helps[n] = (helps[n] + " " + stripped).strip()
    return helps


def cli_reference() -> str:
    """Every command and option of ``fluorocal``, walked from its argparse parser."""
    from fluorocal.cli import build_parser

    parser = build_parser()
    out = ["## Options of every command", "", _options_table(parser), ""]
    for name, sub in _subcommands(parser, "fluorocal"):
        out += [f"## `{name}`", "", *_description(sub.description or ""), ""]
        out += ["```text", sub.format_usage().strip(), "```", "", _options_table(sub), ""]
    return "\n".join(out)


def _description(text: str) -> list[str]:
    """A command's description: one line as prose, a longer one (a module docstring) as preformatted text."""
    text = text.strip()
    if "\n" not in text:
        return [_cell(text)]
    return ["```text", text, "```"]


def _subcommands(parser: argparse.ArgumentParser, prefix: str):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield f"{prefix} {name}", sub  # a group of commands (cache) too: it takes the common options
                yield from _subcommands(sub, f"{prefix} {name}")


def _options_table(parser: argparse.ArgumentParser) -> str:
    rows = ["| argument | meaning | default |", "|---|---|---|"]
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.option_strings:
            metavar = "" if action.nargs == 0 else " " + " ".join(_metavars(action))
            name = ", ".join(f"`{o}{metavar}`" for o in action.option_strings)
        else:
            name = f"`{' '.join(_metavars(action))}`"
        default = action.default
        shown = "-" if default in (None, False, [], argparse.SUPPRESS) else _code(default)
        rows.append(f"| {name} | {_cell(action.help or '')} | {_cell(shown)} |")
    return "\n".join(rows)


def _metavars(action: argparse.Action) -> list[str]:
    metavar = action.metavar or (action.dest if not action.option_strings else action.dest.upper())
    if isinstance(metavar, tuple):
        return list(metavar)
    n = action.nargs
    if isinstance(n, int):
        return [metavar] * n
    if n == "?":
        return [f"[{metavar}]"]
    if n in ("*", "+"):
        return [f"{metavar}..."]
    return [metavar]
