"""The parts of a ``calibration.json`` read and checked one by one: names, image sizes, numbers, field files.

Each field entry records its file's SHA-256 (a field file that does not match is refused) and the
document its own (:func:`document_sha256`). Every refusal is an
:class:`~fluorocal.stages.errors.ArtifactError` naming the calibration's file.
"""

from __future__ import annotations

import hashlib
import json
import logging
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
#: the key of the document's own SHA-256 (:func:`document_sha256`)
DOCUMENT_SHA256 = "document_sha256"

log = logging.getLogger(__name__)


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


def read_checked_field(path: Path, entry, w: int, h: int) -> CorrectionField:
    """The field an entry of ``calibration.json`` names, refused unless its SHA-256 is the one recorded.

    Files written before the hash was recorded (no ``sha256`` in the entry) are read as they are.
    """
    file = field_file(path, entry["file"])
    expected = entry.get("sha256")
    if expected is not None:
        try:
            actual = hashlib.sha256(file.read_bytes()).hexdigest()
        except OSError as exc:
            raise ArtifactError(f"{file}: cannot read field file ({exc.strerror or exc})") from exc
        if actual != expected:
            raise ArtifactError(
                f"{file}: field file does not match {path.name} (sha256 {actual[:12]}..., recorded "
                f"{str(expected)[:12]}...): it was changed or belongs to another calibration; "
                "use the field files written with this calibration"
            )
    return read_field(file, w, h)


def vector(value, n: int, what: str, path: Path, *, nulls: bool = False) -> np.ndarray:
    """``value`` as ``n`` finite floats (``None`` read as NaN where ``nulls``), else ArtifactError naming ``what``."""
    ok = isinstance(value, list) and len(value) == n
    ok = ok and all((v is None and nulls) or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in value)
    array = np.array([np.nan if v is None else v for v in value], dtype=float) if ok else None
    if array is None or not (np.isfinite(array) | (nulls & np.isnan(array))).all():
        raise ArtifactError(f"{path}: {what} must be {n} finite numbers; got {_shown(value)}")
    return array


def quaternion(value, what: str, path: Path) -> np.ndarray:
    """``value`` as a unit quaternion ``(w, x, y, z)`` (norm within 1e-6 of 1), else ArtifactError naming ``what``."""
    q = vector(value, 4, what, path)
    if abs(np.linalg.norm(q) - 1.0) > 1e-6:  # saved from a normalised solve: off by rounding (~1e-16) only
        raise ArtifactError(f"{path}: {what} must be a unit quaternion (w, x, y, z); got norm {np.linalg.norm(q):.6g}")
    return q


def angle(value, what: str, path: Path) -> float | None:
    """An orientation angle: ``None`` or a finite number of degrees."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ArtifactError(f"{path}: {what} must be a finite number of degrees or null; got {_shown(value)}")
    return float(value)


def document_sha256(doc: dict) -> str:
    """SHA-256 of a calibration document's canonical JSON, without its own ``document_sha256``."""
    body = {k: v for k, v in doc.items() if k != DOCUMENT_SHA256}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def check_document_sha256(doc: dict, path: Path) -> bool:
    """Whether the document is as written (True also when no hash was recorded); warn in the log if not.

    An edited calibration is still read (its values are checked one by one); the log says it was edited.
    """
    recorded = doc.get(DOCUMENT_SHA256)
    if recorded is None or recorded == document_sha256(doc):
        return True
    log.warning("%s was edited after fluorocal wrote it (its content no longer matches %s)", path, DOCUMENT_SHA256)
    return False


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
