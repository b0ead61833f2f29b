"""Scoring a grid-plate calibration against the simulator's truth (shared by tests and benchmarks/plate.py).

- :func:`true_layout`: the simulator's true hole positions in the calibration's own numbering, matched
  through the first frame (the labelling numbers the holes from wherever the plate sits);
- :func:`layout_error_mm`: estimated against true layout, after the best homography (the datum: a
  plate calibration determines its layout up to one), RMS per component;
- :func:`field_error_px`: a learned correction against the true one, over the field of view where the
  field is supported, after the best homography of the undistorted image (which every plate
  calibration is free to carry), RMS per component.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.field import CorrectionField, bilinear
from fluorocal.stages.geometry import homography_fit
from scipy.spatial import cKDTree


def true_layout(truth: dict, obs_xy_px: np.ndarray, obs_id: np.ndarray, frame: int = 0) -> dict:
    """Our hole id -> the true plate position ``(x, y)`` mm, matched by position in truth frame ``frame``.

    ``obs_xy_px``, ``obs_id``: our observations of that frame.
    """
    f = truth["frames"][frame]["beads"]
    xy = np.asarray(f["outline_xy_px"])
    d, nn = cKDTree(xy).query(obs_xy_px)
    ids = np.asarray(truth["phantom"]["ids"])
    true_xyz = np.asarray(truth["phantom"]["true_xyz_mm"])
    row = {int(i): r for r, i in enumerate(ids)}
    near = d < 1.0
    return {int(o): true_xyz[row[int(f["ids"][n])], :2] for o, n in zip(obs_id[near], nn[near])}


def layout_error_mm(estimated_mm: np.ndarray, true_mm: np.ndarray) -> float:
    """RMS per component of ``estimated - H(true)`` with ``H`` the least-squares homography."""
    return float(np.sqrt(np.mean(homography_fit(true_mm, estimated_mm)[1] ** 2)))


def truth_field(grid: dict, width: int, height: int) -> CorrectionField:
    """The simulator's correction grid as a field."""
    x, y, delta = (np.asarray(grid[k], float) for k in ("x_px", "y_px", "delta_px"))
    return CorrectionField(x, y, delta, np.zeros(delta.shape[:2]), np.ones(delta.shape[:2], bool), width, height)


def field_error_px(field: CorrectionField, true_field: CorrectionField, fov: dict, step_px: float = 8.0) -> float:
    """RMS per component of the difference of the undistorted points modulo a homography, px.

    Over the points of a ``step_px`` lattice inside the field of view (less 4 % of its radius) where the
    learned field is supported.
    """
    w, h = field.width_px, field.height_px
    yy, xx = np.mgrid[0:h:step_px, 0:w:step_px]
    pts = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    centre, radius = np.asarray(fov["centre_xy_px"]), 0.96 * float(fov["radius_px"])
    pts = pts[np.linalg.norm(pts - centre, axis=1) < radius]
    pts = pts[field.support_at(pts)]
    ideal_est = pts - field.correction_at(pts)
    ideal_true = pts - bilinear(true_field.x_nodes_px, true_field.y_nodes_px, true_field.delta_px, pts)
    return float(np.sqrt(np.mean(homography_fit(ideal_true, ideal_est)[1] ** 2)))


def truth_problem(data, noise_px: float, rng: np.random.Generator):
    """The plate problem of a simulated grid acquisition (system 0) from its truth centroids, no rendering.

    Observations: every hole whose outline neither overlaps another nor meets the field of view's rim, at its
    true distorted outline centre plus Gaussian noise of ``noise_px`` per component, stated as a ``sigma_px``
    of ``max(noise_px, 0.03)``; one orientation per simulated orientation (or one for all frames). Returns
    ``(problem, true_mm)``: the problem and the true plate position ``(K, 2)`` mm of each of its holes.
    """
    from fluorocal.stages.plate.solve import PlateProblem

    row = {int(i): r for r, i in enumerate(data.phantom.ids)}
    frames, holes, xy = [], [], []
    for f, truth in enumerate(data.truth.frames[0]):
        ok = ~truth.overlap & ~truth.field_edge
        frames.append(np.full(int(ok.sum()), f))
        holes.append(np.array([row[int(i)] for i in truth.ids[ok]], np.int64))
        xy.append(truth.outline_xy_px[ok])
    exposure_orientation = np.asarray(data.truth.acquisition.exposure_orientation)
    orient = np.maximum(exposure_orientation, 0)
    used, hole = np.unique(np.concatenate(holes), return_inverse=True)
    n = len(hole)
    measured = np.vstack(xy) + rng.normal(scale=noise_px, size=(n, 2))
    stated = max(noise_px, 0.03)  # at least the real frames' centroid floor: the priors weigh as on real data
    sigma = np.column_stack([np.full(n, stated), np.full(n, stated), np.zeros(n)])
    size = int(data.params.image_size_px)
    problem = PlateProblem(
        np.concatenate(frames).astype(np.int64),
        np.unique(orient, return_inverse=True)[1].astype(np.int64),
        hole.astype(np.int64),
        data.phantom.xyz_mm[used, :2],
        measured,
        sigma,
        (size, size),
    )
    return problem, np.asarray(data.truth.true_xyz_mm)[used, :2]
