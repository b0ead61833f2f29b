"""Video through OpenCV: every frame as 8-bit (or 16-bit) grey; written back with the source's codec and rate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.pixels import Derivation, checked_indices

NAME = "video (OpenCV)"
SUFFIXES = (".avi", ".mp4", ".mov", ".mkv", ".m4v", ".wmv")
#: EBML (Matroska/WebM) and ASF (Windows Media) headers
_MAGIC = (b"\x1a\x45\xdf\xa3", b"\x30\x26\xb2\x75\x8e\x66\xcf\x11")


def sniff_content(head: bytes) -> bool:
    """AVI (RIFF....AVI), ISO media (MP4/MOV, ``ftyp`` box), Matroska or ASF, by signature."""
    return (
        (head[:4] == b"RIFF" and head[8:12] == b"AVI ")
        or head[4:8] in (b"ftyp", b"moov", b"mdat", b"wide")
        or head.startswith(_MAGIC)
    )


def _open(path: Path):
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"{path}: cannot open as a video")
    return cap


def probe(path: Path) -> tuple[int, tuple[int, int]]:
    """Frame count and ``(width, height)`` px. Containers' frame counts are unreliable, so frames are counted."""
    frames = read(path)
    return len(frames), (frames[0].shape[1], frames[0].shape[0])


def read(path: Path, indices: list[int] | None = None) -> list[Radiograph]:
    """Frames ``indices`` (every decodable frame when None), converted to grey, in the order given.

    Containers cannot seek to an exact frame reliably, so the file is read from its start up to
    the last frame wanted; only the frames wanted are kept.
    """
    import cv2

    wanted = None if indices is None else checked_indices(path, indices, None)
    keep = None if wanted is None else set(wanted)
    last = None if wanted is None else max(wanted, default=-1)
    cap = _open(path)
    kept = {}
    try:
        index = 0
        while last is None or index <= last:
            ok, frame = cap.read()
            if not ok:
                break
            if keep is None or index in keep:
                grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
                bits = 16 if grey.dtype == np.uint16 else 8
                kept[index] = Radiograph(grey.astype(np.float32), bits, str(path), index, {"format": "video"})
            index += 1
    finally:
        cap.release()
    if not kept and wanted is None:
        raise InputError(f"{path}: video holds no decodable frame")
    if wanted is None:
        return [kept[i] for i in sorted(kept)]
    missing = [i for i in wanted if i not in kept]
    if missing:
        raise InputError(f"{path}: holds {index} decodable frame(s); frame {missing[0]} asked for")
    return [kept[i] for i in wanted]


def write_like(source: Path, frames: list[Radiograph], out_path: Path, derivation: Derivation | None = None) -> None:
    """The source's container, codec (FourCC) and frame rate, 8-bit grey frames (``derivation`` is not recorded)."""
    import cv2

    cap = cv2.VideoCapture(str(source))
    fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
    fourcc = int(cap.get(cv2.CAP_PROP_FOURCC)) or cv2.VideoWriter_fourcc(*"MJPG")
    cap.release()
    h, w = frames[0].shape

    def _write(tmp):
        writer = cv2.VideoWriter(tmp, fourcc, fps, (w, h), isColor=False)
        if not writer.isOpened():
            raise InputError(f"{out_path}: cannot open a video writer for this codec")
        for f in frames:
            writer.write(np.clip(np.rint(f.image), 0, 255).astype(np.uint8))
        writer.release()

    atomic_write(out_path, _write)
