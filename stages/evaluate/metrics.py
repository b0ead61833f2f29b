"""The figures of the paper's protocol (section VI, TABLE I), as pure functions of adjusted or intersected points.

- :func:`biplanar_pairs`, :func:`two_ray_points`, :func:`mapping_errors`: the
  two-ray spatial intersection of beads both systems saw at an epoch, each
  epoch's points fitted onto reference coordinates by a 6-parameter rigid
  transform (no scale: the calibrated baseline carries it);
- :func:`summarise`: mean and RMS 3D distance, per-axis RMSE and their average
  (the paper's "Average RMSE");
- :func:`check_point_errors`: adjusted object points against surveyed check
  points after a rigid or a similarity fit;
- :func:`select`, :func:`inlier_rms_px`: observation subsets and reprojection RMS.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Observations
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import image_rays, intersect_rays, similarity_fit

#: fewest common points a rigid or similarity fit is computed on (3 determine it; a few more make it a check)
MIN_FIT_POINTS = 4


def select(obs: Observations, keep: np.ndarray) -> Observations:
    """The observations where ``keep (N,) bool`` holds (system names kept)."""
    return Observations(
        obs.system[keep], obs.exposure[keep], obs.bead_id[keep], obs.xy_px[keep], obs.sigma_px[keep], obs.system_names
    )


def with_xy(obs: Observations, xy_px: np.ndarray) -> Observations:
    """The same observations at other image coordinates ``(N, 2)`` px."""
    return Observations(obs.system, obs.exposure, obs.bead_id, xy_px, obs.sigma_px, obs.system_names)


def inlier_rms_px(adj) -> float:
    """RMS per coordinate, px, of an adjustment's residuals over the observations it used as inliers."""
    keep = adj.inlier & adj.used
    return float(np.sqrt(np.mean(adj.residual_px[keep] ** 2))) if keep.any() else float("nan")


def biplanar_pairs(obs) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows of the same bead at the same epoch in systems 0 and 1.

    Returns
    -------
    exposure, bead_id : (P,) int64 ndarray
    row_a, row_b : (P,) int64 ndarray
        Indices into ``obs`` of system 0's and system 1's observation.
    """
    rows = [np.flatnonzero(obs.system == s) for s in (0, 1)]
    # one key per (epoch, bead): ids are small non-negative integers
    span = int(obs.bead_id.max()) + 1 if len(obs) else 1
    keys = [obs.exposure[r] * span + obs.bead_id[r] for r in rows]
    _, ia, ib = np.intersect1d(keys[0], keys[1], assume_unique=True, return_indices=True)
    row_a, row_b = rows[0][ia], rows[1][ib]
    return obs.exposure[row_a], obs.bead_id[row_a], row_a, row_b


def two_ray_points(ideal_a_px, ideal_b_px, iop_px, rop_q, rop_source_mm) -> np.ndarray:
    """Intersections ``(P, 3)`` mm, in system A's camera frame, of corresponding ideal points of A and B."""
    rays = [image_rays(xy, iop_px[s], rop_q[s], rop_source_mm[s]) for s, xy in enumerate((ideal_a_px, ideal_b_px))]
    return intersect_rays(rays)[0]


def mapping_errors(xyz_mm, exposure, truth_mm) -> np.ndarray:
    """Error vectors ``(P, 3)`` mm after a rigid fit of each epoch's points onto the truth, in the truth's frame.

    Epochs with fewer than :data:`MIN_FIT_POINTS` points get NaN rows (no fit).
    """
    err = np.full_like(truth_mm, np.nan)
    for e in np.unique(exposure):
        sel = exposure == e
        if sel.sum() < MIN_FIT_POINTS:
            continue
        _, R, t = similarity_fit(xyz_mm[sel], truth_mm[sel], with_scale=False)
        err[sel] = xyz_mm[sel] @ R.T + t - truth_mm[sel]
    return err


def ideal_points(obs, corrections) -> np.ndarray:
    """Observations undistorted by each system's correction: ``xy - Δ_s(xy)``, ``corrections[s]`` a callable."""
    ideal = obs.xy_px.copy()
    for s, correction in enumerate(corrections):
        sel = obs.system == s
        ideal[sel] -= correction(obs.xy_px[sel])
    return ideal


def biplanar_errors(obs, ideal_px, iop_px, rop_q, rop_source_mm, ref_ids, ref_xyz_mm) -> np.ndarray:
    """Two-ray error vectors ``(P, 3)`` mm of every bead with a reference that both systems saw at an epoch of ``obs``.

    ``ideal_px (N, 2)`` are the observations undistorted by their system's correction (pairs with a
    non-finite one are left out); epochs with fewer than :data:`MIN_FIT_POINTS` such beads are left out.
    """
    exposure, bead_id, row_a, row_b = biplanar_pairs(obs)
    known = np.isin(bead_id, ref_ids) & np.isfinite(ideal_px[row_a]).all(1) & np.isfinite(ideal_px[row_b]).all(1)
    exposure, bead_id, row_a, row_b = exposure[known], bead_id[known], row_a[known], row_b[known]
    xyz = two_ray_points(ideal_px[row_a], ideal_px[row_b], iop_px, rop_q, rop_source_mm)
    order = np.argsort(ref_ids)
    truth = ref_xyz_mm[order[np.searchsorted(ref_ids, bead_id, sorter=order)]]
    err = mapping_errors(xyz, exposure, truth)
    return err[np.isfinite(err[:, 0])]


def summarise(err_mm) -> dict:
    """Mean and RMS 3D distance, per-axis RMSE and their average (the paper's "Average RMSE"), mm."""
    dist = np.linalg.norm(err_mm, axis=1)
    axes = np.sqrt(np.mean(err_mm**2, axis=0)) if len(err_mm) else np.full(3, np.nan)
    return {
        "mean": float(dist.mean()) if len(dist) else float("nan"),
        "rms": float(np.sqrt(np.mean(dist**2))) if len(dist) else float("nan"),
        "axes": axes,
        "avg_rmse": float(axes.mean()),
        "n": len(dist),
    }


def check_point_errors(bead_id, xyz_mm, ref_ids, ref_xyz_mm, *, with_scale: bool) -> np.ndarray:
    """3D distances ``(n,)`` mm of adjusted object points from their check points after a fit onto them.

    Parameters
    ----------
    bead_id : (M,) int64 ndarray
    xyz_mm : (M, 3) float64 ndarray, mm
        Adjusted object points (any datum).
    ref_ids : (R,) int64 ndarray
    ref_xyz_mm : (R, 3) float64 ndarray, mm
        Surveyed check points.
    with_scale : bool
        A 7-parameter similarity (True) or a 6-parameter rigid fit (False).

    Raises
    ------
    InputError
        Fewer than :data:`MIN_FIT_POINTS` object points have a check point.

    Examples
    --------
    >>> ref = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    >>> d = check_point_errors(np.arange(4), 2 * ref + 1, np.arange(4), ref, with_scale=True)
    >>> bool(np.all(d < 1e-9))
    True
    """
    common, ia, ib = np.intersect1d(bead_id, ref_ids, return_indices=True)
    if len(common) < MIN_FIT_POINTS:
        raise InputError(
            f"only {len(common)} adjusted object point(s) have a check point with the same id (need "
            f">= {MIN_FIT_POINTS}); the reference's ids must be the phantom's"
        )
    src, dst = xyz_mm[ia], ref_xyz_mm[ib]
    scale, R, t = similarity_fit(src, dst, with_scale=with_scale)
    return np.linalg.norm(scale * src @ R.T + t - dst, axis=1)


__all__ = [
    "MIN_FIT_POINTS",
    "select",
    "with_xy",
    "inlier_rms_px",
    "biplanar_pairs",
    "two_ray_points",
    "mapping_errors",
    "ideal_points",
    "biplanar_errors",
    "summarise",
    "check_point_errors",
]
