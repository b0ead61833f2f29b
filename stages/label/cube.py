"""3D bead phantoms: one frame labelled from seeds, from its marker beads, or from another frame's pose."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.geometry import matrix_to_quat, quat_to_matrix
from fluorocal.stages.label.camera import project_cam
from fluorocal.stages.label.correction import fit_correction, max_degree
from fluorocal.stages.label.cube_frame import CubeFrame, make_cube_frame
from fluorocal.stages.label.detections import Detections
from fluorocal.stages.label.iterate import acceptable, agreement, iterate
from fluorocal.stages.label.labels import Labels, failed_labels
from fluorocal.stages.label.markers import marker_poses, pose_from_seeds
from fluorocal.stages.label.motion import OrientationPrior
from fluorocal.stages.label.params import (
    STATUS_AMBIGUOUS,
    STATUS_LABELLED,
    STATUS_REJECTED,
    STATUS_UNMATCHED,
    LabelParams,
)
from fluorocal.stages.label.prior import label_from_prior
from fluorocal.stages.label.rivals import explains_most, settle

# a second pose hypothesis whose coarse score reaches this fraction of the best's is labelled too
_RIVAL_SCORE = 0.8
#: uncertainty (deg, 1 sigma) of a prior pose's orientation given without one
_PRIOR_SIGMA_DEG = 2.0


def label_cube(
    det: Detections,
    phantom: Phantom,
    params: LabelParams,
    iop: np.ndarray,
    prior_pose,
    orientation_prior: OrientationPrior | None = None,
    turn_search: bool = False,
    from_markers: bool = True,
    pool: bool = False,
    reference: Labels | None = None,
    search_around: bool = True,
) -> Labels:
    """Label one frame of a 3D phantom from seeds, else from the markers and then from ``prior_pose``.

    See :func:`fluorocal.stages.kinds.labelling.label_beads`. ``orientation_prior`` (optional) says how far the
    orientation of ``prior_pose`` may be off (by default ``_PRIOR_SIGMA_DEG`` about any axis);
    ``turn_search`` lets a frame that still fails be searched over turns about its axis.
    ``from_markers=False`` skips the markers (they failed before); ``pool=True`` weighs the markers'
    labellings together with those found from the prior (a frame whose markers gave a pose far from its
    neighbours'). ``reference`` (a labelled frame of the same system) lends its camera to the search:
    its principal distance and the distortion seen on its beads (:func:`_camera_of`). ``search_around=False``
    keeps a marker labelling that leaves much of the frame unexplained as it is, without searching the poses
    around it (:func:`_searched_around`): a sequence weighs it against its neighbours instead.
    """
    frame, det = make_cube_frame(det, phantom, params, iop)
    if frame is None:
        return failed_labels(det.valid, iop, f"only {int(det.valid.sum())} usable detections")
    if params.seeds:
        pose, why = pose_from_seeds(frame)
        if pose is None:
            return failed_labels(det.valid, iop, why, "seeds")
        found, why = _label_from_poses(frame, [pose], None)
        return _finish(frame, found[0] if found else None, why, "seeds")
    reasons, best, found = [], None, []
    if from_markers or prior_pose is None:
        poses, scores, why = marker_poses(frame)
        if poses:
            found, why = _label_from_poses(frame, poses, scores)
            if found and not (pool and prior_pose is not None):
                best, why = settle(frame, found)
                if search_around and best is not None and not explains_most(frame, best):
                    best, why = _searched_around(frame, best, found)
        if best is not None or prior_pose is None:
            return _finish(frame, best, why, "markers")
        reasons.append(f"from the markers: {why}")
    q, T = prior_pose
    R = quat_to_matrix(np.asarray(q, float))
    if orientation_prior is None:
        orientation_prior = OrientationPrior.isotropic(R, np.radians(_PRIOR_SIGMA_DEG))
    # where the prior pose puts the phantom's centre, in the camera frame, at the predicted depth if any
    p_centre = R @ (phantom.xyz_mm.mean(0) - np.asarray(T, float))
    if orientation_prior.depth_mm is not None:
        p_centre[2] = orientation_prior.depth_mm
    camera = None if reference is None else _camera_of(frame, reference)
    if camera is not None:
        # the depth goes with the principal distance the search sees it with
        p_centre[2] *= camera["iop"][2] / frame.iop[2]
    best, why = label_from_prior(
        frame, orientation_prior, p_centre, turn_search=turn_search, also=found if pool else (), camera=camera
    )
    reasons.append(why)
    source = "markers" if best is not None and any(best is f for f in found) else "prior"
    return _finish(frame, best, "; ".join(reasons), source)


def _searched_around(frame: CubeFrame, best: dict, found: list) -> tuple[dict | None, str]:
    """A marker labelling that leaves much of the frame unexplained, weighed against the poses around it.

    A marker pose a few degrees off converges with its polynomial correction bent to fit and passes every
    check (:func:`~fluorocal.stages.label.rivals.explains_most`); the truth then lies within a few degrees of
    it. Rotations within the prior search's region around it (``_PRIOR_SIGMA_DEG`` a standard deviation) are
    searched with the position free, and the marker labellings compete with what is found on their evidence
    alone: the region is centred on the suspect pose, so nearness to it decides nothing, and labellings the
    frame cannot tell apart leave it failed. The result keeps ``pose_source = "markers"``: in a sequence, one
    that still leaves much unexplained is weighed against its neighbours' prediction too.
    """
    R, T = best["R"], best["T"]
    p_centre = R @ (frame.phantom.xyz_mm.mean(0) - T)
    # its depth was found with its own principal distance; the search sees the frame with the assumed one
    p_centre[2] *= frame.iop[2] / best["iop"][2]
    prior = OrientationPrior.isotropic(R, np.radians(_PRIOR_SIGMA_DEG))
    around, why = label_from_prior(frame, prior, p_centre, also=found, decide=False)
    return (around, "") if around is not None else (None, f"around the markers' pose: {why}")


def _camera_of(frame: CubeFrame, labels: Labels) -> dict | None:
    """The camera of a labelled frame: its ``iop`` and the polynomial correction its beads show (None if too few).

    The correction is refitted (degree up to the labelling's own, 3 by default) on the labelled beads'
    pinhole projections through the frame's pose and their measured centres: the system's distortion,
    which a neighbouring frame of the same system shares.
    """
    if len(labels) < 6 or not labels.ok:
        return None
    iop = np.asarray(labels.iop, dtype=np.float64)
    ideal = project_cam((labels.object_xyz_mm - labels.source_mm) @ quat_to_matrix(labels.q).T, iop)
    degree = min(frame.params.correction_degree, max_degree(len(labels)))
    scale = 0.5 * float(np.hypot(frame.width, frame.height))
    return {"iop": iop, "corr": fit_correction(ideal, labels.xy_px, degree, iop[:2], scale)}


def _finish(frame: CubeFrame, best: dict | None, why: str, source: str) -> Labels:
    """The Labels of labelling ``best`` found from ``source``, or of the failure ``why``."""
    if best is None:
        return failed_labels(frame.det.valid, frame.iop, why, source)
    best["source"] = source
    return _labels_from_result(frame, best)


def _label_from_poses(frame: CubeFrame, poses: list, scores: list | None) -> tuple[list, str]:
    """Acceptable labellings from ``poses`` (best first): the first, and the next if it scores about as well.

    Returns the labellings (none: ``[]`` and the last failure's reason). The next pose is labelled too
    when its coarse score comes within ``_RIVAL_SCORE`` of the accepted one's: two poses that explain the
    detections about as well must both be weighed (:func:`~fluorocal.stages.label.rivals.settle`).
    """
    reason = "no pose hypothesis converged"
    for i in range(len(poses)):
        best = iterate(frame, *poses[i])
        ok, why = (False, "the labelling diverged") if best is None else acceptable(frame, best)
        if ok:
            break
        reason = why
    else:
        return [], reason
    found = [best]
    if scores is not None and i + 1 < len(poses) and scores[i + 1] >= _RIVAL_SCORE * scores[i]:
        rival = iterate(frame, *poses[i + 1])
        if rival is not None and acceptable(frame, rival)[0] and agreement(rival, best) < 0.9:
            found.append(rival)
    return found, ""


def _labels_from_result(frame: CubeFrame, res: dict) -> Labels:
    """The Labels artifact of an accepted labelling ``res`` (see :func:`fluorocal.stages.label.iterate.iterate`)."""
    det = frame.det
    status = np.where(det.valid, STATUS_UNMATCHED, STATUS_REJECTED).astype(np.int8)
    status[frame.det_idx[res["ambiguous_det"]]] = STATUS_AMBIGUOUS
    idx = frame.det_idx[res["det"]]
    status[idx] = STATUS_LABELLED
    order = np.argsort(idx)
    idx, beads = idx[order], res["bead"][order]
    q = matrix_to_quat(res["R"])
    return Labels(
        idx,
        frame.phantom.ids[beads],
        det.xy_px[idx],
        det.sigma_px[idx],
        frame.phantom.xyz_mm[beads],
        status,
        q,
        res["T"],
        res["iop"],
        n_labelled=len(idx),
        n_ambiguous=int((status == STATUS_AMBIGUOUS).sum()),
        n_unmatched=int((status == STATUS_UNMATCHED).sum()),
        rms_px=res["rms_px"],
        rms_corrected_px=res["rms_corrected_px"],
        ok=True,
        reason="",
        pose_source=res["source"],
        explains_most=explains_most(frame, res),
    )
