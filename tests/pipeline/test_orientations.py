"""A field per C-arm orientation, around the calibration stage that fits the fields.

The config's groups, the default grouping, DICOM angles, the calibration file with several orientations,
``fluorocal undistort --orientation`` and ``fluorocal inspect calibration.json``.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pydicom
import pytest
from fluorocal.calibration import Calibration
from fluorocal.cli import main
from fluorocal.config import ConfigError, OrientationConfig, load_config
from fluorocal.orientations import default_orientation_name, frame_orientations, orientation_report
from fluorocal.stages.errors import ArtifactError, InputError
from fluorocal.stages.io import read_frames, write_still
from fluorocal.stages.io.dicom import positioner_angles_deg
from fluorocal.stages.orientation import OrientationField, interpolate_field
from fluorocal.units import frame_units

from tests.pipeline.orientation_toys import H, W, angled_dicom, constant_field, orientation_calibration, toy_system
from tests.pipeline.toy import make_project

# --- config ----------------------------------------------------------------------------------------


def _with_orientations(tmp_path, groups: str):
    path = make_project(tmp_path, extra_toml=f"orientations = [{groups}]\n")
    return path


def test_orientations_are_read_with_globs_angles_and_the_systems_own_paths(tmp_path):
    path = _with_orientations(
        tmp_path,
        '{name = "centred", frames = "frames/f[01].tif", orbit = 0, tilt = 0}, '
        '{name = "orbit30", frames = ["frames/f2.tif"], orbit = 30.5, tilt = -2}',
    )
    system = load_config(path).systems[0]
    assert system.orientations == (
        OrientationConfig("centred", system.frames[:2], 0.0, 0.0),
        OrientationConfig("orbit30", system.frames[2:], 30.5, -2.0),
    )
    assert load_config(make_project(tmp_path / "plain")).systems[0].orientations == ()
    no_angles = _with_orientations(tmp_path / "b", '{name = "all", frames = "frames/*.tif"}')
    assert load_config(no_angles).systems[0].orientations[0].orbit_deg is None


ALL = 'frames = "frames/*.tif"'


@pytest.mark.parametrize(
    "groups, match",
    [
        (f'{{name = "a", {ALL}, colour = "red"}}', r"#1 orientations #1 key 'colour': unknown key; allowed keys are"),
        (
            '{name = "a", frames = ["frames/f0.tif"]}, {name = "a", frames = ["frames/f1.tif", "frames/f2.tif"]}',
            r"orientations #2 key 'name': 'a' names two orientations",
        ),
        (
            f'{{name = "a", {ALL}}}, {{name = "b", frames = ["frames/f1.tif"]}}',
            r"orientations #2 key 'frames': f1.tif is already in orientation 'a'",
        ),
        (
            '{name = "a", frames = ["frames/f0.tif", "frames/f1.tif"]}',
            r"#1 key 'orientations': frame f2.tif is in no orientation",
        ),
        (f'{{name = "a/../b", {ALL}}}', r"orientations #1 key 'name': orientation name 'a/../b' cannot be part of"),
        ('{name = "a", frames = ["phantom.csv"]}', r"key 'frames': .*phantom.csv is not one of the system's frames"),
        (f'{{name = "a", {ALL}, orbit = 30}}', r"key 'orbit': give both orbit and tilt"),
        (f'{{name = "a", {ALL}, orbit = 200, tilt = 0}}', r"key 'orbit': orbit must be a finite angle in -180..180"),
        (f'{{name = "a", {ALL}, orbit = nan, tilt = 0}}', r"key 'orbit': orbit must be a finite angle"),
        (f'{{name = "a", {ALL}, orbit = "30", tilt = 0}}', r"key 'orbit': orbit must be a finite angle"),
        (
            '{name = "a", frames = ["frames/f0.tif"], orbit = 30, tilt = 0}, '
            '{name = "b", frames = ["frames/f1.tif", "frames/f2.tif"], orbit = 30, tilt = 0}',
            r"orientations #2 key 'orbit': orientations 'a' and 'b' have the same angles",
        ),
        ('{name = "a", frames = "nothing/*.tif"}', r"orientations #1 key 'frames': no file matches"),
        ('"f0"', r"orientations #1 key 'orientations': expected a table"),
        ("", r"key 'orientations': expected a list of tables"),
    ],
)
def test_orientation_errors_name_the_key(tmp_path, groups, match):
    path = _with_orientations(tmp_path, groups)
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path)
    assert str(info.value).startswith("project.toml: [[systems]] #1") and "\n" not in str(info.value)


# --- DICOM angles ----------------------------------------------------------------------------------


def test_positioner_angles_are_read_from_the_header(tmp_path):
    assert positioner_angles_deg(angled_dicom(tmp_path / "a.dcm", angles=(30.5, -15))) == (30.5, -15.0)
    assert positioner_angles_deg(angled_dicom(tmp_path / "none.dcm")) == (None, None)
    assert positioner_angles_deg(angled_dicom(tmp_path / "empty.dcm", empty_tags=True)) == (None, None)
    # the positioner moved during a cine: the file's angles are not every frame's
    assert positioner_angles_deg(angled_dicom(tmp_path / "c.dcm", angles=(10, 0), n_frames=3, motion="DYNAMIC")) == (
        None,
        None,
    )
    with pytest.raises(InputError, match=r"bad.dcm: PositionerPrimaryAngle must be within -180..180 degrees"):
        positioner_angles_deg(angled_dicom(tmp_path / "bad.dcm", angles=(200, 0)))


def test_the_real_frames_record_no_angles(arcadis_dir):
    """The ARCADIS frames carry both tags without a value: their orientations need names (or angles) in a config."""
    for name in ("grid_centered_0", "grid_orbit_30", "grid_tilt_30"):
        ds = pydicom.dcmread(arcadis_dir / f"{name}.dcm", stop_before_pixels=True)
        assert "PositionerPrimaryAngle" in ds and ds.PositionerPrimaryAngle is None
        assert positioner_angles_deg(arcadis_dir / f"{name}.dcm") == (None, None)


# --- grouping frames -------------------------------------------------------------------------------


def _dicom_project(root, extra: str = ""):
    frames = root / "frames"
    angled_dicom(frames / "a.dcm", angles=(30, 0))
    angled_dicom(frames / "b.dcm")
    angled_dicom(frames / "c.dcm", angles=(0, 15), n_frames=3)
    (root / "phantom.csv").write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n4,0,0,10\n")
    cfg = root / "project.toml"
    cfg.write_text(
        '[phantom]\nfile = "phantom.csv"\n\n[[systems]]\nname = "A"\nframes = "frames/*.dcm"\n'
        "source_image_distance = 1100\npixel_pitch = 0.25\n" + extra
    )
    return load_config(cfg)


def test_by_default_frames_are_grouped_by_their_recorded_angles_else_each_its_own(tmp_path):
    config = _dicom_project(tmp_path)
    got = frame_orientations(config, frame_units(config))
    # issue 32: frames recording the same C-arm angles are one orientation, named by them
    assert [tuple(o) for o in got] == [
        ("orbit30_tilt0", 30.0, 0.0),
        ("b", None, None),
        ("orbit0_tilt15", 0.0, 15.0),
        ("orbit0_tilt15", 0.0, 15.0),
        ("orbit0_tilt15", 0.0, 15.0),
    ]
    tiffs = load_config(make_project(tmp_path / "tif"))
    assert [tuple(o) for o in frame_orientations(tiffs, frame_units(tiffs))] == [
        ("f0", None, None),
        ("f1", None, None),
        ("f2", None, None),
    ]


def test_groups_take_the_configs_angles_else_their_frames(tmp_path):
    config = _dicom_project(
        tmp_path,
        'orientations = [{name = "side", frames = ["frames/a.dcm", "frames/b.dcm"]}, '
        '{name = "up", frames = ["frames/c.dcm"], orbit = -1, tilt = 14}]\n',
    )
    got = frame_orientations(config, frame_units(config))
    # a.dcm records (30, 0) and b.dcm nothing: the group takes what is recorded; the config's angles win
    assert [tuple(o) for o in got] == [("side", 30.0, 0.0), ("side", 30.0, 0.0)] + [("up", -1.0, 14.0)] * 3


def test_a_group_whose_frames_record_different_angles_is_refused(tmp_path):
    config = _dicom_project(tmp_path, 'orientations = [{name = "all", frames = "frames/*.dcm"}]\n')
    with pytest.raises(InputError, match=r"orientation 'all' of system 'A': its frames record different angles"):
        frame_orientations(config, frame_units(config))


def test_two_files_with_one_stem_need_named_orientations(tmp_path):
    path = make_project(tmp_path)
    write_still(tmp_path / "frames" / "f0.png", np.full((8, 10), 100, np.uint16))
    path.write_text(path.read_text().replace('frames = "frames/*.tif"', 'frames = ["frames/f0.tif", "frames/f0.png"]'))
    config = load_config(path)
    with pytest.raises(InputError, match=r"f0.tif and .*f0.png of system 'A' would both be orientation 'f0'"):
        frame_orientations(config, frame_units(config))


def test_default_names_are_safe_file_names():
    assert default_orientation_name("x/grid tilt+15°.dcm") == "grid_tilt_15_"
    assert default_orientation_name(".hidden.tif") == "hidden"
    assert len(default_orientation_name("a" * 200 + ".tif", 7)) == 64


# --- the calibration file --------------------------------------------------------------------------


def test_save_and_load_several_orientations(tmp_path):
    cal = orientation_calibration()
    written = cal.save(tmp_path / "calibration.json")
    assert sorted(p.name for p in written) == [
        "calibration.json",
        "field_A_named.npz",
        "field_A_o0.npz",
        "field_A_o30.npz",
        "field_B.npz",
    ]
    doc = json.loads((tmp_path / "calibration.json").read_text())
    a, b = doc["systems"]
    assert doc["schema_version"] == 2 and "field" not in a and b["field"]["file"] == "field_B.npz"
    assert [(o["name"], o["orbit_deg"], o["tilt_deg"], o["field"]["file"]) for o in a["orientations"]] == [
        ("o0", 0.0, 0.0, "field_A_o0.npz"),
        ("o30", 30.0, 0.0, "field_A_o30.npz"),
        ("named", None, None, "field_A_named.npz"),
    ]
    assert b["orientations"] == [] and a["orientations"][0]["field"]["max_correction_px"] == 2.0
    back = Calibration.load(tmp_path / "calibration.json")
    assert back.orientation_names("A") == ["o0", "o30", "named"] and back.orientation_names("B") == []
    for before, after in zip(cal.systems["A"].orientations, back.systems["A"].orientations):
        assert (after.name, after.orbit_deg, after.tilt_deg) == (before.name, before.orbit_deg, before.tilt_deg)
        np.testing.assert_array_equal(after.field.delta_px, before.field.delta_px)
    assert back.systems["A"].field is None
    np.testing.assert_array_equal(back.field("B").delta_px, cal.field("B").delta_px)


def test_one_named_orientation_keeps_the_systems_one_field_file(tmp_path):
    cal = Calibration([toy_system("A", [OrientationField("centred", 0.0, 0.0, constant_field(1.0, 0.0))])], {}, {})
    cal.save(tmp_path / "calibration.json")
    (a,) = json.loads((tmp_path / "calibration.json").read_text())["systems"]
    assert a["field"]["file"] == a["orientations"][0]["field"]["file"] == "field_A.npz"
    back = Calibration.load(tmp_path / "calibration.json")
    assert back.field("A") is back.field("A", "centred") is back.systems["A"].field


def test_a_version_1_file_still_loads(tmp_path):
    """Version 1 had one ``field`` per system and no ``orientations``."""
    cal = Calibration([toy_system("A", field=constant_field(1.0, -1.0))], {}, {})
    cal.save(tmp_path / "calibration.json")
    doc = json.loads((tmp_path / "calibration.json").read_text())
    doc["schema_version"] = 1
    for s in doc["systems"]:
        del s["orientations"]
    (tmp_path / "calibration.json").write_text(json.dumps(doc))
    back = Calibration.load(tmp_path / "calibration.json")
    np.testing.assert_array_equal(back.undistort_points("A", [[10.0, 10.0]]), [[9.0, 11.0]])
    doc["schema_version"] = 3
    (tmp_path / "calibration.json").write_text(json.dumps(doc))
    with pytest.raises(ArtifactError, match="not a fluorocal-calibration file of version 1 or 2"):
        Calibration.load(tmp_path / "calibration.json")


def test_field_file_names_that_would_clash_are_refused(tmp_path):
    a = [
        OrientationField("b_c", None, None, constant_field(0, 0)),
        OrientationField("d", None, None, constant_field(0, 0)),
    ]
    ab = [
        OrientationField("c", None, None, constant_field(0, 0)),
        OrientationField("e", None, None, constant_field(0, 0)),
    ]
    cal = Calibration([toy_system("A", a), toy_system("A_b", ab)], {}, {})
    with pytest.raises(InputError, match="two fields would both be written as field_A_b_c.npz"):
        cal.save(tmp_path / "calibration.json")
    assert not list(tmp_path.iterdir())


def test_orientation_names_in_the_file_are_checked(tmp_path):
    orientation_calibration().save(tmp_path / "calibration.json")
    doc = json.loads((tmp_path / "calibration.json").read_text())
    doc["systems"][0]["orientations"][0]["name"] = "../o0"
    (tmp_path / "calibration.json").write_text(json.dumps(doc))
    with pytest.raises(ArtifactError, match=r"calibration.json: orientation name '../o0' cannot be part of a file"):
        Calibration.load(tmp_path / "calibration.json")


def test_the_api_chooses_by_name_interpolates_by_angles_and_lists_names():
    cal = orientation_calibration()
    xy = np.array([[10.0, 20.0], [40.0, 5.0]])
    np.testing.assert_allclose(cal.undistort_points("A", xy, "o30"), xy - [0.0, 2.0])
    np.testing.assert_allclose(cal.undistort_points("A", xy, orientation="named"), xy + [2.0, 0.0])
    # two calibrated angles: the line between them, halfway at 15°
    np.testing.assert_allclose(cal.undistort_points("A", xy, {"orbit": 15, "tilt": 0}), xy - [1.0, 1.0])
    np.testing.assert_allclose(cal.distort_points("A", xy - [1.0, 1.0], {"orbit": 15, "tilt": 0}), xy, atol=1e-9)
    expected = interpolate_field(cal.systems["A"].orientations, 7.5, 0.0)
    np.testing.assert_array_equal(cal.field("A", {"orbit": 7.5, "tilt": 0}).delta_px, expected.delta_px)
    with pytest.raises(InputError, match=r"system 'A' is calibrated at 3 orientations \(o0, o30, named\); choose"):
        cal.undistort_points("A", xy)
    with pytest.raises(InputError, match=r"orientation 'o60' is not calibrated for system 'A'; its orientations"):
        cal.field("A", "o60")
    with pytest.raises(InputError, match=r"orbit 0..30°, tilt 0°: o0 \(orbit 0°, tilt 0°\), o30"):
        cal.field("A", {"orbit": 45, "tilt": 0})
    with pytest.raises(InputError, match=r"orientation must be None, a name or"):
        cal.field("A", {"orbit": 15})
    with pytest.raises(InputError, match=r"not calibrated for system 'B'; it has one field and no named orientations"):
        cal.field("B", "o0")
    np.testing.assert_allclose(cal.undistort_points("B", xy), xy - 0.5)


def test_a_system_takes_a_field_or_orientations():
    with pytest.raises(InputError, match="give its field or its orientations; got neither"):
        toy_system("A")
    o = [
        OrientationField("x", None, None, constant_field(0, 0)),
        OrientationField("y", None, None, constant_field(0, 0)),
    ]
    with pytest.raises(InputError, match="not both"):
        toy_system("A", o, constant_field(0, 0))
    with pytest.raises(InputError, match="orientation names must differ"):
        toy_system("A", [o[0], o[0]])


# --- fluorocal undistort --orientation ---------------------------------------------------------------


@pytest.fixture()
def undistort_setup(tmp_path):
    """A saved calibration and a ramp frame whose value tells where each pixel came from (10 x + 1000 y)."""
    cal = tmp_path / "cal" / "calibration.json"
    cal.parent.mkdir()
    orientation_calibration().save(cal)
    yy, xx = np.mgrid[0:H, 0:W]
    ramp = (10 * xx + 1000 * yy).astype(np.uint16)
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("o30.tif", "other.tif"):
        write_still(frames / name, ramp)
    return cal, frames, ramp


def _run_undistort(cal, frame, out, *options):
    # --outside keep: the ramp's dim corner would be taken for outside the collimated area (issue 32's edges)
    args = ["--quiet", "undistort", str(cal), str(frame), "--system", "A", "--out", str(out)]
    return main(args + ["--outside", "keep", *options])


@pytest.mark.parametrize(
    "frame, options, shift_xy",
    [
        ("other.tif", ["--orientation", "o0"], (2, 0)),  # Δ = (2, 0): the output at x shows the input at x + 2
        ("other.tif", ["--orientation", "named"], (-2, 0)),
        ("o30.tif", [], (0, 2)),  # no --orientation: the one named like the file
        ("other.tif", ["--orientation", "orbit=15,tilt=0"], (1, 1)),  # halfway between o0 and o30
    ],
)
def test_undistort_uses_the_orientation_asked_for(undistort_setup, tmp_path, frame, options, shift_xy):
    cal, frames, ramp = undistort_setup
    assert _run_undistort(cal, frames / frame, tmp_path / "u", *options) == 0
    (out,) = read_frames(tmp_path / "u" / frame)
    dx, dy = shift_xy
    # interior pixels: their sources lie inside the frame, at integer positions, so linear resampling is exact
    inner = out.image[2 : H - 2, 2 : W - 2]
    np.testing.assert_array_equal(inner, ramp[2 + dy : H - 2 + dy, 2 + dx : W - 2 + dx])


@pytest.mark.parametrize(
    "frame, options, message",
    [
        ("other.tif", [], r"calibrated at 3 orientations \(o0, o30, named\) and none is named 'other' like this file"),
        ("other.tif", ["--orientation", "o60"], r"orientation 'o60' is not calibrated for system 'A'"),
        ("other.tif", ["--orientation", "orbit=45,tilt=0"], r"lies beyond the calibrated orientations .*extrapolate"),
        ("other.tif", ["--orientation", "orbit=15"], r"expected a name, or orbit=DEG,tilt=DEG"),
        ("other.tif", ["--orientation", "orbit=x,tilt=0"], r"orbit must be a number of degrees"),
    ],
)
def test_undistort_orientation_errors_are_one_line_and_write_nothing(
    undistort_setup, tmp_path, capsys, frame, options, message
):
    cal, frames, _ = undistort_setup
    assert _run_undistort(cal, frames / frame, tmp_path / "u", *options) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("fluorocal: error: ")
    assert re.search(message, err), err
    assert not (tmp_path / "u").exists()


# --- how the field changes: the report and fluorocal inspect ---------------------------------------------


def test_orientation_report_figures(tmp_path):
    """Analytic figures of constant fields.

    Δ − Δref = (0.3, 0.4) has RMS per coordinate sqrt((0.09 + 0.16) / 2) = 0.354 px and max 0.5 px, and is a
    translation, so nothing remains modulo a homography.
    """
    fields = [
        OrientationField("tilt30", 0.0, 30.0, constant_field(0.3, 0.4)),
        OrientationField("centred", 0.0, 0.0, constant_field(0.0, 0.0)),
    ]
    paths, lines = orientation_report(tmp_path, "A", fields)
    assert [p.name for p in paths] == ["orientations_A.png", "orientation_maps_A.png"]
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in paths)
    assert "Against orientation centred (orbit 0°, tilt 0°)" in "\n".join(lines)
    assert "| tilt30 | 0 | 30 | 0.354 | 0.500 | 0.000 | 0.000 |" in lines
    assert "| centred | 0 | 0 | 0.000 | 0.000 | 0.000 | 0.000 |" in lines
    assert lines[-1] == "![orientation_maps_A](orientation_maps_A.png)"
    assert orientation_report(tmp_path, "A", fields[:1]) == ([], [])


def test_inspect_a_calibration(undistort_setup, tmp_path, capsys):
    cal, _, _ = undistort_setup
    assert main(["inspect", str(cal), "--out", str(tmp_path / "plots")]) == 0
    out = capsys.readouterr().out
    assert "system A: 64x48 px, 3 field(s)" in out and "system B: 64x48 px, 1 field(s)" in out
    assert "  o30 (orbit 30°, tilt 0°): max |Δ| 2.00 px where supported" in out
    assert "  one field, no named orientation: max |Δ| 0.71 px where supported" in out  # B: |(0.5, 0.5)|
    # against o0 (nearest 0°): o30's Δ − Δref = (−2, 2), RMS per coordinate 2, max 2√2
    assert f"| o30 | 30 | 0 | 2.000 | {2 * math.sqrt(2):.3f} | 0.000 | 0.000 |" in out
    assert (tmp_path / "plots" / "orientations_A.png").is_file()
    assert main(["inspect", str(cal), "label"]) == 2
