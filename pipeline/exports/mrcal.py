"""``--format mrcal``: an mrcal ``.cameramodel`` per system (and orientation), the field as a splined model.

``<system>.cameramodel`` (``<system>_<orientation>.cameramodel`` per orientation where a system has
several): mrcal's text format, a Python-literal dict with ``lensmodel``
``LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx=.._Ny=.._fov_x_deg=..``, ``intrinsics`` (the core
``[fx, fy, cx, cy]``, then ``Δu_x, Δu_y`` of each control point, x fastest), ``extrinsics``
``rt_cam_ref`` (rotation vector, then translation in mm, from the reference system's camera frame:
zero for the reference system) and ``imagersize`` ``[W, H]``.

mrcal's splined stereographic model projects a camera-frame point ``p`` to
``q = f (u + Δu(u)) + c`` with ``u = 2 p_xy / (|p| + p_z)`` and ``Δu`` a cubic B-spline surface on
a regular grid of control points in ``u``, ``(Nx - 3) / (2 u_edge)`` segments per unit of ``u`` with
``u_edge = 2 tan(fov_x / 4)`` and index ``i = u · segments + (N - 1) / 2`` (mrcal's ``mrcal.c``).
The core is fluorocal's interior orientation (``f = c``, ``(cx, cy) = (xp, yp)``); the control points
are fitted by linear least squares to where fluorocal's model puts the measured pixel of each
camera-frame direction, on every :data:`FIT_SPACING_PX`-th pixel of the image, the spline spacing
half the field's node spacing. The fit's RMS and largest error (px), over the field's support and
over the whole image, are stated in the file's header and in the export's output.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from fluorocal.exports.common import field_files, require_geometry, write_text
from fluorocal.stages.geometry import quat_to_matrix

#: spacing of the fitted pixel grid, px
FIT_SPACING_PX = 4.0
#: the spline's knot spacing as a fraction of the field's node spacing (a bilinear field has kinks at its nodes)
KNOT_FRACTION = 0.5
#: ridge on the control points in the normal equations (a pixel's 16 weights sum to 1)
RIDGE = 1e-9
#: margin of the spline's extent beyond the image's directions (the edge patches stay inside the valid region)
EXTENT_MARGIN = 1.05


def lensmodel_name(nx: int, ny: int, fov_x_deg: int) -> str:
    """The mrcal name of a cubic splined stereographic model."""
    return f"LENSMODEL_SPLINED_STEREOGRAPHIC_order=3_Nx={nx}_Ny={ny}_fov_x_deg={fov_x_deg}"


def stereographic(directions: np.ndarray) -> np.ndarray:
    """The normalised stereographic projection of mrcal, ``u = 2 p_xy / (|p| + p_z)``, of ``(N, 3)`` points."""
    return 2.0 * directions[:, :2] / (np.linalg.norm(directions, axis=1) + directions[:, 2])[:, None]


def _layout(u: np.ndarray, knot_spacing_u: float) -> tuple[int, int, int, float]:
    """``(Nx, Ny, fov_x_deg, segments per u)`` of a cubic spline whose valid region holds every ``u`` ``(N, 2)``."""
    edge_x, edge_y = np.abs(u).max(axis=0) * EXTENT_MARGIN
    fov_x_deg = math.ceil(math.degrees(4.0 * math.atan(edge_x / 2.0)))  # mrcal's fov_x_deg is an integer
    u_edge = 2.0 * math.tan(math.radians(fov_x_deg) / 4.0)
    nx = 3 + max(1, math.ceil(2.0 * u_edge / knot_spacing_u))
    segments_per_u = (nx - 3) / (2.0 * u_edge)
    ny = 3 + max(1, math.ceil(2.0 * edge_y * segments_per_u))  # the y extent follows from the spacing
    return nx, ny, fov_x_deg, segments_per_u


def design(u: np.ndarray, nx: int, ny: int, segments_per_u: float):
    """Sparse ``(N, Nx·Ny)`` matrix of the cubic B-spline weights at ``u`` (column ``iy·Nx + ix``)."""
    from scipy.interpolate import BSpline
    from scipy.sparse import csr_matrix

    def basis(index, n):  # control point i centred at index i: knots at i - 2 .. i + 2
        return BSpline.design_matrix(index, np.arange(-2.0, n + 2.0), 3).tocsr()

    bx = basis(u[:, 0] * segments_per_u + (nx - 1) / 2.0, nx)
    by = basis(u[:, 1] * segments_per_u + (ny - 1) / 2.0, ny)
    n = len(u)
    # each row holds the 4 non-zero weights of each axis: their outer product is the surface's 16
    wx, cx = bx.data.reshape(n, 4), bx.indices.reshape(n, 4)
    wy, cy = by.data.reshape(n, 4), by.indices.reshape(n, 4)
    data = (wy[:, :, None] * wx[:, None, :]).reshape(n, 16)
    columns = (cy[:, :, None] * nx + cx[:, None, :]).reshape(n, 16)
    return csr_matrix((data.ravel(), columns.ravel(), np.arange(0, 16 * n + 1, 16)), shape=(n, nx * ny))


def fit_splined(field, iop_px, image_size_px) -> tuple[str, np.ndarray, dict]:
    """The splined stereographic model of ``field`` with the interior orientation ``iop_px``.

    Returns
    -------
    lensmodel : str
        Its mrcal name.
    intrinsics : (4 + 2 Nx Ny,) float64 ndarray
        ``[fx, fy, cx, cy, Δu_x, Δu_y, ...]``, control points with x fastest.
    errors : dict
        ``rms_px``, ``max_px`` over the supported pixels and ``rms_all_px``, ``max_all_px`` over
        the whole image (RMS per coordinate, max of the length), and ``n_pixels``.
    """
    from scipy.sparse import identity
    from scipy.sparse.linalg import factorized

    w, h = image_size_px
    xp, yp, c = (float(v) for v in iop_px)
    xs, ys = np.arange(0.0, w, FIT_SPACING_PX), np.arange(0.0, h, FIT_SPACING_PX)
    measured = np.stack(np.meshgrid(np.append(xs, w - 1.0), np.append(ys, h - 1.0)), axis=-1).reshape(-1, 2)
    ideal = field.undistort_points(measured)
    directions = np.column_stack([(ideal - [xp, yp]) / c, np.ones(len(ideal))])
    u = stereographic(directions)
    node_spacing_px = float(np.diff(field.x_nodes_px).mean())
    nx, ny, fov_x_deg, segments_per_u = _layout(u, KNOT_FRACTION * node_spacing_px / c)
    A = design(u, nx, ny, segments_per_u)
    target = (measured - [xp, yp]) / c - u  # Δu that puts each direction on its measured pixel
    # normal equations, banded (each pixel touches 4×4 control points); a light ridge holds the control
    # points no pixel reaches at zero, far below the weight of the pixels that do
    solve = factorized((A.T @ A + RIDGE * identity(A.shape[1])).tocsc())
    control = np.column_stack([solve(A.T @ target[:, k]) for k in (0, 1)])
    error = c * (u + A @ control) + [xp, yp] - measured
    supported = field.support_at(measured)
    inside = error[supported] if supported.any() else error
    errors = {
        "rms_px": float(np.sqrt(np.mean(inside**2))),
        "max_px": float(np.linalg.norm(inside, axis=1).max()),
        "rms_all_px": float(np.sqrt(np.mean(error**2))),
        "max_all_px": float(np.linalg.norm(error, axis=1).max()),
        "n_pixels": int(len(measured)),
    }
    intrinsics = np.concatenate([[c, c, xp, yp], control.ravel()])  # (Nx·Ny, 2) row-major: Δu_x, Δu_y per knot
    return lensmodel_name(nx, ny, fov_x_deg), intrinsics, errors


def cameramodel_text(lensmodel: str, intrinsics, rt_cam_ref, image_size_px, comments: list[str]) -> str:
    """The text of an mrcal ``.cameramodel``: ``#`` comment lines, then the dict as a Python literal."""
    body = [
        "{",
        f"    'lensmodel': '{lensmodel}',",
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
    for name, system, orientation in field_files(cal, "mrcal", "", ".cameramodel"):  # names checked before writing
        s = cal.systems[system]
        R = quat_to_matrix(s.rop_q)
        rt_cam_ref = np.concatenate([Rotation.from_matrix(R).as_rotvec(), -(R @ s.rop_source_mm)])
        lensmodel, intrinsics, e = fit_splined(cal.field(system, orientation), s.iop_px, s.image_size_px)
        where = f"system {system}" + ("" if orientation is None else f", orientation {orientation}")
        fit = (
            f"fit to fluorocal's field: RMS {e['rms_px']:.4f} px per coordinate, max {e['max_px']:.4f} px "
            f"where the field is supported; RMS {e['rms_all_px']:.4f} px, max {e['max_all_px']:.4f} px "
            "over the whole image"
        )
        comments = [
            f"fluorocal export of {cal.path}: {where}",
            f"{fit} ({e['n_pixels']} pixels, every {FIT_SPACING_PX:g} px)",
            "extrinsics: rt_cam_ref from the reference system's camera frame, mm",
        ]
        text = cameramodel_text(lensmodel, intrinsics, rt_cam_ref, s.image_size_px, comments)
        path = write_text(out_dir, name, text)
        lines.append(f"{path}: {where}, {lensmodel}, {fit}")
    return lines
