"""Frame and table readers and writers: the only place where stages' data meets files.

- :mod:`~fluorocal.stages.io.frames`: the registry of frame formats (DICOM, video, stills) and
  :func:`read_frames`, :func:`probe_frames`, :func:`write_frames_like`, each one loop over it;
  the formats themselves in :mod:`~fluorocal.stages.io.dicom`, :mod:`~fluorocal.stages.io.video`
  and :mod:`~fluorocal.stages.io.still`.
- :mod:`~fluorocal.stages.io.tables`: one schema per CSV table, :func:`read_table` and :func:`write_table`.
- :mod:`~fluorocal.stages.io.atomic`: :func:`atomic_write` and the one PNG writer :func:`write_png`.
- :mod:`~fluorocal.stages.io.names`: file names as OpenImageIO and OpenCV open them, under any locale.
"""

from fluorocal.stages.io.atomic import atomic_write, write_png
from fluorocal.stages.io.dicom import write_dicom
from fluorocal.stages.io.frames import (
    DICOM_SUFFIXES,
    FORMATS,
    VIDEO_SUFFIXES,
    FrameFormat,
    frame_format,
    open_stored,
    probe_frames,
    read_frames,
    series_of,
    write_frames_like,
    write_stored_like,
)
from fluorocal.stages.io.pixels import Derivation, StoredFrames
from fluorocal.stages.io.still import write_still
from fluorocal.stages.io.tables import (
    DETECTIONS,
    LABELS,
    OBJECT_POINTS,
    OBSERVATIONS,
    PHANTOM,
    SEEDS,
    TABLES,
    Column,
    Table,
    check_finite,
    columns_of,
    csv_text,
    read_phantom,
    read_seeds,
    read_table,
    write_csv,
    write_table,
)

__all__ = [
    "DETECTIONS",
    "DICOM_SUFFIXES",
    "FORMATS",
    "LABELS",
    "OBJECT_POINTS",
    "OBSERVATIONS",
    "PHANTOM",
    "SEEDS",
    "StoredFrames",
    "TABLES",
    "VIDEO_SUFFIXES",
    "Column",
    "Derivation",
    "FrameFormat",
    "Table",
    "atomic_write",
    "check_finite",
    "columns_of",
    "csv_text",
    "frame_format",
    "open_stored",
    "probe_frames",
    "read_frames",
    "read_phantom",
    "read_seeds",
    "read_table",
    "series_of",
    "write_csv",
    "write_dicom",
    "write_frames_like",
    "write_png",
    "write_still",
    "write_stored_like",
    "write_table",
]
