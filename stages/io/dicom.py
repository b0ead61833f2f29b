"""DICOM frames through pydicom: single and multi-frame, signed or not, any rescale, MONOCHROME1 or 2.

One writer, :func:`write_dicom`, saves every DICOM file fluorocal makes (the
simulator's XA frames and the undistorted copies of a source data set).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.pixels import Derivation, StoredFrames, check_stored, checked_indices

NAME = "DICOM"
SUFFIXES = (".dcm", ".ima", ".dicom")
#: the tags copied into a frame's metadata when present
_META_TAGS = ("PixelSpacing", "ImagerPixelSpacing", "DistanceSourceToDetector", "FieldOfViewDimensions")
#: a derived instance's Derivation Code Sequence item: CID 7203 "Image Derivation" has no code for a
#: geometric or distortion correction; undistortion resamples the image onto the ideal pinhole grid
DERIVATION_CODE = ("113085", "DCM", "Spatial resampling")
#: the Purpose of Reference of its Source Image Sequence item (CID 7202 "Source Image Purposes of Reference")
SOURCE_PURPOSE_CODE = ("121322", "DCM", "Source image for image processing operation")
#: appended to a derived instance's Series Description (VR LO: 64 characters at most in all)
SERIES_MARK = "(undistorted)"
#: a derived series' SeriesNumber is its source's plus this (21 -> 1021), so a PACS lists it apart and beside it
SERIES_NUMBER_OFFSET = 1000


def sniff_content(head: bytes) -> bool:
    """A DICOM Part 10 file: ``DICM`` after the 128-byte preamble."""
    return head[128:132] == b"DICM"


def probe(path: Path) -> tuple[int, tuple[int, int]]:
    """Frame count and ``(width, height)`` px from the header (pixels not read)."""
    import pydicom

    ds = pydicom.dcmread(path, stop_before_pixels=True)
    return int(getattr(ds, "NumberOfFrames", 1) or 1), (int(ds.Columns), int(ds.Rows))


def positioner_angles_deg(path: Path) -> tuple[float | None, float | None]:
    """The C-arm's orbit and tilt in degrees from a DICOM header (pixels not read); None where not recorded.

    The orbit is ``PositionerPrimaryAngle`` (0018,1510), the tilt ``PositionerSecondaryAngle``
    (0018,1511). Both are None when either is absent or empty (many C-arms write the tags without a
    value), and when the positioner moved during a multi-frame acquisition (``PositionerMotion``
    ``DYNAMIC``): the file's angles are then not every frame's.

    Raises
    ------
    InputError
        The file is not readable DICOM, or an angle is not a number within ±180°.
    """
    import pydicom

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except (OSError, pydicom.errors.InvalidDicomError) as exc:
        raise InputError(f"{path}: cannot read the DICOM header ({exc})") from exc
    if str(ds.get("PositionerMotion", "")).upper() == "DYNAMIC" and int(ds.get("NumberOfFrames", 1) or 1) > 1:
        return None, None
    return _angles_of(ds, path) or (None, None)


def frame_angles_deg(path: Path) -> tuple:
    """Each frame's C-arm orbit and tilt in degrees from a DICOM header (pixels not read): ``(orbit, tilt)`` or None.

    In order of preference: the per-frame functional groups' Positioner Position Sequence (enhanced
    XA: ``PositionerPrimaryAngle``/``PositionerSecondaryAngle`` per frame), the shared functional
    groups' (one for every frame); for a rotational run (``PositionerMotion`` ``DYNAMIC``, several
    frames), the start angles (``PositionerPrimaryAngle``, ``PositionerSecondaryAngle``) moved by
    ``PositionerPrimaryAngleIncrement`` and ``PositionerSecondaryAngleIncrement`` as DICOM PS3.3
    C.8.7.5.1.3 defines them: one value is the average change per frame (frame ``k`` at
    ``start + k * increment``), one value per frame is each frame's offset from the start angles
    (frame ``k`` at ``start + increment[k]``; a vector of absolute angles with start angles 0 reads
    the same), or None per frame without them; else the file's angles (:func:`positioner_angles_deg`)
    for every frame.

    Raises
    ------
    InputError
        The file is not readable DICOM; an angle is not a number within ±180°; increments or per-frame
        items that are not one per frame (increments: one value, or one per frame).
    """
    import pydicom

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except (OSError, pydicom.errors.InvalidDicomError) as exc:
        raise InputError(f"{path}: cannot read the DICOM header ({exc})") from exc
    n = int(ds.get("NumberOfFrames", 1) or 1)
    per_frame = [_positioner(item, path) for item in ds.get("PerFrameFunctionalGroupsSequence") or []]
    if per_frame and any(a is not None for a in per_frame):
        if len(per_frame) != n:
            raise InputError(f"{path}: {len(per_frame)} per-frame functional group item(s) for {n} frame(s)")
        return tuple(per_frame)
    shared = [_positioner(item, path) for item in ds.get("SharedFunctionalGroupsSequence") or []]
    if shared and shared[0] is not None:
        return (shared[0],) * n
    if str(ds.get("PositionerMotion", "")).upper() == "DYNAMIC" and n > 1:
        start = _angles_of(ds, path)
        steps = [ds.get(f"Positioner{axis}AngleIncrement") for axis in ("Primary", "Secondary")]
        if start is None or any(step in (None, "") for step in steps):
            return (None,) * n
        columns = []
        for axis, step in zip(("Primary", "Secondary"), steps):
            values = [_angle(v, f"Positioner{axis}AngleIncrement", path, limit=360.0) for v in _values(step)]
            if len(values) not in (1, n):
                raise InputError(
                    f"{path}: Positioner{axis}AngleIncrement has {len(values)} values for {n} frames; "
                    "DICOM allows one (the change per frame) or one per frame (each frame's offset from the start)"
                )
            columns.append(values[0] * np.arange(n) if len(values) == 1 else np.asarray(values))
        out = [(start[0] + float(a), start[1] + float(b)) for a, b in zip(*columns)]
        for orbit, tilt in out:
            _angle(orbit, "PositionerPrimaryAngle + increments", path)
            _angle(tilt, "PositionerSecondaryAngle + increments", path)
        return tuple(out)
    return (_angles_of(ds, path),) * n


def _values(value) -> list:
    from pydicom.multival import MultiValue

    return list(value) if isinstance(value, (list, tuple, MultiValue)) else [value]


def _positioner(item, path: Path):
    """``(orbit, tilt)`` of a functional group item's Positioner Position Sequence, or None without one."""
    sequence = item.get("PositionerPositionSequence") or []
    return _angles_of(sequence[0], path) if sequence else None


def _angles_of(ds, path: Path):
    """``(PositionerPrimaryAngle, PositionerSecondaryAngle)`` of a data set (or item), None when either is empty."""
    angles = []
    for tag in ("PositionerPrimaryAngle", "PositionerSecondaryAngle"):
        value = ds.get(tag)
        if value is None or value == "":
            return None
        angles.append(_angle(value, tag, path))
    return angles[0], angles[1]


def _angle(value, tag: str, path: Path, limit: float = 180.0) -> float:
    """``value`` as degrees within ``±limit`` (an angle's 180; an increment, a change or an offset, a turn's 360)."""
    try:
        angle = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {tag} must be one number (degrees); got {value!r}") from None
    if not np.isfinite(angle) or abs(angle) > limit:
        raise InputError(f"{path}: {tag} must be within -{limit:g}..{limit:g} degrees; got {angle:g}")
    return angle


def read(path: Path, indices: list[int] | None = None) -> list[Radiograph]:
    """Frames ``indices`` (every frame when None) as displayed, larger = brighter (:func:`display`), float32.

    The stored frames are :func:`open_stored`'s, the reader ``undistort`` uses: only the frames
    ``indices`` are decoded, in the order given.
    """
    import pydicom

    ds = pydicom.dcmread(path, stop_before_pixels=True)
    n_frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
    wanted = list(range(n_frames)) if indices is None else checked_indices(path, indices, n_frames)
    meta = _meta(ds)
    frames = _decoded(path, ds, wanted)
    return [Radiograph(display(f, ds), _bits_stored(ds), str(path), i, meta) for i, f in zip(wanted, frames)]


def display(stored: np.ndarray, ds) -> np.ndarray:
    """A stored frame as displayed through its modality LUT and photometric, in stored steps above black, float32.

    The modality LUT (RescaleSlope, RescaleIntercept) is affine, so the displayed value is an affine
    function of ``stored - darkest`` where ``darkest`` is the stored value displayed darkest (the
    smallest the stored bits hold, signed or not; the largest for a negative slope or MONOCHROME1).
    That difference, ``0 .. 2**BitsStored - 1`` larger = brighter, is the frame every command
    detects on: a frame reads the same whatever rescale or sign its file stores it with.

    Examples
    --------
    >>> from pydicom.dataset import Dataset
    >>> ds = Dataset()
    >>> ds.BitsStored, ds.PixelRepresentation, ds.RescaleSlope, ds.RescaleIntercept = 12, 1, 2, -1000
    >>> display(np.array([[-2048, 0, 2047]], np.int16), ds)
    array([[   0., 2048., 4095.]], dtype=float32)
    """
    low, high = stored_range(ds)
    brighter = (_slope(ds) > 0) != (str(ds.get("PhotometricInterpretation", "MONOCHROME2")) == "MONOCHROME1")
    values = stored.astype(np.float32)
    return values - low if brighter else high - values


def stored_range(ds) -> tuple[int, int]:
    """The smallest and largest stored values of BitsStored bits, signed when PixelRepresentation is 1."""
    bits = _bits_stored(ds)
    return (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if _signed(ds) else (0, 2**bits - 1)


def _bits_stored(ds) -> int:
    return int(ds.get("BitsStored", ds.get("BitsAllocated", 16)) or 16)


def _signed(ds) -> bool:
    return int(ds.get("PixelRepresentation", 0) or 0) == 1


def _slope(ds) -> float:
    return float(ds.get("RescaleSlope", 1) or 1)


def _decoded(path: Path, ds, wanted: list[int]):
    """The stored frames ``wanted`` (2-D, native byte order, signed as stored), one at a time.

    Deflated files are inflated whole (pydicom decodes their frames from the data set only);
    every other transfer syntax decodes only the frames wanted.
    """
    import pydicom
    from pydicom.pixels import iter_pixels
    from pydicom.uid import DeflatedExplicitVRLittleEndian

    if not wanted:
        return
    if ds.file_meta.get("TransferSyntaxUID") == DeflatedExplicitVRLittleEndian:
        full = pydicom.dcmread(path).pixel_array
        frames = (full.reshape((-1,) + full.shape[-2:]) if full.ndim == 2 else full)[wanted]
    else:
        frames = iter_pixels(path, indices=wanted)
    for frame in frames:
        if frame.ndim != 2:
            raise InputError(f"{path}: expected monochrome frames; got pixel array of shape {frame.shape}")
        yield frame.astype(frame.dtype.newbyteorder("="), copy=False)


def _meta(ds) -> dict:
    import pydicom

    meta = {
        "format": "dicom",
        "modality": str(getattr(ds, "Modality", "")),
        "photometric": str(getattr(ds, "PhotometricInterpretation", "")),
    }
    for tag in _META_TAGS:
        if tag in ds and ds.data_element(tag).value not in (None, ""):
            value = ds.data_element(tag).value
            meta[tag] = (
                [float(v) for v in value]
                if isinstance(value, (list, tuple, pydicom.multival.MultiValue))
                else float(value)
            )
    return meta


def write_dicom(path: str | os.PathLike, ds, pixels: np.ndarray) -> None:
    """Save data set ``ds`` with ``pixels`` as its pixel data, uncompressed, atomically.

    The one DICOM writer: the transfer syntax becomes explicit VR little endian,
    the pixels are stored in the data set's ``BitsAllocated`` (8 or 16) and ``PixelRepresentation`` and, for
    more than one frame, ``NumberOfFrames`` is set. Every other tag is written as
    ``ds`` holds it.

    Parameters
    ----------
    path : path-like
        The file to write.
    ds : pydicom.Dataset
        The data set, with ``file_meta``, ``Rows``, ``Columns`` and ``BitsAllocated``.
    pixels : (H, W) or (F, H, W) integer ndarray
        Stored pixel values (before the modality LUT).

    Raises
    ------
    InputError
        ``pixels`` do not have the data set's ``Rows`` x ``Columns``.
    """
    from pydicom.uid import ExplicitVRLittleEndian

    pixels = np.asarray(pixels)
    if pixels.shape[-2:] != (int(ds.Rows), int(ds.Columns)) or pixels.ndim not in (2, 3):
        raise InputError(f"{path}: pixels must have shape ([F,] {ds.Rows}, {ds.Columns}); got {pixels.shape}")
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    frames = pixels[0] if pixels.ndim == 3 and len(pixels) == 1 else pixels
    ds.PixelData = np.ascontiguousarray(frames, dtype="<" + _stored_dtype(ds).str[1:]).tobytes()
    if frames.ndim == 3:
        ds.NumberOfFrames = len(frames)
    atomic_write(path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))


def _stored_dtype(ds) -> np.dtype:
    size = 2 if int(ds.get("BitsAllocated", 16)) == 16 else 1
    return np.dtype(f"{'i' if _signed(ds) else 'u'}{size}")


def open_stored(path: Path) -> StoredFrames:
    """The frames as stored (signed or not, native byte order), read one at a time.

    Monochrome frames of 8 or 16 bits allocated, signed or unsigned, any rescale: resampling the
    stored values and storing the result back keeps the file's representation, its modality LUT
    applying as before. The border is the stored value displayed darkest (:func:`display`).

    Raises
    ------
    InputError
        Colour or palette frames, or bits allocated other than 8 or 16, naming the file.
    """
    import pydicom

    ds = pydicom.dcmread(path, stop_before_pixels=True)
    photometric = str(ds.get("PhotometricInterpretation", "MONOCHROME2"))
    if photometric not in ("MONOCHROME1", "MONOCHROME2") or int(ds.get("SamplesPerPixel", 1)) != 1:
        raise InputError(f"{path}: DICOM {photometric} frames are not supported; only monochrome frames")
    if int(ds.get("BitsAllocated", 16)) not in (8, 16):
        bits = ds.get("BitsAllocated")
        raise InputError(f"{path}: DICOM frames of {bits} bits allocated are not supported (8 or 16)")
    low, high = stored_range(ds)
    black = float(low if display(np.array([low, high]), ds)[0] == 0 else high)
    size, dtype = (int(ds.Columns), int(ds.Rows)), _stored_dtype(ds)
    n_frames = int(ds.get("NumberOfFrames", 1) or 1)
    frames = (check_stored(path, f, dtype, size, i) for i, f in enumerate(_decoded(path, ds, list(range(n_frames)))))
    return StoredFrames(n_frames, size, dtype, black, frames)


def source_series(path: Path) -> str:
    """The series a DICOM file belongs to, from its header (pixels not read), after checking it can be referenced.

    Its SeriesInstanceUID; for a file without one, ``file:`` and its resolved path, so that it
    shares no other file's series. A derived copy names its source by SOP Class and Instance UID
    (:func:`derived_header`), so a file without them is refused here, before anything is written.

    Raises
    ------
    InputError
        The file is not readable DICOM, or lacks its SOP Class or Instance UID.
    """
    import pydicom

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True)
    except (OSError, pydicom.errors.InvalidDicomError) as exc:
        raise InputError(f"{path}: cannot read the DICOM header ({exc})") from exc
    for tag in ("SOPClassUID", "SOPInstanceUID"):
        if not _uid(ds, tag):
            raise InputError(f"{path}: DICOM file has no {tag}, so a derived copy cannot reference it")
    return str(ds.get("SeriesInstanceUID", "") or "").strip() or f"file:{Path(path).resolve()}"


def _uid(ds, tag: str) -> str:
    """``tag`` of the data set, else of its file meta (MediaStorage...), else the empty string."""
    value = ds.get(tag) or getattr(getattr(ds, "file_meta", None), "MediaStorage" + tag, None)
    return str(value or "").strip()


def _code(value: str, scheme: str, meaning: str):
    from pydicom.dataset import Dataset

    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = value, scheme, meaning
    return item


def derived_header(source: Path, derivation: Derivation | None = None):
    r"""``source``'s header (pixels not read) as that of a derived instance in a new series.

    A new SOP Instance UID and the ``derivation``'s Series Instance UID (a new one when it has
    none); ImageType ``DERIVED\SECONDARY`` followed by the source's further values; the Series
    Description marked ``(undistorted)``; a Source Image Sequence referencing the source instance
    (:data:`SOURCE_PURPOSE_CODE`); the Derivation Code Sequence (:data:`DERIVATION_CODE`) and the
    derivation's description; SeriesNumber the source's plus :data:`SERIES_NUMBER_OFFSET` (the offset
    alone when the source has none, the source's when the sum would not fit VR IS), and ContentDate and
    ContentTime the derivation's (``derivation.when``, else now). Every other attribute is the source's;
    the transfer syntax becomes explicit VR little endian.
    """
    from datetime import datetime

    import pydicom
    from pydicom.dataset import Dataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    derivation = derivation or Derivation()
    ds = pydicom.dcmread(source, stop_before_pixels=True)
    reference = Dataset()
    reference.ReferencedSOPClassUID = _uid(ds, "SOPClassUID")
    reference.ReferencedSOPInstanceUID = _uid(ds, "SOPInstanceUID")
    reference.PurposeOfReferenceCodeSequence = [_code(*SOURCE_PURPOSE_CODE)]
    ds.SourceImageSequence = [reference]
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    ds.SeriesInstanceUID = derivation.series_uid or generate_uid()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    image_type = ds.get("ImageType") or []
    ds.ImageType = ["DERIVED", "SECONDARY"] + ([image_type] if isinstance(image_type, str) else list(image_type))[2:]
    series = str(ds.get("SeriesDescription", "") or "").strip()
    ds.SeriesDescription = f"{series[: 64 - len(SERIES_MARK) - 1]} {SERIES_MARK}" if series else SERIES_MARK
    ds.DerivationCodeSequence = [_code(*DERIVATION_CODE)]
    ds.DerivationDescription = derivation.description
    ds.SeriesNumber = derived_series_number(ds.get("SeriesNumber"))
    when = derivation.when or datetime.now()
    ds.ContentDate, ds.ContentTime = when.strftime("%Y%m%d"), when.strftime("%H%M%S.%f")
    return ds


def derived_series_number(source) -> int:
    """A derived series' SeriesNumber from its source's (an int, a DICOM IS, or None/empty).

    Examples
    --------
    >>> derived_series_number(21), derived_series_number(None), derived_series_number(2**31 - 10)
    (1021, 1000, 2147483638)
    """
    try:
        number = int(source)
    except (TypeError, ValueError):
        return SERIES_NUMBER_OFFSET
    return number + SERIES_NUMBER_OFFSET if number + SERIES_NUMBER_OFFSET < 2**31 else number


def write_stored(
    source: Path, frames: Iterable[np.ndarray], out_path: Path, n_frames: int, derivation: Derivation | None = None
) -> None:
    """Write ``n_frames`` stored frames, streamed, as a derived copy of ``source``'s data set, atomically.

    The header is :func:`derived_header`'s; the frames are appended to the file one at a time as
    the pixel data, so memory holds one frame, not the file.

    Raises
    ------
    InputError
        A frame of another size or dtype than the source's, or a count other than ``n_frames``.
    """
    import pydicom

    ds = derived_header(source, derivation)
    if n_frames > 1 or "NumberOfFrames" in ds:
        ds.NumberOfFrames = n_frames
    size, dtype = (int(ds.Columns), int(ds.Rows)), _stored_dtype(ds)
    n_bytes = n_frames * size[0] * size[1] * dtype.itemsize
    # (7FE0,0010) in explicit VR little endian: tag, VR, 2 reserved bytes, 4-byte length (even)
    element = struct.pack("<HH2s2xI", 0x7FE0, 0x0010, b"OW" if dtype.itemsize == 2 else b"OB", n_bytes + n_bytes % 2)

    def _write(tmp):
        # dcmwrite, not save_as: it re-encodes a big-endian source's header as little endian
        pydicom.dcmwrite(tmp, ds, enforce_file_format=True, little_endian=True, implicit_vr=False)
        with open(tmp, "ab") as fh:
            fh.write(element)
            count = 0
            for frame in frames:
                fh.write(
                    np.ascontiguousarray(
                        check_stored(out_path, frame, dtype, size, count), dtype="<" + dtype.str[1:]
                    ).data
                )
                count += 1
            if count != n_frames:
                raise InputError(f"{out_path}: expected {n_frames} frame(s) like {source}; got {count}")
            fh.write(b"\0" * (n_bytes % 2))

    atomic_write(out_path, _write)


def write_like(source: Path, frames: list[Radiograph], out_path: Path, derivation: Derivation | None = None) -> None:
    """The source's data set with new pixel data, as a derived instance (:func:`derived_header`, :func:`write_stored`).

    The frames' values (as :func:`read` gives them) are stored back through the inverse of
    :func:`display`, rounded once and clipped to the stored bits.
    """
    import pydicom

    ds = pydicom.dcmread(source, stop_before_pixels=True)
    low, high = stored_range(ds)
    ramp = display(np.array([low, high]), ds)

    def stored(frame: Radiograph) -> np.ndarray:
        values = frame.image.astype(np.float64)
        values = low + values if ramp[0] == 0 else high - values
        return np.clip(np.rint(values), low, high).astype(_stored_dtype(ds))

    write_stored(source, map(stored, frames), out_path, len(frames), derivation)
