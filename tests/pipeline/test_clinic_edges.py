"""Issue 32, edges: nothing from beyond the field's support or the collimated area is warped into the picture.

The invariant checked: a bright rim row (a detector artefact) changes no output pixel once the outside is set
to the background, while with ``--outside keep`` it is warped into a streak. And the derived DICOM series gets
its own SeriesNumber and the derivation's ContentDate/ContentTime.
"""

from __future__ import annotations

import datetime
import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
from fluorocal.cli import main
from fluorocal.stages.io.dicom import SERIES_NUMBER_OFFSET
from fluorocal.stages.undistort import (
    UndistortParams,
    clear_outside,
    collimated_area,
    remap_image,
    supported_output,
)

from tests.stages.plate_truth import truth_field

RIM_DN = 4091  # the ARCADIS spine frame's bright first row reaches this


@pytest.fixture(scope="module")
def simulated():
    """A simulated 256 px grid frame (round field of view inside the image) and its true correction field."""
    from fluorocal.stages.simulate import SimulateParams, simulate, truth_to_dict

    data = simulate(SimulateParams(phantom="grid", n_frames=1, image_size_px=256, seed=3))
    truth = truth_to_dict(data)
    field = truth_field(truth["systems"][0]["correction_grid"], 256, 256)
    centre, radius = np.asarray(truth["fov"]["centre_xy_px"]), float(truth["fov"]["radius_px"])
    # a calibration sees holes only inside the field of view: its support ends there
    inside = np.linalg.norm(field.nodes_px.reshape(field.support.shape + (2,)) - centre, axis=-1) < radius
    return data.frames[0][0].image.astype(np.uint16), field.with_delta(field.delta_px, support=inside), centre, radius


def _undistorted(image, field, outside):
    maps = field.remap_maps()
    params = UndistortParams(outside=outside)
    return clear_outside(image, remap_image(image, *maps, params), *maps, params, supported_output(field, *maps))


def test_a_bright_rim_row_of_a_simulated_frame_is_not_warped_into_the_picture(simulated):
    clean, field, centre, radius = simulated
    rim = clean.copy()
    rim[0] = RIM_DN
    # without the option the strong pincushion's inverse map reaches row 0 from output rows 1..8: a streak
    streak = np.abs(_undistorted(rim, field, "keep").astype(int) - _undistorted(clean, field, "keep")) > 1000
    assert streak.sum() > 100
    # with it, the rim row changes no output pixel by more than the background's median does (1 DN), but for
    # at most 0.1 % on the field's outline (the rim row moves the collimated area's threshold a little)
    out = _undistorted(rim, field, "background")
    changed = np.abs(out.astype(int) - _undistorted(clean, field, "background")) > 1
    assert changed.sum() <= 0.001 * out.size and not changed[streak].any()
    # the cleared pixels hold the frame's background: the median outside the field of view (dark, < 1 % of 4095)
    yy, xx = np.mgrid[0:256, 0:256]
    outside_fov = np.hypot(xx - centre[0], yy - centre[1]) > radius + 2
    background = float(np.median(clean[outside_fov]))
    cleared = out != remap_image(rim, *field.remap_maps(), UndistortParams())
    assert streak[cleared].sum() == streak.sum() and background < 41
    # within 3 DN: the rim row is 1.7 % of the pixels outside the disc, which moves their median by 1-2 DN of noise
    assert np.all(np.abs(out[cleared].astype(float) - background) <= 3)
    # and inside 90 % of the field's radius (the supported, exposed picture) nothing is cleared
    ideal_inside = np.hypot(xx - centre[0], yy - centre[1]) < 0.9 * radius
    assert not cleared[ideal_inside].any()


def test_the_collimated_area_is_the_bright_disc_and_not_a_rim_row(simulated):
    clean, _, centre, radius = simulated
    rim = clean.copy()
    rim[0] = RIM_DN
    mask = collimated_area(rim)
    yy, xx = np.mgrid[0:256, 0:256]
    r = np.hypot(xx - centre[0], yy - centre[1])
    # within 3 px of the true round field of view (the simulated rim is blurred and vignetted)
    assert mask[r < radius - 3].all() and not mask[r > radius + 3].any() and not mask[0].any()


def test_outside_is_checked():
    from fluorocal.stages.errors import InputError

    with pytest.raises(InputError, match="outside must be one of background, keep"):
        UndistortParams(outside="crop")


# --- the real spine frame ---------------------------------------------------------------------------


@pytest.mark.slow
def test_spine_frame_rim_row_is_not_warped_and_the_series_is_new(centred_calibration, arcadis_dir, tmp_path):
    source = Path(arcadis_dir) / "spine_centered_0.dcm"
    no_rim = tmp_path / "no_rim" / "spine_centered_0.dcm"
    no_rim.parent.mkdir()
    shutil.copyfile(source, no_rim)
    ds = pydicom.dcmread(no_rim)
    pixels = ds.pixel_array.copy()
    assert pixels[0].max() == RIM_DN and pixels[1:].max() < RIM_DN  # the artefact the issue names
    pixels[0] = pixels[1]  # the frame as it would be without the rim row
    ds.PixelData = pixels.tobytes()
    ds.save_as(no_rim)
    before = datetime.datetime.now().replace(microsecond=0)
    out = {}
    for name, path, outside in (("rim", source, "keep"), ("rim", source, "background"), ("clean", no_rim, "keep")):
        folder = tmp_path / f"{name}_{outside}"
        args = ["--quiet", "undistort", str(centred_calibration), str(path), "--system", "arcadis"]
        assert main(args + ["--out", str(folder), "--outside", outside]) == 0
        out[name, outside] = pydicom.dcmread(folder / "spine_centered_0.dcm")
    keep, clean = (out[k].pixel_array.astype(int) for k in (("rim", "keep"), ("clean", "keep")))
    # without the option: the curved streak at the top (more than 1000 DN above the rim-less frame's remap)
    streak = np.abs(keep - clean) > 1000
    assert streak.sum() > 200 and np.nonzero(streak)[0].max() <= 40
    # with it: every output pixel the rim row reaches is set to the background (0 DN outside the disc)
    background = out["rim", "background"].pixel_array.astype(int)
    assert np.all(background[streak] == 0)
    # and the rest of the picture is the plain remap: the cleared pixels lie outside the disc's supported part
    cleared = background != keep
    yy, xx = np.mgrid[0:1024, 0:1024]
    assert not cleared[np.hypot(xx - 511.5, yy - 511.5) < 400].any() and np.all(background[cleared] == 0)
    # the derived series: its own number, the derivation's date and time, and the edge rule recorded
    derived, original = out["rim", "background"], pydicom.dcmread(source, stop_before_pixels=True)
    assert int(derived.SeriesNumber) == int(original.SeriesNumber) + SERIES_NUMBER_OFFSET == 1021
    made = datetime.datetime.strptime(derived.ContentDate + derived.ContentTime.split(".")[0], "%Y%m%d%H%M%S")
    assert before <= made <= datetime.datetime.now() and derived.ContentDate != original.ContentDate
    assert "outside the field's support and the collimated area: background" in derived.DerivationDescription
