"""Tests of the simulated grid plate (stages/simulate/): its manufacturing errors, the C-arm orientations, its realism.

The grid frames are set against the real ARCADIS grid frames' ranges (one estimator for both); the orientations'
distortion changes against the real C-arm's; and `fluorocal simulate --phantom grid --orientation`. The
simulator's other tests: test_simulate.py.
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.simulate import (
    ImageDistortion,
    SimulateParams,
    make_phantom,
    simulate,
    truth_to_dict,
)
from scipy import ndimage

from tests.helpers import rms_modulo_homography

# ---------------------------------------------------------------- grid plate: manufacturing errors


def _rows_of(xy_mm: np.ndarray, pitch_mm: float) -> np.ndarray:
    """Lattice row of each nominal hole (rows at y = row * pitch * sqrt(3) / 2)."""
    return np.rint(xy_mm[:, 1] / (pitch_mm * np.sqrt(3) / 2)).astype(np.int64)


@pytest.mark.parametrize("seed", [0, 3])
def test_plate_errors_have_the_requested_rms_and_a_drilled_plates_structure(seed):
    """True - nominal hole positions: 0.02 mm 2D RMS by default, in the plate, structured like the real plate.

    The real plate (../shared/data/README.md): rows displaced by ~0.1 px and
    alternate rows offset by ±0.07 px of 0.19 px in all, i.e. variance shares
    ~0.28 (rows), ~0.14 (alternate rows), the rest (~0.58) per hole. Expected
    here: the per-row mean error 0.02 * sqrt(0.42) = 0.0130 mm RMS, the error
    about it 0.02 * sqrt(0.58) = 0.0152 mm, odd rows' mean x minus even rows'
    ±2 * 0.02 * sqrt(0.14) = ±0.0150 mm. Bounds: 81 rows give ~8 % sampling
    spread on row figures (cross terms of the independent parts), 4381 holes ~2 %.
    """
    params = SimulateParams(phantom="grid", seed=seed)
    nominal, true_xyz, _ = make_phantom(params)
    err = true_xyz[:, :2] - nominal.xyz_mm[:, :2]
    assert np.all(true_xyz[:, 2] == nominal.xyz_mm[:, 2])  # in-plane only: the plate stays flat
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) == pytest.approx(params.plate_error_mm, rel=1e-9)
    # no net shift, turn or scale: the plate keeps its nominal place and size
    x, y = nominal.xyz_mm[:, 0], nominal.xyz_mm[:, 1]
    assert np.abs(err.mean(axis=0)).max() < 1e-12
    assert abs(np.mean(x * err[:, 1] - y * err[:, 0])) < 1e-12 and abs(np.mean(x * err[:, 0] + y * err[:, 1])) < 1e-12
    row = _rows_of(nominal.xyz_mm, params.grid_pitch_mm)
    _, index = np.unique(row, return_inverse=True)
    row_mean = np.stack([np.bincount(index, err[:, c]) / np.bincount(index) for c in range(2)], axis=1)[index]
    assert np.sqrt(np.mean(np.sum(row_mean**2, axis=1))) == pytest.approx(0.02 * np.sqrt(0.42), rel=0.1)
    assert np.sqrt(np.mean(np.sum((err - row_mean) ** 2, axis=1))) == pytest.approx(0.02 * np.sqrt(0.58), rel=0.05)
    odd = row % 2 == 1
    assert abs(err[odd, 0].mean() - err[~odd, 0].mean()) == pytest.approx(2 * 0.02 * np.sqrt(0.14), rel=0.2)


def test_plate_error_is_a_parameter_and_the_cube_keeps_its_fabrication_error():
    nominal, true_xyz, _ = make_phantom(SimulateParams(phantom="grid", plate_error_mm=0.05, seed=1))
    assert np.sqrt(np.mean(np.sum((true_xyz - nominal.xyz_mm) ** 2, axis=1))) == pytest.approx(0.05, rel=1e-9)
    nominal, true_xyz, _ = make_phantom(SimulateParams(phantom="grid", plate_error_mm=0.0))
    assert np.array_equal(true_xyz, nominal.xyz_mm)
    # the cube's beads ignore plate_error_mm
    a = make_phantom(SimulateParams())[1]
    assert np.array_equal(a, make_phantom(SimulateParams(plate_error_mm=0.3))[1])


# ---------------------------------------------------------------- C-arm orientations


def _transfer_rms(truth: dict) -> dict:
    """Per orientation: what the centred orientation's true correction leaves, modulo a homography (px).

    Holes measured at ``m`` (grid points inside the field of view) are
    corrected with the centred field (``m - Δ_0(m)``) and compared with their
    true ideal positions (``m - Δ_o(m)``) up to a homography (the plate's pose
    is refitted at each orientation): the real C-arm's "a field fitted at the
    centred orientation leaves ..." figures, here from truth.json alone.
    """
    (system,) = truth["systems"]
    by_name = {o["name"]: o for o in system["orientations"]}
    grid = by_name["centred"]["correction_grid"]
    gx, gy = np.meshgrid(grid["x_px"], grid["y_px"])
    measured = np.stack([gx, gy], axis=-1)
    centre = np.array(truth["fov"]["centre_xy_px"])
    inside = np.hypot(gx - centre[0], gy - centre[1]) < truth["fov"]["radius_px"]
    corrected = (measured - np.array(grid["delta_px"]))[inside]
    return {
        name: rms_modulo_homography(
            (measured - np.array(o["correction_grid"]["delta_px"]))[inside], corrected, refine=True
        )
        for name, o in by_name.items()
    }


def _orientation_truth(seed: int) -> dict:
    """truth.json (geometry only) of ``seed`` at the real C-arm's orientations and a few more."""
    angles = ((0, 0), (0, 15), (0, 22.5), (0, 30), (0, 45), (0, 60), (30, 0), (60, 0))
    params = SimulateParams(phantom="grid", n_frames=1, orientations_deg=angles, seed=seed)
    return json.loads(json.dumps(truth_to_dict(simulate(params, render=False))))


@pytest.fixture(scope="module")
def orientation_truth():
    """:func:`_orientation_truth` of seed 0 (another seed in `make check`)."""
    return _orientation_truth(0)


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.check)])
def test_orientation_change_has_the_real_c_arms_size(seed, orientation_truth):
    """The centred field's transfer error at 15, 30, 45-60 degrees (orbit or tilt) is the real C-arm's.

    Real (../shared/data, issue 12): 0.16-0.25 px at 15°, 0.36-0.40 px at 30°,
    0.5-0.68 px at 45-60°, against ~0.06 px for a field fitted at the
    orientation (that is noise; the truth here has none, so the ranges are used
    as they are). 0 at the centred orientation itself.
    """
    rms = _transfer_rms(orientation_truth if seed == 0 else _orientation_truth(seed))
    assert rms["centred"] < 1e-6
    assert 0.16 <= rms["tilt15"] <= 0.25
    assert 0.36 <= rms["tilt30"] <= 0.40 and 0.36 <= rms["orbit30"] <= 0.40
    for name in ("tilt45", "tilt60", "orbit60"):
        assert 0.5 <= rms[name] <= 0.68, name


def test_orientation_change_is_smooth_and_mostly_tangential(orientation_truth):
    """The change is smooth in the angles and mostly tangential about the image centre (the earth field's S-distortion).

    Smooth: the field at 22.5° is within 0.05 px RMS of the mean of those at 15°
    and 30° (the issue asks interpolation across 30° steps to reach 0.10 px, so
    the truth itself must be far smoother than that). Tangential: of the change
    from the centred field at 30° (field minus its best affine fit), more than
    60 % of the variance is tangential (a purely radial change would give 0 %,
    an isotropic one 50 %).
    """
    truth = orientation_truth
    by_name = {o["name"]: o for o in truth["systems"][0]["orientations"]}
    grid = by_name["centred"]["correction_grid"]
    gx, gy = np.meshgrid(grid["x_px"], grid["y_px"])
    centre = np.array(truth["fov"]["centre_xy_px"])
    inside = np.hypot(gx - centre[0], gy - centre[1]) < truth["fov"]["radius_px"]
    delta = {name: np.array(o["correction_grid"]["delta_px"])[inside] for name, o in by_name.items()}
    mid = delta["tilt22.5"] - (delta["tilt15"] + delta["tilt30"]) / 2
    assert np.sqrt(np.mean(np.sum(mid**2, axis=1))) < 0.05
    xy = np.column_stack([gx[inside], gy[inside]]) - centre
    change = delta["tilt30"] - delta["centred"]
    design = np.column_stack([np.ones(len(xy)), xy])
    change = change - design @ np.linalg.lstsq(design, change, rcond=None)[0]
    radial = xy / np.linalg.norm(xy, axis=1, keepdims=True)
    tangential = np.sum(change * radial[:, ::-1] * [-1, 1], axis=1)
    assert np.sum(tangential**2) / np.sum(change**2) > 0.6


def test_correction_grids_of_every_orientation_invert_its_distortion(orientation_truth):
    """truth.json's per-orientation grids follow DESIGN (ideal = measured - Δ) for its stored forward model (1e-8)."""
    for o in orientation_truth["systems"][0]["orientations"]:
        distortion = ImageDistortion.from_dict(o["distortion"])
        grid = o["correction_grid"]
        measured = np.stack(np.meshgrid(grid["x_px"], grid["y_px"]), axis=-1)
        np.testing.assert_allclose(
            distortion.distort_points(measured - np.array(grid["delta_px"])), measured, atol=1e-8
        )


def test_truth_json_names_each_frames_orientation(orientation_truth):
    truth = orientation_truth
    orientations = truth["systems"][0]["orientations"]
    assert [o["name"] for o in orientations][:3] == ["centred", "tilt15", "tilt22.5"]
    for o in orientations:
        for k in o["exposures"]:
            frame = truth["frames"][k]
            assert (frame["exposure"], frame["orientation"]) == (k, o["name"])
            assert (frame["orbit_deg"], frame["tilt_deg"]) == (o["orbit_deg"], o["tilt_deg"])
    # the stored per-frame projections go through the orientation's distortion
    frame = truth["frames"][orientations[5]["exposures"][0]]
    distortion = ImageDistortion.from_dict(orientations[5]["distortion"])
    beads = frame["beads"]
    np.testing.assert_allclose(
        distortion.distort_points(np.array(beads["ideal_xy_px"])), beads["distorted_xy_px"], atol=1e-9
    )


def test_the_plate_moves_a_few_px_between_orientations(orientation_truth):
    """Real: the plate moves relative to the image by up to ~7 px between orientations; here 1-8 px."""
    truth = orientation_truth
    frames = truth["frames"]
    shifts = []
    for a in frames:
        for b in frames:
            if a["exposure"] < b["exposure"]:
                _, ia, ib = np.intersect1d(a["beads"]["ids"], b["beads"]["ids"], return_indices=True)
                d = np.array(b["beads"]["outline_xy_px"])[ib] - np.array(a["beads"]["outline_xy_px"])[ia]
                shifts.append(np.hypot(*np.median(d, axis=0)))
    assert 1.0 <= max(shifts) <= 8.0


def test_orientation_params_are_checked():
    with pytest.raises(InputError, match="orientations_deg needs phantom='grid'"):
        SimulateParams(orientations_deg=((0, 0),))
    with pytest.raises(InputError, match="must not repeat"):
        SimulateParams(phantom="grid", orientations_deg=((0, 15), (0, 15)))
    with pytest.raises(InputError, match="within ±90"):
        SimulateParams(phantom="grid", orientations_deg=((0, 120),))
    with pytest.raises(InputError, match="pairs"):
        SimulateParams(phantom="grid", orientations_deg=((0, 1, 2),))
    p = SimulateParams(phantom="grid", n_frames=3, orientations_deg=((0, 0), (0, 15)))
    assert p.n_exposures == 6 and SimulateParams(phantom="grid", n_frames=3).n_exposures == 3


def test_an_orientations_frames_do_not_depend_on_the_other_orientations():
    """The same seed and orientation give the same frame and truth, whatever else is simulated with it."""
    common = dict(phantom="grid", n_frames=1, image_size_px=128, detector_size_mm=96.0, seed=5)
    both = simulate(SimulateParams(orientations_deg=((0, 0), (0, 30)), **common))
    alone = simulate(SimulateParams(orientations_deg=((0, 30),), **common))
    assert both.frames[0][1].image.tobytes() == alone.frames[0][0].image.tobytes()
    np.testing.assert_array_equal(both.truth.frames[0][1].outline_xy_px, alone.truth.frames[0][0].outline_xy_px)
    assert both.frames[0][0].image.tobytes() != both.frames[0][1].image.tobytes()


def test_grid_frames_are_rendered_through_their_orientations_distortion():
    """Noise-free hole centroids at a turned orientation equal the truth's outline centres (0.03 px).

    The orientation's change is made large (orientation_distortion_px = 20) so
    that the base (centred) distortion would put the holes > 1 px away. The
    plate is opaque and glare is off, so the hole signal over a flat field
    (the same geometry without steel) is the exact weight; the window
    (radius + 3 px) holds the blurred edge (sigma ~1.3 px) and stops short of
    the neighbouring holes; holes within 12 px of the field's rim are left out
    (the rim's blur does not divide out). Residual: edge sub-sampling, larger
    on these ~8.6 px holes than on beads: median 0.009 px, at most ~0.025 px
    with 21 sub-samples (0.005 / 0.012 px with 89).
    """
    params = SimulateParams(
        phantom="grid",
        n_frames=1,
        orientations_deg=((0, 60),),
        orientation_distortion_px=20.0,
        image_size_px=384,
        detector_size_mm=96.0,
        noise_scale=0.0,
        mu_steel_per_mm=50.0,
        glare_fraction=0.0,
        seed=2,
    )
    data = simulate(params)
    flat = simulate(replace(params, mu_steel_per_mm=0.0)).frames[0][0].image
    ft, img = data.truth.frames[0][0], data.frames[0][0].image
    weight = img / np.maximum(flat, 1.0)
    yy, xx = np.mgrid[: img.shape[0], : img.shape[1]]
    inner = ft.visible & (
        np.linalg.norm(ft.outline_xy_px - params.image_centre_xy_px, axis=1) < params.fov_radius_px - 12
    )
    errors = []
    for n in np.flatnonzero(inner):
        x0, y0 = ft.outline_xy_px[n]
        w = weight * (np.hypot(xx - x0, yy - y0) < ft.diameter_px[n] / 2 + 3)
        errors.append(np.hypot((w * xx).sum() / w.sum() - x0, (w * yy).sum() / w.sum() - y0))
    assert len(errors) > 200 and max(errors) < 0.03
    base = data.truth.systems[0].distortion.distort_points(ft.ideal_xy_px[inner])
    assert np.median(np.linalg.norm(base - ft.distorted_xy_px[inner], axis=1)) > 1.0


# ---------------------------------------------------------------- grid plate: realism


def _grid_frame_figures(img: np.ndarray, radius_px: float = 300.0) -> dict:
    """What a grid frame looks like in its central disc: one estimator for the real and the simulated frames.

    Holes are the local maxima of the smoothed frame; for each, a radial
    profile about its intensity centroid (0.5 px bins) gives the hole level
    (first 1.25 px), the plate level (7.5-9 px out), the diameter at half the
    step and the 90 -> 10 % edge width. Noise: robust spread of the residual
    from a 5 x 5 quadratic (Savitzky-Golay) fit at the plate's darkest pixels,
    scaled to the pixel spread of white noise. Medians over the holes.
    """
    from scipy.signal import savgol_coeffs
    from scipy.spatial import cKDTree

    img = img.astype(np.float64)
    n = img.shape[0]
    yy, xx = np.mgrid[:n, :n]
    central = np.hypot(xx - (n - 1) / 2, yy - (n - 1) / 2) < radius_px
    smooth = ndimage.gaussian_filter(img, 2.5)
    lo, hi = np.percentile(img[central], [10, 98])
    peaks = np.argwhere((smooth == ndimage.maximum_filter(smooth, 9)) & central & (smooth > (lo + hi) / 2))
    gy, gx = np.mgrid[-9:10, -9:10]
    figures, centres = [], []
    for y, x in peaks:
        patch = img[y - 9 : y + 10, x - 9 : x + 10]
        w = np.clip(patch - (lo + hi) / 2, 0, None) * (np.hypot(gx, gy) < 7)
        cx, cy = (w * gx).sum() / w.sum(), (w * gy).sum() / w.sum()
        bins = (np.hypot(gx - cx, gy - cy) * 2).astype(int).ravel()
        counts = np.bincount(bins)
        used = np.flatnonzero(counts[:18])
        profile = np.bincount(bins, weights=patch.ravel())[used] / counts[used]
        radius = used / 2 + 0.25
        top, bottom = profile[:3].mean(), profile[-3:].mean()
        step = (profile - bottom) / (top - bottom)
        r90, r50, r10 = (np.interp(-level, -step, radius) for level in (0.9, 0.5, 0.1))
        figures.append((top, bottom, 2 * r50, r10 - r90))
        centres.append((x + cx, y + cy))
    k = savgol_coeffs(5, 2)
    residual = img - ndimage.convolve1d(ndimage.convolve1d(img, k, axis=0), k, axis=1)
    plate = residual[central & (smooth < np.percentile(smooth[central], 10))]
    white = np.sqrt(1 - 2 * (k**2).sum() + (k**2).sum() ** 2)  # residual spread of unit white noise
    hole_dn, plate_dn, fwhm_px, edge_px = np.median(figures, axis=0)
    centres = np.array(centres)
    return {
        "hole_dn": hole_dn,
        "plate_dn": plate_dn,
        "hole_fwhm_px": fwhm_px,
        "edge_90_10_px": edge_px,
        "noise_dn": 1.4826 * np.median(np.abs(plate - np.median(plate))) / white,
        "pitch_px": np.median(cKDTree(centres).query(centres, k=2)[0][:, 1]),
    }


#: ranges of the real ARCADIS grid frames (grid_centered_0 / grid_tilt_60 measure hole 2966 / 2929 DN,
#: plate 1425 / 1431 DN, hole FWHM 8.18 / 8.09 px, edge 3.08 / 3.03 px, noise 11.9 / 10.8 DN,
#: pitch 15.39 / 15.39 px at the centre), widened by ~5-10 %; the simulated edge is 3.4 px (the
#: intensifier blur is the cube's, whose bead edges match the real bead frames)
GRID_FRAME_RANGES = {
    "hole_dn": (2800, 3100),
    "plate_dn": (1300, 1550),
    "hole_fwhm_px": (7.6, 8.8),
    "edge_90_10_px": (2.7, 3.6),
    "noise_dn": (9.0, 14.0),
    "pitch_px": (15.0, 15.8),
}


def _assert_in_ranges(figures: dict):
    for name, (lo, hi) in GRID_FRAME_RANGES.items():
        assert lo <= figures[name] <= hi, f"{name} = {figures[name]:.2f} outside [{lo}, {hi}]"


@pytest.mark.parametrize("name", ["grid_centered_0", "grid_tilt_60"])
def test_real_grid_frames_fall_in_the_stated_ranges(arcadis_dir, name):
    """The ranges the simulator is held to describe the real frames (same estimator)."""
    from fluorocal.stages.io import read_frames

    _assert_in_ranges(_grid_frame_figures(read_frames(arcadis_dir / f"{name}.dcm")[0].image))


@pytest.mark.check  # a full 1024² grid render, set against the real frames' ranges (whose own test is a check)
def test_default_grid_frame_falls_in_the_real_frames_ranges():
    """A default grid frame (1024², strong distortion, centred C-arm) looks like the real ones (GRID_FRAME_RANGES)."""
    data = simulate(SimulateParams(phantom="grid", n_frames=1, orientations_deg=((0, 0),)))
    _assert_in_ranges(_grid_frame_figures(data.frames[0][0].image))


# ---------------------------------------------------------------- command line


def test_cmd_simulate_grid_orientations(tmp_path):
    """`--phantom grid --orientation`: named DICOM frames with the C-arm's angles, orientations in the config, truth.

    Each orientation's frames are named by it and carry its orbit and tilt
    (PositionerPrimaryAngle, PositionerSecondaryAngle); fluorocal.toml lists
    them under the system's ``orientations``; truth.json names each frame's.
    """
    import pydicom
    from fluorocal.cli import main

    out = tmp_path / "grid"
    args = ["-q", "simulate", str(out), "--phantom", "grid", "--frames", "2"]
    for orbit, tilt in ((0, 0), (0, 15), (30, 0)):
        args += ["--orientation", f"orbit={orbit},tilt={tilt}"]
    assert main([*args, "--image-size", "128", "128", "--format", "dicom", "--plate-error", "0.03"]) == 0
    names = ["centred", "centred", "tilt15", "tilt15", "orbit30", "orbit30"]
    files = sorted((out / "frames" / "A").iterdir())
    assert [f.name for f in files] == [f"frame_{k:03d}_{n}.dcm" for k, n in enumerate(names)]
    angles = [
        (float(ds.PositionerPrimaryAngle), float(ds.PositionerSecondaryAngle)) for ds in map(pydicom.dcmread, files)
    ]
    assert angles == [(0, 0), (0, 0), (0, 15), (0, 15), (30, 0), (30, 0)]
    (system,) = tomllib.loads((out / "fluorocal.toml").read_text())["systems"]
    assert system["frames"] == "frames/A/*.dcm"
    assert [(o["name"], o["orbit"], o["tilt"]) for o in system["orientations"]] == [
        ("centred", 0, 0),
        ("tilt15", 0, 15),
        ("orbit30", 30, 0),
    ]
    listed = [f for o in system["orientations"] for f in o["frames"]]
    assert listed == [f"frames/A/{f.name}" for f in files]
    truth = json.loads((out / "truth.json").read_text())
    assert truth["params"]["orientations_deg"] == [[0, 0], [0, 15], [30, 0]]
    assert truth["params"]["plate_error_mm"] == 0.03
    assert [f["orientation"] for f in truth["frames"]] == names
    assert [o["exposures"] for o in truth["systems"][0]["orientations"]] == [[0, 1], [2, 3], [4, 5]]
    # the options are the grid plate's
    assert main(["-q", "simulate", str(tmp_path / "cube"), "--orientation", "orbit=0,tilt=0"]) == 2
    assert main(["-q", "simulate", str(tmp_path / "cube"), "--plate-error", "0.01"]) == 2
    assert main(["-q", "simulate", str(tmp_path / "bad"), "--phantom", "grid", "--orientation", "0:15"]) == 2
