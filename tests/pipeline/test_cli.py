"""The command line: one-line errors with exit code 2, no traceback; --help is instant."""

from __future__ import annotations

import subprocess
import sys

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
        "print(sorted(m for m in ('cv2', 'OpenImageIO', 'scipy', 'skimage') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
