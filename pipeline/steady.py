"""Frames read from a file that holds still: the bytes decoded are the bytes the cache keys name.

A frame's cache key is the hash of its file taken when the run was planned
(:func:`fluorocal.units.frame_units`). A file replaced after that, or while it is
read, would leave another file's beads cached under that key, served to every
later run. :func:`read_steady` hashes the file just before and just after
decoding it and refuses the frames unless both hashes are the planned one.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from fluorocal.stages.errors import InputError


def file_sha256(path: str | os.PathLike) -> str:
    """Content hash of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_steady(path: str | Path, planned_sha256: str, indices=None) -> list:
    """The frames of ``path`` (all, or ``indices``), read only if its content is ``planned_sha256`` throughout.

    Raises
    ------
    InputError
        The file's content differs from the planned one before or after the read (it was replaced or is
        being written); nothing read from it is returned, so nothing of it is cached.

    Examples
    --------
    >>> import tempfile
    >>> import numpy as np
    >>> from fluorocal.stages.io.still import write_still
    >>> with tempfile.TemporaryDirectory() as d:
    ...     path = Path(d) / "f.tif"
    ...     write_still(path, np.full((4, 6), 1000, np.uint16))
    ...     planned = file_sha256(path)
    ...     (frame,) = read_steady(path, planned)
    ...     write_still(path, np.full((4, 6), 7, np.uint16))  # replaced after the run was planned
    ...     try:
    ...         read_steady(path, planned)
    ...     except InputError as exc:
    ...         refused = "changed before fluorocal read it" in str(exc)
    >>> frame.image.shape, refused
    ((4, 6), True)
    """
    from fluorocal.stages import io

    _check(path, file_sha256(path), planned_sha256, "before")
    frames = io.read_frames(Path(path), indices)
    _check(path, file_sha256(path), planned_sha256, "while")
    return frames


def _check(path, actual: str, planned: str, when: str) -> None:
    if actual != planned:
        raise InputError(
            f"{path}: changed {when} fluorocal read it (content sha256 {actual[:12]}..., {planned[:12]}... when the "
            "run started); nothing read from it was used or cached: run again once the file is complete"
        )
