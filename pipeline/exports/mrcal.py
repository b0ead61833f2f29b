"""``--format mrcal``: an mrcal ``.cameramodel`` per system (and orientation), the field fitted by LENSMODEL_OPENCV8.

``<system>.cameramodel`` (``<system>_<orientation>.cameramodel`` per orientation where a system has
several): mrcal's text format, a Python-literal dict with ``lensmodel``, ``intrinsics``
``[fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6]``, ``extrinsics`` ``rt_cam_ref`` (rotation vector,
then translation in mm, from the reference system's camera frame: zero for the reference system)
and ``imagersize`` ``[W, H]``.

mrcal's LENSMODEL_OPENCV8 is OpenCV's rational model (``cv2.projectPoints`` with 8 coefficients).
It is fitted by least squares, all 12 intrinsics free, to where fluorocal's model puts the
measured pixel of each camera-frame direction, on a grid of pixels every
:data:`FIT_SPACING_PX` px over the field's support. A fluoroscope's distortion is not a lens's:
the fit's RMS and largest error (px) are stated in the file's header and in the export's output,
and where they matter, use the opencv export's maps (exact) instead. mrcal's splined model
(LENSMODEL_SPLINED_STEREOGRAPHIC) would follow the field more closely; it is not written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fluorocal.exports.common import orientations, require_geometry, write_text
from fluorocal.outputs import safe_name
from fluorocal.stages.geometry import quat_to_matrix

#: spacing of the fitted pixel grid, px
FIT_SPACING_PX = 8.0
LENSMODEL = "LENSMODEL_OPENCV8"


def _project(intrinsics: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Camera-frame points ``(N, 3)`` through LENSMODEL_OPENCV8 ``intrinsics`` (12,): ``(N, 2)`` px."""
    import cv2

    fx, fy, cx, cy = intrinsics[:4]
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    xy, _ = cv2.projectPoints(directions.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, intrinsics[4:])
    return xy.reshape(-1, 2)


def fit_opencv8(field, iop_px, image_size_px) -> tuple[np.ndarray, float, float, int]:
    """LENSMODEL_OPENCV8 intrinsics fitted to ``field`` with the interior orientation ``iop_px``.

    Returns
    -------
    intrinsics : (12,) float64 ndarray
        ``[fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6]``, px and unitless.
    rms_px, max_px : float
        The fit's RMS error per coordinate and its largest error (length), px, over the fitted grid.
    n_points : int
        How many grid pixels were fitted.
    """
    from scipy.optimize import least_squares

    w, h = image_size_px
    xs, ys = np.arange(0, w, FIT_SPACING_PX), np.arange(0, h, FIT_SPACING_PX)
    measured = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    supported = field.support_at(measured)
    if supported.any():
        measured = measured[supported]
    xp, yp, c = (float(v) for v in iop_px)
    ideal = field.undistort_points(measured)
    directions = np.column_stack([(ideal[:, 0] - xp) / c, (ideal[:, 1] - yp) / c, np.ones(len(ideal))])
    start = np.array([c, c, xp, yp] + [0.0] * 8)
    scale = np.array([c, c, w, h] + [1.0] * 8)

    def residual(u):
        return (_project(u * scale, directions) - measured).ravel()

    fitted = least_squares(residual, start / scale, method="lm", x_scale="jac").x * scale
    error = (_project(fitted, directions) - measured).reshape(-1, 2)
    return fitted, float(np.sqrt(np.mean(error**2))), float(np.linalg.norm(error, axis=1).max()), len(measured)


def cameramodel_text(intrinsics, rt_cam_ref, image_size_px, comments: list[str]) -> str:
    """The text of an mrcal ``.cameramodel``: ``#`` comment lines, then the dict as a Python literal."""
    body = [
        "{",
        f"    'lensmodel': '{LENSMODEL}',",
        f"    'intrinsics': [ {', '.join(repr(float(v)) for v in intrinsics)} ],",
        f"    'extrinsics': [ {', '.join(repr(float(v)) for v in rt_cam_ref)} ],",
        f"    'imagersize': [ {int(image_size_px[0])}, {int(image_size_px[1])} ],",
        "}",
    ]
    return "\n".join([f"# {c}" for c in comments] + body) + "\n"


def write(cal, out_dir: Path) -> list[str]:
    """Write a ``.cameramodel`` per system and orientation; return a line per file with the fit error."""
    from scipy.spatial.transform import Rotation

    require_geometry(cal, "mrcal")
    lines = []
    for system in cal.system_names:
        s = cal.systems[system]
        R = quat_to_matrix(s.rop_q)
        rt_cam_ref = np.concatenate([Rotation.from_matrix(R).as_rotvec(), -(R @ s.rop_source_mm)])
        for suffix, orientation in orientations(cal, system):
            fitted, rms, worst, n = fit_opencv8(cal.field(system, orientation), s.iop_px, s.image_size_px)
            where = f"system {system}" + ("" if orientation is None else f", orientation {orientation}")
            fit = f"fit to fluorocal's field: RMS {rms:.4f} px per coordinate, max {worst:.4f} px over {n} pixels"
            comments = [
                f"fluorocal export of {cal.path}: {where}",
                f"{LENSMODEL} {fit} (every {FIT_SPACING_PX:g} px where the field is supported)",
                "extrinsics: rt_cam_ref from the reference system's camera frame, mm",
            ]
            text = cameramodel_text(fitted, rt_cam_ref, s.image_size_px, comments)
            path = write_text(out_dir, f"{safe_name(system, what='system name')}{suffix}.cameramodel", text)
            lines.append(f"{path}: {where}, {LENSMODEL} {fit}")
    return lines
