"""Tests of the shared geometry helpers in stages/geometry.py: the rigid/similarity fit and ray intersection."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.geometry import (
    image_rays,
    intersect_rays,
    project,
    quat_to_matrix,
    rotvec_to_quat,
    similarity_fit,
)


def _points(rng, n=40):
    return rng.uniform(-60, 60, (n, 3))


def test_rigid_fit_recovers_a_rigid_motion_exactly():
    rng = np.random.default_rng(0)
    src = _points(rng)
    R = quat_to_matrix(rotvec_to_quat(np.array([0.3, -0.2, 1.1])))
    t = np.array([5.0, -3.0, 700.0])
    s, R_fit, t_fit = similarity_fit(src, src @ R.T + t, with_scale=False)
    assert s == 1.0
    # exact data: only rounding remains
    np.testing.assert_allclose(R_fit, R, atol=1e-12)
    np.testing.assert_allclose(t_fit, t, atol=1e-9)


def test_rigid_fit_leaves_a_scale_error_visible_the_similarity_absorbs_it():
    rng = np.random.default_rng(1)
    src = _points(rng)
    R = quat_to_matrix(rotvec_to_quat(np.array([-0.4, 0.1, 0.2])))
    dst = 1.01 * src @ R.T + [1.0, 2.0, 3.0]
    s, R_sim, t_sim = similarity_fit(src, dst)
    assert abs(s - 1.01) < 1e-12
    np.testing.assert_allclose(s * src @ R_sim.T + t_sim, dst, atol=1e-9)
    _, R_rig, t_rig = similarity_fit(src, dst, with_scale=False)
    # the least-squares rotation does not depend on the scale
    np.testing.assert_allclose(R_rig, R, atol=1e-12)
    rms = np.sqrt(np.mean(np.sum((src @ R_rig.T + t_rig - dst) ** 2, axis=1)))
    # a 1 % scale error over points ~60 mm from their centroid: ~0.6 mm RMS stays in the residuals
    assert 0.4 < rms < 0.8, rms


def test_two_exact_rays_meet_at_the_projected_point():
    rng = np.random.default_rng(2)
    xyz = rng.uniform(-50, 50, (25, 3))
    iop = np.array([510.0, 505.0, 4000.0])
    poses = [
        (rotvec_to_quat(np.array([0.0, 0.0, 0.0])), np.array([0.0, 0.0, -700.0])),
        (rotvec_to_quat(np.array([0.0, -np.pi / 2, 0.0])), np.array([-700.0, 0.0, 0.0])),
    ]
    rays = [image_rays(project(xyz, q, T, iop), iop, q, T) for q, T in poses]
    found, miss = intersect_rays(rays)
    # exact projections, 90 deg between the views: rounding only (1e-9 mm at 700 mm)
    np.testing.assert_allclose(found, xyz, atol=1e-9)
    assert miss.max() < 1e-9
