"""Atomic file writes: a temporary file in the target's directory, then a rename; and the one PNG writer."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
from fluorocal.stages.errors import CalibError, InputError

#: the eight bytes every PNG file starts with
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, writer) -> None:
    """Call ``writer(tmp_path)`` then rename the temporary file onto ``path``.

    The temporary file sits in the same directory (same file system) and keeps
    the suffix, so format detection by extension still works; it is removed if
    ``writer`` fails, so nothing half-written is ever left under ``path``.

    Raises
    ------
    OSError
        Whatever the file system raised (a full disk, a read-only folder, ...), with
        ``path`` as its ``filename`` (not the temporary file's), so a message can name it.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
        os.close(fd)
        writer(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp creates 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException as exc:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, CalibError) and exc.errno is not None:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


def write_png(path: str | os.PathLike, image: np.ndarray | bytes, *, compression: int | None = None) -> None:
    """Write a PNG atomically: an image array encoded with OpenCV, or bytes already encoded as PNG.

    Parameters
    ----------
    path : path-like
        The file to write.
    image : (H, W) or (H, W, 3) uint8 or uint16 ndarray, or bytes
        Grey or BGR pixels (OpenCV's channel order), or a whole PNG file (e.g. from
        matplotlib's ``savefig(..., format="png")``), written as given.
    compression : int, optional
        zlib level 0-9 for arrays (default: OpenCV's).

    Raises
    ------
    InputError
        ``image`` is bytes that are not a PNG, or OpenCV cannot encode the array.

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     write_png(Path(d) / "a.png", np.zeros((4, 6), np.uint8))
    ...     (Path(d) / "a.png").read_bytes()[:8] == PNG_SIGNATURE
    True
    """
    if isinstance(image, (bytes, bytearray)):
        if not bytes(image[:8]) == PNG_SIGNATURE:
            raise InputError(f"{path}: the bytes given are not a PNG file")
        data = bytes(image)
    else:
        import cv2

        params = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
        ok, encoded = cv2.imencode(".png", np.asarray(image), params)
        if not ok:
            raise InputError(f"{path}: cannot encode the image as PNG")
        data = encoded.tobytes()
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))
