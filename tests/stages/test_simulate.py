"""Tests of the radiograph simulator (stages/simulate/) and `fluorocal simulate` (pipeline/cmd_simulate.py).

The grid plate's manufacturing errors, the C-arm orientations and the grid frames' realism: test_simulate_grid.py.
"""

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
