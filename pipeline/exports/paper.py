"""``--format paper``: the paper's photogrammetric text files ``.iop``, ``.eop``, ``.xyz`` and ``.pho``.

Whitespace-separated columns, ``#`` comment lines (the first names the columns). Image frame of the
paper: x = column, y = -row (y up), px, so the principal point is ``(xp, -yp)`` and an observation
``(x, -y)``; the camera frame has z pointing back towards the source, and the collinearity equation reads

    x - xp - Δx = -c · m1·(P - T) / m3·(P - T),    y - yp - Δy = -c · m2·(P - T) / m3·(P - T)

with ``M = R3(κ) R2(φ) R1(ω)`` (rows m1, m2, m3; R1(ω) = [[1, 0, 0], [0, cos ω, sin ω], [0, -sin ω, cos ω]],
likewise R2, R3), ``T = (Xc, Yc, Zc)`` the X-ray source in the phantom's object space (mm).

- ``calibration.iop``: ``system xp yp c sd_xp sd_yp sd_c width height`` (px);
- ``calibration.eop``: ``exposure system Xc Yc Zc omega phi kappa`` (mm, degrees), every system at
  every training exposure;
- ``calibration.xyz``: ``id X Y Z sd_X sd_Y sd_Z`` (mm), the adjusted object points;
- ``calibration.pho``: ``system exposure id x y sd_x sd_y rho dx dy inlier``: measured coordinates,
  their standard deviations and correlation, and the correction Δ (px).

``.xyz`` and ``.pho`` come from ``object_points.csv`` and ``observations.csv`` beside the calibration;
without them only ``.iop`` and ``.eop`` are written.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fluorocal.exports.common import require_geometry, tables_beside, write_text
from fluorocal.stages.geometry import quat_to_matrix

#: the paper's camera frame from fluorocal's: y and z flipped (y up, z towards the source)
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def opk_deg(M: np.ndarray) -> np.ndarray:
    """``(ω, φ, κ)`` in degrees of a rotation ``M = R3(κ) R2(φ) R1(ω)`` (photogrammetry's sequence).

    Examples
    --------
    >>> M = opk_matrix([10.0, -20.0, 30.0])
    >>> bool(np.isclose(M[2, 0], np.sin(np.radians(-20.0))))  # m31 = sin φ
    True
    >>> np.round(opk_deg(M), 9).tolist()
    [10.0, -20.0, 30.0]
    """
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(M.T).as_euler("XYZ", degrees=True)


def opk_matrix(omega_phi_kappa_deg) -> np.ndarray:
    """``M = R3(κ) R2(φ) R1(ω)`` of angles in degrees, the inverse of :func:`opk_deg`."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("XYZ", omega_phi_kappa_deg, degrees=True).as_matrix().T


def _num(v) -> str:
    return repr(float(v))


def _iop_text(cal) -> str:
    rows = ["# system xp yp c sd_xp sd_yp sd_c width height  (px; x = column, y = -row)"]
    for system in cal.system_names:
        s = cal.systems[system]
        xp, yp, c = s.iop_px
        sd = [v if np.isfinite(v) else float("nan") for v in s.iop_std_px]
        rows.append(" ".join([system, _num(xp), _num(-yp), _num(c), *map(_num, sd), *map(str, s.image_size_px)]))
    return "\n".join(rows) + "\n"


def _eop_text(cal) -> str:
    rows = ["# exposure system Xc Yc Zc omega phi kappa  (mm, degrees; M = R3(kappa) R2(phi) R1(omega))"]
    for exposure in sorted(cal.exposures):
        for system in cal.system_names:
            q, source_mm = cal.pose(system, exposure)
            angles = opk_deg(FLIP_YZ @ quat_to_matrix(q))
            rows.append(" ".join([str(exposure), system, *map(_num, source_mm), *map(_num, angles)]))
    return "\n".join(rows) + "\n"


def _xyz_text(points: dict) -> str:
    rows = ["# id X Y Z sd_X sd_Y sd_Z  (mm)"]
    for k in range(len(points["id"])):
        rows.append(
            " ".join([str(int(points["id"][k]))] + [_num(points[c][k]) for c in ("x", "y", "z", "sx", "sy", "sz")])
        )
    return "\n".join(rows) + "\n"


def _pho_text(obs: dict) -> str:
    rows = ["# system exposure id x y sd_x sd_y rho dx dy inlier  (px; x = column, y = -row)"]
    for k in range(len(obs["id"])):
        values = [obs["x"][k], -obs["y"][k], obs["sigma_x"][k], obs["sigma_y"][k], -obs["rho"][k]]
        values += [obs["delta_x"][k], -obs["delta_y"][k]]
        inlier = obs["inlier"][k]
        rows.append(
            " ".join([str(obs["system"][k]), str(int(obs["exposure"][k])), str(int(obs["id"][k]))])
            + " "
            + " ".join(map(_num, values))
            + f" {int(bool(inlier))}"
        )
    return "\n".join(rows) + "\n"


def write(cal, out_dir: Path) -> list[str]:
    """Write ``calibration.iop``, ``.eop`` and, when the tables are beside the calibration, ``.xyz`` and ``.pho``."""
    require_geometry(cal, "paper")
    tables = tables_beside(cal)
    written = [
        write_text(out_dir, "calibration.iop", _iop_text(cal)),
        write_text(out_dir, "calibration.eop", _eop_text(cal)),
    ]
    lines = [f"{written[0]}: interior orientation of {len(cal.system_names)} system(s)"]
    lines.append(f"{written[1]}: {len(cal.exposures)} exposure(s) x {len(cal.system_names)} system(s)")
    if tables is None:
        lines.append("no .xyz or .pho: object_points.csv and observations.csv are not beside the calibration")
        return lines
    points, obs = tables
    path = write_text(out_dir, "calibration.xyz", _xyz_text(points))
    lines.append(f"{path}: {len(points['id'])} object points")
    path = write_text(out_dir, "calibration.pho", _pho_text(obs))
    lines.append(f"{path}: {len(obs['id'])} observations")
    return lines
