"""Debug overlays of the detect and centroid stages: a pure function from artifacts to an RGB image."""

from __future__ import annotations

import numpy as np

#: BGR colours (OpenCV order)
_ACCEPTED = (60, 220, 60)
_FAILED_FIT = (0, 165, 255)
_REJECTED = (60, 60, 255)
_FOV = (255, 160, 0)


def stretch_to_uint8(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Contrast-stretch an image to uint8 between its 0.5 and 99.5 percentiles (inside ``mask`` if given)."""
    values = image[mask > 0] if mask is not None and np.any(mask) else image
    lo, hi = np.percentile(values, [0.5, 99.5]) if values.size else (0.0, 1.0)
    scaled = (image.astype(np.float32) - lo) * (255.0 / max(float(hi - lo), 1e-6))
    return np.clip(scaled, 0, 255).astype(np.uint8)


def render_overlay(radiograph, candidates, centroids=None) -> np.ndarray:
    """Draw detections over a frame.

    Parameters
    ----------
    radiograph : stages.artifacts.Radiograph
    candidates : stages.detect.BeadCandidates
    centroids : stages.centroid.Centroids, optional
        When given, accepted beads are drawn as their fitted ellipses (green,
        orange where the fit failed, with its reason); otherwise as circles.

    Returns
    -------
    (H, W, 3) uint8 ndarray
        BGR image (as ``cv2.imwrite`` expects): the contrast-stretched frame,
        the field-of-view circle (blue), accepted beads (green) and rejected
        candidates (red, with their reason).
    """
    import cv2

    grey = stretch_to_uint8(radiograph.image)
    out = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    shift = 4  # draw with 1/16 px precision
    one = 1 << shift

    def fixed(v):
        return int(round(float(v) * one))

    cx, cy = candidates.fov_center_xy_px
    if candidates.fov_radius_px > 0:
        cv2.circle(out, (fixed(cx), fixed(cy)), fixed(candidates.fov_radius_px), _FOV, 1, cv2.LINE_AA, shift)
    font = cv2.FONT_HERSHEY_PLAIN
    for (x, y), r, why in zip(candidates.xy_px, candidates.radius_px, candidates.reason):
        if why:
            cv2.circle(out, (fixed(x), fixed(y)), fixed(max(r, 2.0)), _REJECTED, 1, cv2.LINE_AA, shift)
            cv2.putText(out, why, (int(x + r + 2), int(y + 4)), font, 0.8, _REJECTED, 1, cv2.LINE_AA)
        elif centroids is None:
            cv2.circle(out, (fixed(x), fixed(y)), fixed(r), _ACCEPTED, 1, cv2.LINE_AA, shift)
    if centroids is not None:
        for (x, y), a, b, angle, ok, why in zip(
            centroids.xy_px, centroids.major_px, centroids.minor_px, centroids.angle_rad, centroids.ok, centroids.reason
        ):
            colour = _ACCEPTED if ok else _FAILED_FIT
            if np.all(np.isfinite([x, y, a, b, angle])) and a > 0:
                cv2.ellipse(
                    out,
                    (fixed(x), fixed(y)),
                    (fixed(a), fixed(b)),
                    float(np.degrees(angle)),
                    0,
                    360,
                    colour,
                    1,
                    cv2.LINE_AA,
                    shift,
                )
                cv2.drawMarker(out, (int(round(x)), int(round(y))), colour, cv2.MARKER_CROSS, 3, 1)
            if not ok:
                cv2.putText(out, why, (int(x + a + 2), int(y + 4)), font, 0.8, colour, 1, cv2.LINE_AA)
    return out


def render_label_overlay(radiograph, centroids, labels):
    """Draw the labelling of one frame over it.

    Parameters
    ----------
    radiograph : stages.artifacts.Radiograph
    centroids : stages.centroid.Centroids
        The detections ``labels`` was computed from.
    labels : stages.label.Labels

    Returns
    -------
    (H, W, 3) uint8 ndarray
        BGR image: labelled detections green with their bead id, ambiguous orange, unmatched red,
        rejected grey; the labelling summary in the top-left corner.
    """
    import cv2
    import numpy as np
    from fluorocal.stages.label import STATUS_AMBIGUOUS, STATUS_LABELLED, STATUS_UNMATCHED

    out = cv2.cvtColor(stretch_to_uint8(radiograph.image), cv2.COLOR_GRAY2BGR)
    colours = {STATUS_LABELLED: (60, 220, 60), STATUS_AMBIGUOUS: (0, 165, 255), STATUS_UNMATCHED: (60, 60, 255)}
    ids = dict(zip(labels.det_index.tolist(), labels.bead_id.tolist()))
    font = cv2.FONT_HERSHEY_PLAIN
    for k, ((x, y), r, status) in enumerate(zip(centroids.xy_px, centroids.minor_px, labels.detection_status)):
        if not np.all(np.isfinite([x, y])):
            continue
        colour = colours.get(int(status), (150, 150, 150))
        radius = int(round(r)) if np.isfinite(r) and r > 0 else 4
        cv2.circle(out, (int(round(x)), int(round(y))), radius, colour, 1, cv2.LINE_AA)
        if k in ids:
            cv2.putText(out, str(ids[k]), (int(x + radius + 1), int(y + 4)), font, 0.8, colour, 1, cv2.LINE_AA)
    cv2.putText(out, labels.summary()[:120], (8, 16), font, 1.0, (255, 255, 255), 1, cv2.LINE_AA)
    return out
