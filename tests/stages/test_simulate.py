"""Tests of the radiograph simulator (stages/simulate/) and `fluorocal simulate` (pipeline/cmd_simulate.py)."""

from __future__ import annotations

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import project, quat_multiply, quat_to_matrix
from fluorocal.stages.simulate import (
    ImageDistortion,
    SimulateParams,
    ideal_pixel_map,
    make_distortion,
    make_phantom,
    project_beads,
    simulate,
    truth_to_dict,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from tests.helpers import rms_modulo_homography

# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def geometry():
    """Biplanar truth without rendering (fast)."""
    return simulate(SimulateParams(n_frames=3, n_systems=2, image_size_px=512, seed=3), render=False)


@pytest.fixture(scope="module")
def default_frame():
    """One frame at default settings (1024², cube, strong distortion, noise on)."""
    return simulate(SimulateParams(n_frames=1))


def _strong(system: int, size: int = 1024) -> ImageDistortion:
    return make_distortion(SimulateParams(image_size_px=size, distortion="strong", seed=11), system)


# ---------------------------------------------------------------- params and phantom


def test_params_reject_bad_values_naming_them():
    with pytest.raises(InputError, match="distortion must be one of"):
        SimulateParams(distortion="huge")
    with pytest.raises(InputError, match="n_systems must be 1 or 2"):
        SimulateParams(n_systems=3)
    with pytest.raises(InputError, match="n_systems must be 1 for phantom='grid'"):
        SimulateParams(phantom="grid", n_systems=2)
    with pytest.raises(InputError, match="supersample must be one of"):
        SimulateParams(supersample=16)


def test_cube_phantom_matches_the_papers_design():
    params = SimulateParams()
    nominal, true_xyz, ref_xyz = make_phantom(params)
    small = nominal.role != "marker"
    assert 450 <= nominal.n_beads <= 550  # the paper's cube: 503 beads
    assert (nominal.role == "marker").sum() >= 4
    assert np.all(nominal.diameter_mm[small] == 3.5)
    assert np.all(nominal.diameter_mm[~small] > 3.5)
    # every bead lies in the mid-plane of one of the four vertical walls
    mid = params.cube_side_mm / 2 - params.wall_thickness_mm / 2
    assert np.allclose(np.max(np.abs(nominal.xyz_mm[:, :2]), axis=1), mid)
    # fabrication error 0.1 mm and survey noise 0.025 mm (3D RMS); 494 draws: ±15 % sampling spread
    fab = np.sqrt(np.mean(np.sum((true_xyz - nominal.xyz_mm) ** 2, axis=1)))
    survey = np.sqrt(np.mean(np.sum((ref_xyz - true_xyz) ** 2, axis=1)))
    assert fab == pytest.approx(0.1, rel=0.15)
    assert survey == pytest.approx(0.025, rel=0.15)


def test_grid_phantom_is_a_hex_plate():
    nominal, true_xyz, _ = make_phantom(SimulateParams(phantom="grid"))
    assert nominal.lattice == "hex" and nominal.pitch_mm == 3.6
    assert np.all(nominal.xyz_mm[:, 2] == 0) and np.all(true_xyz[:, 2] == 0)  # a plate stays flat
    from scipy.spatial import cKDTree

    d, _ = cKDTree(nominal.xyz_mm[:, :2]).query(nominal.xyz_mm[:, :2], k=7)
    assert np.allclose(d[:, 1], 3.6)  # nearest neighbour at one pitch
    interior = np.linalg.norm(nominal.xyz_mm[:, :2], axis=1) < 100
    assert np.allclose(d[interior, 1:], 3.6)  # six neighbours at one pitch: hexagonal


# ---------------------------------------------------------------- geometry truth


def test_acquisition_geometry_is_in_the_specified_ranges(geometry):
    p = geometry.params
    for system in geometry.truth.systems:
        assert 1000 <= system.source_image_distance_mm <= 1200
        assert system.iop_px[2] == pytest.approx(system.source_image_distance_mm / p.pixel_pitch_mm)
    # the biplanar systems are 60-90 degrees apart
    za, zb = (quat_to_matrix(s.lab_from_camera_q)[:, 2] for s in geometry.truth.systems)
    assert 60 <= np.degrees(np.arccos(za @ zb)) <= 90
    # relative orientation of B to A is the same at every exposure (rigid biplanar rig)
    q = geometry.truth.acquisition.q
    rel = [quat_to_matrix(q[1, k]) @ quat_to_matrix(q[0, k]).T for k in range(p.n_frames)]
    assert np.allclose(rel, rel[0], atol=1e-12)
    # bead images 10-25 px across (markers larger)
    small = np.concatenate(
        [
            ft.diameter_px[np.isin(ft.ids, geometry.phantom.ids[geometry.phantom.role == ""])]
            for per in geometry.truth.frames
            for ft in per
        ]
    )
    assert 10 * p.px_scale <= small.min() and small.max() <= 25 * p.px_scale


def test_reprojection_from_truth_json_reproduces_stored_projections(geometry):
    """Rebuild poses from the lab placement and re-project the true coordinates (1e-6 px).

    Independent of the simulator's own pose bookkeeping: the pose is recomputed
    from the stored lab placement of camera and turntable, and everything comes
    from truth.json (floats written exactly by json).
    """
    truth = json.loads(json.dumps(truth_to_dict(geometry)))
    true_xyz = np.array(truth["phantom"]["true_xyz_mm"])
    index = {i: n for n, i in enumerate(truth["phantom"]["ids"])}
    systems = {s["name"]: s for s in truth["systems"]}
    n_checked = 0
    for frame in truth["frames"]:
        system = systems[frame["system"]]
        exposure = truth["exposures"][frame["exposure"]]
        # p_cam = C^T (R_k P + t_k - S): q = conj(q_lab_from_camera) * q_lab_from_phantom
        q_cl = np.array(system["lab_from_camera_q"]) * [1, -1, -1, -1]
        q = quat_multiply(q_cl, exposure["lab_from_phantom_q"])
        R_k = quat_to_matrix(exposure["lab_from_phantom_q"])
        source = R_k.T @ (np.array(system["source_lab_mm"]) - exposure["turntable_translation_mm"])
        assert np.allclose(source, frame["source_mm"], atol=1e-9)
        beads = frame["beads"]
        xyz = true_xyz[[index[i] for i in beads["ids"]]]
        ideal = project(xyz, q, source, np.array(system["iop_px"]))
        distortion = ImageDistortion.from_dict(system["distortion"])
        np.testing.assert_allclose(ideal, beads["ideal_xy_px"], atol=1e-6, rtol=0)
        np.testing.assert_allclose(distortion.distort_points(ideal), beads["distorted_xy_px"], atol=1e-6, rtol=0)
        n_checked += len(xyz)
    assert n_checked > 1000


def test_outline_centre_differs_from_centre_projection_as_the_cone_predicts():
    """A sphere off the axis: its outline ellipse's centre lies further out than its centre's projection.

    Exact check: in the plane through the axis and the sphere's centre, the
    silhouette's extreme rays are at angles α ± asin(r / D) from the axis, and
    the ellipse's centre is the midpoint of their image points (1e-6 relative:
    float round-off only).
    """
    c = 4000.0
    iop = np.array([500.0, 500.0, c])
    r, depth, off = 20.0, 400.0, 300.0  # a large sphere far off-axis makes the effect visible
    ft = project_beads(
        np.array([0]),
        np.array([[off, 0.0, depth]]),
        np.array([2 * r]),
        np.array([1.0, 0, 0, 0]),
        np.zeros(3),
        iop,
        ImageDistortion.identity(4000),
        image_size_px=4000,
        fov_radius_px=10000,
    )
    shift = ft.outline_ideal_xy_px[0, 0] - ft.ideal_xy_px[0, 0]
    # exact: the tangent cone's silhouette edges are at angles atan(off/depth) ± asin(r/D)
    alpha, half = np.arctan2(off, depth), np.arcsin(r / np.hypot(off, depth))
    exact = c * (np.tan(alpha + half) + np.tan(alpha - half)) / 2 - c * off / depth
    assert shift > 0
    assert shift == pytest.approx(exact, rel=1e-6)
    assert ft.outline_xy_px[0] == pytest.approx(ft.outline_ideal_xy_px[0], abs=1e-9)  # no distortion: same centre


def test_overlap_and_field_edge_flags_on_a_constructed_case():
    """Beads in a plane facing the source at 800 mm: 5.5 px per mm, 3.5 mm beads are 19.25 px across.

    Pair (0, 1): centres 3.7 mm apart, outlines 1.1 px apart < 2 px margin -> overlap.
    Pair (2, 3): centres 4.2 mm apart, outlines 3.85 px apart > margin -> no overlap.
    Bead 4: isolated. Bead 5: straddles the field-of-view rim -> field_edge.
    """
    c = 4400.0
    iop = np.array([511.5, 511.5, c])
    xyz = np.array(
        [[-40, -20, 0], [-36.3, -20, 0], [10, 20, 0], [14.2, 20, 0], [30, -30, 0], [86.0, 0, 0]], dtype=float
    )
    ft = project_beads(
        np.arange(6),
        xyz,
        np.full(6, 3.5),
        np.array([1.0, 0, 0, 0]),
        np.array([0, 0, -800.0]),
        iop,
        ImageDistortion.identity(1024),
        image_size_px=1024,
        fov_radius_px=481.28,
        overlap_margin_px=2.0,
    )
    assert list(ft.ids) == [0, 1, 2, 3, 4, 5]
    # beads off the axis image slightly larger (by up to 1/cos³ of the obliquity, < 0.5 % here)
    assert ft.diameter_px == pytest.approx(3.5 * c / 800, rel=5e-3)
    assert list(ft.overlap) == [True, True, False, False, False, False]
    assert list(ft.field_edge) == [False, False, False, False, False, True]


# ---------------------------------------------------------------- distortion


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    system=st.integers(0, 1),
    points=st.lists(
        st.tuples(st.floats(-0.5, 1023.5, width=64), st.floats(-0.5, 1023.5, width=64)), min_size=1, max_size=40
    ),
)
def test_distortion_round_trip_below_1e_3_px(system, points):
    distortion = _strong(system)
    xy = np.array(points)
    assert np.max(np.abs(distortion.distort_points(distortion.undistort_points(xy)) - xy)) < 1e-3
    assert np.max(np.abs(distortion.undistort_points(distortion.distort_points(xy)) - xy)) < 1e-3


def test_distortion_levels_have_the_specified_size():
    """Strong: radial 10-20 px at the field edge, random field 0.3-1 px RMS; mild smaller; none identity."""
    size = 1024
    edge = np.array([[511.5 + 481.0, 511.5], [511.5, 511.5 - 481.0], [511.5 - 340.0, 511.5 + 340.0]])
    for system in (0, 1):
        strong = _strong(system)
        shift = np.linalg.norm(strong.distort_points(edge) - edge, axis=1)
        assert np.all((8 < shift) & (shift < 30))
        radial_only = replace(strong, s_rad=0.0, p1=0.0, p2=0.0, field_coeffs_px=np.zeros((2, 1, 1)))
        radial = np.linalg.norm(radial_only.distort_points(edge) - edge, axis=1)
        assert np.all((10 <= radial) & (radial <= 20))
        g = np.linspace(0, size - 1, 64)
        field = strong._field(np.stack(np.meshgrid(g, g), axis=-1))
        assert 0.3 <= np.sqrt(np.mean(np.sum(field**2, axis=-1))) <= 1.0
        # correlation length 50-100 px: the field decorrelates to 1/e within that lag
        lag = [np.corrcoef(field[:, :-j, 0].ravel(), field[:, j:, 0].ravel())[0, 1] for j in range(1, 12)]
        first_below = (np.argmax(np.array(lag) < np.exp(-1)) + 1) * (g[1] - g[0])
        assert 40 <= first_below <= 110
    mild = make_distortion(SimulateParams(distortion="mild", seed=11), 0)
    assert np.max(np.linalg.norm(mild.distort_points(edge) - edge, axis=1)) < 10
    assert make_distortion(SimulateParams(distortion="none"), 0).is_identity
    # the two systems differ
    assert not np.allclose(_strong(0).distort_points(edge), _strong(1).distort_points(edge))


def test_correction_grid_follows_the_design_convention():
    """DESIGN: ideal = measured - Δ(measured), so distort(grid - Δ) returns the grid."""
    distortion = _strong(0, size=256)
    gx, gy, delta = distortion.correction_grid(256, 16.0)
    measured = np.stack(np.meshgrid(gx, gy), axis=-1)
    assert gx[0] == 0 and gx[-1] == 255 and delta.shape == (len(gy), len(gx), 2)
    np.testing.assert_allclose(distortion.distort_points(measured - delta), measured, atol=1e-8)


def test_rendering_inverse_map_is_exact_per_pixel():
    """The per-pixel ideal map used for rendering equals the Newton inverse (1e-6 px)."""
    distortion = _strong(1, size=512)
    ideal = ideal_pixel_map(distortion, 512)
    rng = np.random.default_rng(0)
    rc = rng.integers(0, 512, size=(500, 2))
    exact = distortion.undistort_points(rc[:, ::-1].astype(float))
    assert np.max(np.abs(ideal[rc[:, 0], rc[:, 1]] - exact)) < 1e-6


def test_edge_subsamples_map_to_ideal_rays_to_first_order():
    """Sub-samples use ideal(pixel) + J·offset; versus the exact inverse the error stays < 5e-4 px.

    Bound: second derivative of the strong distortion (~5e-4 /px at the rim)
    times offset² / 2 (<= 0.25 px²) plus one-sided differences at the image border.
    """
    from fluorocal.stages.simulate import local_jacobian

    distortion = _strong(0)
    ideal = ideal_pixel_map(distortion, 1024)
    rng = np.random.default_rng(1)
    flat_idx = rng.integers(0, 1024 * 1024, 2000)
    offsets = rng.uniform(-0.5, 0.5, (2000, 2))
    y, x = np.divmod(flat_idx, 1024)
    approx = ideal.reshape(-1, 2)[flat_idx] + np.einsum("nij,nj->ni", local_jacobian(ideal, flat_idx), offsets)
    exact = distortion.undistort_points(np.column_stack([x, y]) + offsets)
    assert np.max(np.abs(approx - exact)) < 5e-4


# ---------------------------------------------------------------- rendering


@pytest.mark.parametrize("distortion", ["none", "strong"])
def test_opaque_bead_centroid_is_its_outline_centre(distortion):
    """Zero noise: absorption-weighted centroid of isolated opaque beads vs their outline centres.

    Tolerance 0.02 px (the issue's bound, stated for no distortion; it holds
    through the strong distortion too, which shows frames are rendered through
    the distortion and not warped). Absorption is taken against a flat field
    rendered with the same geometry and no steel (it divides out vignetting and
    heel, which would otherwise tilt the weights); beads are made opaque
    (mu = 50 /mm); the window (radius + 6 px) holds the blurred edge (sigma
    ~1.3 px) whole. Residual error: edge sub-sampling (~0.01 px with 21 points).
    """
    params = SimulateParams(
        n_frames=4,
        image_size_px=256,
        detector_size_mm=64.0,
        distortion=distortion,
        noise_scale=0.0,
        mu_steel_per_mm=50.0,
        mu_acrylic_per_mm=0.0,
        seed=5,
    )
    xyz = np.array([[4.0, -3.0, 2.0], [-8.0, 5.0, -6.0], [6.0, 8.0, 7.0]])
    beads = Phantom(np.array([3, 5, 7]), xyz, np.full(3, 3.5), np.full(3, ""))
    data = simulate(params, phantom=beads)
    flat = simulate(replace(params, mu_steel_per_mm=0.0), phantom=beads)
    yy, xx = np.mgrid[:256, :256]
    errors = []
    for k in range(params.n_frames):
        ft = data.truth.frames[0][k]
        absorption = 1.0 - data.frames[0][k].image.astype(np.float64) / np.maximum(flat.frames[0][k].image, 1.0)
        for n in np.flatnonzero(~ft.field_edge & ~ft.overlap):
            x0, y0 = ft.outline_xy_px[n]
            w = absorption * (np.hypot(xx - x0, yy - y0) < ft.diameter_px[n] / 2 + 6)
            centroid = np.array([(w * xx).sum(), (w * yy).sum()]) / w.sum()
            errors.append(np.linalg.norm(centroid - ft.outline_xy_px[n]))
    assert len(errors) >= 6
    assert max(errors) < 0.02


def test_same_seed_same_bytes_and_different_seed_differs():
    params = SimulateParams(n_frames=1, n_systems=2, image_size_px=128)
    a, b = simulate(params), simulate(params)
    c = simulate(replace(params, seed=1))
    for s in range(2):
        assert a.frames[s][0].image.tobytes() == b.frames[s][0].image.tobytes()
        assert a.frames[s][0].image.tobytes() != c.frames[s][0].image.tobytes()
    assert json.dumps(truth_to_dict(a)) == json.dumps(truth_to_dict(b))


def test_render_false_gives_the_same_truth_without_frames():
    params = SimulateParams(n_frames=1, image_size_px=128)
    rendered, geometry_only = simulate(params), simulate(params, render=False)
    assert geometry_only.frames == ((),)
    assert json.dumps(truth_to_dict(rendered)) == json.dumps(truth_to_dict(geometry_only))


def test_frames_are_12_bit_with_a_dark_round_field():
    data = simulate(SimulateParams(n_frames=1, image_size_px=128, seed=2))
    frame = data.frames[0][0]
    img = frame.image
    assert frame.bit_depth == 12 and img.dtype == np.float32 and img.shape == (128, 128)
    assert img.min() >= 0 and img.max() <= 4095 and np.all(img == np.rint(img))
    assert img[:8, :8].mean() < 50  # corners outside the intensifier disc are dark
    assert img[60:68, 60:68].mean() > 500


def test_grid_plate_renders_bright_holes():
    data = simulate(
        SimulateParams(n_frames=1, phantom="grid", image_size_px=256, detector_size_mm=128.0, noise_scale=0.0)
    )
    ft, img = data.truth.frames[0][0], data.frames[0][0].image
    inner = ~ft.field_edge & ~ft.overlap
    holes = ndimage.map_coordinates(img, ft.outline_xy_px[inner][:, ::-1].T, order=1)
    assert len(holes) > 300
    assert np.median(holes) > 1.4 * np.median(img[64:192, 64:192])  # holes brighter than the plate


def _isolated_bead_stats(img: np.ndarray, centres: np.ndarray, diameters: np.ndarray):
    """Median contrast, background and 90->10 % edge width (px) of isolated beads."""
    contrasts, backgrounds, widths = [], [], []
    for (x, y), d in zip(centres, diameters):
        r, h = d / 2, int(d * 1.1)
        xi, yi = int(round(x)), int(round(y))
        patch = img[yi - h : yi + h + 1, xi - h : xi + h + 1].astype(np.float64)
        yy, xx = np.mgrid[-h : h + 1, -h : h + 1]
        rr = np.hypot(xx - (x - xi), yy - (y - yi))
        background = np.median(patch[(rr > r + 4) & (rr < 2 * r)])
        centre = patch[rr < 2].mean()
        contrasts.append(1 - centre / background)
        backgrounds.append(background)
        # radial profile in 0.5 px bins (empty bins skipped)
        bins = (rr * 2).astype(int).ravel()
        counts = np.bincount(bins)
        used = np.flatnonzero(counts[: int(3.2 * r)])
        profile = np.bincount(bins, weights=patch.ravel())[used] / counts[used]
        radius = used / 2 + 0.25
        step = (profile - centre) / (background - centre)
        widths.append(np.interp(0.9, step, radius) - np.interp(0.1, step, radius))
    return np.median(contrasts), np.median(backgrounds), np.median(widths)


def test_default_frames_fall_in_the_real_frames_measured_ranges(default_frame):
    """Compare with the ARCADIS measurements in ../shared/data/README.md.

    Real: open field 1400-1800 DN falling to the rim; noise ~16 DN after removing
    a sigma = 3 px Gaussian background; small beads 18-20 px across, centre
    140-150 DN on ~1400 DN (contrast ~90 %), 90->10 % edge over 4-6 px.
    Tolerances are a little wider than the real ranges because the real figures
    come from two frames and a different phantom (whose plastic differs from
    our acrylic walls): open field 1300-1850 DN, noise 13-20 DN, contrast 0.85-0.95,
    diameter 17-22 px (the cube's front wall is magnified more than its back), edge 3.5-6.5 px.
    """
    ft = default_frame.truth.frames[0][0]
    img = default_frame.frames[0][0].image.astype(np.float64)
    size = img.shape[0]
    yy, xx = np.mgrid[:size, :size]
    r = np.hypot(xx - (size - 1) / 2, yy - (size - 1) / 2)
    away = np.ones(img.shape, dtype=bool)
    for (x, y), d in zip(ft.outline_xy_px, ft.diameter_px):
        away[max(0, int(y - d)) : int(y + d) + 1, max(0, int(x - d)) : int(x + d) + 1] = False
    open_field = img[(r < 0.45 * size) & away]
    lo, med, hi = np.percentile(open_field, [5, 50, 95])
    assert 1300 <= lo and hi <= 1850 and 1400 <= med <= 1800
    residual = img - ndimage.gaussian_filter(img, 3)
    # flat regions only: residual of the acrylic wall edges would inflate the figure
    flat = (
        (r < 0.4 * size) & away & (np.abs(ndimage.gaussian_gradient_magnitude(ndimage.gaussian_filter(img, 3), 2)) < 3)
    )
    assert 13 <= residual[flat].std() <= 20
    small = (
        (~ft.overlap) & (~ft.field_edge) & np.isin(ft.ids, default_frame.phantom.ids[default_frame.phantom.role == ""])
    )
    diam = ft.diameter_px[small]
    assert 17 <= np.median(diam) <= 22
    contrast, background, width = _isolated_bead_stats(img, ft.outline_xy_px[small], diam)
    assert 0.85 <= contrast <= 0.95
    assert 1300 <= background <= 1800
    assert 3.5 <= width <= 6.5
    assert img[r > 0.5 * size].mean() < 50  # dark outside the disc


# ---------------------------------------------------------------- command line


def test_cmd_simulate_writes_a_readable_dataset(tmp_path):
    from fluorocal.cli import main
    from fluorocal.stages.io import read_frames, read_phantom

    out = tmp_path / "sim"
    assert (
        main(
            ["-q", "simulate", str(out), "--frames", "2", "--systems", "2", "--image-size", "128", "128", "--seed", "4"]
        )
        == 0
    )
    for name in ("phantom.csv", "reference.csv", "truth.json", "fluorocal.toml", "montage.png"):
        assert (out / name).is_file(), name
    expected = simulate(SimulateParams(n_frames=2, n_systems=2, image_size_px=128, seed=4))
    for s, name in enumerate(("A", "B")):
        files = sorted((out / "frames" / name).glob("*.tif"))
        assert [f.name for f in files] == ["frame_000.tif", "frame_001.tif"]
        for k, f in enumerate(files):
            (frame,) = read_frames(f)
            np.testing.assert_array_equal(frame.image, expected.frames[s][k].image)
    phantom = read_phantom(out / "phantom.csv")
    np.testing.assert_allclose(phantom.xyz_mm, expected.phantom.xyz_mm, atol=1e-6)
    assert list(phantom.role) == list(expected.phantom.role)
    truth = json.loads((out / "truth.json").read_text())
    assert truth["schema"] == "fluorocal-simulation-truth" and len(truth["frames"]) == 4
    config = tomllib.loads((out / "fluorocal.toml").read_text())
    assert config["phantom"]["file"] == "phantom.csv" and config["output"]["dir"] == "out"
    assert [s["frames"] for s in config["systems"]] == ["frames/A/*.tif", "frames/B/*.tif"]
    # refuses a non-empty directory unless --overwrite
    assert main(["-q", "simulate", str(out), "--frames", "1", "--image-size", "64", "64"]) == 2
    assert main(["-q", "simulate", str(out), "--frames", "1", "--image-size", "64", "64", "--overwrite"]) == 0
    assert sorted(p.name for p in (out / "frames" / "A").iterdir()) == ["frame_000.tif"]


def test_cmd_simulate_dicom(tmp_path):
    from fluorocal.cli import main
    from fluorocal.stages.io import read_frames

    out = tmp_path / "dcm"
    assert (
        main(
            [
                "-q",
                "simulate",
                str(out),
                "--frames",
                "1",
                "--image-size",
                "64",
                "64",
                "--format",
                "dicom",
                "--noise",
                "0",
            ]
        )
        == 0
    )
    (frame,) = read_frames(out / "frames" / "A" / "frame_000.dcm")
    assert frame.bit_depth == 12 and frame.metadata["modality"] == "XA"
    assert frame.metadata["ImagerPixelSpacing"] == [4.0, 4.0]
    expected = simulate(SimulateParams(n_frames=1, image_size_px=64, noise_scale=0.0))
    np.testing.assert_array_equal(frame.image, expected.frames[0][0].image)


@pytest.mark.parametrize("fmt", ["tiff", "dicom"])
def test_cmd_simulate_same_seed_same_files(tmp_path, fmt):
    """Every written file is byte-identical across runs (no timestamps, UIDs derived from the seed)."""
    from fluorocal.cli import main

    args = ["--frames", "1", "--systems", "2", "--image-size", "64", "64", "--format", fmt, "--seed", "9"]
    for name in ("one", "two"):
        assert main(["-q", "simulate", str(tmp_path / name), *args]) == 0
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*") if p.is_file())
    assert len(files) == 7  # 2 frames, phantom, reference, truth, config, montage
    for rel in files:
        assert (tmp_path / "one" / rel).read_bytes() == (tmp_path / "two" / rel).read_bytes(), rel


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


# ---------------------------------------------------------------- defaults unchanged


def test_cube_frames_and_truth_are_those_of_the_committed_fixture():
    """fixtures/sim is reproduced: the same pixels and the same truth.

    Its frames were written by simulator version 1, before the grid's
    orientations and plate errors, and are unchanged since; its truth.json
    was rewritten by version 2 with only ``params`` (new fields) and
    ``simulator_version`` changed (checked then against version 1's file).
    """
    import importlib.util
    from pathlib import Path

    from fluorocal.stages.io import read_frames

    root = Path(__file__).resolve().parents[2] / "fixtures"
    spec = importlib.util.spec_from_file_location("make_fixtures", root / "make_fixtures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    data = simulate(module.PARAMS)
    for s, name in enumerate(data.system_names):
        for k, frame in enumerate(data.frames[s]):
            (stored,) = read_frames(root / "sim" / "frames" / name / f"frame_{k:03d}.tif")
            np.testing.assert_array_equal(frame.image, stored.image)
    stored = json.loads((root / "sim" / "truth.json").read_text())
    fresh = json.loads(json.dumps(truth_to_dict(data)))
    for key in set(stored) - {"params", "simulator_version"}:
        _assert_same_truth(fresh[key], stored[key], key)
    assert {k: v for k, v in fresh["params"].items() if k in stored["params"]} == stored["params"]


def _assert_same_truth(fresh, stored, where: str) -> None:
    """Equal structure, ids and flags; floats to 1e-9 (numpy/scipy releases move the outlines' last bits, ~1e-11 px)."""
    if isinstance(stored, dict):
        assert fresh.keys() == stored.keys(), where
        for key in stored:
            _assert_same_truth(fresh[key], stored[key], f"{where}.{key}")
    elif isinstance(stored, list) and stored and isinstance(stored[0], (dict, list)):
        assert len(fresh) == len(stored), where
        for i, (a, b) in enumerate(zip(fresh, stored)):
            _assert_same_truth(a, b, f"{where}[{i}]")
    elif isinstance(stored, float) or (isinstance(stored, list) and any(isinstance(v, float) for v in stored)):
        np.testing.assert_allclose(fresh, stored, rtol=0, atol=1e-9, err_msg=where)
    else:
        assert fresh == stored, where


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
