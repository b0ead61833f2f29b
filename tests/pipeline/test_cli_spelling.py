"""One spelling per concept across every command: the parsers are walked, every option of every subcommand checked.

The table below is the one allowed spelling of each concept that more than one command takes (see
``fluorocal.cli_common``); a synonym of any of them, in any command, fails the test. A new command
(``pipeline/cmd_<name>.py`` in ``cli.COMMAND_MODULES``) is walked too, without being listed here.
"""

from __future__ import annotations

import argparse

import pytest
from fluorocal.cli import build_parser, main
from fluorocal.cli_common import positive_int
from fluorocal.config import SYSTEM_RANGES_MM

#: concept -> its one option string
SPELLING = {
    "write over existing outputs": "--overwrite",
    "recompute a stage": "--force",
    "a C-arm orientation": "--orientation",
    "the frames' size in px": "--image-size",
    "the folder a command writes into": "--out",
    "source-image distance (a system's config key)": "--source-image-distance",
    "detector pixel pitch (a system's config key)": "--pixel-pitch",
}

#: option strings that would spell one of those concepts a second way
SYNONYMS = {
    "--replace",
    "--clobber",
    "--orientations",
    "--angles",
    "--angle",
    "--orbit",
    "--tilt",
    "--size",
    "--image-width",
    "--image-height",
    "--width",
    "--height",
    "--px",
    "--sid",
    "--source-distance",
    "--pitch-px",
    "--output",
    "--outdir",
    "--out-dir",
    "--output-dir",
    "--out-file",
    "-o",
    "--calibration",
    "--cal",
    "--recompute",
    "--redo",
    "--rerun",
    "--yes",
    "-f",
    "-y",
}


def _commands(parser: argparse.ArgumentParser, prefix: str = ""):
    """(command path, its parser) for every subcommand, nested ones (``cache clean``) too."""
    for action in parser._actions:  # argparse keeps no public list of a parser's actions
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _commands(sub, f"{prefix} {name}".strip())
                yield f"{prefix} {name}".strip(), sub


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings}


COMMANDS = dict(_commands(build_parser()))


def test_every_command_is_walked():
    # the walk finds what the top-level help lists: a command the walk missed would escape the checks below
    assert {"run", "inspect", "cache clean", "simulate", "detect", "label", "adjust", "undistort", "export"} <= set(
        COMMANDS
    )


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_no_concept_is_spelled_two_ways(command):
    options = _options(COMMANDS[command])
    assert not SYNONYMS & set(options), f"{command}: {sorted(SYNONYMS & set(options))} spell a concept of {SPELLING}"
    if "--force" in options:  # recomputing a stage, never writing over an output
        assert command == "run" and options["--force"].metavar == "STAGE"
    if "--overwrite" in options:
        assert isinstance(options["--overwrite"], argparse._StoreTrueAction)
    if "--out" in options:
        assert options["--out"].metavar == "DIR", f"{command}: --out is a folder everywhere"
    if "--image-size" in options:
        size = options["--image-size"]
        assert (size.nargs, size.metavar, size.type) == (2, ("W", "H"), positive_int), command
    if "--orientation" in options:
        assert options["--orientation"].type is None  # parsed by cli_common.parse_orientation, in one place


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_geometry_options_are_the_config_keys(command):
    options = _options(COMMANDS[command])
    # --pitch is the grid plate's hole pitch, [phantom] pitch; the others are a system's rough geometry
    geometry = {a.dest for s, a in options.items() if ("distance" in s or "pitch" in s) and s != "--pitch"}
    keys = {key for key, _, _ in SYSTEM_RANGES_MM}
    assert geometry == (keys if command in ("label", "adjust") else set()), command


@pytest.mark.parametrize("command", ["undistort", "export"])
def test_a_calibration_file_is_the_first_positional(command):
    positionals = [a for a in COMMANDS[command]._actions if not a.option_strings and a.nargs != 0]
    assert positionals[0].dest == "calibration" and positionals[0].metavar == "CALIBRATION"


def test_version(capsys):
    """``--version``: the installed distribution's version, looked up when asked."""
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out == f"fluorocal {version('fluorocal')}\n"


@pytest.mark.parametrize("where", ["before", "after"])
def test_common_options_before_or_after_the_command(tmp_path, capsys, where):
    # --quiet after the command was "unrecognized arguments"; a missing config is a one-line refusal either way
    config = str(tmp_path / "nope.toml")
    argv = ["--quiet", "--debug", "run", config] if where == "before" else ["run", config, "--quiet", "--debug"]
    with pytest.raises(Exception, match="config file not found"):  # --debug raises instead of the one line
        main(argv)
    argv = ["-q", "cache", "clean", config] if where == "before" else ["cache", "clean", config, "-q"]
    assert main(argv) == 2
    assert "config file not found" in capsys.readouterr().err


def test_holdout_does_not_swallow_the_config(tmp_path, capsys):
    # `evaluate --holdout odd CONFIG` read CONFIG as a second --holdout value, then missed the config
    assert main(["evaluate", "--holdout", "odd", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml: config file not found" in capsys.readouterr().err


def test_no_option_is_taken_by_an_abbreviation(capsys):
    # argparse's prefixes would be second spellings (--orient for --orientation, --over for --overwrite)
    with pytest.raises(SystemExit) as exc:
        main(["undistort", "c.json", "f.tif", "--system", "A", "--over"])
    assert exc.value.code == 2 and "unrecognized arguments: --over" in capsys.readouterr().err
