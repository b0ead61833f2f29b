"""The labelling iteration of a 3D phantom from a start pose, its pose solvers, and the acceptance tests.

From a start pose, every bead is projected through the pose and the assumed interior orientation plus a
low-order 2D polynomial correction, detections are assigned to projections within a gate, the pose
(RANSAC first, then least squares with the principal distance) and the correction are refined on the
assigned pairs, until the assignment stops changing (see :mod:`fluorocal.stages.label`).
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
from fluorocal.stages.geometry import camera_matrix
from fluorocal.stages.label.assign import ambiguous, assign, told_apart
from fluorocal.stages.label.camera import pose_from_cv, pose_to_cv, project_cam
from fluorocal.stages.label.correction import Correction, fit_correction, max_degree
from fluorocal.stages.label.cube_frame import CubeFrame, visible

# ... and if its labelling explains this fraction of the best's, with other labels, the frame is ambiguous
_RIVAL_LABELS = 0.95
# correction degree at each labelling iteration (then the configured degree)
_DEGREE_SCHEDULE = (0, 1, 3, 5)
# c is refined only when the labelled beads' depths spread by this fraction of their mean depth (std)
_MIN_DEPTH_SPREAD = 0.02
# ... in the first iterations after the coarse pose only (it settles in two)
_C_ITERATIONS = 2
# overlapping beads are told apart by detections within this many times the frame's RMS residual of their
# predictions: a 2D Gaussian residual exceeds 3 RMS with probability exp(-9), about 1e-4
_RESOLVE_RMS = 3.0
# ... and outlines closer than touching by this many times the frame's relative spread of bead sizes still overlap
_OUTLINE_SIGMAS = 2.0
# ... at most (sizes that scattered say little of the outlines; beads overlapping more have biased centroids)
_MAX_SLACK = 0.1


def iterate(frame: CubeFrame, R: np.ndarray, T: np.ndarray) -> dict | None:
    """Assign, refine pose and correction, repeat until the assignment is stable."""
    p = frame.params
    xyz = frame.phantom.xyz_mm
    scale = 0.5 * float(np.hypot(frame.width, frame.height))
    corr = Correction(frame.iop[:2].copy(), scale)
    previous, target_degree = None, 0
    for it in range(p.max_iterations):
        vis, ideal, diam = visible(frame, R, T)
        if len(vis) < 4:
            return None
        pred = corr.distort_points(ideal[vis])
        i_pred, i_det = assign(pred, p.gate_bead_diameters * diam[vis], frame.det_xy, frame.det_tree)
        key = (vis[i_pred].tobytes(), i_det.tobytes())
        if key == previous and corr.degree >= target_degree:
            break
        previous = key
        use = ~ambiguous(pred, diam[vis], p.ambiguity_bead_diameters)[i_pred]
        beads, dets = vis[i_pred[use]], i_det[use]
        if len(beads) < 6:
            return None
        obj = xyz[beads]
        measured = frame.det_xy[dets]
        if it == 0:
            R, T, inl = ransac_pose(frame, obj, measured, R, T)
            beads, dets, measured, obj = beads[inl], dets[inl], measured[inl], obj[inl]
        else:
            img = corr.undistort_points(measured, ideal[beads])
            if it <= _C_ITERATIONS:
                R, T, c = solve_pose_and_c(frame, obj, img, R, T)
            else:
                (R, T), c = solve_pose(frame, obj, img, R, T), frame.iop[2]
            if c != frame.iop[2]:
                iop = np.array([frame.iop[0], frame.iop[1], c])
                frame = replace(frame, iop=iop, K=camera_matrix(iop))
        ideal_now = project_cam((obj - T) @ R.T, frame.iop)
        target_degree = min(p.correction_degree, max_degree(len(beads)))
        degree = min(target_degree, _DEGREE_SCHEDULE[min(it, len(_DEGREE_SCHEDULE) - 1)])
        if degree > 0:
            corr = fit_correction(ideal_now, measured, degree, frame.iop[:2], scale)
        else:
            corr = Correction(frame.iop[:2], scale)

    # final labels: pairs within the final gate of the final prediction
    vis, ideal, diam = visible(frame, R, T)
    pred = corr.distort_points(ideal[vis])
    i_pred, i_det = assign(pred, p.gate_bead_diameters * diam[vis], frame.det_xy, frame.det_tree)
    resid = np.linalg.norm(pred[i_pred] - frame.det_xy[i_det], axis=1)
    # overlap is judged on the measured outlines where a bead was detected, on the prediction elsewhere
    where = pred.copy()
    where[i_pred] = frame.det_xy[i_det]
    app = apparent_diameters(corr, ideal[vis], pred, diam[vis])
    amb = ambiguous(where, app, p.ambiguity_bead_diameters)
    close = resid <= p.final_gate_bead_diameters * diam[vis][i_pred]
    if amb.any():
        amb &= ~_told_apart(frame, where, app, i_pred, i_det, resid, close & ~amb[i_pred])
    lab = close & ~amb[i_pred]
    ambig = amb[i_pred]
    beads, dets = vis[i_pred[lab]], i_det[lab]
    ideal_lab = ideal[beads]
    pin = np.linalg.norm(ideal_lab - frame.det_xy[dets], axis=1)
    evidence = size_evidence(frame, R, T, beads, dets)
    return {
        "R": R,
        "T": T,
        "iop": frame.iop,
        "bead": beads,
        "det": dets,
        "ambiguous_det": i_det[ambig],
        "n_labelled": len(beads),
        "n_ambiguous": int(ambig.sum()),
        "rms_px": float(np.sqrt(np.mean(pin**2))) if len(pin) else np.nan,
        "rms_corrected_px": float(np.sqrt(np.mean(resid[lab] ** 2))) if lab.any() else np.nan,
        "sizes_consistent": evidence is None or evidence[1] <= max(2, int(0.5 * evidence[2])),
        "size_evidence": evidence,
        "corr": corr,
    }


def _told_apart(
    frame: CubeFrame,
    where: np.ndarray,
    app: np.ndarray,
    i_pred: np.ndarray,
    i_det: np.ndarray,
    resid: np.ndarray,
    clean: np.ndarray,
) -> np.ndarray:
    """``(P,) bool``: beads judged overlapping whose own detections tell them apart (:func:`.assign.told_apart`).

    From the ``clean`` pairs (labelled, not overlapping): the tolerance is ``_RESOLVE_RMS`` times their RMS
    residual (the frame's centroid noise and unmodelled distortion, which a detection merging two beads
    exceeds), and the overlap test's slack is ``_OUTLINE_SIGMAS`` times the robust spread of their
    measured sizes over their apparent diameters (how precisely the frame shows a bead's outline; a
    separation estimated that close to touching does not tell whether the outlines overlap).
    """
    p = frame.params
    if clean.sum() < 6:
        return np.zeros(len(where), dtype=bool)
    tol = _RESOLVE_RMS * float(np.sqrt(np.mean(resid[clean] ** 2)))
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.log(frame.det.size_px[frame.det_idx[i_det[clean]]] / app[i_pred[clean]])
    log_ratio = log_ratio[np.isfinite(log_ratio)]
    spread = 1.4826 * float(np.median(np.abs(log_ratio - np.median(log_ratio)))) if len(log_ratio) >= 6 else 0.0
    fits = np.zeros(len(where), dtype=bool)
    fits[i_pred[resid <= tol]] = True
    return told_apart(where, app, p.ambiguity_bead_diameters, fits, tol, min(_OUTLINE_SIGMAS * spread, _MAX_SLACK))


def apparent_diameters(corr: Correction, ideal: np.ndarray, pred: np.ndarray, diam: np.ndarray) -> np.ndarray:
    """The pinhole's diameters ``diam`` scaled by the local magnification of ``corr`` (``pred = corr(ideal)``)."""
    h = 1.0
    jac = (
        np.stack([corr.distort_points(ideal + [h, 0.0]) - pred, corr.distort_points(ideal + [0.0, h]) - pred], axis=-1)
        / h
    )
    return diam * np.sqrt(np.abs(np.linalg.det(jac)))


def _pnp_arguments(frame: CubeFrame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray) -> tuple:
    """The positional arguments of OpenCV's PnP solvers, starting from the pose ``(R, T)``, no lens model."""
    rvec, tvec = pose_to_cv(R, T)
    return obj, img, frame.K, None, rvec.reshape(3, 1).copy(), tvec.reshape(3, 1).copy()


def solve_pose(frame: CubeFrame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray):
    """Refine a pose on correspondences (Levenberg-Marquardt from the current pose)."""
    import cv2

    if len(obj) < 6:
        return R, T
    ok, rvec, tvec = cv2.solvePnP(
        *_pnp_arguments(frame, obj, img, R, T), useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok or not np.all(np.isfinite(tvec)):
        return R, T
    return pose_from_cv(rvec, tvec)


def solve_pose_and_c(frame: CubeFrame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray):
    """Refine the pose and the principal distance ``c`` together (least squares from the current values).

    The configured source-image distance and pixel pitch are rough; a wrong ``c`` leaves a perspective
    error across the depth of a 3D phantom that the 2D correction cannot absorb. ``c`` is observable
    only through that depth, so it is refined only when the labelled beads span enough of it.

    Returns
    -------
    R : (3, 3) float64 ndarray
    T : (3,) float64 ndarray, mm
    c : float, px
    """
    from scipy.optimize import least_squares

    c0 = float(frame.iop[2])
    R, T = solve_pose(frame, obj, img, R, T)
    z = (obj - T) @ R[2]
    if len(obj) < 30 or np.std(z) < _MIN_DEPTH_SPREAD * np.mean(z):
        return R, T, c0
    rvec, tvec = pose_to_cv(R, T)
    x0 = np.concatenate([rvec, tvec, [0.0]])
    fit = least_squares(
        pose_c_residuals, x0, jac=pose_c_jacobian, method="lm", x_scale="jac", args=(obj, img, frame.iop)
    )
    c = c0 * float(np.exp(fit.x[6]))
    if not (fit.success and 0.5 * c0 < c < 2.0 * c0):
        return R, T, c0
    return (*pose_from_cv(fit.x[:3], fit.x[3:6]), c)


def pose_c_residuals(x: np.ndarray, obj: np.ndarray, img: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """``(2N,)``: the pinhole's misfit (px) of ``obj`` on ``img`` at ``x`` = OpenCV rvec, tvec, log(c / iop[2])."""
    import cv2

    Rx, _ = cv2.Rodrigues(x[:3])
    p_cam = obj @ Rx.T + x[3:6]
    return (project_cam(p_cam, np.array([iop[0], iop[1], iop[2] * np.exp(x[6])])) - img).ravel()


def pose_c_jacobian(x: np.ndarray, obj: np.ndarray, img: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """``(2N, 7)``: the derivatives of :func:`pose_c_residuals` by ``x`` (OpenCV's, by rvec, tvec and fx = fy = c)."""
    import cv2

    c = iop[2] * np.exp(x[6])
    K = np.array([[c, 0.0, iop[0]], [0.0, c, iop[1]], [0.0, 0.0, 1.0]])
    jac = cv2.projectPoints(obj, x[:3], x[3:6], K, None)[1]
    return np.column_stack([jac[:, :6], c * (jac[:, 6] + jac[:, 7])])


def ransac_pose(frame: CubeFrame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray):
    """Robust pose on a coarse assignment; returns the pose and the inlier mask."""
    import cv2

    if len(obj) < 6:
        return R, T, np.ones(len(obj), dtype=bool)
    thr = frame.params.ransac_threshold_bead_diameters * frame.diam_ref_px
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        *_pnp_arguments(frame, obj, img, R, T),
        useExtrinsicGuess=True,
        iterationsCount=frame.params.ransac_iterations,
        reprojectionError=thr,
        confidence=0.999,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    mask = np.zeros(len(obj), dtype=bool)
    if not ok or inliers is None or len(inliers) < 6:
        return R, T, np.ones(len(obj), dtype=bool)
    mask[inliers.ravel()] = True
    return (*pose_from_cv(rvec, tvec), mask)


def sizes_consistent(frame: CubeFrame, R: np.ndarray, T: np.ndarray, beads: np.ndarray, dets: np.ndarray) -> bool:
    """False if beads of distinct diameters (markers) were given detections of the wrong size — a wrong pose.

    See :func:`size_evidence`; one or two borderline sizes are tolerated (a wrong pose swaps many).
    Phantoms whose beads all have about one diameter pass unchecked.
    """
    evidence = size_evidence(frame, R, T, beads, dets)
    if evidence is None:
        return True
    return evidence[1] <= max(2, int(0.5 * evidence[2]))


def size_evidence(
    frame: CubeFrame, R: np.ndarray, T: np.ndarray, beads: np.ndarray, dets: np.ndarray
) -> tuple[int, int, int] | None:
    """How the sizes of labelled detections fit their beads: ``(n_fit, n_off, n_distinct)``, or None.

    The predicted apparent diameter ``c D / z`` of each labelled bead is compared with its detection's,
    after removing their median ratio (edge definition, blur and the guessed magnification scale both).
    A ratio off by more than half the log-spread of the phantom's diameters is off. ``n_distinct`` counts
    the labelled beads of a distinct diameter (markers), ``n_fit`` those of them whose size fits, and
    ``n_off`` every labelled bead whose size is off. None when the sizes say nothing: fewer than 3
    known sizes, or beads all of about one diameter.
    """
    d_mm = frame.bead_diam_mm[beads]
    measured = frame.det.size_px[frame.det_idx[dets]]
    known = np.isfinite(d_mm) & np.isfinite(measured) & (measured > 0)
    if known.sum() < 3:
        return None
    median, spread = _diameter_spread(frame.bead_diam_mm.tobytes())
    if spread < 1.15:
        return None
    z = (frame.phantom.xyz_mm[beads[known]] - T) @ R[2]
    log_ratio = np.log(measured[known] / (frame.iop[2] * d_mm[known] / z))
    off = np.abs(log_ratio - np.median(log_ratio)) > 0.5 * np.log(spread)
    distinct = np.abs(np.log(d_mm[known] / median)) > 0.5 * np.log(spread)
    return int((distinct & ~off).sum()), int(off.sum()), int(distinct.sum())


@functools.lru_cache(maxsize=4)
def _diameter_spread(diameters_mm: bytes) -> tuple[np.float64, float]:
    """The median bead diameter and the largest over it, of the phantom's diameters (float64 bytes, NaN ignored).

    Once per phantom: :func:`size_evidence` weighs every pose searched.
    """
    d = np.frombuffer(diameters_mm)
    median = np.nanmedian(d)
    return median, float(np.nanmax(d) / median)


def acceptable(frame: CubeFrame, result: dict) -> tuple[bool, str]:
    """``(True, "")`` if the labelling ``result`` of :func:`iterate` is sound, else ``(False, reason)``."""
    p = frame.params
    n_valid = len(frame.det_idx)
    n_lab = result["n_labelled"]
    if n_lab < p.min_labelled:
        return False, f"only {n_lab} beads labelled (min_labelled = {p.min_labelled})"
    explained = (n_lab + result["n_ambiguous"]) / max(n_valid, 1)
    if explained < p.min_labelled_fraction:
        return False, (
            f"only {explained:.0%} of {n_valid} detections explained by the phantom "
            f"(min_labelled_fraction = {p.min_labelled_fraction})"
        )
    limit = max(p.max_rms_floor_px, p.max_rms_bead_diameters * frame.diam_ref_px)
    if not result["rms_corrected_px"] <= limit:
        # right labels leave centroid noise and unmodelled distortion; chance matches spread over the gate
        rms = result["rms_corrected_px"]
        return False, f"labelling residuals of {rms:.2f} px RMS exceed {limit:.2f} px: chance matches, not a fit"
    if not result["sizes_consistent"]:
        return (
            False,
            "the labelling puts beads of one diameter on detections of another (markers misplaced): wrong pose",
        )
    return True, ""


def rivals(best: dict, other: dict) -> bool:
    """True if ``other`` labels about as many detections as ``best``, mostly with other ids."""
    if other["n_labelled"] < _RIVAL_LABELS * best["n_labelled"]:
        return False
    return agreement(best, other) < 0.9


def agreement(a: dict, b: dict) -> float:
    """Fraction of ``a``'s labelled detections that ``b`` gives the same bead."""
    if not len(a["det"]):
        return 0.0
    # b's bead per detection (-1: none); each labelling gives a detection one bead at most
    bead_of = np.full(max(int(a["det"].max()), int(b["det"].max(initial=-1))) + 1, -1)
    bead_of[b["det"]] = b["bead"]
    return float(np.mean(bead_of[a["det"]] == a["bead"]))
