"""The pinhole camera of the labelling: camera matrix, poses to and from OpenCV, projection, P3P.

Poses are kept as ``(R, T)``: ``R`` (3, 3) rotates object vectors into the camera frame and ``T``
(mm) is the X-ray source in object space, so ``p_cam = R (P - T)`` (docs/concepts.md, "Conventions";
:mod:`fluorocal.stages.geometry` has the same model with quaternions). OpenCV's camera frame
(x right, y down, z forward) is ours; it maps object to camera as ``p = R P + t``, so ``t = -R T``
and ``T = -R^T t``.
"""

from __future__ import annotations

import numpy as np


def pose_to_cv(R: np.ndarray, source_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(rvec (3,), tvec (3,))`` of our pose ``(R, T)``."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rvec.reshape(3), -R @ np.asarray(source_mm, dtype=np.float64)


def pose_from_cv(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our pose ``(R (3, 3), T (3,) mm)`` of OpenCV's ``(rvec, tvec)``; the inverse of :func:`pose_to_cv`.

    Examples
    --------
    >>> R, T = pose_from_cv(np.zeros(3), np.array([0.0, 0.0, 500.0]))
    >>> T
    array([   0.,    0., -500.])
    """
    import cv2

    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))
    return R, -R.T @ np.asarray(tvec, dtype=np.float64).reshape(3)


def pose_batch_from_cv(rvecs, tvecs) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pose_from_cv` of many OpenCV poses at once: ``Rs (H, 3, 3)``, ``Ts (H, 3)`` mm."""
    from scipy.spatial.transform import Rotation

    Rs = Rotation.from_rotvec(np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)).as_matrix()
    return Rs, -np.einsum("hji,hj->hi", Rs, np.asarray(tvecs, dtype=np.float64).reshape(-1, 3))


def project_cam(p_cam: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """Pinhole image points ``(..., 2)`` px of camera-frame points ``(..., 3)``; NaN or inf behind the source.

    The projection of :func:`fluorocal.stages.geometry.project`, ``x = xp + c p_x / p_z``, on points
    already in the camera frame (the labelling keeps poses as rotation matrices).

    Examples
    --------
    >>> project_cam(np.array([[10.0, -5.0, 1000.0]]), np.array([512.0, 512.0, 4000.0]))
    array([[552., 492.]])
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return iop[:2] + iop[2] * p_cam[..., :2] / p_cam[..., 2:3]


def p3p(obj: np.ndarray, img: np.ndarray, K: np.ndarray) -> tuple[list, list]:
    """The OpenCV poses ``(rvecs, tvecs)`` (lists of (3,) arrays) that put three object points on three image points."""
    import cv2

    n, rvecs, tvecs = cv2.solveP3P(obj, img, K, None, flags=cv2.SOLVEPNP_AP3P)
    return [r.reshape(3) for r in rvecs[:n]], [t.reshape(3) for t in tvecs[:n]]
