"""``--format opencv``: OpenCV FileStorage YAML with the camera matrix, the image size and the ``cv2.remap`` maps.

One gzip-compressed file per system, ``opencv_<system>.yml.gz`` (``opencv_<system>_<orientation>.yml.gz``
per orientation where a system has several), read with ``cv2.FileStorage`` as it is. The maps are
:meth:`fluorocal.calibration.Calibration.remap_maps`' float32 maps, bit for bit, stored as byte planes
(``map_x_bytes``, ``map_y_bytes``): a ``(4 H, W)`` uint8 matrix whose rows ``k H`` to ``(k + 1) H - 1`` hold
byte ``k`` of each little-endian float32 (0 the least significant). Joining the planes gives the maps back
exactly, so the remap equals ``fluorocal undistort``::

    fs = cv2.FileStorage("opencv_A.yml.gz", cv2.FILE_STORAGE_READ)
    h = int(fs.getNode("image_height").real())
    planes = [fs.getNode(f"map_{a}_bytes").mat().reshape(4, h, -1) for a in "xy"]
    map_x, map_y = (np.ascontiguousarray(p.transpose(1, 2, 0)).view("<f4")[..., 0] for p in planes)
    ideal = cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR)

(in C++, ``cv::merge`` of the four planes' ``rowRange`` gives the ``CV_8UC4`` matrix whose memory is the
``CV_32FC1`` map on a little-endian machine). Why planes: a smooth map's high bytes repeat and compress to
almost nothing, while its low bytes are rounding noise; interleaved in each float, the noise spoils the
compression of the rest. ``benchmarks/exports.py`` prints each file's size beside that of the same maps as
float32 matrices (half of it for a real 1024² calibration). Fixed-point maps (``cv2.convertMaps``) would be
smaller still but are not exact: OpenCV 5 remaps uint8, uint16 and float32 frames through float32 maps
without rounding them to its 1/32 px table, and the results differ (``benchmarks/undistort.py``).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
from fluorocal.exports.common import field_files, has_geometry
from fluorocal.outputs import inside
from fluorocal.stages.geometry import camera_matrix
from fluorocal.stages.io import atomic_write

#: the file's own note on its maps (a YAML comment and the string node ``map_encoding``)
ENCODING = (
    "map_x_bytes, map_y_bytes: the float32 cv2.remap maps (H x W) as byte planes, a (4 H) x W uint8 matrix "
    "whose rows k H .. (k+1) H - 1 hold byte k of each little-endian float32 (k = 0 the least significant); "
    "numpy: map_x = np.ascontiguousarray(planes.reshape(4, H, W).transpose(1, 2, 0)).view('<f4')[..., 0] "
    "of planes = fs.getNode('map_x_bytes').mat(), likewise map_y; then cv2.remap(frame, map_x, map_y, "
    "cv2.INTER_LINEAR)"
)


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


def byte_planes(map_: np.ndarray) -> np.ndarray:
    """A ``(H, W)`` float32 map as its ``(4 H, W)`` uint8 byte planes, the least significant byte's first.

    Examples
    --------
    >>> m = np.array([[1.0, -2.5]], dtype=np.float32)
    >>> bool(np.array_equal(from_byte_planes(byte_planes(m)), m))
    True
    """
    h, w = map_.shape
    as_bytes = np.ascontiguousarray(map_, dtype="<f4").view(np.uint8).reshape(h, w, 4)
    return np.ascontiguousarray(as_bytes.transpose(2, 0, 1)).reshape(4 * h, w)


def from_byte_planes(planes: np.ndarray) -> np.ndarray:
    """The ``(H, W)`` float32 map of its ``(4 H, W)`` uint8 byte planes (:func:`byte_planes`), bit for bit."""
    h4, w = planes.shape
    joined = np.ascontiguousarray(np.asarray(planes, dtype=np.uint8).reshape(4, h4 // 4, w).transpose(1, 2, 0))
    return joined.view("<f4")[..., 0].astype(np.float32)


def read_maps(path) -> tuple[np.ndarray, np.ndarray]:
    """``map_x, map_y`` (float32, px) of an ``opencv_*.yml.gz`` file of this format, read with ``cv2.FileStorage``."""
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return from_byte_planes(fs.getNode("map_x_bytes").mat()), from_byte_planes(fs.getNode("map_y_bytes").mat())
    finally:
        fs.release()


def _write_yaml(tmp, *, system, orientation, size, K, nominal, map_x, map_y) -> None:
    import cv2

    # the temporary name keeps the ".gz" suffix, from which FileStorage compresses
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML | cv2.FILE_STORAGE_BASE64)
    try:
        fs.writeComment(ENCODING)
        fs.write("system", system)
        fs.write("orientation", "" if orientation is None else orientation)
        fs.write("image_width", int(size[0]))
        fs.write("image_height", int(size[1]))
        fs.write("camera_matrix", np.asarray(K, dtype=np.float64))
        fs.write("camera_matrix_nominal", int(nominal))
        fs.write("map_encoding", ENCODING)
        fs.write("map_x_bytes", byte_planes(map_x))
        fs.write("map_y_bytes", byte_planes(map_y))
    finally:
        fs.release()
