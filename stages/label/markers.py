"""Start poses of a 3D phantom from its marker beads (P3P on marker-sized detections) or from seeds.

Markers are recognised by their larger apparent size. With three or more marker-sized detections, P3P is
solved on triples of them against ordered triples of markers and scored by the other markers, then by all
beads; with fewer, beads near a marker detection in the image complete the P3P (they are often its
neighbours on the phantom).
"""

from __future__ import annotations

import itertools

import numpy as np
from fluorocal.stages.errors import InputError
from fluorocal.stages.label.camera import p3p, pose_batch_from_cv, pose_from_cv, project_cam
from fluorocal.stages.label.cube_frame import CubeFrame, coarse_score, marker_mask

# P3P problems solved per frame from marker triples, and marker hypotheses verified on all beads
_P3P_BUDGET = 1500
_N_VERIFY = 6
# beads sampled to pre-rank many marker hypotheses
_N_SAMPLE = 64
# with only two marker detections: their nearest detections and the markers' nearest beads tried as a third pair
_PAIR_NEAR_DETECTIONS = 3
_PAIR_NEAR_BEADS = 8
# a marker pose whose pinhole projection has a detection near this fraction of all detections ends the search
_GOOD_COARSE = 0.6


def marker_poses(frame: CubeFrame, n_keep: int = 4):
    """Pose hypotheses from marker correspondences: P3P on triples, scored by all markers, then by all beads."""
    markers = np.flatnonzero(marker_mask(frame))
    if not len(markers):
        return [], [], "the phantom has no marker beads (role 'marker'); give seeds"
    thr = _marker_threshold(frame)
    if thr is None:
        return [], [], "marker beads are not distinguishable by size (diameters missing or too similar); give seeds"
    sizes = frame.det.size_px[frame.det_idx]
    cand = np.flatnonzero(sizes > thr)
    cand = cand[np.argsort(-sizes[cand])][: frame.params.max_marker_candidates]
    if not len(cand):
        return [], [], "no marker-sized detection found; need 1 or more, or seeds"
    if len(cand) == 1:
        poses, scores = _rank_hypotheses(frame, *_single_hypotheses(frame, cand[0], markers), n_keep)
        return poses, scores, "" if poses else "no pose fits the one marker-sized detection"
    if len(cand) == 2 or len(markers) == 2:
        poses, scores = _rank_hypotheses(frame, *_pair_hypotheses(frame, cand[:2], markers), n_keep)
        return poses, scores, "" if poses else "no pose fits the two marker-sized detections"
    cand_xy = frame.det_xy[cand]
    m_xyz = frame.phantom.xyz_mm[markers]
    # a marker's detection lies within half its apparent diameter of its projection, up to distortion
    gate = 0.5 * thr
    # candidate triples, largest detections first (the surest markers), each against every ordered triple of
    # phantom markers; a triple of true markers soon yields a pose that predicts a fourth
    marker_triples = list(itertools.permutations(range(len(markers)), 3))
    batches = []
    for i_triple, t in enumerate(itertools.combinations(range(len(cand)), 3)):
        if i_triple and i_triple * len(marker_triples) >= _P3P_BUDGET:
            break
        img = cand_xy[list(t)]
        rvecs, tvecs = [], []
        for mt in marker_triples:
            rv, tv = p3p(m_xyz[list(mt)], img, frame.K)
            rvecs.extend(rv)
            tvecs.extend(tv)
        if rvecs:
            batches.append(_score_marker_hyps(frame, np.array(rvecs), np.array(tvecs), m_xyz, cand_xy, gate))
            n_m, mean_d, Rs, Ts = batches[-1]
            # a pose from three markers that predicts a fourth and explains most detections: look no further
            best = np.lexsort((mean_d, -n_m))[:2]
            good = _GOOD_COARSE * len(frame.det_idx)
            if any(n_m[h] >= 4 and coarse_score(frame, Rs[h], Ts[h]) >= good for h in best):
                break
    if batches:
        n_matched, mean_d, Rs, Ts = (np.concatenate(x) for x in zip(*batches))
    else:
        n_matched, mean_d, Rs, Ts = np.zeros(0, int), np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3))
    # a pose that predicts a fourth marker is evidence; three are fitted by every P3P solution
    best_n = int(n_matched.max(initial=0))
    plausible = np.flatnonzero(n_matched >= (best_n if best_n >= 4 else 3))
    if len(plausible) > _N_VERIFY:
        # marker counts tie (three candidates fit every P3P solution): pre-rank on a sample of all beads
        order = plausible[_prerank(frame, Rs[plausible], Ts[plausible])]
    else:
        order = plausible[np.lexsort((mean_d[plausible], -n_matched[plausible]))]
    top = _distinct_poses(Rs, Ts, order)
    # verify the best marker hypotheses on all beads
    scores = np.array([coarse_score(frame, R, T) for R, T in top])
    if scores.max(initial=0) < _GOOD_COARSE * len(frame.det_idx):
        # maybe one of the marker-sized detections is not a marker: try the pairs of the largest three
        for pair in itertools.combinations(cand[:3], 2):
            Rp, Tp = _pair_hypotheses(frame, np.array(pair), markers)
            poses, more = _rank_hypotheses(frame, Rp, Tp, n_keep)
            top, scores = top + poses, np.concatenate([scores, more])
    keep = np.argsort(-scores, kind="stable")[:n_keep]
    return [top[i] for i in keep], scores[keep].tolist(), "" if top else "no pose fits the marker-sized detections"


def _marker_threshold(frame: CubeFrame) -> float | None:
    """Apparent diameter (px) above which a detection is taken as a marker, or None if markers are not distinct."""
    markers = marker_mask(frame)
    ratio = frame.params.marker_size_ratio
    if not ratio > 0:
        d = frame.phantom.diameter_mm
        if not (np.isfinite(d[markers]).any() and np.isfinite(d[~markers]).any()):
            return None
        ratio = float(np.nanmedian(d[markers]) / np.nanmedian(d[~markers]))
    if ratio < 1.15 or not np.isfinite(frame.diam_ref_px):
        return None
    # the geometric midpoint between the two sizes is robust to the depth spread of magnification
    return frame.diam_ref_px * np.sqrt(ratio)


def _score_marker_hyps(
    frame: CubeFrame, rvecs: np.ndarray, tvecs: np.ndarray, m_xyz: np.ndarray, cand_xy: np.ndarray, gate: float
):
    """Markers matched and their mean distance for each OpenCV pose hypothesis of plausible depth.

    Returns
    -------
    n_matched : (H,) int ndarray
    mean_d : (H,) float64 ndarray, px
    Rs : (H, 3, 3) float64 ndarray
    Ts : (H, 3) float64 ndarray, mm
    """
    Rs, Ts = pose_batch_from_cv(rvecs, tvecs)
    # shape (H, M, 3)
    p_cam = np.einsum("hij,mj->hmi", Rs, m_xyz) + tvecs[:, None, :]
    z = p_cam[..., 2]
    front = np.all(z > 0, axis=1) & (np.median(z, axis=1) < frame.iop[2] * frame.params.pixel_pitch_mm)
    Rs, Ts, p_cam = Rs[front], Ts[front], p_cam[front]
    xy = project_cam(p_cam, frame.iop)
    # shape (H, M, C)
    d = np.linalg.norm(xy[:, :, None, :] - cand_xy[None, None, :, :], axis=-1)
    nearest = d.min(axis=1)  # each candidate's nearest projected marker
    matched = nearest < gate
    n = matched.sum(1)
    mean_d = np.where(matched, nearest, 0).sum(1) / np.maximum(n, 1)
    return n, mean_d, Rs, Ts


def _pair_hypotheses(frame: CubeFrame, pair: np.ndarray, markers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose hypotheses ``(Rs (H, 3, 3), Ts (H, 3))`` from two marker detections, each completed by a neighbour.

    Beads near a marker in the image are often its neighbours on the phantom: for each assignment of two
    markers to the two detections, P3P is solved with a third correspondence between one of the detections
    nearest to a marker detection in the image and one of the ordinary beads nearest to that marker.
    """
    xyz = frame.phantom.xyz_mm
    ordinary = np.flatnonzero(~marker_mask(frame))
    k_img = min(_PAIR_NEAR_DETECTIONS, len(frame.det_idx) - 2)
    k_obj = min(_PAIR_NEAR_BEADS, len(ordinary))
    if k_img < 1 or k_obj < 1:
        return _poses([], [])
    # for each marker detection its nearest other detections; for each marker its nearest ordinary beads
    _, near_det = frame.det_tree.query(frame.det_xy[pair], k=k_img + 3)
    near_det = [[d for d in row if d not in pair][:k_img] for row in near_det]
    near_bead = dict(zip(markers.tolist(), _nearest_beads(xyz, ordinary, markers, k_obj)))
    rvecs, tvecs = [], []
    for i, j in itertools.permutations(markers.tolist(), 2):
        for m_bead, neighbours in ((i, near_det[0]), (j, near_det[1])):
            for d in neighbours:
                img = frame.det_xy[[pair[0], pair[1], d]]
                for k in near_bead[m_bead]:
                    rv, tv = p3p(xyz[[i, j, k]], img, frame.K)
                    rvecs.extend(rv)
                    tvecs.extend(tv)
    return _poses(rvecs, tvecs)


def _single_hypotheses(frame: CubeFrame, a: int, markers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose hypotheses ``(Rs, Ts)`` from one marker detection and two of its neighbours.

    See :func:`_pair_hypotheses`.
    """
    xyz = frame.phantom.xyz_mm
    ordinary = np.flatnonzero(~marker_mask(frame))
    k_img = min(_PAIR_NEAR_DETECTIONS + 1, len(frame.det_idx) - 1)
    k_obj = min(_PAIR_NEAR_BEADS, len(ordinary))
    if k_img < 2 or k_obj < 2:
        return _poses([], [])
    _, near_det = frame.det_tree.query(frame.det_xy[a], k=k_img + 1)
    near_det = [d for d in near_det if d != a][:k_img]
    near = _nearest_beads(xyz, ordinary, markers, k_obj)
    rvecs, tvecs = [], []
    for i, beads in zip(markers.tolist(), near):
        for d1, d2 in itertools.combinations(near_det, 2):
            img = frame.det_xy[[a, d1, d2]]
            for k1, k2 in itertools.permutations(beads.tolist(), 2):
                rv, tv = p3p(xyz[[i, k1, k2]], img, frame.K)
                rvecs.extend(rv)
                tvecs.extend(tv)
    return _poses(rvecs, tvecs)


def _nearest_beads(xyz_mm: np.ndarray, beads: np.ndarray, markers: np.ndarray, k: int) -> np.ndarray:
    """``(M, k)`` int: for each of the ``markers`` its ``k`` nearest ``beads`` on the phantom."""
    from scipy.spatial import cKDTree

    _, near = cKDTree(xyz_mm[beads]).query(xyz_mm[markers], k=k)
    return beads[np.asarray(near).reshape(len(markers), -1)]


def _poses(rvecs: list, tvecs: list) -> tuple[np.ndarray, np.ndarray]:
    """``(Rs (H, 3, 3), Ts (H, 3))`` of OpenCV's pose solutions ``rvecs``, ``tvecs`` (none: empty arrays)."""
    if not rvecs:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    return pose_batch_from_cv(rvecs, tvecs)


def _rank_hypotheses(frame: CubeFrame, Rs: np.ndarray, Ts: np.ndarray, n_keep: int) -> tuple[list, list]:
    """The ``n_keep`` best distinct poses: pre-ranked on a sample of the beads, then scored on all of them."""
    if not len(Rs):
        return [], []
    top = _distinct_poses(Rs, Ts, _prerank(frame, Rs, Ts))
    scores = np.array([coarse_score(frame, R, T) for R, T in top])
    keep = np.argsort(-scores, kind="stable")[:n_keep]
    return [top[k] for k in keep], scores[keep].tolist()


def _distinct_poses(Rs: np.ndarray, Ts: np.ndarray, order: np.ndarray) -> list:
    """The first :data:`_N_VERIFY` poses ``(R, T)`` taken in ``order`` that differ from every pose taken before."""
    top = []
    for h in order:
        if len(top) == _N_VERIFY:
            break
        if not any(_same_pose(Rs[h], Ts[h], R, T) for R, T in top):
            top.append((Rs[h], Ts[h]))
    return top


def _prerank(frame: CubeFrame, Rs: np.ndarray, Ts: np.ndarray) -> np.ndarray:
    """Order of many pose hypotheses, best first, by coarse scores on samples of the beads.

    A small sample sorts out the bulk; the best tenth is re-scored on a larger one.
    """
    coarse = _coarse_scores(frame, Rs, Ts, n_sample=_N_SAMPLE // 4)
    order = np.argsort(-coarse, kind="stable")
    head = order[: max(4 * _N_VERIFY, len(order) // 10)]
    fine = _coarse_scores(frame, Rs[head], Ts[head], n_sample=_N_SAMPLE)
    return head[np.argsort(-fine, kind="stable")]


def _coarse_scores(frame: CubeFrame, Rs: np.ndarray, Ts: np.ndarray, *, n_sample: int) -> np.ndarray:
    """:func:`coarse_score` of many poses at once, on an evenly spaced sample of the beads."""
    step = max(1, frame.phantom.n_beads // n_sample)
    xyz = frame.phantom.xyz_mm[::step]
    # shape (H, S, 3)
    p_cam = np.einsum("hij,hsj->hsi", Rs, xyz[None, :, :] - Ts[:, None, :])
    z = p_cam[..., 2]
    xy = project_cam(p_cam, frame.iop)
    inside = (z > 0) & np.all(np.isfinite(xy), axis=-1)
    inside &= (xy[..., 0] > -0.5) & (xy[..., 0] < frame.width - 0.5)
    inside &= (xy[..., 1] > -0.5) & (xy[..., 1] < frame.height - 0.5)
    d = np.full(z.shape, np.inf)
    gate = frame.params.gate_bead_diameters * frame.diam_ref_px
    d[inside], _ = frame.det_tree.query(xy[inside], distance_upper_bound=gate)
    return np.isfinite(d).sum(axis=1)


def _same_pose(R1, T1, R2, T2) -> bool:
    """Poses closer than about 2 degrees and 20 mm lead to the same labelling start."""
    cos = 0.5 * (np.trace(R1.T @ R2) - 1.0)
    return cos > np.cos(np.radians(2.0)) and np.linalg.norm(T1 - T2) < 20.0


def pose_from_seeds(frame: CubeFrame):
    """A pose from manually identified beads ``(id, x, y)``: SQPnP on 4 or more, P3P + verification on 3."""
    import cv2

    seeds = np.asarray(frame.params.seeds, dtype=np.float64).reshape(-1, 3)
    lookup = {int(i): k for k, i in enumerate(frame.phantom.ids)}
    unknown = [int(i) for i in seeds[:, 0] if int(i) not in lookup]
    if unknown:
        raise InputError(f"params.seeds name beads not in the phantom: {unknown}")
    if len(seeds) < 3:
        return None, f"params.seeds needs at least 3 beads; got {len(seeds)}"
    obj = frame.phantom.xyz_mm[[lookup[int(i)] for i in seeds[:, 0]]]
    img = seeds[:, 1:3].copy()
    if len(seeds) >= 4:
        ok, rvec, tvec = cv2.solvePnP(obj, img, frame.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None, "no pose fits the seeds"
        if len(seeds) >= 6:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, frame.K, None, rvec, tvec)
        return pose_from_cv(rvec, tvec), ""
    poses = _p3p_poses(frame, obj, img)
    if not poses:
        return None, "no pose fits the seeds"
    scores = [coarse_score(frame, R, T) for R, T in poses]
    return poses[int(np.argmax(scores))], ""


def _p3p_poses(frame: CubeFrame, obj: np.ndarray, img: np.ndarray) -> list:
    """The P3P poses ``[(R, T)]`` of three correspondences that put the phantom between source and detector."""
    out = []
    for rvec, tvec in zip(*p3p(obj, img, frame.K)):
        R, T = pose_from_cv(rvec, tvec)
        # the phantom must lie in front of the source, between it and the detector
        z = (frame.phantom.xyz_mm.mean(0) - T) @ R[2]
        if 0 < z < frame.iop[2] * frame.params.pixel_pitch_mm:
            out.append((R, T))
    return out
