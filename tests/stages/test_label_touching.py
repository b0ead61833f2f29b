"""Beads that touch a neighbour without overlapping it are labelled from their own detection (issue 12).

The labelling judges overlap on its estimates of the beads' centres and apparent diameters, which are off
by ~1-2 %: beads within a few % of touching were left out as ambiguous although the detector sees each
alone. A bead judged overlapping is labelled when its own detection tells it apart
(:func:`fluorocal.stages.label.assign.told_apart`); beads that do overlap, or merge into one blob, stay
out. Ground truth: analytic point sets, and the simulator's geometry made detection-like by
:func:`tests.stages.test_label.detections_from_truth`.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.kinds.labelling import label_beads
from fluorocal.stages.label import LabelParams
from fluorocal.stages.label.assign import ambiguous, told_apart
from fluorocal.stages.simulate import SimulateParams, simulate
from scipy.spatial import cKDTree

from tests.stages.label_truth import detections_from_truth, make_centroids, params_of, unambiguous_ids

# --------------------------------------------------------------------------------------------
# told_apart on hand-built pairs (20 px beads)
# --------------------------------------------------------------------------------------------

DIAM = np.full(2, 20.0)


def test_a_pair_just_short_of_touching_is_told_apart_within_the_slack():
    """Centres 0.99 diameters apart: overlapping for the test of ambiguous, told apart with 2 % slack, not 0.5 %."""
    xy = np.array([[0.0, 0.0], [19.8, 0.0]])
    fits = np.ones(2, bool)
    assert ambiguous(xy, DIAM, 1.0).all()
    assert told_apart(xy, DIAM, 1.0, fits, tol_px=1.0, slack=0.02).all()
    assert not told_apart(xy, DIAM, 1.0, fits, tol_px=1.0, slack=0.005).any()


def test_only_beads_whose_detection_fits_are_told_apart():
    """One bead's detection is off its prediction (``fits`` False): it stays out, its neighbour is told apart."""
    xy = np.array([[0.0, 0.0], [19.8, 0.0]])
    np.testing.assert_array_equal(
        told_apart(xy, DIAM, 1.0, np.array([True, False]), tol_px=1.0, slack=0.02), [True, False]
    )


def test_overlapping_beads_are_not_told_apart():
    """Centres 0.8 diameters apart overlap by far more than any slack up to 10 %; 0.2 diameters: within 3 tol."""
    fits = np.ones(2, bool)
    assert not told_apart(np.array([[0.0, 0.0], [16.0, 0.0]]), DIAM, 1.0, fits, tol_px=1.0, slack=0.1).any()
    # a slack of 0.9 would pass the overlap test: the 3-tolerance exclusion still holds the pair out
    assert not told_apart(np.array([[0.0, 0.0], [4.0, 0.0]]), DIAM, 1.0, fits, tol_px=1.5, slack=0.9).any()


def test_a_bead_with_a_third_overlapping_neighbour_stays_out():
    """Bead 0 is told apart from bead 1 (0.99 diameters) but overlaps bead 2 (0.7): it stays out, bead 1 does not."""
    xy = np.array([[0.0, 0.0], [19.8, 0.0], [-14.0, 0.0]])
    out = told_apart(xy, np.full(3, 20.0), 1.0, np.ones(3, bool), tol_px=1.0, slack=0.02)
    np.testing.assert_array_equal(out, [False, True, False])


# --------------------------------------------------------------------------------------------
# the labelling, against the simulator's truth
# --------------------------------------------------------------------------------------------


def test_touching_beads_are_labelled_and_overlapping_ones_are_not():
    """Default cube, strong distortion, 4 frames: the clean beads within 5 % of touching are labelled, no others wrong.

    The simulated detector sees a bead alone when no other outline centre lies within one mean diameter
    (the clean beads, :func:`unambiguous_ids`), with 4x the centroid noise when one lies within 1.15
    diameters; overlapping beads merge into one blob (all kept here, ``merged_keep=1``) or vanish.
    """
    sp = SimulateParams(n_frames=4, seed=21, distortion="strong")
    sim = simulate(sp, render=False)
    params = params_of(sp)
    rng = np.random.default_rng(21)
    n_touching = n_touching_labelled = n_clean = n_clean_labelled = 0
    for ft in sim.truth.frames[0]:
        c, ids = detections_from_truth(ft, rng, merged_keep=1.0)
        lab = label_beads(c, sim.phantom, params)
        assert lab.ok, lab.reason
        # no wrong label, and no merged blob (true id -1) labelled as a bead
        np.testing.assert_array_equal(ids[lab.det_index], lab.bead_id)
        clean = np.intersect1d(unambiguous_ids(ft), ids)
        # clean beads within 5 % of touching: the separation the labelling estimates is off by ~1.5 % (1 sigma)
        close = np.intersect1d(clean, unambiguous_ids(ft, factor=1.05))
        touching = np.setdiff1d(clean, close)
        n_clean += len(clean)
        n_clean_labelled += int(np.isin(clean, lab.bead_id).sum())
        n_touching += len(touching)
        n_touching_labelled += int(np.isin(touching, lab.bead_id).sum())
    assert n_touching >= 20  # the frames have enough touching beads for the fraction below to mean something
    # judged on its estimates alone, a fifth of the touching beads were left out (65 of 81 labelled); their
    # own detections tell >= 90 % apart (those within ~1 % of touching may still be judged overlapping)
    assert n_touching_labelled >= 0.9 * n_touching, (n_touching_labelled, n_touching)
    # the rest of the clean beads: all but the field edge's few (>= 99.5 %)
    assert n_clean_labelled >= 0.995 * n_clean, (n_clean_labelled, n_clean)


def test_labelled_beads_do_not_overlap_their_neighbours():
    """No labelled bead's true outline centre lies within 0.94 mean diameters of another's (overlap beyond the slack).

    Detections as a detector that splits overlapping beads would give: every visible bead detected at its own
    outline centre, merged or not, so only the labelling's overlap test keeps overlapping beads out. The slack
    is twice the frame's spread of bead sizes (+-3 % uniform here: 1.7 % std), so beads overlapping by
    more than ~3.5 % stay out; 0.94 leaves room for the error of the separation estimate (~1-2 %: the
    projected diameters' ~1 %, the centres' 0.05 px noise). Without the overlap test (the detections'
    fit alone) beads overlapping by half a diameter are labelled.
    """
    sp = SimulateParams(n_frames=2, seed=22)
    sim = simulate(sp, render=False)
    params = params_of(sp)
    rng = np.random.default_rng(22)
    for ft in sim.truth.frames[0]:
        keep = ~ft.field_edge
        xy = ft.outline_xy_px[keep] + rng.normal(scale=0.05, size=(keep.sum(), 2))
        size = ft.diameter_px[keep] * rng.uniform(0.97, 1.03, keep.sum())
        lab = label_beads(make_centroids(xy, size), sim.phantom, params)
        assert lab.ok, lab.reason
        np.testing.assert_array_equal(ft.ids[keep][lab.det_index], lab.bead_id)
        tree = cKDTree(ft.outline_xy_px)
        pos = {b: k for k, b in enumerate(ft.ids)}
        k = np.array([pos[b] for b in lab.bead_id])
        d, j = tree.query(ft.outline_xy_px[k], k=2)
        mean_d = 0.5 * (ft.diameter_px[k] + ft.diameter_px[j[:, 1]])
        assert np.all(d[:, 1] >= 0.94 * mean_d), np.min(d[:, 1] / mean_d)


# --------------------------------------------------------------------------------------------
# pairs that nearly touch, and merge: a face-on view
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def face_on():
    """A rendered 512 px frame of the cube seen face-on (turntable at 0 deg): its data, truth and centroids."""
    from fluorocal.stages.centroid import CentroidParams, centroid_beads
    from fluorocal.stages.detect import DetectParams, detect_beads

    p = SimulateParams(n_frames=3, image_size_px=512, seed=3, turntable_step_deg=15.0)
    data = simulate(p)
    radiograph = data.frames[0][0]
    c = centroid_beads(radiograph, detect_beads(radiograph, DetectParams()), CentroidParams())
    size = (p.image_size_px,) * 2
    params = LabelParams(
        source_image_distance_mm=p.source_image_distance_mm, pixel_pitch_mm=p.pixel_pitch_mm, image_size_px=size
    )
    return data, data.truth.frames[0][0], c, params


def test_a_face_on_view_labelled_from_its_markers_explains_most_of_the_frame(face_on):
    """The face-on frame's marker labelling stands as it is: right, and it explains most of the frame.

    The near and far walls' beads pair up there, 1.02-1.25 diameters apart, and the detector sees each pair
    as one blob or none: the right labelling leaves 35 beads undetected that are clear of the ambiguity gate.
    They are not held against it (:func:`fluorocal.stages.label.rivals.explains_most`), so the frame is not
    searched around its markers' pose (which took 7-8 s a frame and found the same labels).
    """
    data, ft, c, params = face_on
    lab = label_beads(c, data.phantom, params)
    assert lab.ok and lab.pose_source == "markers" and lab.explains_most, lab.summary()
    # each label is its nearest true outline's, within the final gate (a quarter of a diameter)
    d, i = cKDTree(ft.outline_xy_px).query(lab.xy_px)
    assert np.all(d < 0.25 * ft.diameter_px[i]) and np.array_equal(ft.ids[i], lab.bead_id)
    # every detection of a bead clear of its neighbours is labelled (measured 239 of the 244 usable detections)
    eligible = np.intersect1d(unambiguous_ids(ft), ft.ids[cKDTree(ft.outline_xy_px).query(c.xy_px[c.ok])[1]])
    assert np.isin(eligible, lab.bead_id).mean() >= 0.99


@pytest.mark.parametrize(("axis", "turn_deg", "depth"), [(1, -6.0, 1.0), (0, 3.0, 1.1)])
def test_a_wrong_labelling_of_the_face_on_view_does_not_explain_most_of_it(face_on, axis, turn_deg, depth):
    """Started a few degrees off (and 10 % too far), a labelling converges wrong yet acceptable: it explains too little.

    Its shortfall is 212-214 detections (measured), of which 73-80 missing beads nearly touch another; at most
    10 % of the detections' worth of those are forgiven, which leaves it far outside the 10 % bound.
    """
    from fluorocal.stages.geometry import quat_to_matrix
    from fluorocal.stages.label.cube_frame import make_cube_frame
    from fluorocal.stages.label.detections import Detections, assumed_iop
    from fluorocal.stages.label.iterate import acceptable, iterate
    from fluorocal.stages.label.rivals import explains_most
    from scipy.spatial.transform import Rotation

    data, ft, c, params = face_on
    det = Detections.from_centroids(c)
    frame, _ = make_cube_frame(det, data.phantom, params, assumed_iop(det, c, params, need_c=True))
    R0, centre = quat_to_matrix(ft.q), data.phantom.xyz_mm.mean(0)
    R = Rotation.from_rotvec(np.radians(turn_deg) * np.eye(3)[axis]).as_matrix() @ R0
    # the phantom's centre where the camera sees it, its depth scaled
    seen = R0 @ (centre - ft.source_mm) * [1.0, 1.0, depth]
    model = iterate(frame, R, centre - R.T @ seen)
    assert model is not None and acceptable(frame, model)[0]
    true_id = dict(zip(ft.ids.tolist(), ft.outline_xy_px))
    right = np.linalg.norm(
        frame.det_xy[model["det"]]
        - np.array([true_id.get(i, (np.inf, np.inf)) for i in data.phantom.ids[model["bead"]].tolist()]),
        axis=1,
    )
    assert np.mean(right < 0.25 * ft.diameter_px.mean()) < 0.9  # wrong: most labels another bead's
    assert not explains_most(frame, model)
