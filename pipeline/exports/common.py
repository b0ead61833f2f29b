"""What the export formats share: the geometry check, writing inside the folder, the tables beside a calibration."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from fluorocal.outputs import inside, safe_name
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import quat_to_matrix
from fluorocal.stages.io import OBJECT_POINTS, OBSERVATIONS, atomic_write, read_table


def has_geometry(cal) -> bool:
    """Whether ``cal`` estimated an interior orientation and poses (a grid plate's calibration did not)."""
    return cal.meta.get("geometry_estimated", True) is not False


def require_geometry(cal, fmt: str) -> None:
    """Refuse, naming ``fmt``, a calibration without interior orientation and poses (a grid plate's)."""
    if not has_geometry(cal):
        raise InputError(
            f"--format {fmt} needs the interior orientation and the poses, and {cal.path} comes from a grid plate "
            "(geometry_estimated false) that has none; export it with --format opencv (maps only), or calibrate "
            "with a 3D bead phantom"
        )


def write_text(out_dir: Path, name: str, text: str) -> Path:
    """Write ``text`` atomically as ``out_dir / name`` (refused outside ``out_dir``); return the path."""
    path = inside(out_dir, name)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
    return path


def field_files(cal, fmt: str, prefix: str, extension: str) -> list[tuple[str, str, str | None]]:
    """``(file name, system, orientation)`` of each field of each system, refused where two names would coincide.

    The name is ``<prefix><system><extension>`` for a system's one field (orientation None), else
    ``<prefix><system>_<orientation><extension>`` per orientation. ``_`` may occur in the names
    themselves, so system ``A`` at orientation ``x`` and a system ``A_x`` would share a file; and
    names differing only in case would on a case-insensitive file system. Both are refused before
    anything is written.

    Raises
    ------
    InputError
        Two fields would be written to one file (naming both, the file and the format).
    """
    found: list[tuple[str, str, str | None]] = []
    seen: dict[str, str] = {}
    for system in cal.system_names:
        names = cal.orientation_names(system)
        stem = prefix + safe_name(system, what="system name")
        for orientation in names if len(names) > 1 else [None]:
            name = stem + ("" if orientation is None else "_" + safe_name(orientation, what="orientation name"))
            name += extension
            what = f"system {system}" + ("" if orientation is None else f" at orientation {orientation}")
            other = seen.setdefault(name.casefold(), what)
            if other != what:
                raise InputError(
                    f"--format {fmt}: {other} and {what} would both be written as {name} (names joined by '_', "
                    f"letter case ignored); rename a system or an orientation of {cal.path}"
                )
            found.append((name, system, orientation))
    return found


def projection_matrix(cal, system: str, exposure: int) -> np.ndarray:
    """The 3×4 pinhole projection ``K [R | -R T]`` of ``system`` at a training ``exposure``, fluorocal's pixel frame.

    ``P @ [X, Y, Z, 1]`` is proportional to ``[x, y, 1]``, the ideal (undistorted) pixel of an object
    point in mm (docs/concepts.md, "Conventions").
    """
    q, source_mm = cal.pose(system, exposure)
    R = quat_to_matrix(q)
    return cal.intrinsics(system)["K"] @ np.hstack([R, -(R @ source_mm)[:, None]])


def tables_beside(cal) -> tuple[dict, dict] | None:
    """``(object points, observations)`` of the calibration's run, or None when either file is absent.

    ``fluorocal run`` writes ``object_points.csv`` and ``observations.csv`` beside ``calibration.json``.
    """
    folder = Path(cal.path).parent
    points, observations = folder / "object_points.csv", folder / "observations.csv"
    if not (points.is_file() and observations.is_file()):
        return None
    obs = read_table(observations, OBSERVATIONS)
    missing = [c for c in ("exposure", "inlier") if c not in obs]
    if missing:
        raise InputError(
            f"{observations}: lacks column(s) {', '.join(missing)}; the exports read the observations.csv "
            "that `fluorocal run` writes beside calibration.json (move this file away to export without it)"
        )
    return read_table(points, OBJECT_POINTS), obs
