"""Sequences fluorocal was not tuned on (issue 12): other marker layouts, a wobbling turntable, large shifts.

The simulator's motion and marker options are checked against their definitions; the labelling against the
simulator's truth (detections made detection-like by ``test_label.detections_from_truth``). The full
figures over many seeds are in ``benchmarks/label_varied.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import quat_to_matrix
from fluorocal.stages.label import LabelParams, label_sequence
from fluorocal.stages.label.motion import OrientationPrior, predict
from fluorocal.stages.simulate import SimulateParams, make_phantom, simulate
from scipy.spatial.transform import Rotation

from tests.stages.test_label import detections_from_truth, seeds_from_truth, unambiguous_ids

#: the motion of issue 12: the turntable's axis wobbling by up to 5 deg, shifts of up to +-20 mm
WOBBLY = dict(turntable_wobble_deg=5.0, turntable_translation_mm=20.0, turntable_step_deg=10.0)


def params_of(sp: SimulateParams) -> LabelParams:
    return LabelParams(
        source_image_distance_mm=sp.source_image_distance_mm,
        pixel_pitch_mm=sp.pixel_pitch_mm,
        image_size_px=(sp.image_size_px, sp.image_size_px),
    )


# --------------------------------------------------------------------------------------------
# the simulator's options
# --------------------------------------------------------------------------------------------


def test_marker_layouts():
    """Fixed slots (the first n of the design's eight) or a seeded random choice of any number of beads."""
    default, _, _ = make_phantom(SimulateParams())
    three, _, _ = make_phantom(SimulateParams(n_markers=3))
    is_marker = default.role == "marker"
    assert is_marker.sum() == 8 and (three.role == "marker").sum() == 3
    # the fixed layout's first three slots are three of the default's markers, with the marker diameter
    assert np.all(is_marker[three.role == "marker"]) and np.all(three.diameter_mm[three.role == "marker"] == 5.0)
    a, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=6, seed=1))
    b, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=6, seed=1))
    c, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=6, seed=2))
    assert (a.role == "marker").sum() == 6 and np.array_equal(a.role, b.role) and not np.array_equal(a.role, c.role)
    assert np.array_equal(a.xyz_mm, default.xyz_mm)  # only the roles and diameters change
    none, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=0))
    assert not (none.role == "marker").any() and np.all(none.diameter_mm == 3.5)
    with pytest.raises(InputError, match="n_markers"):
        SimulateParams(n_markers=9)
    with pytest.raises(InputError, match="n_markers"):
        make_phantom(SimulateParams(marker_layout="random", n_markers=10_000))


def test_turntable_step_and_wobble():
    """Exposures step by the turn asked for; the turntable's axis tilts by up to the wobble, in every direction."""
    k = 40
    acq = simulate(SimulateParams(n_frames=k, **WOBBLY), render=False).truth.acquisition
    steps = np.degrees(np.diff(acq.turntable_angle_rad))
    assert np.allclose(steps, 10.0, atol=1e-9)
    # the phantom's vertical axis in the lab at each exposure
    up = np.array([quat_to_matrix(q) @ [0.0, 0.0, 1.0] for q in acq.lab_from_phantom_q])
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
    assert tilt.max() <= 5.0 + 1e-9
    # uniform up to 5 deg over 40 exposures: the largest is above 4 deg unless p = 0.8^40 ~ 1e-4
    assert tilt.max() > 4.0
    # tilted towards every quadrant (uniform directions: each is missed with p = 0.75^40 ~ 1e-5)
    quadrant = (np.degrees(np.arctan2(up[:, 1], up[:, 0])) // 90).astype(int) % 4
    assert set(quadrant) == {0, 1, 2, 3}
    still = simulate(SimulateParams(n_frames=3, turntable_step_deg=10.0), render=False).truth.acquisition
    assert np.allclose([quat_to_matrix(q)[2, 2] for q in still.lab_from_phantom_q], 1.0, atol=1e-15)


def test_hidden_markers_leave_the_frame_and_its_truth():
    """Frames drawn to hide markers lack 1 to all of them, in the truth and in the rendered image; all else is kept."""
    base = dict(n_frames=4, image_size_px=256, seed=3)
    shown = simulate(SimulateParams(**base))
    hidden = simulate(SimulateParams(**base, hidden_marker_fraction=1.0))
    markers = shown.phantom.ids[shown.phantom.role == "marker"]
    n_hidden = []
    for ft_s, ft_h, img_s, img_h in zip(
        shown.truth.frames[0], hidden.truth.frames[0], shown.frames[0], hidden.frames[0]
    ):
        gone = np.setdiff1d(ft_s.ids, ft_h.ids)
        assert np.all(np.isin(gone, markers)) and set(ft_h.ids) <= set(ft_s.ids)
        # the other beads' truth is unchanged, bit for bit (same geometry, same streams)
        keep = np.isin(ft_s.ids, ft_h.ids)
        assert np.array_equal(
            ft_s.outline_xy_px[keep & ~np.isin(ft_s.ids, gone)], ft_h.outline_xy_px[~np.isin(ft_h.ids, gone)]
        )
        n_hidden.append(len(gone))
        for b in gone:
            x, y = np.rint(ft_s.outline_xy_px[ft_s.ids == b][0]).astype(int)
            if ft_s.overlap[ft_s.ids == b][0]:
                continue
            # a 5 mm steel bead absorbs most of the beam at its centre (~90 % contrast): gone, the pixel is bright
            assert img_h.image[y, x] > 2.0 * img_s.image[y, x]
    # every frame hides at least one marker at fraction 1 (the visible ones; all 8 are in view here)
    assert min(n_hidden) >= 1


# --------------------------------------------------------------------------------------------
# the labelling
# --------------------------------------------------------------------------------------------


def check_sequence(labs, dets, fts, *, min_fraction: float):
    """Every frame labelled, no wrong label, ``min_fraction`` of the clean beads labelled over all frames."""
    eligible = correct = 0
    for lab, (_, ids), ft in zip(labs, dets, fts):
        assert lab.ok, lab.reason
        assert np.array_equal(ids[lab.det_index], lab.bead_id), "a detection got another bead's id"
        clean = np.intersect1d(unambiguous_ids(ft), ids)
        eligible += len(clean)
        correct += int(np.isin(clean, lab.bead_id).sum())
    assert correct >= min_fraction * eligible, (correct, eligible)


def test_three_random_markers_on_a_wobbling_turntable():
    """Three markers at random, wobble +-5 deg, shifts +-20 mm, 10 deg steps, markers hidden in half the frames.

    Frames that show fewer than two markers, or hide them, are labelled from their neighbours.
    """
    # seed 7: frames 1 and 5 label from their markers, the others show none or too few
    sp = SimulateParams(n_frames=8, seed=7, marker_layout="random", n_markers=3, hidden_marker_fraction=0.5, **WOBBLY)
    sim = simulate(sp, render=False)
    rng = np.random.default_rng(7)
    fts = sim.truth.frames[0]
    dets = [detections_from_truth(ft, rng, merged_keep=0.2) for ft in fts]
    labs = label_sequence([c for c, _ in dets], sim.phantom, params_of(sp))
    assert [lab.pose_source for lab in labs].count("prior") == 6
    # 97 %: the labelling leaves out beads within a few % of touching (ambiguous), ~1 % of the clean ones
    check_sequence(labs, dets, fts, min_fraction=0.97)


def test_no_markers_seeds_on_the_first_frame_of_a_wobbling_sequence():
    """A phantom without markers, six seeds on the first frame: every other frame follows from its neighbours."""
    sp = SimulateParams(n_frames=6, seed=5, marker_layout="random", n_markers=0, **WOBBLY)
    sim = simulate(sp, render=False)
    rng = np.random.default_rng(5)
    fts = sim.truth.frames[0]
    dets = [detections_from_truth(ft, rng, merged_keep=0.2) for ft in fts]
    labs = label_sequence([c for c, _ in dets], sim.phantom, params_of(sp), {0: seeds_from_truth(fts[0], rng)})
    assert [lab.pose_source for lab in labs] == ["seeds"] + ["prior"] * 5
    check_sequence(labs, dets, fts, min_fraction=0.97)


def test_a_labelling_one_row_off_gives_way_to_the_truth():
    """A labelling one bead row or column off (a slip of the truth): among its own rivals is the truth, which wins.

    The default cube without markers (no sizes to tell them apart): only the phantom's ends in the image do.
    """
    from fluorocal.stages.label.cube_frame import make_cube_frame
    from fluorocal.stages.label.detections import Detections, assumed_iop
    from fluorocal.stages.label.iterate import acceptable, iterate
    from fluorocal.stages.label.rivals import _slip_poses, settle

    from tests.stages.test_label import without_roles

    # a view 30 deg off a wall's, where a slip explains the detections well enough to be acceptable (at most
    # views the phantom's ends rule slips out at once)
    sp = SimulateParams(n_frames=4, seed=2, turntable_step_deg=10.0)
    sim = simulate(sp, render=False)
    phantom = without_roles(sim.phantom)
    ft = sim.truth.frames[0][0]
    c, ids = detections_from_truth(ft, np.random.default_rng(2))
    params = params_of(sp)
    det = Detections.from_centroids(c)
    frame, det = make_cube_frame(det, phantom, params, assumed_iop(det, c, params, need_c=True))

    def right(result):
        return np.mean(ids[frame.det_idx[result["det"]]] == phantom.ids[result["bead"]])

    truth = iterate(frame, quat_to_matrix(ft.q), ft.source_mm)
    assert right(truth) == 1.0
    slips = [iterate(frame, R, T) for R, T in _slip_poses(frame, truth, truth["R"], truth["T"])]
    slips = [r for r in slips if r is not None and acceptable(frame, r)[0] and right(r) < 0.5]
    assert slips, "the cube's periodic layout gives acceptable labellings a row off"
    for slipped in slips:
        best, why = settle(frame, [slipped])
        assert best is not None and right(best) == 1.0, why


def test_orientation_prior_distance_in_sigmas():
    """A turn about the axis counts in turn sigmas, a tilt across it in tilt sigmas (exact for single rotations)."""
    R0 = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    axis = np.array([0.0, 1.0, 0.0])
    prior = OrientationPrior(R0, axis, np.radians(0.5), np.radians(3.0))
    turn = Rotation.from_rotvec(np.radians(1.0) * axis).as_matrix() @ R0
    tilt = Rotation.from_rotvec(np.radians(6.0) * np.array([1.0, 0.0, 0.0])).as_matrix() @ R0
    assert prior.distance(turn) == pytest.approx(2.0, rel=1e-9)
    assert prior.distance(tilt) == pytest.approx(2.0, rel=1e-9)
    assert prior.distance(R0) == pytest.approx(0.0, abs=1e-9)


def test_prediction_of_a_regular_turntable():
    """Regular 9 deg steps about a fixed axis, wobble up to 2 deg: the turn predicted closely, the tilt within it.

    Between labelled frames (interpolated) and beyond them (the mean step).
    """
    rng = np.random.default_rng(0)
    axis = np.array([0.1, 0.99, 0.05]) / np.linalg.norm([0.1, 0.99, 0.05])
    base = Rotation.from_rotvec([0.3, 0.2, -0.1])
    rotations = {}
    for k in range(12):
        w = np.cross(axis, rng.normal(size=3))
        w *= np.radians(rng.uniform(0, 2.0)) / np.linalg.norm(w)  # a tilt across the axis, up to 2 deg
        rotations[k] = (Rotation.from_rotvec(w) * Rotation.from_rotvec(np.radians(9.0 * k) * axis) * base).as_matrix()
    for i, sides in ((5, "both"), (11, "one")):
        known = {k: R for k, R in rotations.items() if k != i}
        prior, near, motion_known = predict(i, known)
        assert motion_known and near in (i - 1, i + 1)
        assert abs(abs(float(prior.axis @ axis)) - 1) < 1e-3  # the axis, up to its sign
        miss = Rotation.from_matrix(rotations[i] @ prior.R.T).as_rotvec()
        # the turn: second order in the tilts (< 0.1 deg); the tilt: at most the sum of three wobbles
        assert abs(np.degrees(miss @ axis)) < 0.1, sides
        assert np.degrees(np.linalg.norm(miss)) < 6.0, sides
        # the measured spread: the floor about the axis (0.5 deg), a few deg across it
        assert np.degrees(prior.sigma_turn_rad) == pytest.approx(0.5)
        assert 0.3 < np.degrees(prior.sigma_tilt_rad) < 4.0
