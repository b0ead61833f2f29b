"""Tests of stages/learn/nodes.py: the grid's support rule.

Ground truth: the count of points within the radius of each node by brute force (every point against every node,
the squared distance against the squared radius), on point sets with points exactly at the radius and a rounding
away from it.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.learn.nodes import GridSpec, node_coordinates


def _brute_force_support(spec: GridSpec, xy: np.ndarray, xn: np.ndarray, yn: np.ndarray) -> np.ndarray:
    nodes = node_coordinates(xn, yn)
    d2 = np.sum((xy[None, :, :] - nodes[:, None, :]) ** 2, axis=2)
    return np.sum(d2 <= spec.support_radius_px**2, axis=1) >= spec.min_support


@pytest.mark.parametrize("seed", range(6))
def test_support_mask_counts_the_points_within_the_radius(seed):
    # random grids, radii and thresholds; points scattered past the image's edges, and half of them on a node's
    # row at exactly the radius from it (or one rounding nearer or farther), where the count is decided
    rng = np.random.default_rng(seed)
    spec = GridSpec(
        spacing_px=float(rng.choice([8.0, 16.0, 20.0])),
        support_radius_px=float(rng.choice([10.0, 32.0, 33.3])),
        min_support=int(rng.integers(1, 5)),
    )
    size = (int(rng.integers(40, 300)), int(rng.integers(40, 300)))
    xn, yn = spec.nodes(size)
    xy = rng.uniform(-40.0, max(size) + 40.0, (600, 2))
    on_edge = xy[:300]
    on_edge[:, 0] = rng.choice(xn, 300) + spec.support_radius_px * rng.choice([-1.0, 1.0], 300)
    on_edge[:, 1] = rng.choice(yn, 300)
    on_edge[100:200, 0] = np.nextafter(on_edge[100:200, 0], rng.choice([-np.inf, np.inf], 100))
    np.testing.assert_array_equal(spec.support_mask(xy, xn, yn), _brute_force_support(spec, xy, xn, yn))


def test_support_mask_of_few_or_no_points():
    spec = GridSpec(spacing_px=16.0, support_radius_px=32.0, min_support=1)
    xn, yn = spec.nodes((64, 48))
    assert not spec.support_mask(np.zeros((0, 2)), xn, yn).any()
    one = np.array([[10.0, 10.0]])
    np.testing.assert_array_equal(spec.support_mask(one, xn, yn), _brute_force_support(spec, one, xn, yn))
    # one point a rounding past the radius of a node along its row (-16.000000000000002 px off, whose square rounds to
    # the radius's: within it), of the two-by-two grid of a one-pixel image
    spec = GridSpec(spacing_px=1.0, support_radius_px=16.0, min_support=1)
    at_radius = np.array([[np.nextafter(-15.5, -np.inf), -0.5]])
    xn, yn = spec.nodes((1, 1))
    expected = _brute_force_support(spec, at_radius, xn, yn)
    np.testing.assert_array_equal(spec.support_mask(at_radius, xn, yn), expected)
    assert expected.tolist() == [True, True, True, False]


@pytest.mark.parametrize("seed", range(8))
def test_support_mask_counts_points_clear_of_the_radius(seed):
    # no point within 1e-6 of the radius of any node, so that the count is decided without the KD-tree's help; radii
    # below, at and past the spacing, grids of two nodes a side, spacings that do not divide the image
    rng = np.random.default_rng(100 + seed)
    spacing = float(rng.choice([1.0, 7.3, 16.0, 33.3]))
    spec = GridSpec(spacing, float(rng.choice([0.4, 1.0, 2.0, np.sqrt(2)]) * spacing), int(rng.integers(1, 4)))
    size = (int(rng.choice([1, 2, 37, 130])), int(rng.choice([1, 3, 64, 101])))
    xn, yn = spec.nodes(size)
    xy = rng.uniform(-2 * spec.support_radius_px, max(size) + 2 * spec.support_radius_px, (800, 2))
    xy[:300] = np.round(xy[:300])  # pixel centres: many on the nodes' lines
    d = np.sqrt(np.sum((xy[None] - node_coordinates(xn, yn)[:, None]) ** 2, axis=2))
    xy = xy[np.all(np.abs(d - spec.support_radius_px) > 1e-6, axis=0)]
    np.testing.assert_array_equal(spec.support_mask(xy, xn, yn), _brute_force_support(spec, xy, xn, yn))


def test_support_mask_of_a_radius_of_many_spacings_in_bounded_memory():
    # a radius of 60 spacings (support_radius_px is the user's, unbounded): each point's window would hold 123 x 123
    # nodes, 2000 points' windows 240 MB an array; the count stays the brute force's and the memory a few arrays of
    # the points' and nodes' size
    import tracemalloc

    spec = GridSpec(spacing_px=1.0, support_radius_px=60.0, min_support=800)
    xn, yn = spec.nodes((128, 128))
    xy = np.random.default_rng(5).uniform(0, 128, (2000, 2))
    tracemalloc.start()
    try:
        mask = spec.support_mask(xy, xn, yn)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64e6
    r2 = spec.support_radius_px**2
    dx2 = (xy[None, :, 0] - xn[:, None]) ** 2
    counts = np.concatenate([np.sum(dx2 + (xy[:, 1] - y) ** 2 <= r2, axis=1) for y in yn])  # a node row at a time
    expected = counts >= spec.min_support
    assert expected.any() and not expected.all()  # the centre's disc holds ~1400 points, a corner's ~350
    np.testing.assert_array_equal(mask, expected)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_support_mask_refuses_positions_that_are_not_finite(bad):
    from fluorocal.stages.errors import InputError

    xy = np.full((5, 2), 20.0)
    xy[2, 1] = bad
    xn, yn = GridSpec().nodes((64, 64))
    with pytest.raises(InputError, match="xy_px"):
        GridSpec(min_support=1).support_mask(xy, xn, yn)
