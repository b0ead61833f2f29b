"""The command line: one-line errors with exit code 2, no traceback; --help is instant."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from fluorocal.cli import main

from tests.pipeline.toy import make_project


def test_bad_config_key_is_one_line_exit_2(tmp_path, capsys):
    cfg = make_project(tmp_path)
    cfg.write_text(cfg.read_text() + "\nbogus = 1\n")
    assert main(["run", str(cfg)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fluorocal: error: project.toml: [[systems]] #1 key 'bogus': unknown key") and "\n" not in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists() and not (tmp_path / ".fluorocal").exists()


def test_missing_config_is_exit_2(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "nope.toml")]) == 2
    assert "config file not found" in capsys.readouterr().err


def test_help_does_not_import_heavy_libraries():
    code = (
        "import sys; from fluorocal.cli import build_parser; build_parser(); "
        "print(sorted(m for m in ('cv2', 'OpenImageIO', 'scipy', 'skimage', 'numpy', 'importlib.metadata') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"


def test_inspect_reads_a_project_whose_folders_cannot_be_written(tmp_path, monkeypatch, capsys):
    cfg = make_project(tmp_path)
    monkeypatch.setattr("fluorocal.config.os.access", lambda path, mode: False)  # a read-only share, even for root
    assert main(["inspect", str(cfg)]) == 0
    assert "missing" in capsys.readouterr().out
    assert main(["run", str(cfg)]) == 2
    assert "is not writable" in capsys.readouterr().err
    assert not (tmp_path / "out").exists() and not (tmp_path / ".fluorocal").exists()


@pytest.mark.parametrize(
    "command",
    [
        ["label", "d.csv", "--lattice", "hex", "--pitch", "2"],
        ["adjust", "--observations", "o.csv", "--phantom", "p.csv"],
    ],
)
def test_a_usage_error_is_one_line_naming_the_option(tmp_path, capsys, command):
    with pytest.raises(SystemExit) as exc:
        main([*command, "--out", str(tmp_path / "l"), "--image-size", "-1", "0"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1
    assert err.startswith("fluorocal: error: argument --image-size: expected a positive integer; got '-1'")
    assert not (tmp_path / "l").exists()


def test_simulate_names_the_option_behind_a_refused_parameter(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "sim"), "--frames", "-3"]) == 2
    assert capsys.readouterr().err.strip() == "fluorocal: error: --frames: n_frames must be >= 1; got -3"
    assert not (tmp_path / "sim").exists()


def test_a_closed_output_pipe_ends_quietly(tmp_path):
    # `fluorocal inspect ... | head` ended with "error: broken pipe": the reader is gone before anything is written
    cfg = make_project(tmp_path)
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "fluorocal.cli", "inspect", str(cfg)], stdout=write_end, stderr=subprocess.PIPE
        )
    finally:
        os.close(write_end)
    assert proc.stderr.decode() == "" and proc.returncode == 141
