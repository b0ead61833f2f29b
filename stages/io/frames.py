"""The registry of frame formats and the three calls that loop over it: read, probe, write-like.

Frames reach the stages as :class:`fluorocal.stages.artifacts.Radiograph`
(float32, larger = brighter) with their source bit depth and metadata beside them.

Each :class:`FrameFormat` entry knows its files by content (a signature in the
first bytes) and, failing that, by suffix; every file is first offered to
every entry by content, then by suffix, in the order of :data:`FORMATS`:

- DICOM (single and multi-frame) via pydicom (:mod:`fluorocal.stages.io.dicom`);
- video (``.avi``, ``.mp4``, ``.mov``, ``.mkv``, ...) via OpenCV (:mod:`fluorocal.stages.io.video`);
- TIFF, PNG and other stills via OpenImageIO (:mod:`fluorocal.stages.io.still`).

The registry is a tuple in this module: nothing read from disk chooses the code that runs.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import dicom, still, video
from fluorocal.stages.io.pixels import Derivation, StoredFrames

#: bytes read from the start of a file for the content sniffers (DICOM's signature ends at byte 132)
_HEAD_BYTES = 160


@dataclass(frozen=True)
class FrameFormat:
    """One frame format: how to recognise, probe, read and write back its files.

    Attributes
    ----------
    name : str
        Shown in messages.
    suffixes : tuple of str
        The usual suffixes (lower case, with the dot), shown in messages.
    accepts_suffix : callable (str) -> bool
        Whether a lower-case suffix is this format's: the fallback when no content sniffer claims a file.
    sniff_content : callable (bytes) -> bool
        Whether the first bytes of a file are this format's signature.
    probe : callable (Path) -> (int, (int, int))
        Frame count and ``(width, height)`` px, without decoding pixels where the format allows.
    read : callable (Path, list of int or None) -> list of Radiograph
        Every frame of the file, or only the frames of the given indices, in their order.
    write_like : callable (Path, list of Radiograph, Path, Derivation or None) -> None
        Write frames to the output path in the source's format, bit depth and metadata, atomically,
        recording the :class:`~fluorocal.stages.io.pixels.Derivation` where the format's header can.
    open_stored : callable (Path) -> StoredFrames
        The frames as stored, read one at a time: the one decoder, ``read`` displays its frames.
        Raises InputError (one line, naming the file and why) for a file whose frames cannot be
        written back as stored.
    write_stored : callable (Path, iterable of ndarray, Path, int, Derivation or None) -> None
        Write that many stored frames like the source as they come, atomically (the derivation as above).
    series : callable (Path) -> str, optional
        The series a file belongs to, from its header, for formats that group files in series
        (DICOM); a derived copy gets a new series per source series.
    """

    name: str
    suffixes: tuple[str, ...]
    accepts_suffix: Callable[[str], bool]
    sniff_content: Callable[[bytes], bool]
    probe: Callable[[Path], tuple[int, tuple[int, int]]]
    read: Callable[[Path, list[int] | None], list[Radiograph]]
    write_like: Callable[[Path, list[Radiograph], Path, Derivation | None], None]
    open_stored: Callable[[Path], StoredFrames]
    write_stored: Callable[[Path, Iterable[np.ndarray], Path, int, Derivation | None], None]
    series: Callable[[Path], str] | None = None

    def describe(self) -> str:
        """The name with its usual suffixes, for messages."""
        return f"{self.name} ({' '.join(self.suffixes)})"


DICOM = FrameFormat(
    dicom.NAME,
    dicom.SUFFIXES,
    dicom.SUFFIXES.__contains__,
    dicom.sniff_content,
    dicom.probe,
    dicom.read,
    dicom.write_like,
    dicom.open_stored,
    dicom.write_stored,
    dicom.source_series,
)
VIDEO = FrameFormat(
    video.NAME,
    video.SUFFIXES,
    video.SUFFIXES.__contains__,
    video.sniff_content,
    video.probe,
    video.read,
    video.write_like,
    video.open_stored,
    video.write_stored,
)
STILL = FrameFormat(
    still.NAME,
    still.COMMON_SUFFIXES,
    still.accepts_suffix,
    still.sniff_content,
    still.probe,
    still.read,
    still.write_like,
    still.open_stored,
    still.write_stored,
)

#: every supported frame format, in the order files are offered to them
FORMATS: tuple[FrameFormat, ...] = (DICOM, VIDEO, STILL)

#: kept for callers of the earlier module
VIDEO_SUFFIXES = set(video.SUFFIXES)
DICOM_SUFFIXES = set(dicom.SUFFIXES)


def frame_format(path: str | os.PathLike) -> FrameFormat:
    """The entry of :data:`FORMATS` that ``path`` belongs to: by content first, then by suffix.

    Raises
    ------
    InputError
        The file is missing, or no format claims it (the message lists the formats supported).
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a frame file")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(_HEAD_BYTES)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc})") from exc
    for fmt in FORMATS:
        if fmt.sniff_content(head):
            return fmt
    suffix = path.suffix.lower()
    for fmt in FORMATS:
        if fmt.accepts_suffix(suffix):
            return fmt
    raise InputError(
        f"{path}: not a frame format fluorocal reads; supported: {'; '.join(f.describe() for f in FORMATS)}"
    )


def _call(path: Path, what: Callable):
    """Run one format's reader, naming the file in whatever a library raises."""
    try:
        return what(path)
    except InputError as exc:
        if "\n" in str(exc):  # a library's message of several lines
            raise InputError(_one_line(str(exc))) from exc
        raise
    except Exception as exc:  # library errors differ by format; name the file
        raise InputError(f"{path}: cannot read as an image ({type(exc).__name__}: {_one_line(str(exc))})") from exc


def _one_line(text: str) -> str:
    r"""A message on one line: runs of whitespace, newlines included, become one space.

    Examples
    --------
    >>> _one_line("read error\n  PNG: truncated ")
    'read error PNG: truncated'
    """
    return " ".join(text.split())


def read_frames(path: str | os.PathLike, indices: Iterable[int] | None = None) -> list[Radiograph]:
    """Read every frame of an image, DICOM or video file, or only the frames ``indices`` (in that order).

    With ``indices``, the other frames of a multi-frame file are not kept in memory (DICOM and
    multi-page stills do not decode them at all; a video decodes the frames before the last one wanted).

    Raises
    ------
    InputError
        The file is missing, unreadable, of no supported format or holds no monochrome frame; an
        index beyond the file's frames.
    """
    path = Path(path)
    wanted = None if indices is None else list(indices)
    return _call(path, lambda p: frame_format(p).read(p, wanted))


def probe_frames(path: str | os.PathLike) -> tuple[int, tuple[int, int]]:
    """Number of frames in a file and their size ``(width, height)`` px, from the header where possible.

    Raises
    ------
    InputError
        The file is missing, unreadable or of no supported format.
    """
    path = Path(path)
    return _call(path, frame_format(path).probe)


def write_frames_like(
    source: str | os.PathLike,
    frames: list[Radiograph],
    out_path: str | os.PathLike,
    *,
    derivation: Derivation | None = None,
) -> None:
    """Write ``frames`` to ``out_path`` in the format, bit depth and metadata of ``source``, atomically.

    DICOM: the source's data set with new pixel data (uncompressed), as a derived instance of a new
    series that references the source and records ``derivation``
    (:func:`fluorocal.stages.io.dicom.derived_header`; None: a generic note and a series of its
    own). Stills: the same type via OpenImageIO. Video: the same container and codec via OpenCV.
    Neither has a header that records the derivation.

    Raises
    ------
    InputError
        ``source`` is of no supported format, or its format cannot hold the frames given.
    """
    source = Path(source)
    frame_format(source).write_like(source, frames, Path(out_path), derivation)


def open_stored(path: str | os.PathLike) -> StoredFrames:
    """The frames of a file as stored, read one at a time as they are iterated, for streaming.

    The frames :func:`read_frames` displays, in the file's own sample type, channels and
    photometric: what :func:`write_stored_like` writes back exactly (video: through its lossy codec).

    Raises
    ------
    InputError
        The file is missing, unreadable or of no supported format, or its frames cannot be written
        back as stored (frames that fail to decode raise while iterated, naming the file).
    """
    path = Path(path)
    stored = _call(path, frame_format(path).open_stored)
    return replace(stored, frames=_named(path, stored.frames))


def _named(path: Path, frames):
    """The frames, with whatever a library raises while decoding one naming the file."""
    iterator = iter(frames)
    while True:
        frame = _call(path, lambda _: next(iterator, None))
        if frame is None:
            return
        yield frame


def write_stored_like(
    source: str | os.PathLike,
    frames: Iterable[np.ndarray],
    out_path: str | os.PathLike,
    n_frames: int,
    *,
    derivation: Derivation | None = None,
) -> None:
    """Write ``n_frames`` stored frames (as :func:`open_stored` gives them) like ``source``, as they come, atomically.

    ``derivation`` as in :func:`write_frames_like`.

    Raises
    ------
    InputError
        ``source``'s frames cannot be written back as stored, a frame does not fit the source, or the
        count is not ``n_frames``.
    """
    source = Path(source)
    frame_format(source).write_stored(source, frames, Path(out_path), n_frames, derivation)


def series_of(path: str | os.PathLike) -> str | None:
    """The series ``path`` belongs to (DICOM: its SeriesInstanceUID); None for formats without series.

    Raises
    ------
    InputError
        The file is missing, unreadable or of no supported format, or a DICOM file a derived copy
        cannot reference (no SOP Class or Instance UID).
    """
    path = Path(path)
    fmt = frame_format(path)
    return None if fmt.series is None else _call(path, fmt.series)
