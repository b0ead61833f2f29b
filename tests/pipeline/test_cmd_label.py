"""`fluorocal label` between `fluorocal detect` and `fluorocal adjust`: each reads what the one before writes."""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.cli import main
from fluorocal.stages.io import DETECTIONS, OBSERVATIONS, read_table

_HEADER = "file,frame,x,y,sigma_x,sigma_y,rho,major,minor"


def test_detect_label_adjust_round_trip(tmp_path, calibrated_project):
    """Detect -> label -> adjust on a small simulated sequence, every table passed on as the command wrote it.

    Three frames of the session's simulated project (system A, 512 px, 0.5 mm pixels, SID 1100 mm): enough beads
    per frame to label each one alone (its fourth frame, whose touching beads leave it doubtful alone, is searched
    around for seconds: the labelling tests cover that).
    """
    sim = calibrated_project
    geometry = ["--source-image-distance", "1100", "--pixel-pitch", "0.5", "--image-size", "512", "512"]
    frames = sorted(str(p) for p in (sim / "frames" / "A").glob("*.tif"))[:3]
    det_csv, labels_csv = tmp_path / "det" / "detections.csv", tmp_path / "lab" / "labels.csv"
    assert main(["-q", "detect", *frames, "--out", str(tmp_path / "det")]) == 0
    label = ["-q", "label", str(det_csv), "--phantom", str(sim / "phantom.csv"), *geometry]
    assert main([*label, "--out", str(tmp_path / "lab")]) == 0
    adjust = ["-q", "adjust", "--observations", str(labels_csv), "--phantom", str(sim / "phantom.csv")]
    assert main([*adjust, *geometry, "--out", str(tmp_path / "out")]) == 0

    det = read_table(det_csv, DETECTIONS)
    labels = read_table(labels_csv, OBSERVATIONS)
    assert labels_csv.read_text().splitlines()[0] == "file,frame,id,x,y,sigma_x,sigma_y,rho"
    assert set(labels["file"]) == set(frames) and len(labels["id"]) > 3 * 200
    # every label is a detection, its values passed on exactly (both tables write floats in full)
    detected = {
        (f, int(k), x, y, sx) for f, k, x, y, sx in zip(*(det[c] for c in ("file", "frame", "x", "y", "sigma_x")))
    }
    assert all(r in detected for r in zip(*(labels[c] for c in ("file", "frame", "x", "y", "sigma_x"))))
    adjusted = read_table(tmp_path / "out" / "observations.csv", OBSERVATIONS)
    assert np.array_equal(adjusted["id"], labels["id"]) and np.array_equal(adjusted["x"], labels["x"])
    assert np.array_equal(adjusted["exposure"], np.searchsorted(np.array(frames), labels["file"]))


def test_ok_column_and_non_finite_values(tmp_path):
    """No ``ok`` column: every detection is ok; ``ok`` false or a non-finite value makes it not ok."""
    from fluorocal.cmd_label import _read_detections

    path = tmp_path / "det.csv"
    path.write_text(f"{_HEADER}\na.tif,0,1,2,0.1,0.1,0,3,3\na.tif,0,5,6,0.1,nan,0,3,3\nb.tif,2,1,2,0.1,0.1,0,3,3\n")
    got = _read_detections(path)
    assert sorted(got) == [("a.tif", 0), ("b.tif", 2)]
    assert got[("a.tif", 0)].ok.tolist() == [True, False] and got[("a.tif", 0)].reason.tolist() == ["", "input"]
    path.write_text(
        f"{_HEADER},ok\na.tif,0,1,2,0.1,0.1,0,3,3,0\na.tif,0,5,6,0.1,0.1,0,3,3,\na.tif,0,7,8,0.1,0.1,0,3,3,1\n"
    )
    np.testing.assert_array_equal(_read_detections(path)[("a.tif", 0)].ok, [False, True, True])
    np.testing.assert_array_equal(_read_detections(path)[("a.tif", 0)].xy_px, [[1, 2], [5, 6], [7, 8]])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (f"{_HEADER}\na.tif,0,1,2,0.1,0.1,0,3,3\na.tif,0,x1,2,0.1,0.1,0,3,3\n", r"det.csv:3: not a number in column x"),
        (f"{_HEADER}\na.tif,one,1,2,0.1,0.1,0,3,3\n", r"det.csv:2: not an integer in column frame"),
        ("file,frame,x,y,sigma_x,sigma_y,rho\na.tif,0,1,2,0.1,0.1,0\n", r"missing major,minor"),
        (f"{_HEADER}\n", r"det.csv: detections CSV has no rows"),
    ],
)
def test_bad_detections_name_file_line_and_column(tmp_path, capsys, text, message):
    (tmp_path / "det.csv").write_text(text)
    argv = [
        "-q",
        "label",
        str(tmp_path / "det.csv"),
        "--lattice",
        "hex",
        "--pitch",
        "2",
        "--out",
        str(tmp_path / "l"),
    ]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "l").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "-1100", "far"])
def test_a_geometry_that_is_not_a_length_is_refused_before_any_file_is_read(tmp_path, capsys, value):
    """``--source-image-distance nan``: refused naming the option, before the (here empty) detections are read."""
    (tmp_path / "det.csv").write_text(f"{_HEADER}\n")
    argv = ["-q", "label", str(tmp_path / "det.csv"), "--phantom", str(tmp_path / "phantom.csv")]
    with pytest.raises(SystemExit) as exc:  # argparse's refusal
        main([*argv, "--source-image-distance", value, "--out", str(tmp_path / "l")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("fluorocal: error: argument --source-image-distance: expected a finite length in mm")
    assert not (tmp_path / "l").exists()
