"""The documentation against the code: every code block runs or parses; the generated references are whole.

Every fenced block of README.md and docs/ must say its kind (toml, python, sh, text):

- TOML blocks are parsed with tomllib; a complete project (``[phantom]`` and ``[[systems]]``) is also
  loaded by the config loader, in a folder holding the files it names.
- Python blocks are compiled; they run, in order within their page, on the calibrated simulated project
  (``calibrated_project``) unless preceded by ``<!-- docs-test: compile-only -->``.
- Shell blocks: every ``fluorocal ...`` command line is parsed by ``fluorocal.cli.build_parser()``, so a
  renamed or removed option fails here.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
#: info strings a block may carry; every block must say which it is, so none is skipped unseen
KINDS = {"toml", "python", "sh", "text"}
COMPILE_ONLY = "<!-- docs-test: compile-only -->"
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```\s*$", re.M | re.S)


def _blocks(page: Path):
    """``(kind, code, compile_only, line)`` of every fenced block of ``page``."""
    text = page.read_text(encoding="utf-8")
    for m in FENCE.finditer(text):
        before = text[: m.start()].rstrip().splitlines()
        compile_only = bool(before) and before[-1].strip() == COMPILE_ONLY
        yield m.group(1), m.group(2), compile_only, text.count("\n", 0, m.start()) + 1


ALL_BLOCKS = [(page, *block) for page in PAGES for block in _blocks(page)]


def _id(block) -> str:
    page, kind, _, _, line = block
    return f"{page.relative_to(ROOT)}:{line}:{kind or 'none'}"


def test_pages_have_blocks():
    """The extraction finds the blocks (a broken pattern would make every test below pass vacuously)."""
    kinds = {b[1] for b in ALL_BLOCKS}
    assert {"toml", "python", "sh"} <= kinds, kinds
    assert len(ALL_BLOCKS) >= 15


@pytest.mark.parametrize("block", ALL_BLOCKS, ids=_id)
def test_block_has_a_known_kind(block):
    page, kind, _, _, line = block
    assert kind in KINDS, f"{page.name}:{line}: code block without a kind in {sorted(KINDS)} (got {kind!r})"


TOML_BLOCKS = [b for b in ALL_BLOCKS if b[1] == "toml"]


@pytest.mark.parametrize("block", TOML_BLOCKS, ids=_id)
def test_toml_block(block, tmp_path):
    """Parses; a complete project loads, with the files it names put in place."""
    from fluorocal.config import load_config
    from fluorocal.graph import stage_params_classes

    data = tomllib.loads(block[2])
    if "phantom" not in data or "systems" not in data:
        return
    _materialise(data, tmp_path)
    (tmp_path / "project.toml").write_text(block[2], encoding="utf-8")
    config = load_config(tmp_path / "project.toml", stage_params_allowed=stage_params_classes())
    assert [s.name for s in config.systems] == [s["name"] for s in data["systems"]]


def _materialise(data: dict, root: Path) -> None:
    """The files a project names: the fixture's phantom, empty frame files for every glob or list."""
    if "file" in data["phantom"]:
        target = root / data["phantom"]["file"]
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / "fixtures" / "sim" / "phantom.csv", target)
    tables = [*data["systems"], *(o for s in data["systems"] for o in s.get("orientations", []))]
    for table in tables:
        frames = table.get("frames", [])
        for name in [frames] if isinstance(frames, str) else frames:
            frame = root / name.replace("*", "0").replace("?", "0")
            frame.parent.mkdir(parents=True, exist_ok=True)
            frame.touch()
    for system in data["systems"]:
        if "seeds" in system:
            (root / system["seeds"]).write_text("id,x,y\n", encoding="utf-8")


def test_readme_walkthrough_config_is_the_fixture():
    """The README's grid-plate project is fixtures/arcadis/centred.toml (which the real-data test runs)."""
    readme = next(tomllib.loads(b[2]) for b in TOML_BLOCKS if b[0].name == "README.md")
    fixture = tomllib.loads((ROOT / "fixtures" / "arcadis" / "centred.toml").read_text(encoding="utf-8"))
    fixture.pop("cache")
    assert readme == fixture


SHELL_BLOCKS = [b for b in ALL_BLOCKS if b[1] == "sh"]


def _commands(code: str):
    """The argument lists of every ``fluorocal`` command in a shell block (continuations joined)."""
    for line in code.replace("\\\n", " ").splitlines():
        line = line.split(" #")[0]
        for segment in re.split(r"&&|\|\||;|\|", line):
            words = shlex.split(segment)
            while words and re.match(r"^\w+=", words[0]):  # VAR=value prefixes
                words.pop(0)
            if words and Path(words[0]).name == "fluorocal":
                yield words[1:]


@pytest.mark.parametrize("block", SHELL_BLOCKS, ids=_id)
def test_shell_block_commands_parse(block, capsys):
    from fluorocal.cli import build_parser

    for argv in _commands(block[2]):
        try:
            build_parser().parse_args(argv)
        except SystemExit:
            pytest.fail(f"{block[0].name}:{block[4]}: `fluorocal {shlex.join(argv)}`: {capsys.readouterr().err}")


def test_shell_blocks_hold_commands():
    """The walk-throughs' commands are found (the parser test is not vacuous)."""
    readme = [argv[0] for b in SHELL_BLOCKS if b[0].name == "README.md" for argv in _commands(b[2])]
    assert {"run", "undistort", "simulate", "inspect", "export", "evaluate"} <= set(readme)


PYTHON_PAGES = sorted({b[0] for b in ALL_BLOCKS if b[1] == "python"})


@pytest.mark.parametrize("page", PYTHON_PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_python_blocks(page, request, tmp_path, monkeypatch):
    """A page's Python blocks compile, and run in order in one namespace.

    They run in a folder where ``out/`` and ``demo/data/`` are a calibrated biplanar project (A and B, 512 px).
    """
    blocks = [b for b in ALL_BLOCKS if b[0] == page and b[1] == "python"]
    code = [compile(b[2], f"{page.name}:{b[4]}", "exec") for b in blocks]
    runnable = [c for c, b in zip(code, blocks) if not b[3]]
    if not runnable:
        return
    import numpy as np

    project = request.getfixturevalue("calibrated_project")
    (tmp_path / "demo").mkdir()
    os.symlink(project, tmp_path / "demo" / "data")
    os.symlink(project / "out", tmp_path / "out")
    monkeypatch.chdir(tmp_path)
    frame = np.zeros((512, 512), np.uint16)
    namespace = {"xy": np.array([[100.0, 200.0], [300.5, 256.0]]), "frame": frame}
    for c in runnable:
        exec(c, namespace)


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _accepted(config_text: str, tmp_path: Path) -> set[str]:
    """The keys the loader lists as allowed when ``config_text`` holds an unknown key ``zz_unknown``."""
    from fluorocal.config import ConfigError, load_config
    from fluorocal.graph import stage_params_classes

    (tmp_path / "p.toml").write_text(config_text, encoding="utf-8")
    with pytest.raises(ConfigError, match="zz_unknown") as err:
        load_config(tmp_path / "p.toml", stage_params_allowed=stage_params_classes())
    match = re.search(r"allowed keys are (.*)$", str(err.value))
    assert match, str(err.value)
    return {k.strip() for k in match.group(1).split(",")}


def _project_text(tmp_path: Path, *, top="", phantom="", system="", extra="") -> str:
    frames = tmp_path / "frames"
    frames.mkdir(exist_ok=True)
    (frames / "f0.tif").touch()
    shutil.copy(ROOT / "fixtures" / "sim" / "phantom.csv", tmp_path / "phantom.csv")
    return (
        f'{top}[phantom]\nfile = "phantom.csv"\n{phantom}\n[[systems]]\nname = "A"\nframes = "frames/*.tif"\n'
        f"source_image_distance = 1100\npixel_pitch = 0.5\n{system}\n{extra}"
    )


def test_config_reference_lists_every_key_the_loader_accepts(tmp_path):
    """Every key the loader accepts is in the generated reference, under its table's heading.

    The accepted keys come from the loader's own refusal of an unknown key, not from its schema.
    """
    from fluorocal.graph import stage_params_classes

    reference = _hooks().config_reference()
    sections = {
        m.group(1): body
        for m in re.finditer(r"^### `(.+?)`\n(.*?)(?=^### |\Z)", reference, re.M | re.S)
        for body in [m.group(2)]
    }
    cases = {
        "[phantom]": _project_text(tmp_path, phantom="zz_unknown = 1\n"),
        "[[systems]]": _project_text(tmp_path, system="zz_unknown = 1\n"),
        "[[systems]] orientations = [...]": _project_text(
            tmp_path, system='orientations = [{name = "a", frames = "frames/*.tif", zz_unknown = 1}]\n'
        ),
    }
    for table in ("calibration", "output", "cache", "compute", *stage_params_classes()):
        cases[f"[{table}]"] = _project_text(tmp_path, extra=f"[{table}]\nzz_unknown = 1\n")
    for title, text in cases.items():
        keys = _accepted(text, tmp_path)
        assert title in sections, f"no section {title} in the generated reference"
        listed = set(re.findall(r"^\| `(\w+)` \|", sections[title], re.M))
        assert keys <= listed, f"{title}: accepted by the loader but not in the reference: {sorted(keys - listed)}"
    tables = _accepted(_project_text(tmp_path, top="zz_unknown = 1\n"), tmp_path)
    headings = {re.sub(r"[\[\]]", "", t).split(" ")[0] for t in sections}
    assert tables <= headings, f"tables missing from the reference: {sorted(tables - headings)}"


def test_cli_reference_lists_every_command_and_option():
    """Every subcommand and option string of the parser appears in the generated command-line page."""
    import argparse

    from fluorocal.cli import build_parser

    reference = _hooks().cli_reference()

    def walk(parser, prefix):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from walk(sub, f"{prefix} {name}")
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    yield prefix, option

    seen = list(walk(build_parser(), "fluorocal"))
    assert len(seen) > 20
    for prefix, option in seen:
        if prefix != "fluorocal":
            assert f"## `{prefix}`" in reference, prefix
        assert f"`{option}" in reference, (prefix, option)


def test_every_written_benchmark_page_is_in_the_navigation():
    """The pages the benchmarks write (``--write-docs``) reach the site's navigation without a hand-kept list."""
    assert "  - Benchmarks:\n      - benchmarks/index.md\n" in (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    nav = [{"Home": "index.md"}, {"Benchmarks": ["benchmarks/index.md"]}, {"Development": "development.md"}]
    written = sorted(p.name for p in (ROOT / "docs" / "benchmarks").glob("*.md") if p.name != "index.md")
    pages = ["benchmarks/index.md", *(f"benchmarks/{name}" for name in written)]
    assert _hooks().with_benchmark_pages(nav) == [nav[0], {"Benchmarks": pages}, nav[2]] and written
