"""Tests of stages/label/: cube phantoms from markers, seeds and a prior pose; grid plates; failures.

Ground truth comes from the simulator's geometry (``simulate(render=False)``):
the distorted outline centre of every visible bead, turned into detection-like
centroids by :func:`detections_from_truth` (heavily overlapping beads merge into
one blob or vanish, as a detector would make of them). One rendered frame goes
through detect and centroid as well.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import project, quat_to_matrix, rotvec_to_quat
from fluorocal.stages.kinds.labelling import label_beads, label_sequence
from fluorocal.stages.label import (
    STATUS_AMBIGUOUS,
    STATUS_LABELLED,
    STATUS_REJECTED,
    LabelParams,
    Labels,
    lattice_id,
    lattice_index,
    lattice_xyz_mm,
)
from fluorocal.stages.simulate import SimulateParams, simulate
from scipy.spatial import cKDTree

from tests.stages.label_truth import (
    detections_from_truth,
    make_centroids,
    seeds_from_truth,
    unambiguous_ids,
    without_roles,
)


@pytest.fixture(scope="module")
def sim():
    """Two systems, three exposures each, default cube and strong distortion: geometry and truth only."""
    return simulate(SimulateParams(n_frames=3, n_systems=2, seed=11), render=False)


@pytest.fixture(scope="module")
def params(sim):
    p = sim.params
    return LabelParams(
        source_image_distance_mm=p.source_image_distance_mm,
        pixel_pitch_mm=p.pixel_pitch_mm,
        image_size_px=(p.image_size_px, p.image_size_px),
    )


def all_frames(sim):
    return [ft for per_system in sim.truth.frames for ft in per_system]


def check_against_truth(lab: Labels, ids: np.ndarray, ft, *, min_fraction: float):
    """No wrong label; ``min_fraction`` of the unambiguous, detected beads labelled."""
    assert lab.ok, lab.reason
    assert np.array_equal(ids[lab.det_index], lab.bead_id), "a detection got another bead's id"
    eligible = np.intersect1d(unambiguous_ids(ft), ids)
    assert np.isin(eligible, lab.bead_id).mean() >= min_fraction


# --------------------------------------------------------------------------------------------
# shapes, parameters, errors
# --------------------------------------------------------------------------------------------


def test_params_are_validated():
    with pytest.raises(InputError, match="gate_bead_diameters"):
        LabelParams(gate_bead_diameters=0)
    with pytest.raises(InputError, match="seeds"):
        LabelParams(seeds=((1.0, 2.0),))
    with pytest.raises(InputError, match="image_size_px"):
        LabelParams(image_size_px=(1024,))


def test_3d_phantom_needs_geometry(sim):
    c = make_centroids(np.zeros((5, 2)), 20.0)
    with pytest.raises(InputError, match="source_image_distance_mm"):
        label_beads(c, sim.phantom, LabelParams())


def test_unknown_seed_id_raises(sim, params):
    ft = sim.truth.frames[0][0]
    c, _ = detections_from_truth(ft, np.random.default_rng(0))
    with pytest.raises(InputError, match="seeds"):
        label_beads(
            c,
            sim.phantom,
            LabelParams(source_image_distance_mm=1100, pixel_pitch_mm=0.25, seeds=((99999.0, 1.0, 2.0),) * 4),
        )


def test_empty_frame_fails_with_shapes(sim, params):
    lab = label_beads(make_centroids(np.empty((0, 2)), 20.0), sim.phantom, params)
    assert not lab.ok and "usable detections" in lab.reason
    assert lab.xy_px.shape == (0, 2) and lab.sigma_px.shape == (0, 3) and lab.detection_status.shape == (0,)
    assert lab.summary().startswith("labelling failed")
    assert lab.to_table() == (["id", "x", "y", "sigma_x", "sigma_y", "rho"], [])


def test_lattice_ids_round_trip():
    ij = np.array([[0, 0], [-40, 17], [123, -999]])
    assert np.array_equal(lattice_index(lattice_id(ij)), ij)
    # hexagonal neighbours are one pitch apart
    xyz = lattice_xyz_mm(np.array([[0, 0], [1, 0], [0, 1], [-1, 1]]), "hex", 2.5)
    assert np.allclose(np.linalg.norm(xyz[1:] - xyz[0], axis=1), 2.5)


# --------------------------------------------------------------------------------------------
# cube phantom, ground truth
# --------------------------------------------------------------------------------------------


def test_markers_label_simulated_frames(sim, params):
    rng = np.random.default_rng(1)
    for ft in all_frames(sim):
        c, ids = detections_from_truth(ft, rng)
        lab = label_beads(c, sim.phantom, params)
        # >= 97 %: the labeller also leaves out borderline pairs (1.00-1.05 diameters apart) whose predicted
        # outlines, from the nominal phantom and a low-order distortion fit, come out just below one diameter
        check_against_truth(lab, ids, ft, min_fraction=0.97)
        assert lab.pose_source == "markers"
        # the labelling pose is close to the truth (the nominal phantom and the assumed IOP differ from the true ones)
        angle = 2 * np.degrees(np.arccos(min(1.0, abs(float(np.dot(lab.q, ft.q))))))
        assert angle < 1.0
        assert lab.rms_corrected_px < 1.5 < lab.rms_px  # the strong distortion is visible, and absorbed
        status = lab.detection_status
        assert (status == STATUS_LABELLED).sum() == lab.n_labelled == len(lab)
        # merged blobs are elongated: rejected as detections of one bead; every other detection is counted once
        elongated = c.major_px / c.minor_px > params.max_axis_ratio
        assert np.array_equal(status == STATUS_REJECTED, elongated)
        assert lab.n_labelled + lab.n_ambiguous + lab.n_unmatched == len(c) - elongated.sum()


def test_rough_geometry(sim, params):
    """Source-image distance and pixel pitch 8 % and 5 % off (c 12 % off): c is refined while labelling."""
    from dataclasses import replace

    rng = np.random.default_rng(13)
    rough = replace(
        params,
        source_image_distance_mm=0.92 * params.source_image_distance_mm,
        pixel_pitch_mm=1.05 * params.pixel_pitch_mm,
    )
    for ft in (sim.truth.frames[0][2], sim.truth.frames[1][2]):
        c, ids = detections_from_truth(ft, rng)
        lab = label_beads(c, sim.phantom, rough)
        check_against_truth(lab, ids, ft, min_fraction=0.97)
        true_c = sim.truth.systems[ft.system].iop_px[2]
        assert abs(lab.iop[2] / true_c - 1) < 0.05  # from 12 % off to within a few %: depth of the cube is limited


def test_ambiguous_beads_are_left_out(sim, params):
    """No labelled detection has another bead's true outline within 0.9 mean diameters."""
    rng = np.random.default_rng(2)
    ft = sim.truth.frames[1][0]
    c, ids = detections_from_truth(ft, rng, merged_keep=1.0)
    lab = label_beads(c, sim.phantom, params)
    assert lab.ok and lab.n_ambiguous > 0
    assert not np.any(ids[lab.detection_status == STATUS_LABELLED] < 0), "a merged blob was labelled"
    pos = {t: k for k, t in enumerate(ft.ids)}
    tree = cKDTree(ft.outline_xy_px)
    for b in lab.bead_id:
        k = pos[b]
        d, j = tree.query(ft.outline_xy_px[k], k=2)
        assert d[1] >= 0.9 * 0.5 * (ft.diameter_px[k] + ft.diameter_px[j[1]])


def test_two_or_fewer_markers(sim, params):
    """Fewer than three marker detections: neighbouring beads complete the pose; never a wrong label."""
    rng = np.random.default_rng(12)
    markers = sim.phantom.ids[sim.phantom.role == "marker"]
    n_ok = {2: 0, 1: 0, 0: 0}
    for ft in sim.truth.frames[0][:2]:
        c, ids = detections_from_truth(ft, rng)
        found = np.flatnonzero(np.isin(ids, markers))
        for n_left in (2, 1, 0):
            keep = np.ones(len(ids), bool)
            keep[found[n_left:]] = False
            sub = make_centroids(c.xy_px[keep], 2 * c.minor_px[keep], major_px=c.major_px[keep])
            lab = label_beads(sub, sim.phantom, params)
            if lab.ok:
                n_ok[n_left] += 1
                check_against_truth(lab, ids[keep], ft, min_fraction=0.97)
            else:
                assert lab.n_labelled == 0 and lab.reason
    assert n_ok[2] == 2  # two markers are enough on the default cube


@pytest.mark.check  # a hand-built phantom searched in full; make test: test_ambiguous_beads_are_left_out
def test_hand_built_overlapping_pair_is_ambiguous():
    """A small 3D phantom where two beads project onto each other: both are excluded, the rest labelled."""
    rng = np.random.default_rng(3)
    g = np.arange(-2, 3) * 12.0
    front = np.array([[x, y, -30.0] for x in g for y in g])
    back = front[:, :] + [6.0, 6.0, 60.0]
    xyz = np.vstack([front, back])
    diameter = np.full(len(xyz), 3.0)
    role = np.full(len(xyz), "", dtype="<U6")
    marker = [0, 4, 20, 30, 38]
    diameter[marker], role[marker] = 5.0, "marker"
    q = rotvec_to_quat(np.array([0.1, -0.2, 0.05]))
    source = -quat_to_matrix(q).T @ np.array([3.0, -4.0, 700.0])
    # bead 150 (index 50) sits 50 mm behind bead 112 (index 12) on the same ray from the source
    ray = (xyz[12] - source) / np.linalg.norm(xyz[12] - source)
    xyz = np.vstack([xyz, xyz[12] + 50.0 * ray])
    diameter, role = np.append(diameter, 3.0), np.append(role, "")
    phantom = Phantom(np.arange(len(xyz)) + 100, xyz, diameter, role)
    iop = np.array([511.5, 511.5, 4000.0])
    xy = project(xyz, q, source, iop)
    z = (xyz - source) @ quat_to_matrix(q)[2]
    size = iop[2] * diameter / z
    keep = np.ones(len(xyz), bool)
    keep[50] = False  # the pair is one blob in the image, detected at bead 112's place
    c = make_centroids(xy[keep] + rng.normal(scale=0.05, size=(keep.sum(), 2)), size[keep])
    lab = label_beads(
        c,
        phantom,
        LabelParams(source_image_distance_mm=1000, pixel_pitch_mm=0.25, image_size_px=(1024, 1024), min_labelled=6),
    )
    assert lab.ok, lab.reason
    assert 112 not in lab.bead_id and 150 not in lab.bead_id
    assert lab.detection_status[12] == STATUS_AMBIGUOUS
    assert np.array_equal(lab.bead_id, phantom.ids[np.flatnonzero(keep)][lab.det_index])
    assert lab.n_labelled == keep.sum() - 1


def test_seeds_without_markers(sim, params):
    rng = np.random.default_rng(4)
    phantom = without_roles(sim.phantom)
    for ft in sim.truth.frames[0]:
        c, ids = detections_from_truth(ft, rng)
        no_seeds = label_beads(c, phantom, params)
        assert not no_seeds.ok and "marker" in no_seeds.reason and len(no_seeds) == 0
        lab = label_beads(c, phantom, LabelParams(**{**params.__dict__, "seeds": seeds_from_truth(ft, rng)}))
        check_against_truth(lab, ids, ft, min_fraction=0.97)
        assert lab.pose_source == "seeds"


def test_three_seeds(sim, params):
    """Three seeds: the P3P solutions are told apart on all beads."""
    from dataclasses import replace

    rng = np.random.default_rng(14)
    ft = sim.truth.frames[1][2]
    c, ids = detections_from_truth(ft, rng)
    lab = label_beads(
        c, without_roles(sim.phantom), replace(params, seeds=seeds_from_truth(ft, rng, n=3, click_noise_px=0.5))
    )
    check_against_truth(lab, ids, ft, min_fraction=0.97)


def test_prior_pose_near_and_far(sim, params):
    """A prior close to the frame's pose labels it; so does one several rows off, by the shift search."""
    rng = np.random.default_rng(5)
    phantom = without_roles(sim.phantom)
    ft = sim.truth.frames[1][1]
    c, ids = detections_from_truth(ft, rng)
    near = (ft.q, ft.source_mm + [1.0, -1.0, 0.5])
    lab = label_beads(c, phantom, params, prior_pose=near)
    check_against_truth(lab, ids, ft, min_fraction=0.97)
    assert lab.pose_source == "prior"
    # 30 mm along the walls' vertical axis (several rows off), 15 mm across and 20 mm along the beam
    R = quat_to_matrix(ft.q)
    far = (ft.q, ft.source_mm + [0.0, 0.0, 30.0] + R.T @ [15.0, 0.0, 20.0])
    lab = label_beads(c, phantom, params, prior_pose=far)
    check_against_truth(lab, ids, ft, min_fraction=0.97)


def test_prior_pose_on_a_periodic_patch_is_refused(sim, params):
    """Detections of an inner patch of the cube only, without markers: shifts by a row fit as well.

    The patch is a periodic lattice without edges, so the shift search finds rival labellings a period
    apart; the frame must be refused (never labelled one row off).
    """
    rng = np.random.default_rng(15)
    phantom = Phantom(
        sim.phantom.ids, sim.phantom.xyz_mm, np.full(sim.phantom.n_beads, 3.5), np.full(sim.phantom.n_beads, "")
    )
    ft = sim.truth.frames[0][1]
    c, ids = detections_from_truth(ft, rng, n_false=0)
    inner = np.all(np.abs(c.xy_px - np.median(c.xy_px, axis=0)) < 120, axis=1)
    sub = make_centroids(c.xy_px[inner], 2 * c.minor_px[inner], major_px=c.major_px[inner])
    R = quat_to_matrix(ft.q)
    far = (ft.q, ft.source_mm + R.T @ [0.0, 12.0, 0.0])
    lab = label_beads(sub, phantom, replace(params, min_labelled=8), prior_pose=far)
    assert not lab.ok and "equally well" in lab.reason, lab.reason
    assert lab.n_labelled == 0


def test_evidence_of_a_pose_that_sees_no_bead(sim, params):
    """A rival pose with every bead behind the source explains nothing: each detection counts against it, no crash."""
    from fluorocal.stages.label.correction import Correction
    from fluorocal.stages.label.cube_frame import CubeFrame
    from fluorocal.stages.label.rivals import evidence
    from scipy.spatial import cKDTree

    xy = np.array([[10.0, 10.0], [50.0, 40.0], [90.0, 80.0]])
    iop = np.array([50.0, 50.0, 4000.0])
    frame = CubeFrame(
        None, sim.phantom, params, iop, None, np.arange(3), xy, cKDTree(xy), 10.0, sim.phantom.diameter_mm, 100.0, 100.0
    )
    behind = np.array([0.0, 0.0, float(sim.phantom.xyz_mm[:, 2].max()) + 1e3])
    model = {"iop": iop, "corr": Correction(iop[:2], 100.0), "R": np.eye(3), "T": behind}
    assert evidence(frame, model) == -3.0


def test_random_points_fail(sim, params):
    rng = np.random.default_rng(6)
    xy = rng.uniform(100, 900, (400, 2))
    size = np.where(rng.random(400) < 0.02, 30.0, 20.0)
    lab = label_beads(make_centroids(xy, size), sim.phantom, params)
    assert not lab.ok and lab.n_labelled == 0
    assert lab.n_unmatched == 400


def test_sequence_propagates_seeds(sim, params):
    """Frames of a sequence without markers: the first is seeded, the next ones follow from small motions."""
    rng = np.random.default_rng(7)
    phantom = without_roles(sim.phantom)
    ft = sim.truth.frames[0][0]
    c0, ids0 = detections_from_truth(ft, rng)
    # the "next frames": the same view with the detections shifted by 2 and 4 px (small motion)
    shifted = [make_centroids(c0.xy_px + s, 2 * c0.minor_px, major_px=c0.major_px) for s in (2.0, 4.0)]
    labs = label_sequence([c0, *shifted], phantom, params, {0: seeds_from_truth(ft, rng)})
    assert [lab.pose_source for lab in labs] == ["seeds", "prior", "prior"]
    for lab in labs:
        assert lab.ok and np.array_equal(ids0[lab.det_index], lab.bead_id)


# eight 1024 px frames, shift and turn search. make test: the seeded sequences above and test_label_varied's (one
# frame from the seeded one); the turns across frames: test_label_sequence's quarter-turn motion
@pytest.mark.check
def test_sequence_seeded_on_one_frame_follows_turns_and_jumps():
    """The paper's manual seeding: seeds on the first frame only, no markers, a turntable sequence.

    Between exposures the phantom turns by 7.5 or 82 degrees and moves by up to 30 mm in height and
    20 mm sideways (several bead rows): every frame is found from its neighbour by the shift and turn
    search, with no wrong label.
    """
    sim4 = simulate(SimulateParams(n_frames=8, n_systems=1, seed=11), render=False)
    p = sim4.params
    params = LabelParams(
        source_image_distance_mm=p.source_image_distance_mm,
        pixel_pitch_mm=p.pixel_pitch_mm,
        image_size_px=(p.image_size_px, p.image_size_px),
    )
    rng = np.random.default_rng(16)
    fts = sim4.truth.frames[0]
    dets = [detections_from_truth(ft, rng) for ft in fts]
    labs = label_sequence([c for c, _ in dets], without_roles(sim4.phantom), params, {0: seeds_from_truth(fts[0], rng)})
    assert [lab.pose_source for lab in labs] == ["seeds"] + ["prior"] * 7
    for (_, ids), lab, ft in zip(dets, labs, fts):
        check_against_truth(lab, ids, ft, min_fraction=0.97)


def test_rendered_frame_through_detection():
    """One rendered frame through detect and centroid: every label agrees with the nearest true outline."""
    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads

    p = SimulateParams(n_frames=1, seed=5)
    data = simulate(p)
    radiograph, ft = data.frames[0][0], data.truth.frames[0][0]
    c = centroid_beads(radiograph, detect_beads(radiograph, DetectParams()), CentroidParams())
    lab = label_beads(
        c,
        data.phantom,
        LabelParams(
            source_image_distance_mm=p.source_image_distance_mm,
            pixel_pitch_mm=p.pixel_pitch_mm,
            image_size_px=(p.image_size_px,) * 2,
        ),
    )
    assert lab.ok, lab.reason
    d, i = cKDTree(ft.outline_xy_px).query(lab.xy_px)
    # the nearest true outline is unmistakable (a few centroids of crowded beads are 1-2 px off) and is the label
    assert np.all(d < 0.25 * ft.diameter_px[i])
    assert np.array_equal(ft.ids[i], lab.bead_id)
    assert lab.n_labelled >= 0.9 * c.ok.sum()


# --------------------------------------------------------------------------------------------
# grid plates
# --------------------------------------------------------------------------------------------


def test_simulated_grid_has_no_slips():
    """The lattice indices are an exact lattice map of the true hole positions (no slip anywhere)."""
    p = SimulateParams(phantom="grid", n_frames=1, seed=2)
    data = simulate(p, render=False)
    ft = data.truth.frames[0][0]
    rng = np.random.default_rng(8)
    c, ids = detections_from_truth(ft, rng, n_false=0)
    lab = label_beads(c, data.phantom, LabelParams())
    assert lab.ok and lab.n_labelled >= 0.98 * len(c)
    true_xy = data.phantom.xyz_mm[np.searchsorted(data.phantom.ids, ids[lab.det_index]), :2]
    # nominal plate coordinates = similarity of the labelled lattice coordinates (a lattice symmetry + shift)
    A = np.column_stack([lab.object_xyz_mm[:, :2], np.ones(len(lab))])
    coef, *_ = np.linalg.lstsq(A, true_xy, rcond=None)
    assert np.abs(A @ coef - true_xy).max() < 1e-6


def homography_radial_rms(object_xy: np.ndarray, image_xy: np.ndarray, centre_xy: np.ndarray) -> float:
    """RMS (px) of a homography then a two-term radial distortion about ``centre_xy``, fitted by least squares."""
    import cv2
    from scipy.optimize import least_squares

    H, _ = cv2.findHomography(object_xy, image_xy, 0)
    scale = float(np.abs(image_xy - centre_xy).max())

    def model(p):
        h = cv2.perspectiveTransform(object_xy[None], np.append(p[:8], 1.0).reshape(3, 3))[0]
        d = h - centre_xy
        r2 = (d**2).sum(1) / scale**2
        return centre_xy + d * (1 + p[8] * r2 + p[9] * r2**2)[:, None]

    fit = least_squares(
        lambda p: (model(p) - image_xy).ravel(), np.append((H / H[2, 2]).ravel()[:8], [0.0, 0.0]), x_scale="jac"
    )
    return float(np.sqrt(np.mean(np.sum((model(fit.x) - image_xy) ** 2, axis=1))))


@pytest.mark.parametrize("name", ["grid_centered_0", "grid_orbit_30"])
def test_real_grid_frames(arcadis_dir, name):
    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads
    from fluorocal.stages.io import read_frames

    radiograph = read_frames(arcadis_dir / f"{name}.dcm")[0]
    c = centroid_beads(radiograph, detect_beads(radiograph, DetectParams(polarity="bright")), CentroidParams())
    lab = label_beads(c, Phantom([], [], [], [], "hex", 2.0), LabelParams())
    assert lab.ok and c.ok.sum() > 3000
    assert lab.n_labelled >= 0.98 * c.ok.sum()
    assert len(np.unique(lab.bead_id)) == len(lab)
    # a slip would leave residuals of a whole hole spacing (~15 px); distortion beyond radial leaves < 1 px
    rms = homography_radial_rms(lab.object_xyz_mm[:, :2], lab.xy_px, np.array([511.5, 511.5]))
    assert rms < 1.0


def test_a_plate_of_no_known_lattice_is_refused():
    """A lattice spelled wrong is refused, not labelled as a square (the lattice geometry's fallback)."""
    from fluorocal.stages.label import label_plate_frame

    ij = np.array([(i, j) for i in range(-5, 6) for j in range(-5, 6)])
    centroids = make_centroids(511.5 + 13.0 * ij, 6.0)  # a square grid a "square" plate labels
    assert label_plate_frame(centroids, Phantom([], [], [], [], "square", 1.0), LabelParams()).ok
    with pytest.raises(InputError, match="'tri'"):
        label_plate_frame(centroids, Phantom([], [], [], [], "tri", 1.0), LabelParams())


def test_square_grid_with_gaps_and_distortion():
    """A square plate seen through a pincushion with a hole-free patch and a round field: no slip across the gap."""
    rng = np.random.default_rng(9)
    ij = np.array([(i, j) for i in range(-40, 41) for j in range(-40, 41)])
    xy = 511.5 + 13.0 * (ij @ np.array([[np.cos(0.2), np.sin(0.2)], [-np.sin(0.2), np.cos(0.2)]]))
    r2 = np.sum((xy - 511.5) ** 2, axis=1) / 480.0**2
    xy = 511.5 + (xy - 511.5) * (1 + 0.03 * r2)[:, None]  # ~15 px of pincushion at the rim
    keep = (np.linalg.norm(xy - 511.5, axis=1) < 470) & (np.linalg.norm(xy - [650, 400], axis=1) > 25)
    keep &= rng.random(len(xy)) > 0.02
    xy, ij = xy[keep] + rng.normal(scale=0.05, size=(keep.sum(), 2)), ij[keep]
    lab = label_beads(make_centroids(xy, 6.0), Phantom([], [], [], [], "square", 1.0), LabelParams())
    assert lab.ok and lab.n_labelled >= 0.99 * len(xy)
    got = lattice_index(lab.bead_id)
    truth = ij[lab.det_index]
    # the indices differ from the truth by a lattice symmetry and a shift, the same everywhere
    A = np.column_stack([got, np.ones(len(got))])
    coef, *_ = np.linalg.lstsq(A, truth.astype(float), rcond=None)
    assert np.abs(A @ coef - truth).max() < 1e-9


def _label_cli_argv(tmp_path, sim, c, frames, phantom, *, roles: bool) -> list:
    """`fluorocal label` arguments up to its options, on CSVs written to ``tmp_path``.

    ``det.csv`` holds ``c`` as the detections of each ``(file, frame)``, ``phantom.csv`` the ``phantom``
    (with its ``role`` column if ``roles``).
    """
    from fluorocal.stages.io import write_csv

    header = "file,frame,x,y,sigma_x,sigma_y,rho,major,minor,angle,fit_rmse,score".split(",")
    rows = [
        [file, f, *c.xy_px[i], c.sigma_x[i], c.sigma_y[i], c.rho[i], c.major_px[i], c.minor_px[i], 0.0, 0.05, 9.0]
        for file, f in frames
        for i in range(len(c))
    ]
    write_csv(tmp_path / "det.csv", header, rows)
    ph = phantom
    write_csv(
        tmp_path / "phantom.csv",
        ["id", "x", "y", "z", "diameter", *(["role"] if roles else [])],
        [[int(i), *x, d, *([r] if roles else [])] for i, x, d, r in zip(ph.ids, ph.xyz_mm, ph.diameter_mm, ph.role)],
    )
    p = sim.params
    return [
        "-q",
        "label",
        str(tmp_path / "det.csv"),
        "--phantom",
        str(tmp_path / "phantom.csv"),
        "--source-image-distance",
        str(p.source_image_distance_mm),
        "--pixel-pitch",
        str(p.pixel_pitch_mm),
    ]


def test_cli_label(tmp_path, sim):
    """`fluorocal label` on a detections CSV: the labels CSV holds the right ids; a missing file is a one-line error."""
    from fluorocal.cli import main
    from fluorocal.stages.io import write_csv

    rng = np.random.default_rng(10)
    ft = sim.truth.frames[0][1]
    c, ids = detections_from_truth(ft, rng)
    argv = _label_cli_argv(tmp_path, sim, c, [("a.tif", 0)], without_roles(sim.phantom), roles=False)
    write_csv(tmp_path / "seeds.csv", ["id", "x", "y"], [[int(s[0]), s[1], s[2]] for s in seeds_from_truth(ft, rng)])
    argv += ["--seeds", str(tmp_path / "seeds.csv"), "--out", str(tmp_path)]
    assert main(argv) == 0
    import csv

    with open(tmp_path / "labels.csv") as fh:
        out = list(csv.DictReader(fh))
    assert len(out) > 200
    d, i = cKDTree(c.xy_px).query([[float(r["x"]), float(r["y"])] for r in out])
    assert d.max() < 1e-5  # 6 decimals in the CSV
    assert np.array_equal(ids[i], [int(r["id"]) for r in out])
    assert (
        main(
            [
                "-q",
                "label",
                str(tmp_path / "missing.csv"),
                "--lattice",
                "hex",
                "--pitch",
                "2",
                "--out",
                str(tmp_path / "x"),
            ]
        )
        == 2
    )


def test_cli_label_overlay_reads_each_frame_file_once(tmp_path, sim, monkeypatch):
    """`--overlay` draws one PNG per frame of a multi-frame file and decodes the file once, not once per frame."""
    import cv2
    from fluorocal.cli import main

    rng = np.random.default_rng(10)
    ft = sim.truth.frames[0][1]
    c, _ = detections_from_truth(ft, rng)
    size = sim.params.image_size_px
    movie = tmp_path / "movie.avi"
    writer = cv2.VideoWriter(str(movie), cv2.VideoWriter_fourcc(*"MJPG"), 10, (size, size), False)
    for _ in range(2):
        writer.write(np.full((size, size), 128, np.uint8))
    writer.release()
    argv = _label_cli_argv(tmp_path, sim, c, [(str(movie), 0), (str(movie), 1)], sim.phantom, roles=True)
    reads = []
    from fluorocal.stages import io as stages_io

    real = stages_io.read_frames
    monkeypatch.setattr(stages_io, "read_frames", lambda path, *a, **k: reads.append(path) or real(path, *a, **k))
    argv += ["--out", str(tmp_path), "--overlay", str(tmp_path / "png")]
    assert main(argv) == 0
    assert sorted(x.name for x in (tmp_path / "png").iterdir()) == ["movie_000_labels.png", "movie_001_labels.png"]
    assert len(reads) == 1


def test_label_overlay(sim, params):
    from fluorocal.overlay import render_label_overlay
    from fluorocal.stages.artifacts import Radiograph

    rng = np.random.default_rng(15)
    ft = sim.truth.frames[0][0]
    c, _ = detections_from_truth(ft, rng)
    lab = label_beads(c, sim.phantom, params)
    image = render_label_overlay(Radiograph(np.full((1024, 1024), 1000.0, np.float32), 12), c, lab)
    assert image.shape == (1024, 1024, 3) and image.dtype == np.uint8
    x, y = np.round(c.xy_px[lab.det_index[0]]).astype(int)
    patch = image[y - 15 : y + 16, x - 15 : x + 16].astype(int)
    assert np.any(patch[..., 1] - patch[..., 2] > 100)  # a green (labelled) outline around the first label
