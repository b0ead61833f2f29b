"""``--format dlt``: the 11 DLT coefficients of each system at each training exposure, as XMALab and DLTdv read them.

``dlt_exposure<E>.csv`` per training exposure: 11 rows (L1..L11), one column per system in the
calibration's order, no header; ``dlt_rms.csv`` states each column's reprojection RMS.

The DLT of a pinhole camera is exact: the coefficients are the normalised projection matrix
``K [R | -R T]`` of the calibration's interior orientation and pose, so they map object points (mm)
to *undistorted* coordinates (undistort frames or points with fluorocal first). Their image frame
is DLTdv's and XMALab's: ``u = x + 1`` (1-based columns) and ``v = H - y`` (1-based rows counted
from the bottom), with ``(x, y)`` fluorocal's pixel coordinates and ``H`` the image height::

    u = (L1 X + L2 Y + L3 Z + L4) / (L9 X + L10 Y + L11 Z + 1)
    v = (L5 X + L6 Y + L7 Z + L8) / (L9 X + L10 Y + L11 Z + 1)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fluorocal.exports.common import projection_matrix, require_geometry, tables_beside, write_text
from fluorocal.report import rms_px
from fluorocal.stages.errors import InputError


def to_dlt_frame(height_px: int) -> np.ndarray:
    """The 3×3 map of fluorocal's pixel ``(x, y, 1)`` onto DLTdv's ``(u, v, 1) = (x + 1, H - y, 1)``."""
    return np.array([[1.0, 0.0, 1.0], [0.0, -1.0, float(height_px)], [0.0, 0.0, 1.0]])


def coefficients(cal, system: str, exposure: int) -> np.ndarray:
    """The 11 DLT coefficients ``(11,)`` of ``system`` at a training ``exposure``, in DLTdv's image frame.

    Raises
    ------
    InputError
        The projection's ``P[2, 3]`` is zero (the object origin lies in the source's focal plane): the
        11-coefficient DLT, which fixes it at 1, cannot represent that pose.
    """
    height = cal.systems[system].image_size_px[1]
    P = to_dlt_frame(height) @ projection_matrix(cal, system, exposure)
    if abs(P[2, 3]) < 1e-12 * np.abs(P).max():
        raise InputError(
            f"system {system}, exposure {exposure}: the object origin lies in the source's plane; "
            "the 11-coefficient DLT cannot represent this pose"
        )
    return (P / P[2, 3]).ravel()[:11]


def project(L, xyz_mm) -> np.ndarray:
    """Object points ``(N, 3)`` mm through DLT coefficients ``L`` (11,): ``(N, 2)`` ``(u, v)`` in DLTdv's frame."""
    L = np.asarray(L, dtype=float)
    xyz1 = np.column_stack([np.asarray(xyz_mm, dtype=float), np.ones(len(xyz_mm))])
    P = np.append(L, 1.0).reshape(3, 4)
    uvw = xyz1 @ P.T
    return uvw[:, :2] / uvw[:, 2:]


def from_dlt_frame(uv, height_px: int) -> np.ndarray:
    """DLTdv's ``(u, v)`` ``(N, 2)`` back to fluorocal's pixel ``(x, y)``."""
    uv = np.asarray(uv, dtype=float)
    return np.column_stack([uv[:, 0] - 1.0, height_px - uv[:, 1]])


def reprojection_rms(cal, system: str, exposure: int, L, tables) -> tuple[int, float]:
    """``(n, RMS px per coordinate)`` of DLT ``L`` against ``system``'s undistorted inliers at ``exposure``."""
    points, obs = tables
    keep = (obs["system"] == system) & (obs["exposure"] == exposure) & obs["inlier"].astype(bool)
    index = {int(i): k for k, i in enumerate(points["id"])}
    ids = [int(i) for i in obs["id"][keep]]
    known = np.array([i in index for i in ids], dtype=bool)
    rows = [index[i] for i, ok in zip(ids, known) if ok]
    if not rows:
        return 0, float("nan")
    xyz = np.column_stack([points["x"], points["y"], points["z"]])[rows]
    measured = np.column_stack([obs["x"][keep], obs["y"][keep]])[known]
    ideal = cal.undistort_points(system, measured)
    height = cal.systems[system].image_size_px[1]
    return len(rows), rms_px(from_dlt_frame(project(L, xyz), height) - ideal)


def write(cal, out_dir: Path) -> list[str]:
    """Write ``dlt_exposure<E>.csv`` per training exposure and ``dlt_rms.csv``; return a line per file and RMS."""
    require_geometry(cal, "dlt")
    if not cal.exposures:
        raise InputError(f"--format dlt: {cal.path} holds no training exposure, so no pose to export")
    tables = tables_beside(cal)
    # every exposure's coefficients first: a pose the DLT cannot represent is refused before anything is written
    per_exposure = {e: [coefficients(cal, system, e) for system in cal.system_names] for e in sorted(cal.exposures)}
    # ... and their reprojection RMS: nothing is written until every figure is in hand
    rms = {
        (e, system): (0, float("nan")) if tables is None else reprojection_rms(cal, system, e, L, tables)
        for e, columns in per_exposure.items()
        for system, L in zip(cal.system_names, columns)
    }
    lines, rms_rows = [], ["exposure,system,column,n_points,rms_px"]
    for exposure, columns in per_exposure.items():
        text = "\n".join(",".join(repr(float(c[k])) for c in columns) for k in range(11)) + "\n"
        path = write_text(out_dir, f"dlt_exposure{exposure}.csv", text)
        lines.append(f"{path}: 11 DLT coefficients x {len(columns)} camera(s) ({', '.join(cal.system_names)})")
        for column, system in enumerate(cal.system_names, start=1):
            n, value = rms[(exposure, system)]
            rms_rows.append(f"{exposure},{system},{column},{n},{value:.6f}")
            if n:
                lines.append(f"  exposure {exposure}, system {system}: reprojection RMS {value:.4f} px over {n} beads")
    path = write_text(out_dir, "dlt_rms.csv", "\n".join(rms_rows) + "\n")
    if tables is None:
        lines.append(f"{path}: no RMS (object_points.csv and observations.csv are not beside the calibration)")
    else:
        lines.append(f"{path}: reprojection RMS per exposure and system, px per coordinate, undistorted inliers")
    return lines
