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

    Every command reads frames through these (``read_frames`` displays them); ``undistort`` resamples
    and writes them back as stored. A linear resampling of stored values equals that of the displayed
    values, the display being an affine function of them (inversion, rescale, sign offset), apart from
    the border, which is given here in stored units.

    Attributes
    ----------
    n_frames : int
    size_px : (int, int)
        ``(width, height)`` px of every frame.
    dtype : numpy.dtype
        Every frame's sample type, as the file stores it (signed, 32-bit and float types too).
    black : float
        The stored value displayed as 0 (the dark outside of the field): the border value to resample with.
    frames : iterator of (H, W) or (H, W, C) ndarray
        The frames, read from the file as they are asked for.
    n_channels : int
        Samples per pixel (C; 1: the frames are 2-D).
    """

    n_frames: int
    size_px: tuple[int, int]
    dtype: np.dtype
    black: float
    frames: Iterator[np.ndarray]
    n_channels: int = 1


def check_stored(
    path, frame: np.ndarray, dtype, size_px: tuple[int, int], i_frame: int, n_channels: int = 1
) -> np.ndarray:
    """``frame`` if ``size_px`` of ``n_channels`` ``dtype`` samples (2-D for one), else InputError naming ``path``."""
    shape = (size_px[1], size_px[0]) + ((n_channels,) if n_channels > 1 else ())
    if frame.dtype != dtype or frame.shape != shape:
        raise InputError(
            f"{path}: frame {i_frame} must be {size_px[0]}x{size_px[1]} px of {n_channels} {np.dtype(dtype)} "
            f"sample(s); got shape {frame.shape} of {frame.dtype}"
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
