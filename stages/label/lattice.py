"""Grid plates: holes indexed on their hexagonal or square lattice by topology, and the lattice ids.

The holes are indexed by growing outward from a hole near the centre with local lattice vectors
re-estimated at every hole, so that the distortion, missing holes and the field edge do not cause slips.
The object coordinates are the lattice coordinates times the pitch, z = 0, and the ids encode the lattice
indices (:func:`lattice_id`).
"""

from __future__ import annotations

import heapq
import logging

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import camera_matrix, matrix_to_quat
from fluorocal.stages.label.camera import pose_from_cv, project_cam
from fluorocal.stages.label.correction import fit_correction, n_terms
from fluorocal.stages.label.detections import Detections
from fluorocal.stages.label.labels import Labels, failed_labels
from fluorocal.stages.label.params import STATUS_LABELLED, STATUS_REJECTED, STATUS_UNMATCHED, LabelParams
from fluorocal.stages.lattices import LATTICES

log = logging.getLogger(__name__)

#: grid-plate ids: ``id = (i + LATTICE_ID_OFFSET) * LATTICE_ID_BASE + (j + LATTICE_ID_OFFSET)``
LATTICE_ID_OFFSET = 5000
LATTICE_ID_BASE = 10000


# hexagonal lattice: hole (i, j) at i*a1 + j*a2 with a2 = a1 rotated by +60 degrees
_HEX_STEPS = np.array([[1, 0], [0, 1], [-1, 1], [-1, 0], [0, -1], [1, -1]])
_SQUARE_STEPS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])


def lattice_id(ij: np.ndarray) -> np.ndarray:
    """Bead ids of grid-plate holes from their lattice indices ``(i, j)``; inverse of :func:`lattice_index`.

    Examples
    --------
    >>> lattice_id(np.array([[0, 0], [-3, 2]]))
    array([50005000, 49975002])
    """
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    return (ij[:, 0] + LATTICE_ID_OFFSET) * LATTICE_ID_BASE + (ij[:, 1] + LATTICE_ID_OFFSET)


def lattice_index(ids: np.ndarray) -> np.ndarray:
    """Lattice indices ``(N, 2)`` of grid-plate hole ids made by :func:`lattice_id`."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    return np.column_stack([ids // LATTICE_ID_BASE - LATTICE_ID_OFFSET, ids % LATTICE_ID_BASE - LATTICE_ID_OFFSET])


def lattice_xyz_mm(ij: np.ndarray, lattice: str, pitch_mm: float) -> np.ndarray:
    """Object coordinates ``(N, 3)`` (mm, z = 0) of lattice indices ``(i, j)``.

    A hexagonal lattice has hole ``(i, j)`` at ``pitch * (i + j/2, j * sqrt(3)/2)``; a square one at
    ``pitch * (i, j)``.
    """
    ij = np.asarray(ij, dtype=np.float64).reshape(-1, 2)
    basis = lattice_basis(lattice)
    return np.column_stack([pitch_mm * ij @ basis.T, np.zeros(len(ij))])


def lattice_basis(lattice: str) -> np.ndarray:
    """Columns: the two lattice vectors in units of the pitch."""
    if lattice == "hex":
        return np.array([[1.0, 0.5], [0.0, np.sqrt(3.0) / 2]])
    return np.eye(2)


def check_lattice(lattice: str, what: str) -> None:
    """Refuse a lattice spelling of no grid plate, naming ``what`` needs one."""
    if lattice not in LATTICES:
        shown = " or ".join(repr(name) for name in LATTICES)
        raise InputError(f"{what} needs a grid plate (phantom.lattice {shown}); got {lattice!r}")


def label_grid(det: Detections, phantom: Phantom, params: LabelParams, iop: np.ndarray) -> Labels:
    """Label the holes of a grid plate by growing their lattice from the centre; see :mod:`fluorocal.stages.label`."""
    det_idx = np.flatnonzero(det.valid)
    if len(det_idx) < 7:
        return failed_labels(det.valid, iop, f"only {len(det_idx)} usable detections on the grid plate")
    xy = det.xy_px[det_idx]
    ij, indexed, spacing, n_conflicts = _grow_lattice(
        xy, phantom.lattice, iop[:2], tolerance_pitch=params.lattice_tolerance_pitch, max_gap=params.lattice_max_gap
    )
    if indexed.sum() < 7:
        why = f"the lattice could not be grown from the centre ({int(indexed.sum())} holes indexed)"
        return failed_labels(det.valid, iop, why, "lattice")
    if n_conflicts:
        log.info("lattice growth met %d conflicting predictions (resolved by distance)", n_conflicts)
    sel = np.flatnonzero(indexed)
    obj = lattice_xyz_mm(ij[sel], phantom.lattice, phantom.pitch_mm)
    # a slip would put holes a whole spacing off the smooth image of the plate: drop such holes, or the frame
    resid = _plate_residuals(obj, xy[sel], iop, params.correction_degree)
    off = resid > params.lattice_tolerance_pitch * spacing
    if off.sum() > max(3, 0.02 * len(sel)):
        why = f"{int(off.sum())} of {len(sel)} indexed holes are off the plate's smooth image: lattice slips"
        return failed_labels(det.valid, iop, why, "lattice")
    sel, obj, resid = sel[~off], obj[~off], resid[~off]
    idx = det_idx[sel]
    status = np.where(det.valid, STATUS_UNMATCHED, STATUS_REJECTED).astype(np.int8)
    status[idx] = STATUS_LABELLED
    q, T, rms = _planar_pose(obj, det.xy_px[idx], iop)
    return Labels(
        idx,
        lattice_id(ij[sel]),
        det.xy_px[idx],
        det.sigma_px[idx],
        obj,
        status,
        q,
        T,
        iop,
        n_labelled=len(idx),
        n_ambiguous=0,
        n_unmatched=int((status == STATUS_UNMATCHED).sum()),
        rms_px=rms,
        rms_corrected_px=float(np.sqrt(np.mean(resid**2))),
        ok=True,
        pose_source="lattice",
    )


def _dominant_angle(vectors: np.ndarray, fold: int) -> float:
    """The lattice orientation (rad) from neighbour vectors, modulo ``2 pi / fold``, closest to +x."""
    theta = np.arctan2(vectors[:, 1], vectors[:, 0])
    phi = np.angle(np.exp(1j * fold * theta).sum()) / fold
    period = 2 * np.pi / fold
    return float((phi + period / 2) % period - period / 2)


def _grow_lattice(xy: np.ndarray, lattice: str, centre: np.ndarray, *, tolerance_pitch: float, max_gap: int):
    """Index holes on their lattice by growing from the hole nearest ``centre``.

    A hole is accepted within ``tolerance_pitch`` of the local spacing of its predicted position, and up to
    ``max_gap`` consecutive missing holes are bridged.

    Returns
    -------
    ij : (N, 2) int64 ndarray
        Lattice indices (valid where ``indexed``).
    indexed : (N,) bool ndarray
    spacing_px : float
        Median nearest-neighbour distance of the holes.
    n_conflicts : int
    """
    from scipy.spatial import cKDTree

    steps = _HEX_STEPS if lattice == "hex" else _SQUARE_STEPS
    tree = cKDTree(xy)
    dists, nbrs = tree.query(xy, k=min(len(steps) + 1, len(xy)))
    spacing = float(np.median(dists[:, 1]))
    start = int(tree.query(centre)[1])
    B0 = _start_basis(xy, tree, nbrs, start, spacing, lattice)
    if B0 is None:
        return np.zeros((len(xy), 2), np.int64), np.zeros(len(xy), bool), spacing, 0

    ij = np.zeros((len(xy), 2), np.int64)
    indexed = np.zeros(len(xy), bool)
    at: dict[tuple[int, int], int] = {}  # lattice index -> detection (real holes only)
    virtual: dict[tuple[int, int], int] = {}  # lattice index -> gap depth of a bridged, missing hole
    pos: dict[tuple[int, int], np.ndarray] = {}
    basis: dict[tuple[int, int], np.ndarray] = {}
    n_conflicts = 0

    key0 = (0, 0)
    at[key0], pos[key0], basis[key0] = start, xy[start], B0
    ij[start], indexed[start] = key0, True
    heap = [(0.0, key0)]
    while heap:
        _, key = heapq.heappop(heap)
        B = _local_basis(xy, steps, at, pos[key], key, basis[key])
        basis[key] = B
        depth = virtual.get(key, 0)
        pred = pos[key] + steps @ B.T
        d, hit = tree.query(pred, distance_upper_bound=tolerance_pitch * spacing)
        for s, p_xy, dist, h in zip(steps, pred, d, hit):
            nb = (key[0] + int(s[0]), key[1] + int(s[1]))
            if np.isfinite(dist):
                if indexed[h]:
                    if tuple(ij[h]) != nb:
                        n_conflicts += 1
                    continue
                if nb in at:
                    n_conflicts += 1
                    continue
                at[nb], pos[nb], basis[nb] = int(h), xy[h], B
                virtual.pop(nb, None)
                ij[h], indexed[h] = nb, True
                heapq.heappush(heap, (float(np.linalg.norm(xy[h] - xy[start])), nb))
            elif nb not in at and nb not in pos and depth < max_gap:
                virtual[nb] = depth + 1
                pos[nb], basis[nb] = p_xy, B
                heapq.heappush(heap, (float(np.linalg.norm(p_xy - xy[start])), nb))
    return ij, indexed, spacing, n_conflicts


def _start_basis(xy: np.ndarray, tree, nbrs: np.ndarray, start: int, spacing: float, lattice: str):
    """Lattice vectors (columns a1, a2, px) around hole ``start``, from its 30 nearest holes' neighbour vectors.

    ``a2`` is ``a1`` turned by +60 (hex) or +90 (square) degrees, toward +y. None without neighbour vectors
    near the ``spacing``.
    """
    fold = 6 if lattice == "hex" else 4
    _, near = tree.query(xy[start], k=min(30, len(xy)))
    vec = (xy[nbrs[near, 1:]] - xy[near, None, :]).reshape(-1, 2)
    length = np.linalg.norm(vec, axis=1)
    vec = vec[(length > 0.7 * spacing) & (length < 1.3 * spacing)]
    if not len(vec):
        return None
    angle = _dominant_angle(vec, fold)
    rot = 2 * np.pi / fold if lattice == "square" else np.pi / 3
    return spacing * np.array([[np.cos(angle), np.cos(angle + rot)], [np.sin(angle), np.sin(angle + rot)]])


def _local_basis(xy: np.ndarray, steps: np.ndarray, at: dict, pos_xy: np.ndarray, key: tuple, fallback: np.ndarray):
    """Lattice vectors from the indexed neighbours (``at``: lattice index -> hole) of ``key`` at ``pos_xy``.

    Least squares on the neighbours' offsets; ``fallback`` with fewer than two independent ones.
    """
    d_list, v_list = [], []
    for s in steps:
        nb = (key[0] + s[0], key[1] + s[1])
        if nb in at:
            d_list.append(s)
            v_list.append(xy[at[nb]] - pos_xy)
    if len(d_list) >= 2:
        D, V = np.array(d_list, float), np.array(v_list)
        if abs(np.linalg.det(D.T @ D)) > 0.5:
            return np.linalg.lstsq(D, V, rcond=None)[0].T
    return fallback


def _plate_residuals(obj: np.ndarray, img: np.ndarray, iop: np.ndarray, correction_degree: int) -> np.ndarray:
    """Distances (px) of the holes from a homography of the plate plus the low-order correction.

    The correction's degree is ``correction_degree``, lower where there are too few holes for it.
    """
    import cv2

    H, _ = cv2.findHomography(obj[:, :2], img, 0)
    if H is None:
        return np.zeros(len(obj))
    from_h = cv2.perspectiveTransform(obj[None, :, :2].astype(np.float64), H)[0]
    degree = correction_degree
    while degree > 0 and len(obj) < 3 * n_terms(degree):
        degree -= 1
    scale = 0.5 * float(np.hypot(*np.ptp(img, axis=0))) or 1.0
    pred = fit_correction(from_h, img, degree, iop[:2], scale).distort_points(from_h) if degree > 0 else from_h
    return np.linalg.norm(pred - img, axis=1)


def _planar_pose(obj: np.ndarray, img: np.ndarray, iop: np.ndarray):
    """Pose (IPPE) of a grid plate and its pinhole RMS (px), when the geometry (``c``) is known; else NaN."""
    import cv2

    if not (np.isfinite(iop[2]) and len(obj) >= 4):
        return np.full(4, np.nan), np.full(3, np.nan), np.nan
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera_matrix(iop), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return np.full(4, np.nan), np.full(3, np.nan), np.nan
    R, T = pose_from_cv(rvec, tvec)
    pin = project_cam((obj - T) @ R.T, iop)
    q = matrix_to_quat(R)
    return q, T, float(np.sqrt(np.mean(np.sum((pin - img) ** 2, axis=1))))
