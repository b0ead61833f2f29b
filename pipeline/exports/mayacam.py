"""``--format mayacam``: XMALab / Autoscoper MayaCam 2.0 camera files, one per system and training exposure.

``mayacam_<system>_exposure<E>.txt`` (the phantom's pose differs per exposure, so each exposure is a
camera of its own in the phantom's frame), 17 lines as XMALab writes them and Autoscoper reads them::

    image size
    W,H

    camera matrix
    c,0,xp
    0,c,yp
    0,0,1

    rotation
    r11,r12,r13
    r21,r22,r23
    r31,r32,r33

    translation
    t1
    t2
    t3

OpenCV's convention: pixels 0-based with y down, ``x_cam = R X + t`` with X in mm (the phantom's
object space), so ``t = -R T`` with ``T`` the X-ray source. The cameras are pinholes: use them on
undistorted frames (``UNDISTORTION.txt``, written beside them, says how).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fluorocal.exports.common import require_geometry, write_text
from fluorocal.outputs import safe_name
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import quat_to_matrix

UNDISTORTION_NOTE = """\
The MayaCam files beside this note describe pinhole cameras: they hold for undistorted frames only.
Undistort the frames with this calibration first, either

  fluorocal undistort {calibration} FRAMES... --system NAME --out undistorted

or, outside fluorocal, with the OpenCV maps of `fluorocal export {calibration} --format opencv --out DIR`:

  fs = cv2.FileStorage("DIR/opencv_NAME.yml.gz", cv2.FILE_STORAGE_READ)
  h = int(fs.getNode("image_height").real())
  planes = [fs.getNode(f"map_{{a}}_bytes").mat().reshape(4, h, -1) for a in "xy"]  # the maps' byte planes
  map_x, map_y = (np.ascontiguousarray(p.transpose(1, 2, 0)).view("<f4")[..., 0] for p in planes)
  undistorted = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR)

and load the undistorted frames in XMALab (no undistortion grid) or Autoscoper.
"""


def _row(values) -> str:
    return ",".join(repr(float(v)) for v in values)


def mayacam_text(K, R, t, image_size_px) -> str:
    """The 17 lines of a MayaCam 2.0 file of camera matrix ``K``, rotation ``R``, translation ``t`` (mm)."""
    lines = ["image size", f"{int(image_size_px[0])},{int(image_size_px[1])}", "", "camera matrix"]
    lines += [_row(r) for r in K] + ["", "rotation"] + [_row(r) for r in R] + ["", "translation"]
    lines += [repr(float(v)) for v in t]
    return "\n".join(lines) + "\n"


def write(cal, out_dir: Path) -> list[str]:
    """Write a MayaCam 2.0 file per system and training exposure, and ``UNDISTORTION.txt``; return a line per file."""
    require_geometry(cal, "mayacam")
    if not cal.exposures:
        raise InputError(f"--format mayacam: {cal.path} holds no training exposure, so no pose to export")
    lines = []
    for system in cal.system_names:
        K = cal.intrinsics(system)["K"]
        size = cal.systems[system].image_size_px
        for exposure in sorted(cal.exposures):
            q, source_mm = cal.pose(system, exposure)
            R = quat_to_matrix(q)
            name = f"mayacam_{safe_name(system, what='system name')}_exposure{exposure}.txt"
            path = write_text(out_dir, name, mayacam_text(K, R, -(R @ np.asarray(source_mm)), size))
            lines.append(f"{path}: system {system}, exposure {exposure}")
    path = write_text(out_dir, "UNDISTORTION.txt", UNDISTORTION_NOTE.format(calibration=cal.path))
    lines.append(f"{path}: how to undistort frames for these pinhole cameras")
    return lines
