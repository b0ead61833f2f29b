"""Video through OpenCV: every frame as 8-bit (or 16-bit) grey; written back with the source's codec and rate."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.names import native_name
from fluorocal.stages.io.pixels import Derivation, StoredFrames, check_stored, checked_indices

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

    cap = cv2.VideoCapture(native_name(path))
    if not cap.isOpened():
        raise InputError(f"{path}: cannot open as a video")
    return cap


def probe(path: Path) -> tuple[int, tuple[int, int]]:
    """Frame count and ``(width, height)`` px. Containers' frame counts are unreliable, so frames are counted.

    Each frame is grabbed (demuxed and decoded, not converted to an array) and none is kept.
    """
    import cv2

    cap = _open(path)
    try:
        n_frames = 0
        while cap.grab():
            n_frames += 1
        size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    finally:
        cap.release()
    if n_frames == 0:
        raise InputError(f"{path}: video holds no decodable frame")
    return n_frames, size


def _grey_frames(path: Path, last: int | None = None):
    """The decoded frames in grey (8 or 16 bits), one at a time, up to frame ``last`` (None: every one)."""
    import cv2

    cap = _open(path)
    try:
        index = 0
        while last is None or index <= last:
            ok, frame = cap.read()
            if not ok:
                return
            yield frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
            index += 1
    finally:
        cap.release()


def read(path: Path, indices: list[int] | None = None) -> list[Radiograph]:
    """Frames ``indices`` (every decodable frame when None), converted to grey, in the order given.

    Containers cannot seek to an exact frame reliably, so the file is read from its start up to
    the last frame wanted; only the frames wanted are kept.
    """
    wanted = None if indices is None else checked_indices(path, indices, None)
    keep = None if wanted is None else set(wanted)
    kept, index = {}, 0
    for index, grey in enumerate(_grey_frames(path, None if wanted is None else max(wanted, default=-1)), 1):
        if keep is None or index - 1 in keep:
            bits = 16 if grey.dtype == np.uint16 else 8
            kept[index - 1] = Radiograph(grey.astype(np.float32), bits, str(path), index - 1, {"format": "video"})
    if not kept and wanted is None:
        raise InputError(f"{path}: video holds no decodable frame")
    if wanted is None:
        return [kept[i] for i in sorted(kept)]
    missing = [i for i in wanted if i not in kept]
    if missing:
        raise InputError(f"{path}: holds {index} decodable frame(s); frame {missing[0]} asked for")
    return [kept[i] for i in wanted]


#: the codecs (FourCC as OpenCV reports it; 0: uncompressed) whose 8-bit grey frames OpenCV writes back sample
#: for sample, by test; the others (MJPEG, MPEG-4, H.264, and HuffYUV through OpenCV's colour conversion) do not
_EXACT_CODECS = {"ffv1": "FFV1", "mpng": "PNG", "\\x00" * 4: "uncompressed"}


def _fourcc(cap) -> int:
    import cv2

    return int(cap.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF


def _as_text(code: int) -> str:
    r"""A FourCC as text, its unprintable bytes escaped.

    Examples
    --------
    >>> _as_text(0x47504A4D), _as_text(0x18424752)
    ('MJPG', 'RGB\\x18')
    """
    return "".join(
        c if c.isprintable() and c.isascii() else f"\\x{ord(c):02x}"
        for c in code.to_bytes(4, "little").decode("latin-1")
    )


def _check_exact(path: Path, cap) -> None:
    """Refuse, in one line, a video whose frames cannot be written back exactly: a lossy codec or colour pixels.

    Raises
    ------
    InputError
        The codec is not one of :data:`_EXACT_CODECS`, or the pixels are not 8-bit grey (they would be
        written back in grey), naming the file and what to do.
    """
    import cv2

    codec, pixels = _as_text(_fourcc(cap)), _as_text(int(cap.get(cv2.CAP_PROP_CODEC_PIXEL_FORMAT)) & 0xFFFFFFFF)
    if codec.lower() in _EXACT_CODECS and pixels == "Y800":
        return
    raise InputError(
        f"{path}: video (codec {codec}, pixels {pixels}) cannot be written back exactly: only 8-bit grey FFV1, "
        "PNG or uncompressed video can; convert it to a multi-page TIFF or to such a video first "
        "(e.g. ffmpeg -i IN -c:v ffv1 -pix_fmt gray OUT.avi)"
    )


def open_stored(path: Path) -> StoredFrames:
    """The frames in 8-bit grey as decoded, one at a time (the count and size by a first pass, :func:`probe`).

    Raises
    ------
    InputError
        A video whose frames cannot be written back exactly (:func:`_check_exact`).
    """
    cap = _open(path)
    try:
        _check_exact(path, cap)
    finally:
        cap.release()
    n_frames, size = probe(path)
    frames = (check_stored(path, f, np.uint8, size, i) for i, f in enumerate(_grey_frames(path)))
    return StoredFrames(n_frames, size, np.dtype(np.uint8), 0.0, frames)


def write_stored(
    source: Path, frames: Iterable[np.ndarray], out_path: Path, n_frames: int, derivation: Derivation | None = None
) -> None:
    """The source's container, codec (FourCC) and frame rate, 8-bit grey frames written as they come.

    ``derivation`` is not recorded. Only a source whose frames are written back exactly is accepted.

    Raises
    ------
    InputError
        A source :func:`_check_exact` refuses, no writer for the codec, or a frame count other than ``n_frames``.
    """
    import cv2

    cap = _open(source)
    try:
        _check_exact(source, cap)
        fps = cap.get(cv2.CAP_PROP_FPS) or 25.0
        fourcc = _fourcc(cap)  # 0: uncompressed, as the source
        size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    finally:
        cap.release()

    def _write(tmp):
        writer = cv2.VideoWriter(native_name(tmp), fourcc, fps, size, isColor=False)
        if not writer.isOpened():
            raise InputError(f"{out_path}: cannot open a video writer for this codec")
        count = 0
        for frame in frames:
            writer.write(check_stored(out_path, frame, np.uint8, size, count))
            count += 1
        writer.release()
        if count != n_frames:
            raise InputError(f"{out_path}: expected {n_frames} frame(s) like {source}; got {count}")

    atomic_write(out_path, _write)


def write_like(source: Path, frames: list[Radiograph], out_path: Path, derivation: Derivation | None = None) -> None:
    """Grey frames as :func:`read` gives them, rounded to 8 bits, like :func:`write_stored`."""
    stored = (np.clip(np.rint(f.image), 0, 255).astype(np.uint8) for f in frames)
    write_stored(source, stored, out_path, len(frames), derivation)
