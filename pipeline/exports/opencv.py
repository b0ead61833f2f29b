"""``--format opencv``: OpenCV FileStorage YAML with the camera matrix, the image size and the ``cv2.remap`` maps.

One gzip-compressed file per system, ``opencv_<system>.yml.gz`` (``opencv_<system>_<orientation>.yml.gz``
per orientation where a system has several), read with ``cv2.FileStorage`` as it is::

    fs = cv2.FileStorage("opencv_A.yml.gz", cv2.FILE_STORAGE_READ)
    map_x, map_y = fs.getNode("map_x").mat(), fs.getNode("map_y").mat()
    ideal = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR)

The maps are :meth:`fluorocal.calibration.Calibration.remap_maps`' float32 maps, written exactly
in FileStorage's base64 form (the float32 bits themselves), so the result equals ``fluorocal undistort``.
The base64 form and the compression make the file a third of the size of the maps as YAML text
(7.9 MB against 27.9 MB for a 1024² frame) and take a quarter of the time to write.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
from fluorocal.exports.common import field_files, has_geometry
from fluorocal.outputs import inside
from fluorocal.stages.geometry import camera_matrix
from fluorocal.stages.io import atomic_write


def write(cal, out_dir: Path) -> list[str]:
    """Write one FileStorage YAML per system and orientation; return a line per file.

    A grid plate's calibration has no interior orientation: its files carry the nominal camera matrix
    (``camera_matrix_nominal: 1``) and are still complete for ``cv2.remap``.
    """
    nominal = not has_geometry(cal)
    # every name and map first: clashing names, or a field that moves pixels beyond the image, are refused
    # before anything is written
    maps = {
        (name, system, orientation): cal.remap_maps(system, orientation=orientation)
        for name, system, orientation in field_files(cal, "opencv", "opencv_", ".yml.gz")
    }
    lines = []
    for (name, system, orientation), (map_x, map_y) in maps.items():
        s = cal.systems[system]
        path = inside(out_dir, name)
        write_maps = partial(_write_yaml, system=system, orientation=orientation, size=s.image_size_px)
        atomic_write(path, partial(write_maps, K=camera_matrix(s.iop_px), nominal=nominal, map_x=map_x, map_y=map_y))
        lines.append(
            f"{path}: system {system}"
            + ("" if orientation is None else f", orientation {orientation}")
            + f", {s.image_size_px[0]}x{s.image_size_px[1]} px maps"
            + (", camera matrix nominal (a grid plate fixes none)" if nominal else "")
        )
    return lines


def _write_yaml(tmp, *, system, orientation, size, K, nominal, map_x, map_y) -> None:
    import cv2

    # the temporary name keeps the ".gz" suffix, from which FileStorage compresses
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML | cv2.FILE_STORAGE_BASE64)
    try:
        fs.write("system", system)
        fs.write("orientation", "" if orientation is None else orientation)
        fs.write("image_width", int(size[0]))
        fs.write("image_height", int(size[1]))
        fs.write("camera_matrix", np.asarray(K, dtype=np.float64))
        fs.write("camera_matrix_nominal", int(nominal))
        fs.write("map_x", np.ascontiguousarray(map_x, dtype=np.float32))
        fs.write("map_y", np.ascontiguousarray(map_y, dtype=np.float32))
    finally:
        fs.release()
