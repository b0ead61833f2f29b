"""Quiet when all is well: a normal run logs no warning and says in one line what the label stage did.

``inspect`` sums every frame of every system, and the report embeds each plot once.
"""

from __future__ import annotations

import logging
import re

import pytest
from fluorocal.cli import main
from fluorocal.cli_common import load_project, project_runner
from fluorocal.stages.field import CorrectionField

from tests.conftest import E2E_SIM


def test_a_normal_run_logs_nothing_at_warning(calibrated_run):
    # the run itself ran with warnings as errors (the suite's filterwarnings); its log had 24 "labelling failed"
    # lines for first attempts the sequence recovered, a warning from matplotlib's arrows of a zero field, ...
    _, records = calibrated_run
    loud = [f"{r.levelname}: {r.getMessage()}" for r in records if r.levelno >= logging.WARNING]
    assert loud == []
    assert not [r for r in records if "labelling failed" in r.getMessage()]
    n_frames = E2E_SIM["n_frames"] * E2E_SIM["n_systems"]
    (line,) = [r.getMessage() for r in records if r.getMessage().startswith("label: ") and "frames" in r.getMessage()]
    assert re.fullmatch(rf"label: {n_frames}/{n_frames} frames( \(\d+ recovered from their neighbours\))?", line)


def test_the_report_embeds_each_plot_once(calibrated_project):
    out = calibrated_project / "out"
    embedded = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (out / "report.md").read_text())
    assert sorted(embedded) == sorted({*embedded}) == sorted(p.name for p in out.glob("*.png"))


def _runner(config_path):
    class Args:
        config, quiet = config_path, True

    return project_runner(Args, load_project(config_path, writable=False))


def test_inspect_sums_every_frame_of_every_system(calibrated_project, capsys):
    # the table showed the last frame's summary; biplanar frames were listed by file name alone (twice)
    cfg = calibrated_project / "fluorocal.toml"
    assert main(["inspect", str(cfg)]) == 0
    table = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()[1:]}
    runner = _runner(cfg)
    for name in ("A", "B"):
        units = [u for u, unit in enumerate(runner.units) if runner.config.systems[unit.system].name == name]
        detected = [runner.get("detect", u) for u in units]
        accepted, found = sum(d.n_accepted for d in detected), sum(len(d) for d in detected)
        assert f"system {name}: {len(units)} frames, {accepted} accepted of {found} candidates" in table["detect"]
        labels = [runner.get("label", u) for u in units]
        beads = sum(lab.n_labelled for lab in labels)
        labelled = rf"system {name}: {len(units)}/{len(units)} frames.* labelled, {beads} detections with an id"
        assert re.search(labelled, table["label"])

    assert main(["inspect", str(cfg), "label"]) == 0
    listed = [line.split(":  ")[0] for line in capsys.readouterr().out.splitlines()]
    assert len(listed) == len(set(listed)) == len(runner.units)
    assert listed[0].startswith("system A: frames/A/frame_000.tif: ") and listed[-1].startswith("system B: ")


def test_inspect_frame_of_a_per_project_stage_says_why(calibrated_project, capsys):
    # `inspect CONFIG learn --frame 0` said "--frame must be in 0..7", though 0 is in that range
    assert main(["inspect", str(calibrated_project / "fluorocal.toml"), "learn", "--frame", "0"]) == 2
    err = capsys.readouterr().err
    assert "stage 'learn' has one artifact per project; --frame is for detect, centroid, label" in err


@pytest.mark.parametrize("several", [False, True])
def test_plots_of_a_zero_field_raise_no_warning(tmp_path, several):
    # scheme "none" learns a zero field: matplotlib's arrows divided by its zero mean length (a RuntimeWarning,
    # an error here as everywhere in the suite)
    from fluorocal.orientations import orientation_report
    from fluorocal.report import field_map
    from fluorocal.stages.orientation import OrientationField

    zero = CorrectionField.constant(256, 256, (0.0, 0.0), spacing_px=32.0)
    if several:
        fields = [OrientationField(name, orbit, 0.0, zero) for name, orbit in (("o0", 0.0), ("o30", 30.0))]
        paths, _ = orientation_report(tmp_path, "A", fields)
    else:
        paths = [field_map(tmp_path / "field.png", zero, "zero")]
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in paths)


def test_long_rotated_tick_labels_add_room_below_the_panels_not_take_it_from_them():
    """Frames named by a 64-character DICOM UID: the figure grows; the panel keeps its height."""
    from fluorocal.report import BOTTOM_IN, new_figure, text_height_in

    names = ["1.2.826.0.1.3680043.8.498.12345678901234567890123456789012345678901"]
    bottom_in = text_height_in(names, fontsize=7) + 0.15
    fig, (ax,) = new_figure(1, height=4.6, bottom_in=bottom_in)
    panel_h_in = ax.get_position().height * fig.get_figheight()
    _, (plain,) = new_figure(1, height=4.6)
    assert bottom_in > 2 * BOTTOM_IN
    assert abs(panel_h_in - plain.get_position().height * 4.6) < 1e-9
