"""`fluorocal export`: two fields that would share an output file are refused before anything is written.

``opencv`` and ``mrcal`` name a file per system and orientation, joined by ``_``; ``_`` may occur in
the names, so system ``A`` at orientation ``x`` and a system ``A_x`` would write the same file, and
names differing only in case would on a case-insensitive file system.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from fluorocal.calibration import Calibration, SystemCalibration
from fluorocal.cli import main
from fluorocal.stages.field import CorrectionField, grid_nodes
from fluorocal.stages.orientation import OrientationField

W, H = 48, 32


def _field(scale: float) -> CorrectionField:
    x, y = grid_nodes(W, H, 16.0)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    delta = scale * np.stack([(xx - W / 2) / W, (yy - H / 2) / H], axis=-1)  # up to ~scale/2 px
    ones = np.ones(xx.shape)
    return CorrectionField(x, y, delta, 0.01 * ones, ones.astype(bool), W, H)


def _system(name, field=None, orientations=()) -> SystemCalibration:
    iop = np.array([W / 2, H / 2, 500.0])
    return SystemCalibration(name, (W, H), iop, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), field, orientations)


def _saved(folder, second: str) -> str:
    """System A at orientations x and y, and a system named ``second`` with one field; saved in ``folder``."""
    a = _system(
        "A", orientations=(OrientationField("x", 0.0, 0.0, _field(1.0)), OrientationField("y", 30.0, 0.0, _field(-1.0)))
    )
    path = folder / "calibration.json"
    folder.mkdir()
    Calibration([a, _system(second, _field(0.5))], {}, {"scheme": "test"}).save(path)
    return path


def _export(calibration, fmt, out) -> int:
    return main(["--quiet", "export", str(calibration), "--format", fmt, "--out", str(out)])


@pytest.mark.parametrize("fmt, file", [("opencv", "opencv_A_x.yml.gz"), ("mrcal", "A_x.cameramodel")])
def test_a_system_named_like_another_systems_orientation_is_refused(tmp_path, capsys, fmt, file):
    path = _saved(tmp_path / "cal", "C")
    assert _export(path, fmt, tmp_path / "ok") == 0  # distinct names: every file written
    assert file in {p.name for p in (tmp_path / "ok").iterdir()}
    # a calibration saved by fluorocal cannot hold the clash (its field files would clash too): edited by hand
    doc = json.loads(path.read_text())
    doc["systems"][1]["name"] = "A_x"
    path.write_text(json.dumps(doc))
    assert _export(path, fmt, tmp_path / "x") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert f"--format {fmt}: system A at orientation x and system A_x would both be written as {file}" in err
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())  # nothing written


@pytest.mark.parametrize("fmt, file", [("opencv", "opencv_a_X.yml.gz"), ("mrcal", "a_X.cameramodel")])
def test_names_differing_only_in_case_are_refused(tmp_path, capsys, fmt, file):
    # field_A_x.npz, field_A_y.npz and field_a_X.npz: saved where case matters (here), clashing where it does not
    path = _saved(tmp_path / "cal", "a_X")
    assert _export(path, fmt, tmp_path / "x") == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert f"--format {fmt}: system A at orientation x and system a_X would both be written as {file}" in err
    assert "letter case ignored" in err
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())
