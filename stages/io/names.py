"""File names as the C libraries (OpenImageIO, OpenCV) take them: UTF-8 text, whatever the locale."""

from __future__ import annotations

import os

from fluorocal.stages.errors import InputError


def native_name(path: str | os.PathLike) -> str:
    r"""``path`` as the text OpenImageIO and OpenCV open: its bytes decoded as UTF-8.

    Python decodes file names with the locale's encoding and keeps undecodable bytes as lone
    surrogates (under ``LC_ALL=C``, every non-ASCII byte); those libraries encode the text they are
    given as UTF-8 and refuse surrogates. Decoding the name's own bytes as UTF-8 gives them the very
    file, under any locale.

    Raises
    ------
    InputError
        A name whose bytes are not UTF-8 (shown in ASCII, other bytes as escapes), and what to do.

    Examples
    --------
    >>> native_name(os.fsdecode(b"fr\xc3\xa4me.tif"))  # as Python decodes it under any locale
    'främe.tif'
    >>> try:
    ...     native_name(os.fsdecode(b"fr\xe4me.tif"))  # Latin-1
    ... except InputError as exc:
    ...     print(str(exc).split(",")[0])
    fr\xe4me.tif: file name is not UTF-8
    """
    raw = os.fsencode(path)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        shown = raw.decode("ascii", "backslashreplace")
        raise InputError(
            f"{shown}: file name is not UTF-8, which OpenImageIO and OpenCV need; rename the file"
        ) from None
