"""3D bead phantoms: one frame labelled from seeds, from its marker beads, or from another frame's pose."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.geometry import matrix_to_quat, quat_to_matrix
from fluorocal.stages.label.cube_frame import CubeFrame, make_cube_frame
from fluorocal.stages.label.detections import Detections
from fluorocal.stages.label.iterate import acceptable, iterate, rivals
from fluorocal.stages.label.labels import Labels, failed_labels
from fluorocal.stages.label.markers import marker_poses, pose_from_seeds
from fluorocal.stages.label.params import (
    STATUS_AMBIGUOUS,
    STATUS_LABELLED,
    STATUS_REJECTED,
    STATUS_UNMATCHED,
    LabelParams,
)
from fluorocal.stages.label.prior import label_from_prior

# a second pose hypothesis whose coarse score reaches this fraction of the best's is labelled too
_RIVAL_SCORE = 0.8


def label_cube(
    det: Detections, phantom: Phantom, params: LabelParams, iop: np.ndarray, prior_pose, turntable_axis=None
) -> Labels:
    """Label one frame of a 3D phantom from seeds, else from the markers and then from ``prior_pose``.

    See :func:`fluorocal.stages.label.label_beads`; ``turntable_axis`` (camera frame, optional) lets a
    frame that fails from the prior pose be searched over turns about it.
    """
    frame, det = make_cube_frame(det, phantom, params, iop)
    if frame is None:
        return failed_labels(det.valid, iop, f"only {int(det.valid.sum())} usable detections")
    groups = []  # (pose source, [(R, T), ...] best first, their coarse scores or None)
    if params.seeds:
        pose, why = pose_from_seeds(frame)
        if pose is None:
            return failed_labels(det.valid, iop, why, "seeds")
        groups.append(("seeds", [pose], None))
    else:
        poses, scores, why = marker_poses(frame)
        if poses:
            groups.append(("markers", poses, scores))
        if prior_pose is not None:
            q, T = prior_pose
            groups.append(("prior", [(quat_to_matrix(np.asarray(q, float)), np.asarray(T, float))], None))
        if not groups:
            return failed_labels(det.valid, iop, why, "markers")
    reason = "no pose hypothesis converged"
    for source, poses, scores in groups:
        if source == "prior":
            (best, why), refused = label_from_prior(frame, *poses[0], turntable_axis), False
        else:
            best, why, refused = _label_from_poses(frame, poses, scores)
        if refused:
            return failed_labels(det.valid, iop, why, source)
        if best is None:
            reason = why
            continue
        best["source"] = source
        return _labels_from_result(frame, best)
    return failed_labels(det.valid, iop, reason, groups[-1][0] if groups else "")


def _label_from_poses(frame: CubeFrame, poses: list, scores: list | None) -> tuple[dict | None, str, bool]:
    """The first acceptable labelling from ``poses`` (best first): ``(result, "", False)``, else ``(None, why, False)``.

    When the next pose's coarse score comes within ``_RIVAL_SCORE`` of the accepted one's and its
    labelling rivals it (:func:`fluorocal.stages.label.iterate.rivals`), the markers do not fix the
    pose: ``(None, reason, True)``, and the frame fails.
    """
    reason = "no pose hypothesis converged"
    for i in range(len(poses)):
        best = iterate(frame, *poses[i])
        ok, why = (False, "the labelling diverged") if best is None else acceptable(frame, best)
        if ok:
            break
        reason = why
    else:
        return None, reason, False
    # a distinct pose that explains the detections about as well means the markers do not fix the pose
    rival_start = scores is not None and i + 1 < len(poses) and scores[i + 1] >= _RIVAL_SCORE * scores[i]
    rival = iterate(frame, *poses[i + 1]) if rival_start else None
    if rival is not None and acceptable(frame, rival)[0] and rivals(best, rival):
        if rival["n_labelled"] > best["n_labelled"]:
            best, rival = rival, best
        why = f"two poses explain the frame about equally well ({best['n_labelled']} vs {rival['n_labelled']} labels)"
        return None, why, True
    return best, "", False


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
    )
