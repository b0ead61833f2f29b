"""Frames back to the integer type of their source: shared by every format's write-like."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Radiograph


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
