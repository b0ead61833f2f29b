"""The parts of a ``calibration.json`` read and checked one by one: names, image sizes, field files.

Every refusal is an :class:`~fluorocal.stages.errors.ArtifactError` naming the calibration's file.
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
from fluorocal.outputs import inside, safe_name
from fluorocal.stages.errors import ArtifactError, InputError
from fluorocal.stages.field import CorrectionField

#: the arrays of a field file, in CorrectionField's order
FIELD_ARRAYS = ("x_nodes_px", "y_nodes_px", "delta_px", "sigma_px", "support")

#: largest image side a calibration may give, px (DICOM's Rows and Columns are 16-bit)
MAX_IMAGE_SIDE_PX = 65535


def image_size(value, path: Path) -> tuple[int, int]:
    sides = value if isinstance(value, list) and len(value) == 2 else [None]
    if not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE_PX for v in sides):
        raise ArtifactError(
            f"{path}: image_size_px must be [width, height], integers in 1..{MAX_IMAGE_SIDE_PX}; got {value!r}"
        )
    return value[0], value[1]


def field_file(path: Path, name) -> Path:
    """The field file ``name`` a calibration at ``path`` refers to: a bare name, in the calibration's folder.

    Raises
    ------
    ArtifactError
        ``name`` is not a bare file name (absolute, a folder, ``..``) or resolves outside the folder.
    """
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", "..") or "\\" in name:
        raise ArtifactError(f"{path}: field file must be a bare file name beside the calibration; got {name!r}")
    try:
        return inside(path.parent, name)
    except InputError as exc:
        raise ArtifactError(f"{path}: field file {name!r}: {exc}") from exc


def read_field(file: Path, w: int, h: int) -> CorrectionField:
    try:
        with open(file, "rb") as fh:  # opened here so that a corrupt file is closed too
            npz = np.load(fh, allow_pickle=False)
            if not isinstance(npz, np.lib.npyio.NpzFile):
                raise ValueError("a single array, not an .npz archive of the field's arrays")
            with npz:
                return CorrectionField(*(npz[k] for k in FIELD_ARRAYS), w, h)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise ArtifactError(f"{file}: unreadable or corrupt field file ({type(exc).__name__}: {exc})") from exc


def checked_name(name, path: Path, what: str) -> str:
    try:
        return safe_name(name, what=what)
    except InputError as exc:
        raise ArtifactError(f"{path}: {exc}") from None
