"""The labelling iteration's solvers (stages/label/iterate.py): the pose and principal distance fit."""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.label.iterate import pose_c_jacobian, pose_c_residuals


@pytest.mark.parametrize("log_c", [0.0, 0.2, -0.3])
def test_pose_c_jacobian_matches_finite_differences(log_c):
    """The analytic derivatives of the pose-and-c misfit agree with central differences.

    A cube of 60 points ~1 m from the source, c about 4000 px: the central difference's error is of order
    h^2 times the third derivative (h = 1e-6 in rad, mm and log c) and its rounding ~1e-16 x |misfit| / h, both
    below 1e-6 of the largest derivative; a wrong term (a sign, c's chain rule, the column order) is off by
    that derivative's size.
    """
    rng = np.random.default_rng(3)
    obj = rng.uniform(-60.0, 60.0, (60, 3))
    img = rng.uniform(0.0, 1024.0, (60, 2))
    iop = np.array([510.0, 498.0, 4000.0])
    x = np.array([0.3, -0.2, 0.1, 12.0, -8.0, 950.0, log_c])
    h = 1e-6
    numeric = np.column_stack(
        [
            (pose_c_residuals(x + e, obj, img, iop) - pose_c_residuals(x - e, obj, img, iop)) / (2 * h)
            for e in h * np.eye(7)
        ]
    )
    analytic = pose_c_jacobian(x, obj, img, iop)
    assert analytic.shape == (120, 7)
    assert np.max(np.abs(analytic - numeric)) < 1e-6 * np.max(np.abs(numeric))
