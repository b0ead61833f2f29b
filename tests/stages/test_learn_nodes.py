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
