"""The project file's keys outside the stage tables: one table that the loader checks against and the docs list.

:data:`SCHEMA` is the one source of truth: the loader (:mod:`fluorocal.config`) accepts exactly its keys in
each table and takes its defaults from it, and the documentation's config reference is generated from it.
"""

from __future__ import annotations

from dataclasses import dataclass

from fluorocal.stages.kinds import LATTICE_SPELLINGS

#: the calibration scheme when ``[calibration] scheme`` is not given (parsed with the rest: ``--help`` imports no stage)
DEFAULT_SCHEME = "knn+iop+smooth"


@dataclass(frozen=True)
class Key:
    """One key of the project file: its table, TOML type, default and meaning.

    The loader accepts exactly the keys of :data:`SCHEMA` in each table (the stage tables take
    their ``Params`` fields), and the documentation's config reference is generated from it.
    """

    section: str
    name: str
    type: str
    default: object = None
    help: str = ""
    required: bool = False


def _spelled(spellings) -> str:
    """``"hex"`` or ``"square"`` (``"a", "b" or "c"`` for three), as the docs show values: code spans."""
    shown = [f'`"{spelling}"`' for spelling in spellings]
    return " or ".join([", ".join(shown[:-1]), shown[-1]] if len(shown) > 1 else shown)


#: every key of the project file outside the stage tables; ``section`` "systems.orientations" is an
#: element of a system's ``orientations`` list
SCHEMA = (
    Key("phantom", "file", "string (path)", None, "phantom CSV `id,x,y,z[,diameter][,role]` in mm (design values)"),
    Key("phantom", "lattice", "string", None, f"a perforated grid plate instead: {_spelled(LATTICE_SPELLINGS)}"),
    Key("phantom", "pitch", "number (mm)", None, "with `lattice`: distance between neighbouring holes (scale only)"),
    Key("systems", "name", "string", None, "1-64 letters, digits, `-`, `_`, `.`; names differ", required=True),
    Key("systems", "frames", "string or list", None, "a glob or a list of frame files", required=True),
    Key("systems", "source_image_distance", "number (mm)", None, "approximate, 100-5000 mm", required=True),
    Key("systems", "pixel_pitch", "number (mm)", None, "at the detector, approximate, 0.01-5 mm", required=True),
    Key("systems", "seeds", "string (path)", None, "CSV `id,x,y[,file,frame]` (px): seeds for frames without markers"),
    Key("systems", "orientations", "list of tables", None, "the frames grouped by C-arm orientation (below)"),
    Key("systems.orientations", "name", "string", None, "1-64 letters, digits, `-`, `_`, `.`", required=True),
    Key("systems.orientations", "frames", "string or list", None, "a glob or a list: the system's own frames"),
    Key("systems.orientations", "orbit", "number (degrees)", None, "C-arm orbit angle; with `tilt`, within 180"),
    Key("systems.orientations", "tilt", "number (degrees)", None, "C-arm tilt angle; with `orbit`, within 180"),
    Key(
        "calibration", "scheme", "string", DEFAULT_SCHEME, "knn, knn+iop, knn+smooth, knn+iop+smooth, none, polynomial"
    ),
    Key("output", "dir", "string (path)", "out", "folder of the published outputs"),
    Key("cache", "dir", "string (path)", ".fluorocal", "folder of the artifact cache"),
    Key("compute", "jobs", "integer", None, "worker processes for the per-frame stages (none: every core; 1: serial)"),
    Key("compute", "threads", "integer", 1, "BLAS/OpenMP/OpenCV threads per process"),
)


def schema_keys(section: str) -> set[str]:
    """The keys :data:`SCHEMA` allows in ``section`` (``"phantom"``, ``"systems.orientations"``, ...).

    Examples
    --------
    >>> sorted(schema_keys("phantom"))
    ['file', 'lattice', 'pitch']
    """
    return {k.name for k in SCHEMA if k.section == section}


def schema_default(section: str, name: str):
    """The default of key ``name`` of ``section`` in :data:`SCHEMA`.

    Examples
    --------
    >>> schema_default("output", "dir")
    'out'
    """
    return next(k.default for k in SCHEMA if k.section == section and k.name == name)
