"""What `fluorocal run` writes is read back by `fluorocal adjust`: one observations schema, exact values."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from fluorocal.cli import main
from fluorocal.cmd_adjust import _read_observations
from fluorocal.export import _stage_tables
from fluorocal.export_tables import write_observations
from fluorocal.stages.io import PHANTOM, write_table

from tests.stages.ba_synthetic import make_problem


def _exported(tmp_path):
    """The observations of a small biplanar problem, written as `fluorocal run` writes them."""
    syn = make_problem(n_beads=80, n_exposures=6, n_systems=2, seed=9)
    obs = syn.observations
    rng = np.random.default_rng(2)
    files = {(s, e): f"{'AB'[s]}_{e:03d}.dcm" for s in range(2) for e in range(6)}
    corrections = rng.normal(0, 1e-9, (len(obs), 2))  # tiny, so the adjustment below sees the problem's own data
    residuals = rng.normal(0, 0.05, (len(obs), 2))
    inlier = rng.random(len(obs)) < 0.95
    path = tmp_path / "observations.csv"
    write_observations(path, obs, files=files, corrections_px=corrections, residual_px=residuals, inlier=inlier)
    return syn, path, corrections


def test_run_observations_round_trip_through_the_adjust_reader(tmp_path):
    syn, path, corrections = _exported(tmp_path)
    obs = syn.observations
    back, table, back_corrections = _read_observations(path)
    assert back.system_names == obs.system_names == ("A", "B")
    # to float precision: floats are written as their shortest exact text, so every value comes back bit for bit
    np.testing.assert_array_equal(back.xy_px, obs.xy_px)
    np.testing.assert_array_equal(back.sigma_px, obs.sigma_px)
    np.testing.assert_array_equal(back_corrections, corrections)
    np.testing.assert_array_equal(back.system, obs.system)
    np.testing.assert_array_equal(back.exposure, obs.exposure)  # the run's exposures, not a renumbering
    np.testing.assert_array_equal(back.bead_id, obs.bead_id)
    assert set(table["file"]) == {f"{s}_{e:03d}.dcm" for s in "AB" for e in range(6)}


def test_adjust_command_runs_on_what_run_exported(tmp_path):
    syn, path, _ = _exported(tmp_path)
    phantom = tmp_path / "phantom.csv"
    xyz = np.asarray(syn.nominal_mm)
    write_table(phantom, PHANTOM, {"id": syn.ids, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    out = tmp_path / "out"
    argv = ["adjust", "--observations", str(path), "--phantom", str(phantom), "--out", str(out)]
    assert main(argv) == 0
    summary = json.loads((out / "orientation.json").read_text())
    assert summary["usable"] and summary["system_names"] == ["A", "B"]
    np.testing.assert_allclose(summary["iop_px"], syn.truth.iop_px, atol=5.0)  # as tests/pipeline/test_cmd_adjust.py
    # and adjust's own output is the same schema again
    again, _, _ = _read_observations(out / "observations.csv")
    np.testing.assert_array_equal(again.xy_px, syn.observations.xy_px)


class _Labels:
    """A per-frame artifact with a table, as the label stage's."""

    def __init__(self, rows):
        self.rows = rows

    def to_table(self):
        return ["id", "x", "y", "sigma_x", "sigma_y", "rho"], self.rows


def test_label_stage_table_is_readable_by_adjust(tmp_path):
    units = [SimpleNamespace(system=s, exposure=e, path=Path(f"{'AB'[s]}{e}.tif")) for s in range(2) for e in range(2)]
    rows = {u: [[7 + k, 10.0 + k / 3, 20.0 - k / 7, 0.01, 0.02, 0.1] for k in range(3)] for u in range(len(units))}
    runner = SimpleNamespace(
        config=SimpleNamespace(output_dir=tmp_path, systems=[SimpleNamespace(name="A"), SimpleNamespace(name="B")]),
        stages=[SimpleNamespace(name="label", per_frame=True)],
        units=units,
        get=lambda name, u: _Labels(rows[u]),
    )
    (path,) = _stage_tables(runner)
    assert path.name == "label.csv"
    obs, _, corrections = _read_observations(path)
    expected = np.array([r[1:3] for u in range(len(units)) for r in rows[u]])
    np.testing.assert_array_equal(obs.xy_px, expected)
    np.testing.assert_array_equal(obs.exposure, [u.exposure for u in units for _ in range(3)])
    assert obs.system_names == ("A", "B") and not corrections.any()
