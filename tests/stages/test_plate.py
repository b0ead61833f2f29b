"""Grid-plate self-calibration (stages/plate) against the truth of a synthetic plate (tests/stages/plate_synthetic.py).

The synthetic plate: a hex lattice (pitch 3.6 mm, 4 px/mm), manufacturing errors of 0.02 mm RMS (2-D),
frames with the plate turned and shifted, an analytic distortion of a few px, 0.02 px centroid noise.
At that noise one hole seen in six frames is located to about 0.02 / 4 / sqrt(6) = 0.002 mm per
component: the bounds below leave room for what the field's smoothness prior takes of it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fluorocal.stages.errors import EstimationError
from fluorocal.stages.plate import PlateParams
from fluorocal.stages.plate.homography import Normaliser, homography_modes
from fluorocal.stages.plate.solve import solve_plate

from tests.stages.plate_synthetic import FOV_RADIUS, PITCH_MM, SIZE, make_plate, true_field
from tests.stages.plate_truth import field_error_px, layout_error_mm

FOV = {"centre_xy_px": [(SIZE - 1) / 2] * 2, "radius_px": FOV_RADIUS}


def _one_orientation(problem):
    return replace(problem, orientation_of_frame=np.zeros(problem.n_frames, np.int64))


@pytest.fixture(scope="module")
def moved_plate():
    """Six frames of one orientation, the plate turned by up to 30 deg and shifted by up to 10 mm between them."""
    problem, _, error = make_plate(0, 6, turn_deg=30, shift_mm=10, plate_error_mm=0.02, noise_px=0.02)
    problem = _one_orientation(problem)
    return problem, error, solve_plate(problem, PlateParams().settings(PITCH_MM, True))


def test_plate_layout_recovered_from_six_frames(moved_plate):
    problem, error, sol = moved_plate
    est = sol.plate_estimated
    nominal = problem.nominal_mm
    truth = nominal + error
    # the target: within 0.005 mm RMS of the truth (the nominal lattice is 0.014 mm off); measured 0.0028 mm
    assert layout_error_mm((nominal + sol.plate_error_mm)[est], truth[est]) < 0.005
    assert layout_error_mm(nominal[est], truth[est]) > 0.012
    assert sol.converged


def test_field_recovered_modulo_homography(moved_plate):
    _, _, sol = moved_plate
    # the target: within 0.05 px of the truth modulo a homography (distortion up to ~4 px here); measured
    # 0.0074 px
    assert field_error_px(sol.fields[0], true_field(), FOV) < 0.05


def test_datum_no_homography_in_plate_errors_or_fields(moved_plate):
    problem, _, sol = moved_plate
    est = sol.plate_estimated
    modes = homography_modes(Normaliser.of(problem.nominal_mm[est]).forward(problem.nominal_mm[est])).reshape(-1, 8)
    coef = np.linalg.lstsq(modes, sol.plate_error_mm[est].ravel(), rcond=None)[0]
    # least-squares homography component of the errors: zero up to rounding (removed exactly each iteration)
    assert np.abs(modes @ coef).max() < 1e-9
    # the field's: a homography of the ideal image (what the frames' homographies absorb), modes at m - Δ(m)
    delta = sol.fields[0].correction_at(problem.xy_px)
    ideal = problem.xy_px - delta
    fmodes = homography_modes(Normaliser.of(ideal).forward(ideal)).reshape(-1, 8)
    fcoef = np.linalg.lstsq(fmodes, delta.ravel(), rcond=None)[0]
    assert np.abs(fmodes @ fcoef).max() < 4e-8  # measured 2.0e-8 px


def test_one_frame_takes_the_plate_as_nominal():
    problem, _, _ = make_plate(1, 1, turn_deg=0, shift_mm=0, plate_error_mm=0.02, noise_px=0.02)
    sol = solve_plate(problem, PlateParams().settings(PITCH_MM, True))
    assert not sol.plate_estimated.any()
    assert np.all(sol.plate_error_mm == 0)
    # the field still takes the distortion: what is left is the plate's errors (0.014 mm = 0.057 px per
    # component) and the noise, which one frame cannot tell apart from a distortion; measured 0.011 px
    assert field_error_px(sol.fields[0], true_field(), FOV) < 0.02


def test_each_orientation_gets_its_own_field():
    angles = np.radians([0, 20, 40, 60])
    problem, _, _ = make_plate(2, 4, turn_deg=1, shift_mm=1.5, plate_error_mm=0.02, noise_px=0.02, angles=angles)
    sol = solve_plate(problem, PlateParams().settings(PITCH_MM, True))
    for o, angle in enumerate(angles):
        # each within 0.05 px of its own truth (the target; measured 0.020-0.022 px); the orientations differ
        # by up to 1.3 px at the rim
        assert field_error_px(sol.fields[o], true_field(angle), FOV) < 0.05
    assert field_error_px(sol.fields[0], true_field(angles[-1]), FOV) > 0.1


def test_scheme_none_fits_homographies_only():
    problem, _, _ = make_plate(3, 2, turn_deg=5, shift_mm=2, plate_error_mm=0.02, noise_px=0.02)
    sol = solve_plate(problem, PlateParams().settings(PITCH_MM, True, learn_fields=False))
    assert all(np.all(f.delta_px == 0) for f in sol.fields)
    assert not sol.plate_estimated.any()
    # what a homography leaves of the synthetic distortion (~4 px at the rim): well above the 0.02 px noise
    assert np.sqrt(np.mean(sol.residual_px**2)) > 0.3


def test_still_plate_errors_are_not_estimated():
    """Frames of a plate that never moved cannot tell its errors from the distortion: taken as nominal."""
    problem, _, _ = make_plate(8, 3, turn_deg=0, shift_mm=0, plate_error_mm=0.02, noise_px=0.02)
    sol = solve_plate(_one_orientation(problem), PlateParams().settings(PITCH_MM, True))
    assert not sol.plate_estimated.any()
    assert np.all(sol.plate_error_mm == 0)


def test_unsorted_observations_are_refused():
    from fluorocal.stages.errors import InputError

    problem, _, _ = make_plate(9, 2, turn_deg=5, shift_mm=2, plate_error_mm=0.02, noise_px=0.02)
    with pytest.raises(InputError, match="sorted by frame"):
        replace(problem, frame=problem.frame[::-1].copy())


def test_frame_with_too_few_holes_is_a_clear_error():
    problem, _, _ = make_plate(4, 2, turn_deg=5, shift_mm=2, plate_error_mm=0.02, noise_px=0.02)
    keep = (problem.frame == 0) | (np.arange(len(problem.frame)) < np.flatnonzero(problem.frame == 1)[0] + 4)
    with pytest.raises(EstimationError, match=">= 5 observations"):
        solve_plate(problem.subset(keep), PlateParams().settings(PITCH_MM, True))


def test_params_refuse_bad_values():
    from fluorocal.stages.errors import InputError

    with pytest.raises(InputError, match="smoothness_orders"):
        PlateParams(smoothness_orders=(7,))
    with pytest.raises(InputError, match="plate_sigma_pitch must lie in"):
        PlateParams(plate_sigma_pitch=0.0)
    with pytest.raises(InputError, match="spacing_px must lie in"):
        PlateParams(spacing_px=float("inf"))
    with pytest.raises(InputError, match="tau_grid_px"):
        PlateParams(tau_grid_px=(float("inf"),))


def test_simulated_plate_turned_between_orientations_is_recovered():
    """The simulator's six-orientation acquisition (benchmarks/plate.py), its truth centroids, the plate turned freely.

    With the plate riding on the intensifier (1-4 px of motion) the plate's smooth errors stay in the fields
    (benchmarks/plate_motion.py); turned between the orientations, its errors land elsewhere in the image at
    each one and the issue's target is met.
    """
    from fluorocal.stages.simulate import SimulateParams, simulate

    from tests.stages.plate_truth import truth_problem

    params = SimulateParams(
        phantom="grid",
        n_frames=1,
        seed=3,
        orientations_deg=((0, 0), (0, 15), (0, 30), (0, 45), (0, 60), (30, 0)),
        plate_play_deg=180.0,
    )
    problem, true = truth_problem(simulate(params, render=False), 0.03, np.random.default_rng(0))
    sol = solve_plate(problem, PlateParams().settings(params.grid_pitch_mm, True))
    est = sol.plate_estimated
    nominal = problem.nominal_mm
    # the target, 0.005 mm (measured 0.0045 mm); the noise alone (0.03 px at ~4.3 px/mm, six frames) leaves
    # ~0.003 mm a hole
    assert layout_error_mm((nominal + sol.plate_error_mm)[est], true[est]) < 0.005
    assert layout_error_mm(nominal[est], true[est]) > 0.012  # the simulator's plate errors: 0.014 mm
    assert est.mean() > 0.95
