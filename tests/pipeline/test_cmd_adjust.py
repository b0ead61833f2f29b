"""`fluorocal adjust` on CSVs written from a small synthetic biplanar problem."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from fluorocal.cli import main

from tests.stages.ba_synthetic import make_problem


def _write_inputs(tmp_path):
    syn = make_problem(n_beads=80, n_exposures=6, n_systems=2, seed=9)
    obs = syn.observations
    phantom = tmp_path / "phantom.csv"
    with open(phantom, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["id", "x", "y", "z"])
        w.writerows([[int(i), *p] for i, p in zip(syn.ids, syn.nominal_mm)])
    table = tmp_path / "obs.csv"
    with open(table, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["file", "frame", "system", "id", "x", "y", "sigma_x", "sigma_y", "rho"])
        for k in range(len(obs)):
            name = "AB"[obs.system[k]]
            w.writerow(
                [f"{name}_{obs.exposure[k]:03d}.tif", 0, name, int(obs.bead_id[k]), *obs.xy_px[k], 0.05, 0.05, 0.0]
            )
    return syn, phantom, table


def test_adjust_command_writes_outputs(tmp_path):
    syn, phantom, table = _write_inputs(tmp_path)
    out = tmp_path / "out"
    rc = main(
        [
            "adjust",
            "--observations",
            str(table),
            "--phantom",
            str(phantom),
            "--source-image-distance",
            "1100",
            "--pixel-pitch",
            "0.25",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    summary = json.loads((out / "orientation.json").read_text())
    assert summary["usable"] and summary["system_names"] == ["A", "B"]
    np.testing.assert_allclose(summary["iop_px"], syn.truth.iop_px, atol=5.0)  # a few σ of this small network
    with open(out / "object_points.csv") as fh:
        assert len(list(csv.DictReader(fh))) == len(syn.ids)
    with open(out / "observations.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(syn.observations)
    assert {"residual_x", "residual_y", "weight", "inlier", "used"} <= set(rows[0])  # the observations schema's names


def test_adjust_command_reports_missing_columns(tmp_path, capsys):
    _, phantom, _ = _write_inputs(tmp_path)
    bad = tmp_path / "bad.csv"
    bad.write_text("file,frame,x,y\na.tif,0,1,2\n")
    rc = main(["adjust", "--observations", str(bad), "--phantom", str(phantom), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "missing id" in capsys.readouterr().err


@pytest.mark.parametrize(
    "flags", [["--source-image-distance", "inf"], ["--pixel-pitch", "nan"]]
)  # --image-size: test_cli.py
def test_adjust_command_refuses_non_finite_start_values(tmp_path, capsys, flags):
    # the attack battery's adjust_sid_inf: an infinite source-image distance ended in an OpenCV assertion's traceback
    # now refused by the option's type, before anything is read: argparse's exit 2, one line naming the option
    _, phantom, table = _write_inputs(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["adjust", "--observations", str(table), "--phantom", str(phantom), "--out", str(tmp_path / "o"), *flags])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and flags[0] in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_adjust_command_names_the_file_and_line_of_a_non_finite_observation(tmp_path, capsys):
    _, phantom, table = _write_inputs(tmp_path)
    lines = table.read_text().splitlines()
    lines[3] = ",".join(v if i != 4 else "nan" for i, v in enumerate(lines[3].split(",")))  # x of the 3rd row
    table.write_text("\n".join(lines) + "\n")
    rc = main(["adjust", "--observations", str(table), "--phantom", str(phantom), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err == f"fluorocal: error: {table}:4: column x must be a finite number; got nan"
    assert not (tmp_path / "o").exists()


def test_adjust_command_says_in_one_line_when_the_adjustment_is_not_usable(tmp_path, capsys, monkeypatch):
    # the attack battery's adjust_obs_latin1: start values far off (--pixel-pitch and --image-size left at their
    # defaults for 0.5 mm, 512 px frames) gave an unusable adjustment: exit 1 and nothing said under --quiet
    import dataclasses

    import fluorocal.stages.adjust as adjust

    real = adjust.adjust_bundle
    monkeypatch.setattr(adjust, "adjust_bundle", lambda *a, **k: dataclasses.replace(real(*a, **k), usable=False))
    _, phantom, table = _write_inputs(tmp_path)
    argv = ["--quiet", "adjust", "--observations", str(table), "--phantom", str(phantom), "--out", str(tmp_path / "o")]
    rc = main([*argv, "--source-image-distance", "1100", "--pixel-pitch", "0.25"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("fluorocal: error: the adjustment of") and "not usable" in err
    assert len(err.splitlines()) == 1 and (tmp_path / "o" / "orientation.json").is_file()
