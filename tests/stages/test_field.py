"""stages/field.py's fast inversion and interpolation give the numbers of the straightforward ones, to the bit.

``remap_maps`` feeds ``undistort``, whose output other tests compare exactly: the maps must not move by
one float32 unit in the last place. The reference below is the straightforward computation the fast
one replaced (``bilinear`` evaluated twice per Newton step, all points of a block stepped until the
largest step is below the tolerance), kept here verbatim as the ground truth. The field is the
simulator's strong distortion sampled on the learning's grid, on a frame whose maps take two blocks
(the second a partial one) and whose edges send sources beyond the node range (the clamped branch).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from fluorocal.stages import field as field_module
from fluorocal.stages.field import CorrectionField, bilinear, grid_nodes
from fluorocal.stages.simulate import SimulateParams, make_distortion

# two blocks of remap_maps at this width (65536 // 512 = 128 rows, then 72), the second a partial one
W, H = 512, 200


def _reference_bilinear(x_nodes, y_nodes, values, xy, *, gradient=False):
    x = np.clip(xy[:, 0], x_nodes[0], x_nodes[-1])
    y = np.clip(xy[:, 1], y_nodes[0], y_nodes[-1])
    i = np.clip(np.searchsorted(x_nodes, x, side="right") - 1, 0, len(x_nodes) - 2)
    j = np.clip(np.searchsorted(y_nodes, y, side="right") - 1, 0, len(y_nodes) - 2)
    hx = x_nodes[i + 1] - x_nodes[i]
    hy = y_nodes[j + 1] - y_nodes[j]
    tx = ((x - x_nodes[i]) / hx)[:, None]
    ty = ((y - y_nodes[j]) / hy)[:, None]
    v00, v01 = values[j, i], values[j, i + 1]
    v10, v11 = values[j + 1, i], values[j + 1, i + 1]
    top = v00 + tx * (v01 - v00)
    bottom = v10 + tx * (v11 - v10)
    out = top + ty * (bottom - top)
    if not gradient:
        return out
    inside_x = ((xy[:, 0] > x_nodes[0]) & (xy[:, 0] < x_nodes[-1]))[:, None]
    inside_y = ((xy[:, 1] > y_nodes[0]) & (xy[:, 1] < y_nodes[-1]))[:, None]
    d_dx = ((1 - ty) * (v01 - v00) + ty * (v11 - v10)) / hx[:, None] * inside_x
    d_dy = (bottom - top) / hy[:, None] * inside_y
    return out, d_dx, d_dy


def _reference_distort(field, xy_ideal, *, tol_px=1e-9, max_iter=50):
    """Newton's method on all points at once until the largest step is below ``tol_px``; unconverged count."""
    nodes = (field.x_nodes_px, field.y_nodes_px, field.delta_px)
    u = np.asarray(xy_ideal, dtype=np.float64).reshape(-1, 2)
    m = u + _reference_bilinear(*nodes, u)
    for _ in range(max_iter):
        f = m - _reference_bilinear(*nodes, m) - u
        _, ddx, ddy = _reference_bilinear(*nodes, m, gradient=True)
        a, b = 1 - ddx[:, 0], -ddy[:, 0]
        c, d = -ddx[:, 1], 1 - ddy[:, 1]
        det = a * d - b * c
        step = -np.column_stack([d * f[:, 0] - b * f[:, 1], -c * f[:, 0] + a * f[:, 1]]) / det[:, None]
        m = m + step
        if len(m) == 0 or np.max(np.abs(step)) < tol_px:
            return m, 0
    return m, int(np.sum(np.abs(step).max(1) >= tol_px))


def _reference_maps(field):
    map_x = np.empty((field.height_px, field.width_px), np.float32)
    map_y = np.empty_like(map_x)
    rows = 65536 // field.width_px
    for top in range(0, field.height_px, rows):
        yy, xx = np.mgrid[top : min(top + rows, field.height_px), 0 : field.width_px].astype(np.float64)
        src, _ = _reference_distort(field, np.column_stack([xx.ravel(), yy.ravel()]))
        map_x[top : top + rows] = src[:, 0].reshape(xx.shape)
        map_y[top : top + rows] = src[:, 1].reshape(xx.shape)
    return map_x, map_y


@pytest.fixture(scope="module")
def simulated_field():
    """The simulator's strong distortion (about 15 px radial at the corners) on the learning's 16 px grid."""
    distortion = make_distortion(SimulateParams(image_size_px=W, distortion="strong", seed=5), 0)
    xn, yn = grid_nodes(W, H, 16.0)
    nodes = np.stack(np.meshgrid(xn, yn), axis=-1)
    delta = distortion.correction_at(nodes)
    return CorrectionField(xn, yn, delta, np.zeros(delta.shape[:2]), np.ones(delta.shape[:2], bool), W, H)


def _bits(a):
    return np.asarray(a).view(np.uint32 if np.asarray(a).dtype == np.float32 else np.uint64)


def test_maps_equal_the_straightforward_computation_bit_for_bit(simulated_field, monkeypatch):
    moving_counts = []
    step = field_module._NewtonPart.step

    def counting_step(part):
        moving_counts.append((len(part._moving), part.step_px.size))
        return step(part)

    monkeypatch.setattr(field_module._NewtonPart, "step", counting_step)
    map_x, map_y = simulated_field.remap_maps()
    ref_x, ref_y = _reference_maps(simulated_field)
    # the test covers the clamped branch (sources beyond the node range) and points set aside once settled
    assert map_x.min() < -0.5 and map_x.max() > W - 0.5 and map_y.min() < -0.5
    assert any(n_moving < n for n_moving, n in moving_counts)
    np.testing.assert_array_equal(_bits(map_x), _bits(ref_x))
    np.testing.assert_array_equal(_bits(map_y), _bits(ref_y))


@pytest.mark.parametrize("step_points", [1000, 8192, 10**9])
def test_distort_points_equal_the_straightforward_newton_bit_for_bit(simulated_field, monkeypatch, step_points):
    # stricter than the maps: a float64 difference that rounds away in float32 fails here (checked: evaluating
    # m - (Δ + u) instead of (m - Δ) - u, or setting points aside once their step is below the tolerance,
    # passes the maps test on this field and fails this one); the size of the parts stepped at once must not
    # change a bit either
    monkeypatch.setattr(field_module, "_STEP_POINTS", step_points)
    rng = np.random.default_rng(3)
    # inside, on node lines and corners, on the image's edges and beyond them
    xy = np.concatenate(
        [
            rng.uniform(-40, [W + 40, H + 40], (5000, 2)),
            np.stack(np.meshgrid(simulated_field.x_nodes_px, simulated_field.y_nodes_px), axis=-1).reshape(-1, 2),
            [[-0.5, -0.5], [W - 0.5, H - 0.5], [-0.5, 100.0], [200.0, H - 0.5]],
        ]
    )
    got = simulated_field.distort_points(xy)
    want, _ = _reference_distort(simulated_field, xy)
    assert got.shape == want.shape and got.flags.c_contiguous
    np.testing.assert_array_equal(_bits(got), _bits(want))


def test_an_unconverged_inversion_gives_the_same_points_and_warning(simulated_field, caplog):
    xy = np.random.default_rng(4).uniform(0, [W, H], (3000, 2))
    want, n_left = _reference_distort(simulated_field, xy, max_iter=1)
    assert n_left > 0  # one step leaves most points short of 1e-9 px
    with caplog.at_level(logging.WARNING, logger="fluorocal.stages.field"):
        got = field_module._newton(simulated_field._interpolator(), np.ascontiguousarray(xy.T), max_iter=1)
    np.testing.assert_array_equal(_bits(got.T), _bits(want))
    assert f"distort_points: {n_left} of 3000 points not converged" in caplog.text


@pytest.mark.parametrize("channels", [1, 2, 3])
def test_bilinear_equals_the_straightforward_interpolation_bit_for_bit(simulated_field, channels):
    rng = np.random.default_rng(channels)
    xn, yn = simulated_field.x_nodes_px, simulated_field.y_nodes_px
    values = rng.normal(0, 3, (len(yn), len(xn), channels))
    xy = np.concatenate([rng.uniform(-20, [W + 20, H + 20], (2000, 2)), [[xn[0], yn[-1]], [xn[3], yn[2]]]])
    np.testing.assert_array_equal(_bits(bilinear(xn, yn, values, xy)), _bits(_reference_bilinear(xn, yn, values, xy)))
    got = bilinear(xn, yn, values, xy, gradient=True)
    want = _reference_bilinear(xn, yn, values, xy, gradient=True)
    for g, w in zip(got, want, strict=True):
        assert g.shape == w.shape == (len(xy), channels)
        np.testing.assert_array_equal(_bits(g), _bits(w))
