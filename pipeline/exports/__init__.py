"""A calibration in the formats of other tools: ``fluorocal export CALIBRATION --format NAME --out DIR``.

One module per format, each exposing ``write(cal, out_dir) -> list[str]`` (what it wrote and the
figures to state); :data:`FORMATS` is the fixed table of them. docs/exports.md, documents
each format, its frame and units.

- ``opencv``: OpenCV FileStorage YAML per system (and orientation): camera matrix, image size and
  the ``cv2.remap`` maps (:mod:`fluorocal.exports.opencv`);
- ``dlt``: the 11 DLT coefficients per training exposure, one column per system, as XMALab and
  DLTdv read them, with their reprojection RMS (:mod:`fluorocal.exports.dlt`);
- ``mayacam``: XMALab / Autoscoper MayaCam 2.0 camera files per system and exposure
  (:mod:`fluorocal.exports.mayacam`);
- ``mrcal``: a ``.cameramodel`` per system (and orientation), the field fitted by mrcal's
  splined stereographic model, with the fit error (:mod:`fluorocal.exports.mrcal`);
- ``paper``: the paper's ``.iop``, ``.eop``, ``.xyz`` and ``.pho`` text files
  (:mod:`fluorocal.exports.paper`).
"""

from __future__ import annotations

from pathlib import Path

from fluorocal.exports import dlt, mayacam, mrcal, opencv, paper
from fluorocal.stages.errors import InputError

#: format name -> its writer ``write(cal, out_dir) -> list[str]``
FORMATS = {
    "opencv": opencv.write,
    "dlt": dlt.write,
    "mayacam": mayacam.write,
    "mrcal": mrcal.write,
    "paper": paper.write,
}


def check_out_dir(out_dir: str | Path, *, overwrite: bool) -> Path:
    """``out_dir`` resolved, after refusing a file, or a non-empty folder unless ``overwrite``.

    Raises
    ------
    InputError
        ``out_dir`` is a file, or a folder holding anything while ``overwrite`` is False.
    """
    out_dir = Path(out_dir).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} is a file; give a folder for the export")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise InputError(f"--out {out_dir} is not empty; choose an empty or new folder, or add --overwrite")
    return out_dir


def export(calibration: str | Path, fmt: str, out_dir: str | Path, *, overwrite: bool = False) -> list[str]:
    """Write ``calibration`` in format ``fmt`` into ``out_dir``; return one line per file and figure.

    Raises
    ------
    InputError
        An unknown format, an ``out_dir`` refused by :func:`check_out_dir`, or a calibration the
        format cannot represent (a grid plate's, for the formats that need the geometry).
    ArtifactError
        An unreadable calibration.
    """
    from fluorocal.calibration import Calibration

    if fmt not in FORMATS:
        raise InputError(f"--format {fmt!r} is not known; formats are {', '.join(FORMATS)}")
    out_dir = check_out_dir(out_dir, overwrite=overwrite)
    cal = Calibration.load(calibration)
    return FORMATS[fmt](cal, out_dir)
