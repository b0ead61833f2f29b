"""Geometry shared by the stages: pixel conventions, quaternions, the collinearity equation.

Conventions (docs/concepts.md, "Conventions"):

- Pixel coordinates ``(x, y)``: x = column to the right, y = row downward, the
  centre of the top-left pixel is ``(0, 0)``. Arrays of points have shape
  ``(N, 2)`` with columns ``(x, y)``; images are indexed ``img[y, x]``.
- Object space in mm, right-handed. Camera frame: z along the viewing
  direction (source -> detector), x and y parallel to the image axes.
- A pose is ``(q, T)``: ``q = (w, x, y, z)`` a unit quaternion rotating
  object-space vectors into the camera frame, ``T`` the X-ray source (the
  perspective centre) in object space, so ``p_cam = R(q) (P - T)``.
- Interior orientation ``iop = (xp, yp, c)`` in px; the ideal (pinhole)
  projection is ``x = xp + c * p_x / p_z``, ``y = yp + c * p_y / p_z``.
- Distortion: a correction ``Δ`` on measured coordinates,
  ``ideal = measured - Δ(measured)``.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.errors import ShapeError


def rc_to_xy(points_rc: np.ndarray) -> np.ndarray:
    """Swap ``(row, col)`` columns into ``(x, y)``; the inverse of :func:`xy_to_rc`.

    Parameters
    ----------
    points_rc : (N, 2) ndarray
        Points as ``(row, col)``, for example from scikit-image.

    Returns
    -------
    points_xy : (N, 2) float64 ndarray, px
    """
    points_rc = np.asarray(points_rc, dtype=np.float64).reshape(-1, 2)
    return points_rc[:, ::-1].copy()


def xy_to_rc(points_xy: np.ndarray) -> np.ndarray:
    """Swap ``(x, y)`` columns into ``(row, col)``."""
    return rc_to_xy(points_xy)


def check_points(name: str, points: np.ndarray, dim: int) -> np.ndarray:
    """Return ``points`` as float64 of shape ``(N, dim)`` or raise naming ``name``."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ShapeError(f"{name} must have shape (N, {dim}); got {arr.shape}")
    return arr


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``(..., 4)`` with ``w >= 0``."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` ``(w, x, y, z)``."""
    q = quat_normalize(q)
    w, x, y, z = np.moveaxis(q, -1, 0)
    # shape (..., 3, 3)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``(..., 4)`` of rotation matrices ``(..., 3, 3)``."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    return quat_normalize(wxyz.reshape(R.shape[:-2] + (4,)))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (apply ``b`` first, then ``a``)."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def rotvec_to_quat(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) ``(..., 4)`` of rotation vectors ``(..., 3)`` (axis * angle, rad)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle -> 1/2 as angle -> 0
    scale = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5)
    return np.concatenate([np.cos(half), rotvec * scale], axis=-1)


def camera_matrix(iop_px) -> np.ndarray:
    """OpenCV's camera matrix ``K`` (3, 3) of the interior orientation ``(xp, yp, c)`` px.

    Examples
    --------
    >>> camera_matrix([511.5, 511.5, 4000.0]).tolist()
    [[4000.0, 0.0, 511.5], [0.0, 4000.0, 511.5], [0.0, 0.0, 1.0]]
    """
    xp, yp, c = (float(v) for v in iop_px)
    return np.array([[c, 0.0, xp], [0.0, c, yp], [0.0, 0.0, 1.0]])


def iop_guess(image_size_px, source_image_distance_mm: float, pixel_pitch_mm: float) -> np.ndarray:
    """Start values ``(xp, yp, c)`` px: the principal point at the image centre, ``c = SID / pitch``.

    Examples
    --------
    >>> iop_guess((1024, 1024), 1100.0, 0.25).tolist()
    [511.5, 511.5, 4400.0]
    """
    width, height = image_size_px
    c = source_image_distance_mm / pixel_pitch_mm if pixel_pitch_mm > 0 else np.nan
    return np.array([(width - 1) / 2, (height - 1) / 2, c])


def to_camera(points_mm: np.ndarray, q: np.ndarray, source_mm: np.ndarray) -> np.ndarray:
    """Object points ``(N, 3)`` into the camera frame of pose ``(q, T)``: ``R(q) (P - T)``."""
    R = quat_to_matrix(q)
    return (np.asarray(points_mm, dtype=np.float64) - np.asarray(source_mm, dtype=np.float64)) @ R.T


def project(points_mm: np.ndarray, q: np.ndarray, source_mm: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """Ideal pinhole projection (the collinearity equation) of object points.

    Parameters
    ----------
    points_mm : (N, 3) float64 ndarray, mm
        Object-space points.
    q : (4,) float64 ndarray
        Unit quaternion ``(w, x, y, z)`` rotating object vectors into the camera frame.
    source_mm : (3,) float64 ndarray, mm
        X-ray source (perspective centre) in object space.
    iop : (3,) float64 ndarray, px
        ``(xp, yp, c)``.

    Returns
    -------
    points_xy : (N, 2) float64 ndarray, px
        Ideal (undistorted) image coordinates.

    Examples
    --------
    >>> project(np.array([[0.0, 0.0, 100.0]]), np.array([1.0, 0, 0, 0]), np.zeros(3), np.array([512.0, 512.0, 4000.0]))
    array([[512., 512.]])
    """
    p_cam = to_camera(check_points("points_mm", points_mm, 3), q, source_mm)
    xp, yp, c = np.asarray(iop, dtype=np.float64)
    return np.column_stack([xp + c * p_cam[:, 0] / p_cam[:, 2], yp + c * p_cam[:, 1] / p_cam[:, 2]])


def similarity_fit(
    src: np.ndarray, dst: np.ndarray, *, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares 7-parameter similarity ``dst ≈ s R src + t`` (Umeyama).

    Parameters
    ----------
    src, dst : (N, 3) float64 ndarray
        Corresponding points.
    with_scale : bool
        False fits the 6-parameter rigid transform (``s = 1``), for example
        when the scale of ``src`` is itself under test (default True).

    Returns
    -------
    scale : float
        1.0 when ``with_scale`` is False.
    R : (3, 3) float64 ndarray
    t : (3,) float64 ndarray
    """
    src = check_points("src", src, 3)
    dst = check_points("dst", dst, 3)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    # the least-squares rotation does not depend on the scale, so the rigid fit shares it
    scale = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean()) if with_scale else 1.0
    return scale, R, mu_d - scale * R @ mu_s


def homography_fit(src_xy: np.ndarray, dst_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Least-squares homography from ``src_xy`` to ``dst_xy`` (each ``(N, 2)``) and ``dst - H(src)``.

    OpenCV's normalised DLT refined by Levenberg–Marquardt on the transfer error (``cv2.findHomography``,
    no RANSAC). Returns ``(H (3, 3), residual (N, 2))``, or None when the points admit no homography
    (fewer than four, or degenerate).

    Examples
    --------
    >>> src = np.array([[0.0, 0], [1, 0], [0, 1], [1, 1], [0.5, 0.3]])
    >>> H, res = homography_fit(src, 2 * src + 3)
    >>> bool(np.abs(res).max() < 1e-6)
    True
    """
    import cv2

    src = np.asarray(src_xy, dtype=np.float64)
    dst = np.asarray(dst_xy, dtype=np.float64)
    if len(src) < 4:
        return None
    H, _ = cv2.findHomography(src, dst, 0)
    if H is None or not np.all(np.isfinite(H)):
        return None
    return H, dst - cv2.perspectiveTransform(src[None], H)[0]


def image_rays(
    ideal_xy_px: np.ndarray, iop_px: np.ndarray, q: np.ndarray, source_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays from the source through ideal (undistorted) image points, in the frame the pose is given in.

    Parameters
    ----------
    ideal_xy_px : (N, 2) float64 ndarray, px
    iop_px : (3,) float64 ndarray, px
        ``(xp, yp, c)``.
    q : (4,) float64 ndarray
        Rotation frame -> camera; ``(q, source_mm)`` is a pose (``p_cam = R(q) (P - T)``).
        For a biplanar rig frame: the ROP ``(rop_q, rop_source_mm)``.
    source_mm : (3,) float64 ndarray, mm
        The source (perspective centre) in that frame.

    Returns
    -------
    origin_mm : (3,) float64 ndarray, mm
    directions : (N, 3) float64 ndarray
        Unit vectors: the points are ``origin + λ d``, λ > 0.

    Examples
    --------
    >>> iop, q = np.array([512.0, 512.0, 1000.0]), np.array([1.0, 0, 0, 0])
    >>> o, d = image_rays(np.array([[612.0, 512.0]]), iop, q, np.zeros(3))
    >>> np.round(d * np.sqrt(1.01), 6)
    array([[0.1, 0. , 1. ]])
    """
    ideal = check_points("ideal_xy_px", ideal_xy_px, 2)
    xp, yp, c = np.asarray(iop_px, dtype=np.float64)
    d_cam = np.column_stack([(ideal[:, 0] - xp) / c, (ideal[:, 1] - yp) / c, np.ones(len(ideal))])
    d = d_cam @ quat_to_matrix(q)  # R^T d for each row
    return np.asarray(source_mm, dtype=np.float64), d / np.linalg.norm(d, axis=1, keepdims=True)


def intersect_rays(rays) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection of corresponding rays (the point nearest to all of them).

    Parameters
    ----------
    rays : sequence of (origin, directions)
        Per view, ``origin`` (3,) or (N, 3) mm and unit ``directions`` (N, 3),
        the N rays of the N points; at least two views.

    Returns
    -------
    xyz_mm : (N, 3) float64 ndarray, mm
        Minimises the sum of squared distances to the rays (for two rays: the
        midpoint of their common perpendicular).
    miss_mm : (N,) float64 ndarray, mm
        RMS distance of the point from its rays.

    Examples
    --------
    >>> x_axis, y_axis = np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    >>> xyz, miss = intersect_rays([(np.zeros(3), x_axis), (np.array([0.0, 0, 1]), y_axis)])
    >>> xyz, miss
    (array([[0. , 0. , 0.5]]), array([0.5]))
    """
    n = len(rays[0][1])
    A = np.zeros((n, 3, 3))
    b = np.zeros((n, 3))
    # projectors orthogonal to each ray, shape (N, 3, 3)
    projectors = [np.eye(3) - d[:, :, None] * d[:, None, :] for _, d in rays]
    for (origin, _), P in zip(rays, projectors):
        A += P
        b += np.einsum("nij,nj->ni", P, np.broadcast_to(origin, (n, 3)))
    xyz = np.linalg.solve(A, b[..., None])[..., 0]
    miss2 = [np.sum(np.einsum("nij,nj->ni", P, xyz - origin) ** 2, axis=1) for (origin, _), P in zip(rays, projectors)]
    return xyz, np.sqrt(np.mean(miss2, axis=0))
