"""Assignment of predicted bead positions to detections, and the overlap (ambiguity) test."""

from __future__ import annotations

import numpy as np

# detections considered per prediction in the assignment (within the gate, nearest first)
_MAX_CANDIDATES = 4
# cost of a forbidden pair in the assignment: larger than any sum of gated distances
_FORBIDDEN = 1e9
# a cKDTree query's bound is strict and compares squared distances: it is set this fraction above the widest gate
_BOUND_SLACK = 1e-9


def assign(pred_xy: np.ndarray, gate_px: np.ndarray, det_xy: np.ndarray, det_tree) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one assignment of predictions to detections within per-prediction gates.

    Parameters
    ----------
    pred_xy : (P, 2) float64 ndarray, px
    gate_px : (P,) float64 ndarray, px
    det_xy : (D, 2) float64 ndarray, px
    det_tree : scipy.spatial.cKDTree of ``det_xy``

    Returns
    -------
    i_pred, i_det : (K,) int64 ndarrays
        Matched pairs; the total distance is minimal among assignments with the most pairs.
    """
    from scipy.optimize import linear_sum_assignment

    if not len(pred_xy) or not len(det_xy):
        return np.empty(0, np.int64), np.empty(0, np.int64)
    k = min(_MAX_CANDIDATES, len(det_xy))
    d, j = det_tree.query(pred_xy, k=k, distance_upper_bound=gate_bound(gate_px))
    d, j = d.reshape(len(pred_xy), k), j.reshape(len(pred_xy), k)
    inside = d <= gate_px[:, None]
    rows = np.nonzero(inside)[0]
    cols = j[inside]
    counts = inside.sum(1)
    if not len(rows):
        return rows, cols
    dist = d[inside]
    col_counts = np.bincount(cols, minlength=len(det_xy))
    # pairs whose prediction and detection have no other candidate need no optimisation
    simple = (counts[rows] == 1) & (col_counts[cols] == 1)
    out_r, out_c = [rows[simple]], [cols[simple]]
    hard_r, hard_c, hard_d = rows[~simple], cols[~simple], dist[~simple]
    if len(hard_r):
        ur, ir = np.unique(hard_r, return_inverse=True)
        uc, ic = np.unique(hard_c, return_inverse=True)
        cost = np.full((len(ur), len(uc)), _FORBIDDEN)
        cost[ir, ic] = hard_d
        a, b = linear_sum_assignment(cost)
        good = cost[a, b] < _FORBIDDEN
        out_r.append(ur[a[good]])
        out_c.append(uc[b[good]])
    return np.concatenate(out_r), np.concatenate(out_c)


def gate_bound(gate_px: np.ndarray) -> float:
    """The ``distance_upper_bound`` of a cKDTree query that finds every point within the widest of ``gate_px``.

    The tree finds only points strictly nearer than its bound (to rounding of their squares): a point at
    the gate itself, within it as the gates are read (``d <= gate``), would be lost at the gate.
    """
    return float(np.max(gate_px)) * (1.0 + _BOUND_SLACK)


def ambiguous(pred_xy: np.ndarray, diam_px: np.ndarray, factor: float, tree=None) -> np.ndarray:
    """Beads whose projection lies within ``factor`` x the mean of both diameters of another's.

    ``tree``: a ``scipy.spatial.cKDTree`` of ``pred_xy`` if the caller has one (else it is built).
    """
    amb = np.zeros(len(pred_xy), dtype=bool)
    amb[overlapping(pred_xy, diam_px, factor, tree).ravel()] = True
    return amb


def overlapping(pred_xy: np.ndarray, diam_px: np.ndarray, factor: float, tree=None) -> np.ndarray:
    """``(K, 2) int``: the pairs of beads whose projections lie within ``factor`` x their mean diameter.

    ``tree``: a ``scipy.spatial.cKDTree`` of ``pred_xy`` if the caller has one (else it is built).
    """
    from scipy.spatial import cKDTree

    if len(pred_xy) < 2:
        return np.empty((0, 2), dtype=np.int64)
    tree = cKDTree(pred_xy) if tree is None else tree
    pairs = tree.query_pairs(r=factor * float(np.max(diam_px)), output_type="ndarray")
    if not len(pairs):
        return np.empty((0, 2), dtype=np.int64)
    d = np.linalg.norm(pred_xy[pairs[:, 0]] - pred_xy[pairs[:, 1]], axis=1)
    return pairs[d < factor * 0.5 * (diam_px[pairs[:, 0]] + diam_px[pairs[:, 1]])].astype(np.int64)


def told_apart(
    xy: np.ndarray, diam_px: np.ndarray, factor: float, fits: np.ndarray, tol_px: float, slack: float
) -> np.ndarray:
    """``(P,) bool``: beads whose own detection tells them apart from their neighbours.

    A bead is told apart when its assigned detection lies within ``tol_px`` of its prediction (``fits``),
    no other bead lies within ``factor * (1 - slack)`` times their mean diameter (the overlap test of
    :func:`ambiguous`, relaxed by ``slack``, the relative precision to which the frame shows a bead's
    outline), and none within ``3 * tol_px``, so that the detection is at least twice as near its own
    bead as any other. Overlapping beads merged into one blob leave a detection between them: for beads
    of one size, equally near both.

    Parameters
    ----------
    xy : (P, 2) float64 ndarray, px
        The beads' centres (measured where detected, predicted elsewhere).
    diam_px : (P,) float64 ndarray, px
        Their apparent diameters.
    factor : float
        The ambiguity distance in mean diameters (:func:`ambiguous`).
    fits : (P,) bool ndarray
        Beads assigned a detection within ``tol_px`` of their prediction.
    tol_px, slack : float
    """
    from scipy.spatial import cKDTree

    out = fits.copy()
    out[overlapping(xy, diam_px, factor * (1.0 - slack)).ravel()] = False
    if len(xy) > 1 and tol_px > 0:
        out[cKDTree(xy).query_pairs(r=3.0 * tol_px, output_type="ndarray").ravel()] = False
    return out
