"""DICOM frames through pydicom: single and multi-frame, modality LUT applied, MONOCHROME1 inverted.

One writer, :func:`write_dicom`, saves every DICOM file fluorocal makes (the
simulator's XA frames and the undistorted copies of a source data set).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError
from fluorocal.stages.io.atomic import atomic_write
from fluorocal.stages.io.pixels import to_source_dtype

NAME = "DICOM"
SUFFIXES = (".dcm", ".ima", ".dicom")
#: the tags copied into a frame's metadata when present
_META_TAGS = ("PixelSpacing", "ImagerPixelSpacing", "DistanceSourceToDetector", "FieldOfViewDimensions")


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
    angles = []
    for tag in ("PositionerPrimaryAngle", "PositionerSecondaryAngle"):
        value = ds.get(tag)
        if value is None or value == "":
            return None, None
        try:
            angle = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{path}: {tag} must be one number (degrees); got {value!r}") from None
        if not np.isfinite(angle) or abs(angle) > 180:
            raise InputError(f"{path}: {tag} must be an angle in -180..180 degrees; got {angle:g}")
        angles.append(angle)
    return angles[0], angles[1]


def read(path: Path) -> list[Radiograph]:
    """Every frame, float32 after the modality LUT, MONOCHROME2 (larger = brighter)."""
    import pydicom
    from pydicom.pixels import apply_modality_lut

    ds = pydicom.dcmread(path)
    if "PixelData" not in ds:
        raise InputError(f"{path}: DICOM file has no pixel data")
    pixels = apply_modality_lut(ds.pixel_array, ds).astype(np.float32)
    n_frames = int(getattr(ds, "NumberOfFrames", 1) or 1)
    frames = pixels.reshape((n_frames,) + pixels.shape[-2:]) if pixels.ndim >= 2 else pixels
    if frames.ndim != 3:
        raise InputError(f"{path}: expected monochrome frames; got pixel array of shape {pixels.shape}")
    bit_depth = int(getattr(ds, "BitsStored", 16))
    if str(getattr(ds, "PhotometricInterpretation", "MONOCHROME2")) == "MONOCHROME1":
        frames = float(2**bit_depth - 1) - frames
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
    return [Radiograph(np.ascontiguousarray(f), bit_depth, str(path), i, meta) for i, f in enumerate(frames)]


def write_dicom(path: str | os.PathLike, ds, pixels: np.ndarray) -> None:
    """Save data set ``ds`` with ``pixels`` as its pixel data, uncompressed, atomically.

    The one DICOM writer: the transfer syntax becomes explicit VR little endian,
    the pixels are stored in the data set's ``BitsAllocated`` (8 or 16) and, for
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
    stored = "<u2" if int(ds.BitsAllocated) == 16 else "u1"
    frames = pixels[0] if pixels.ndim == 3 and len(pixels) == 1 else pixels
    ds.PixelData = np.ascontiguousarray(frames, dtype=stored).tobytes()
    if frames.ndim == 3:
        ds.NumberOfFrames = len(frames)
    atomic_write(path, lambda tmp: ds.save_as(tmp, enforce_file_format=True))


def write_like(source: Path, frames: list[Radiograph], out_path: Path) -> None:
    """The source's data set with new pixel data, a new SOP Instance UID and a derivation note."""
    import pydicom
    from pydicom.uid import generate_uid

    ds = pydicom.dcmread(source)
    pixels = np.stack([to_source_dtype(f) for f in frames])
    if str(getattr(ds, "PhotometricInterpretation", "")) == "MONOCHROME1":
        pixels = (2 ** frames[0].bit_depth - 1 - pixels.astype(np.int64)).astype(pixels.dtype)
    slope, intercept = float(getattr(ds, "RescaleSlope", 1) or 1), float(getattr(ds, "RescaleIntercept", 0) or 0)
    if (slope, intercept) != (1.0, 0.0):  # store raw values so the modality LUT gives the output back
        pixels = np.clip(np.rint((pixels - intercept) / slope), 0, 2 ** int(ds.BitsStored) - 1).astype(np.uint16)
    ds.SOPInstanceUID = generate_uid()
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.DerivationDescription = "geometric distortion corrected by fluorocal"
    ds.ImageType = ["DERIVED", "SECONDARY"] + list(getattr(ds, "ImageType", [])[2:])
    write_dicom(out_path, ds, pixels.astype(np.uint16 if ds.BitsAllocated == 16 else np.uint8))
