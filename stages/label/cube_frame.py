"""One frame as the cube labelling sees it: detections, assumed camera, bead sizes; visibility and coarse scores."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.geometry import camera_matrix
from fluorocal.stages.label.assign import ambiguous, gate_bound
from fluorocal.stages.label.camera import project_cam
from fluorocal.stages.label.detections import Detections
from fluorocal.stages.label.params import LabelParams


@dataclass
class CubeFrame:
    """What the cube labelling needs about one frame, computed once."""

    det: Detections
    phantom: Phantom
    params: LabelParams
    iop: np.ndarray
    K: np.ndarray
    det_idx: np.ndarray  # (D,) indices of the valid detections
    det_xy: np.ndarray  # (D, 2)
    det_tree: object
    diam_ref_px: float  # median apparent diameter of ordinary beads, px
    bead_diam_mm: np.ndarray  # (B,) NaN filled with the median
    width: float
    height: float
    hull: np.ndarray = field(
        default_factory=lambda: np.empty((0, 3))
    )  # (F, 3) the detections' convex hull: unit outward normals and offsets (n.x + o <= 0 inside)


def make_cube_frame(
    det: Detections, phantom: Phantom, params: LabelParams, iop: np.ndarray
) -> tuple[CubeFrame | None, Detections]:
    """The frame of ``det`` for the cube labelling, and the detections with elongated blobs made invalid.

    The frame is None when fewer than 4 detections are usable.
    """
    from scipy.spatial import cKDTree

    # a sphere projects to a nearly round outline: an elongated blob is overlapping beads, not one of them
    det = replace(det, valid=det.valid & ~(det.axis_ratio > params.max_axis_ratio))
    det_idx = np.flatnonzero(det.valid)
    if len(det_idx) < 4:
        return None, det
    sizes = det.size_px[det_idx]
    diam_ref = float(np.nanmedian(sizes)) if np.isfinite(sizes).any() else np.nan
    bead_diam = phantom.diameter_mm.copy()
    if np.isfinite(bead_diam).any():
        bead_diam[~np.isfinite(bead_diam)] = np.nanmedian(bead_diam)
    if not np.isfinite(diam_ref):
        diam_ref = typical_spacing(det.xy_px[det_idx]) / 3.0
    # the image extent, or (unknown) one symmetric about the assumed centre that holds every detection
    pts = det.xy_px[det_idx]
    width = max(2 * iop[0] + 1, 2 * float(pts[:, 0].max()) - 2 * iop[0] + diam_ref)
    height = max(2 * iop[1] + 1, 2 * float(pts[:, 1].max()) - 2 * iop[1] + diam_ref)
    frame = CubeFrame(
        det,
        phantom,
        params,
        iop,
        camera_matrix(iop),
        det_idx,
        pts,
        cKDTree(pts),
        diam_ref,
        bead_diam,
        width,
        height,
        _hull(pts),
    )
    return frame, det


def with_camera(frame: CubeFrame, iop: np.ndarray) -> CubeFrame:
    """``frame`` seen with interior orientation ``iop`` (a labelling's refined principal distance)."""
    return replace(frame, iop=np.asarray(iop, dtype=np.float64), K=camera_matrix(iop))


def _hull(xy: np.ndarray) -> np.ndarray:
    """``(F, 3)``: the convex hull of points ``xy`` as unit outward normals and offsets; empty if degenerate."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return ConvexHull(xy).equations
    except QhullError:
        return np.empty((0, 3))


def inside_hull(frame: CubeFrame, xy: np.ndarray, margin: np.ndarray) -> np.ndarray:
    """``(N,) bool``: points at least ``margin`` inside the convex hull of the frame's usable detections."""
    if not len(frame.hull):
        return np.zeros(len(xy), dtype=bool)
    return np.all(xy @ frame.hull[:, :2].T + frame.hull[:, 2] <= -margin[:, None], axis=1)


def typical_spacing(xy: np.ndarray) -> float:
    """Median nearest-neighbour distance of points ``xy`` (px); 10 for fewer than two."""
    from scipy.spatial import cKDTree

    if len(xy) < 2:
        return 10.0
    d, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(d[:, 1]))


def visible(frame: CubeFrame, R: np.ndarray, T: np.ndarray):
    """Projections of the beads in front of the source and inside the image, and their apparent diameters."""
    p_cam = (frame.phantom.xyz_mm - T) @ R.T
    xy = project_cam(p_cam, frame.iop)
    z = p_cam[:, 2]
    diam = frame.iop[2] * frame.bead_diam_mm / np.where(z > 0, z, np.nan)
    diam = np.where(np.isfinite(diam), diam, frame.diam_ref_px)
    margin = 0.5 * diam
    vis = (z > 0) & np.all(np.isfinite(xy), axis=1)
    vis &= (xy[:, 0] > -0.5 + margin) & (xy[:, 0] < frame.width - 0.5 - margin)
    vis &= (xy[:, 1] > -0.5 + margin) & (xy[:, 1] < frame.height - 0.5 - margin)
    return np.flatnonzero(vis), xy, diam


def coarse_score(frame: CubeFrame, R: np.ndarray, T: np.ndarray) -> int:
    """Number of visible beads with a detection within the gate of their pinhole projection."""
    vis, xy, diam = visible(frame, R, T)
    if not len(vis):
        return 0
    d, _ = frame.det_tree.query(xy[vis], distance_upper_bound=frame.params.gate_bead_diameters * frame.diam_ref_px)
    return int(np.isfinite(d).sum())


def coarse_evidence(frame: CubeFrame, R: np.ndarray, T: np.ndarray) -> int:
    """How well the pinhole projection of pose ``(R, T)`` explains the detections, within the assignment gate.

    ``explained - unexplained - missing``: detections with a projected bead within the gate, those
    without, and projected beads clear of others and well inside the detections' hull without a
    detection within the gate. Unlike :func:`coarse_score`, a pose slipped by a bead row scores lower than
    the true one (a row missing at one end, one unexplained at the other). The distortion, not modelled
    here, costs every pose of one orientation alike.
    """
    from scipy.spatial import cKDTree

    vis, xy, diam = visible(frame, R, T)
    if len(vis) < 2:
        return -len(frame.det_xy)
    gate = frame.params.gate_bead_diameters * diam[vis]
    tree = cKDTree(xy[vis])
    explained = int(np.sum(within_gates(tree, frame.det_xy, gate)))
    d_pred, _ = frame.det_tree.query(xy[vis], distance_upper_bound=gate_bound(gate))
    clear = ~ambiguous(xy[vis], diam[vis], frame.params.ambiguity_bead_diameters, tree)
    missing = int(np.sum(clear & (d_pred > gate) & inside_hull(frame, xy[vis], diam[vis])))
    return 2 * explained - len(frame.det_xy) - missing


def within_gates(tree, xy: np.ndarray, gate_px: np.ndarray) -> np.ndarray:
    """``(N,) bool``: points ``xy`` within the gate ``gate_px`` of the nearest point of ``tree`` (a cKDTree).

    The nearest point's own gate decides. The query stops at the widest gate: a point farther from every
    tree point is within none (its distance is then inf, its index the tree's size).
    """
    d, k = tree.query(xy, distance_upper_bound=gate_bound(gate_px))
    out = np.isfinite(d)
    out[out] = d[out] <= gate_px[k[out]]
    return out


def marker_mask(frame: CubeFrame) -> np.ndarray:
    """``(B,)`` bool: the phantom's marker beads."""
    return frame.phantom.role == "marker"
