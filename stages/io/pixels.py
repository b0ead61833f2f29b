"""Frames back to the integer type of their source, and frames as stored: shared by every format's writers."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import Radiograph
from fluorocal.stages.errors import InputError


def to_source_dtype(radiograph: Radiograph) -> np.ndarray:
    """Round and clip a frame back to the integer type of its bit depth (float32 for float sources).

    Examples
    --------
    >>> frame = Radiograph(np.array([[-3.2, 4095.7]], np.float32), 12, "a.dcm", 0, {})
    >>> to_source_dtype(frame)
    array([[   0, 4095]], dtype=uint16)
    """
    if radiograph.bit_depth > 16:
        return radiograph.image.astype(np.float32)
    dtype = np.uint8 if radiograph.bit_depth <= 8 else np.uint16
    return np.clip(np.rint(radiograph.image), 0, 2**radiograph.bit_depth - 1).astype(dtype)


@dataclass(frozen=True)
class StoredFrames:
    """A file's frames as stored (no modality LUT, no inversion), read one at a time.

    For streaming: a linear resampling of stored values equals that of the displayed values when the
    display is an affine function of them (MONOCHROME1 inversion; a rescale slope of 1), apart from
    the border, which is given here in stored units.

    Attributes
    ----------
    n_frames : int
    size_px : (int, int)
        ``(width, height)`` px of every frame.
    dtype : numpy.dtype
        uint8 or uint16, every frame's.
    black : float
        The stored value displayed as 0 (the dark outside of the field): the border value to resample with.
    frames : iterator of (H, W) ndarray
        The frames, read from the file as they are asked for.
    """

    n_frames: int
    size_px: tuple[int, int]
    dtype: np.dtype
    black: float
    frames: Iterator[np.ndarray]


def check_stored(path, frame: np.ndarray, dtype, size_px: tuple[int, int], i_frame: int) -> np.ndarray:
    """``frame`` if it is a 2-D array of ``dtype`` and ``size_px``, else InputError naming ``path`` and the frame."""
    if frame.ndim != 2 or frame.dtype != dtype or frame.shape != (size_px[1], size_px[0]):
        raise InputError(
            f"{path}: frame {i_frame} must be {size_px[0]}x{size_px[1]} px of {np.dtype(dtype)}; "
            f"got shape {frame.shape} of {frame.dtype}"
        )
    return frame


@dataclass(frozen=True)
class Derivation:
    """How written frames were derived from their source, for the formats whose header records it (DICOM).

    Attributes
    ----------
    description : str
        What was done, naming what it was done with (the calibration, system, orientation):
        DICOM's DerivationDescription (at most 1024 characters).
    series_uid : str or None
        DICOM's new SeriesInstanceUID, shared by the outputs of one run that came from one source
        series; None: a new one for this file alone.
    when : datetime.datetime or None
        When the derivation was made: DICOM's ContentDate and ContentTime (None: when the file is written).
    """

    description: str = "geometric distortion corrected by fluorocal"
    series_uid: str | None = None
    when: object = None

    def __post_init__(self):
        if not self.description or len(self.description) > 1024:
            raise InputError(f"derivation description must be 1 to 1024 characters; got {len(self.description)}")


def checked_indices(path, indices, n_frames: int | None) -> list[int]:
    """``indices`` as a list of ints, each a frame of a file of ``n_frames`` (None: not known yet, only >= 0).

    Raises
    ------
    InputError
        An index outside the file's frames, naming the file.
    """
    wanted = list(indices)
    if not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool) for i in wanted):
        raise InputError(f"{path}: frame indices must be integers; got {wanted!r}")
    wanted = [int(i) for i in wanted]
    for i in wanted:
        if i < 0:
            raise InputError(f"{path}: frames are numbered from 0; frame {i} asked for")
        if n_frames is not None and i >= n_frames:
            raise InputError(f"{path}: holds {n_frames} frame(s); frame {i} asked for")
    return wanted
