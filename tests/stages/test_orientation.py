"""Fields per C-arm orientation: interpolation against analytic fields, refusal to extrapolate, field changes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.orientation import (
    ANGLE_TOL_DEG,
    OrientationField,
    field_change,
    interpolate_field,
    reference_orientation,
)

W, H = 256, 192
GRID = CorrectionField.constant(W, H, spacing_px=32.0)
SHAPE = GRID.delta_px.shape  # (H_g, W_g, 2)


def _coefficients(seed: int, n: int) -> list[np.ndarray]:
    """``n`` per-node coefficient arrays, each within ±0.5 px (the size of the real change over 30°)."""
    rng = np.random.default_rng(seed)
    return [rng.uniform(-0.5, 0.5, SHAPE) for _ in range(n)]


def _field(delta: np.ndarray) -> CorrectionField:
    return GRID.with_delta(delta)


def _truth_1d(theta_deg: float, a, b, c) -> np.ndarray:
    """Node values a + b sin θ + c cos θ: smooth in θ as the intensifier's change with orientation is."""
    t = math.radians(theta_deg)
    return a + b * math.sin(t) + c * math.cos(t)


def _calibrated(points, truth) -> list[OrientationField]:
    return [
        OrientationField(f"o{i}", orbit, tilt, _field(truth(orbit, tilt))) for i, (orbit, tilt) in enumerate(points)
    ]


# --- along a line: the Lagrange polynomial through 2, 3 or 4 orientations ----------------------


@pytest.mark.parametrize("calibrated_deg", [(0, 60), (0, 30, 60), (0, 20, 40, 60)])
@pytest.mark.parametrize("axis", ["orbit", "tilt", "diagonal"])
def test_interpolation_along_a_line_is_within_the_lagrange_bound(calibrated_deg, axis):
    """Held-out angles get the truth within the interpolation remainder, and calibrated ones get their own field.

    Through n orientations the not-a-knot spline is the degree n-1 polynomial (a line, the parabola, the
    cubic), so the error at θ is at most max|f^(n)| / n! · |Π(θ - θ_i)| with θ in radians (the Lagrange
    remainder); for f = a + b sin θ + c cos θ every derivative is at most sqrt(b² + c²), per node. A
    reparametrisation along the line (tilt, or the diagonal orbit = tilt) is affine and leaves the polynomial
    unchanged, so the same bound holds in the line's own angle θ.
    """
    a, b, c = _coefficients(1, 3)

    def place(theta):
        return {"orbit": (theta, 0.0), "tilt": (0.0, theta), "diagonal": (theta, theta)}[axis]

    def truth(orbit, tilt):
        return _truth_1d(orbit if axis != "tilt" else tilt, a, b, c)

    cal = _calibrated([place(t) for t in calibrated_deg], truth)
    amplitude = np.hypot(b, c)
    n = len(calibrated_deg)
    for held_out in (5.0, 15.0, 27.5, 45.0, 59.0):
        got = interpolate_field(cal, *place(held_out)).delta_px
        remainder = abs(np.prod([math.radians(held_out - t) for t in calibrated_deg])) / math.factorial(n)
        error = np.abs(got - truth(*place(held_out)))
        assert np.all(error <= amplitude * remainder + 1e-12), (held_out, error.max(), (amplitude * remainder).max())
    for o in cal:  # exact at the calibrated orientations: their own fields
        assert interpolate_field(cal, o.orbit_deg, o.tilt_deg) is o.field


def test_three_orientations_30_degrees_apart_beat_the_nearest_one():
    """The issue's case: calibrated at 0, 30, 60°, a held-out 15° (and 45°) orientation.

    The parabola leaves at most the Lagrange remainder, amplitude · |15 · 15 · 45| deg³ (in rad³) / 3!
    = 0.0063 px for amplitudes up to sqrt(0.5² + 0.5²) px, far below the issue's 0.10 px target for a
    held-out orientation; transfer from the nearest calibrated field leaves the whole change over 15°.
    """
    a, b, c = _coefficients(2, 3)
    cal = _calibrated([(0, 0), (30, 0), (60, 0)], lambda orbit, tilt: _truth_1d(orbit, a, b, c))
    bound = math.hypot(0.5, 0.5) * math.radians(15) * math.radians(15) * math.radians(45) / 6
    for held_out, nearest in ((15.0, 0), (45.0, 2)):
        truth = _truth_1d(held_out, a, b, c)
        interpolated = np.abs(interpolate_field(cal, held_out, 0.0).delta_px - truth).max()
        transferred = np.abs(cal[nearest].field.delta_px - truth).max()
        assert interpolated <= bound and transferred > 10 * interpolated, (interpolated, transferred)


def test_interpolated_field_keeps_grid_and_is_conservative_about_support_and_sigma():
    a, b, c = _coefficients(3, 3)
    support = np.ones(SHAPE[:2], bool)
    support[0, 0] = False
    everywhere = np.ones(SHAPE[:2], bool)
    fields = [
        GRID.with_delta(
            _truth_1d(t, a, b, c), sigma_px=np.full(SHAPE[:2], s), support=support if t == 30 else everywhere
        )
        for t, s in ((0, 0.01), (30, 0.03), (60, 0.02))
    ]
    cal = [OrientationField(f"o{t}", t, 0, f) for t, f in zip((0, 30, 60), fields)]
    out = interpolate_field(cal, 20.0, 0.0)
    assert np.array_equal(out.x_nodes_px, GRID.x_nodes_px) and np.array_equal(out.y_nodes_px, GRID.y_nodes_px)
    assert not out.support[0, 0] and out.support.sum() == support.sum()  # supported where every field is
    assert np.all(out.sigma_px == 0.03)  # the largest calibrated uncertainty


# --- in 2-D: a thin-plate spline inside the convex hull --------------------------------------------


def test_interpolation_in_two_dimensions_is_within_the_linear_bound():
    """Orientations on a 3 x 3 grid 30° apart in orbit and tilt; held-out angles inside it.

    The truth a + b sin(orbit) + c cos(tilt) + d sin(orbit) sin(tilt) has second derivatives along any
    direction of at most M = |b| + |c| + 2|d| per node (radians). Linear interpolation on the grid's right
    triangles (legs h = 30°) errs by at most M h² / 4 (half M times the squared circumradius h/√2); the
    thin-plate spline, which also reproduces linear functions exactly but bends smoothly, must do no worse.
    """
    a, b, c, d = _coefficients(4, 4)

    def truth(orbit, tilt):
        o, t = math.radians(orbit), math.radians(tilt)
        return a + b * math.sin(o) + c * math.cos(t) + d * math.sin(o) * math.sin(t)

    grid = [(o, t) for o in (-30, 0, 30) for t in (-30, 0, 30)]
    cal = _calibrated(grid, truth)
    bound = (np.abs(b) + np.abs(c) + 2 * np.abs(d)) * math.radians(30) ** 2 / 4
    for held_out in ((15, 15), (-15, 10), (0, 15), (25, -20), (-29, 29)):
        error = np.abs(interpolate_field(cal, *held_out).delta_px - truth(*held_out))
        assert np.all(error <= bound), (held_out, error.max())
    for o in cal:
        assert interpolate_field(cal, o.orbit_deg, o.tilt_deg) is o.field


def test_two_dimensional_interpolation_is_smooth_between_calibrated_orientations():
    """No jump across the triangles of the hull: a 0.01° step changes the field by far less than 0.01 px.

    Along any path the truth changes by at most ~1.5 px per radian here; 0.01° is 1.7e-4 rad.
    """
    a, b, c, d = _coefficients(5, 4)
    cal = _calibrated(
        [(0, 0), (30, 0), (0, 30), (30, 30), (15, 40)],
        lambda o, t: a + b * math.sin(math.radians(o)) + c * math.cos(math.radians(t)) + d,
    )
    steps = [interpolate_field(cal, 15.0 + e, 15.0 - e).delta_px for e in (-0.01, 0.0, 0.01)]
    assert np.abs(steps[1] - steps[0]).max() < 1e-3 and np.abs(steps[2] - steps[1]).max() < 1e-3


# --- refusals ----------------------------------------------------------------------------------


def _line():
    return _calibrated([(0, 0), (30, 0), (60, 0)], lambda o, t: np.full(SHAPE, o / 60.0))


@pytest.mark.parametrize(
    "orbit, tilt, match",
    [
        (75.0, 0.0, r"orbit 75°, tilt 0°\) lies beyond the calibrated orientations \(orbit 0..60°, tilt 0°: o0"),
        (-10.0, 0.0, r"does not extrapolate"),
        (30.0, 5.0, r"tilt 5°\) lies beyond"),  # off the line of the calibrated orientations
    ],
)
def test_refuses_to_extrapolate_along_a_line(orbit, tilt, match):
    with pytest.raises(InputError, match=match) as info:
        interpolate_field(_line(), orbit, tilt, what="system 'A'")
    assert str(info.value).startswith("system 'A': ") and "\n" not in str(info.value)


def test_refuses_to_extrapolate_outside_the_hull_and_accepts_its_edge():
    cal = _calibrated([(0, 0), (30, 0), (0, 30)], lambda o, t: np.full(SHAPE, o + t))
    with pytest.raises(InputError, match=r"orbit 0..30°, tilt 0..30°: o0 \(orbit 0°, tilt 0°\)"):
        interpolate_field(cal, 20.0, 20.0)  # beyond the hypotenuse orbit + tilt = 30
    edge = interpolate_field(cal, 15.0, 15.0).delta_px  # on the hypotenuse: inside
    # the truth is linear (o + t) and the thin-plate spline reproduces linear functions exactly
    np.testing.assert_allclose(edge, 30.0, atol=1e-9)


def test_within_the_read_out_tolerance_is_interpolation_not_refusal():
    """A requested angle 0.03° beyond the last calibrated one (a C-arm reads out to 0.1°) gets that field."""
    cal = _line()
    got = interpolate_field(cal, 60.0 + 0.6 * ANGLE_TOL_DEG, 0.0).delta_px
    np.testing.assert_allclose(got, cal[2].field.delta_px, atol=1e-12)  # clamped onto the segment's end


def test_one_orientation_with_angles_cannot_be_interpolated():
    cal = _calibrated([(0, 0)], lambda o, t: np.zeros(SHAPE))
    cal.append(OrientationField("named", None, None, GRID))
    assert interpolate_field(cal, 0.0, 0.0) is cal[0].field
    with pytest.raises(InputError, match=r"lies beyond the calibrated orientations \(orbit 0°, tilt 0°: o0"):
        interpolate_field(cal, 10.0, 0.0)


def test_orientations_without_angles_duplicated_angles_and_other_grids_are_refused():
    named = [OrientationField("left", None, None, GRID), OrientationField("right", None, None, GRID)]
    with pytest.raises(InputError, match=r"no calibrated orientation has C-arm angles.*\(left, right\)"):
        interpolate_field(named, 0.0, 0.0)
    twins = [
        OrientationField("a", 0, 0, GRID),
        OrientationField("b", 0, 0.01, GRID),
        OrientationField("c", 30, 0, GRID),
    ]
    with pytest.raises(InputError, match=r"orientations 'a' and 'b' are both at orbit 0°"):
        interpolate_field(twins, 10.0, 0.0)
    other = CorrectionField.constant(W, H, spacing_px=16.0)
    with pytest.raises(InputError, match="different grids"):
        interpolate_field([OrientationField("a", 0, 0, GRID), OrientationField("b", 30, 0, other)], 10.0, 0.0)
    with pytest.raises(InputError, match=r"orbit must be a finite angle"):
        interpolate_field(_line(), float("nan"), 0.0)


@pytest.mark.parametrize(
    "orbit, tilt, match",
    [
        (10, None, "both orbit_deg and tilt_deg"),
        (200, 0, "-180..180"),
        (float("inf"), 0, "finite"),
        (True, 0, "got True"),
    ],
)
def test_orientation_field_checks_its_angles(orbit, tilt, match):
    with pytest.raises(InputError, match=match):
        OrientationField("x", orbit, tilt, GRID)


# --- how a field changes ---------------------------------------------------------------------------


def test_field_change_of_a_homography_is_zero_modulo_h():
    """A change that a homography explains (a small rotation, scale and perspective of the ideal image)."""
    nodes = GRID.nodes_px.reshape(SHAPE)
    a = _coefficients(6, 1)[0]
    ideal_ref = nodes - a
    h = np.array([[1.001, 0.002, 0.4], [-0.0015, 0.999, -0.3], [2e-6, -1e-6, 1.0]])
    p = np.concatenate([ideal_ref, np.ones(SHAPE[:2] + (1,))], axis=-1) @ h.T
    ideal = p[..., :2] / p[..., 2:]
    change = field_change(_field(a), _field(nodes - ideal))
    diff = (nodes - ideal) - a
    assert change.rms_px == pytest.approx(np.sqrt(np.mean(diff**2)), rel=1e-12)
    assert change.max_px == pytest.approx(np.linalg.norm(diff, axis=-1).max(), rel=1e-12)
    # exact data: what remains is the fit's own precision (OpenCV's refinement stops near 1e-5 px)
    assert change.max_px > 0.3 and change.max_mod_h_px < 1e-4


def test_field_change_keeps_what_no_homography_follows():
    """Node-to-node alternation of ±0.1 px: a homography (8 parameters) absorbs almost none of 63 nodes' pattern."""
    pattern = np.zeros(SHAPE)
    pattern[..., 0] = 0.1 * (-1.0) ** np.add.outer(np.arange(SHAPE[0]), np.arange(SHAPE[1]))
    change = field_change(GRID, _field(pattern))
    assert change.rms_px == pytest.approx(0.1 / math.sqrt(2), rel=1e-12)  # per coordinate: x only
    assert change.rms_mod_h_px == pytest.approx(change.rms_px, rel=0.05)
    support = np.ones(SHAPE[:2], bool)
    support[1, 1] = False
    part = field_change(GRID.with_delta(GRID.delta_px, support=support), _field(pattern))
    assert np.isnan(part.difference_mod_h_px[1, 1]).all() and part.support.sum() == support.sum()


def test_reference_orientation_is_the_one_nearest_zero():
    fields = [OrientationField(n, o, t, GRID) for n, o, t in (("a", 30, 0), ("b", 0, 10), ("c", -5, 0))]
    assert reference_orientation(fields) == 2
    assert reference_orientation([OrientationField("x", None, None, GRID)] * 2) == 0
