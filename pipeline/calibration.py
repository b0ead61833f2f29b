"""The calibration file and the public Python API.

``calibration.json`` (schema ``fluorocal-calibration``, version 1) holds, per
imaging system, the image size, the interior orientation and the name of the
``.npz`` file beside it with the learned correction field on its grid; the
relative orientation of a biplanar pair; each training exposure's pose; the
scheme and the statistics of the solve. README.md, "Calibration file",
documents every key. Usage::

    from fluorocal import Calibration
    cal = Calibration.load("out/calibration.json")
    ideal_xy = cal.undistort_points("A", [[512.3, 100.7]])
"""

from __future__ import annotations

import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fluorocal.outputs import inside, safe_name
from fluorocal.stages.errors import ArtifactError, InputError
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.geometry import (
    camera_matrix,
    check_points,
    image_rays,
    intersect_rays,
    project,
    quat_multiply,
    quat_normalize,
    quat_to_matrix,
)
from fluorocal.stages.io import atomic_write

SCHEMA = "fluorocal-calibration"
SCHEMA_VERSION = 1
FIELD_ARRAYS = ("x_nodes_px", "y_nodes_px", "delta_px", "sigma_px", "support")
#: largest image side a calibration may give, px (DICOM's Rows and Columns are 16-bit)
MAX_IMAGE_SIDE_PX = 65535


@dataclass(frozen=True)
class SystemCalibration:
    """One imaging system: image size, IOP ``(xp, yp, c)`` px, ROP relative to the reference system, field."""

    name: str
    image_size_px: tuple[int, int]
    iop_px: np.ndarray
    iop_std_px: np.ndarray
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    field: CorrectionField


def _image_size(value, path: Path) -> tuple[int, int]:
    ok = (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE_PX for v in value)
    )
    if not ok:
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


def _read_field(file: Path, w: int, h: int) -> CorrectionField:
    try:
        with open(file, "rb") as fh:  # opened here so that a corrupt file is closed too
            npz = np.load(fh, allow_pickle=False)
            if not isinstance(npz, np.lib.npyio.NpzFile):
                raise ValueError("a single array, not an .npz archive of the field's arrays")
            with npz:
                return CorrectionField(*(npz[k] for k in FIELD_ARRAYS), w, h)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise ArtifactError(f"{file}: unreadable or corrupt field file ({type(exc).__name__}: {exc})") from exc


def _system_from_doc(s: dict, path: Path) -> "SystemCalibration":
    w, h = _image_size(s["image_size_px"], path)
    field = _read_field(field_file(path, s["field"]["file"]), w, h)
    iop = s["iop_px"]
    return SystemCalibration(
        s["name"],
        (w, h),
        np.array([iop["xp"], iop["yp"], iop["c"]], dtype=float),
        np.array(s.get("iop_std_px", [0.0, 0.0, 0.0]), dtype=float),
        np.array(s["rop"]["q_cam_from_ref"], dtype=float),
        np.array(s["rop"]["source_in_ref_camera_mm"], dtype=float),
        field,
    )


class Calibration:
    """A loaded calibration.

    Methods take a system by name and points as ``(N, 2)`` px arrays
    (README.md, "Conventions").
    """

    def __init__(self, systems: list[SystemCalibration], exposures: dict, meta: dict):
        self.systems = {s.name: s for s in systems}
        self._order = [s.name for s in systems]
        self.exposures = exposures  # epoch -> (q (4,), source_mm (3,)) of the reference system
        self.meta = meta

    # --- files -------------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read ``calibration.json`` and the field files beside it.

        Each system's ``field.file`` is a bare file name, read from the
        calibration's own folder: an absolute path, a folder or ``..`` is refused.

        Raises
        ------
        ArtifactError
            Missing, unreadable or corrupt file (the JSON or a field ``.npz``), another schema, a schema
            version this fluorocal does not know, or values out of range; the message names the file.
        """
        path = Path(path)
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ArtifactError(f"{path}: cannot read calibration ({exc})") from exc
        if not isinstance(doc, dict):
            raise ArtifactError(f"{path}: not a {SCHEMA} file (a JSON {type(doc).__name__}, not an object)")
        if doc.get("schema") != SCHEMA or doc.get("schema_version") != SCHEMA_VERSION:
            raise ArtifactError(
                f"{path}: not a {SCHEMA} v{SCHEMA_VERSION} file "
                f"(schema {doc.get('schema')!r} v{doc.get('schema_version')!r})"
            )
        try:
            systems = [_system_from_doc(s, path) for s in doc["systems"]]
            exposures = {
                int(e["exposure"]): (np.array(e["q_cam_from_obj"]), np.array(e["source_mm"]))
                for e in doc.get("exposures", [])
            }
        except (KeyError, TypeError, ValueError, OSError) as exc:
            if isinstance(exc, ArtifactError):
                raise
            raise ArtifactError(f"{path}: malformed calibration ({type(exc).__name__}: {exc})") from exc
        meta = {k: v for k, v in doc.items() if k not in ("systems", "exposures")}
        return cls(systems, exposures, meta)

    def save(self, path: str | Path) -> list[Path]:
        """Write ``calibration.json`` and one ``field_<system>.npz`` per system atomically; return the paths."""
        path = Path(path)
        written, systems = [], []
        for name in self._order:
            s = self.systems[name]
            field_file = inside(path.parent, f"field_{safe_name(name, what='system name')}.npz")
            atomic_write(field_file, lambda tmp, f=s.field: np.savez(tmp, **{k: getattr(f, k) for k in FIELD_ARRAYS}))
            written.append(field_file)
            magnitude = (
                np.linalg.norm(s.field.delta_px, axis=-1)[s.field.support] if s.field.support.any() else np.zeros(1)
            )
            systems.append(
                {
                    "name": name,
                    "image_size_px": list(s.image_size_px),
                    "iop_px": dict(zip(("xp", "yp", "c"), map(float, s.iop_px))),
                    "iop_std_px": [float(v) for v in s.iop_std_px],
                    "rop": {
                        "q_cam_from_ref": [float(v) for v in s.rop_q],
                        "source_in_ref_camera_mm": [float(v) for v in s.rop_source_mm],
                    },
                    "field": {
                        "file": field_file.name,
                        "grid_nodes": [len(s.field.x_nodes_px), len(s.field.y_nodes_px)],
                        "max_correction_px": float(magnitude.max()),
                        "rms_correction_px": float(np.sqrt(np.mean(magnitude**2))),
                        "supported_fraction": float(s.field.support.mean()),
                    },
                }
            )
        doc = {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            **{k: v for k, v in self.meta.items() if k not in ("schema", "schema_version")},
            "systems": systems,
            "exposures": [
                {"exposure": e, "q_cam_from_obj": q.tolist(), "source_mm": t.tolist()}
                for e, (q, t) in sorted(self.exposures.items())
            ],
        }
        atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(doc, indent=1)))
        return written + [path]

    # --- the API -----------------------------------------------------------------------------

    def _system(self, system: str) -> SystemCalibration:
        if system not in self.systems:
            raise InputError(f"system {system!r} is not in this calibration; it has {', '.join(self._order)}")
        return self.systems[system]

    @property
    def system_names(self) -> list[str]:
        return list(self._order)

    def undistort_points(self, system: str, xy) -> np.ndarray:
        """Measured (distorted) ``(N, 2)`` px -> ideal pinhole ``(N, 2)`` px: ``xy - Δ(xy)``."""
        return self._system(system).field.undistort_points(check_points("xy", xy, 2))

    def distort_points(self, system: str, xy) -> np.ndarray:
        """Ideal pinhole ``(N, 2)`` px -> measured ``(N, 2)`` px (the inverse of :meth:`undistort_points`)."""
        return self._system(system).field.distort_points(check_points("xy", xy, 2))

    def intrinsics(self, system: str) -> dict:
        """``{"xp", "yp", "c", "K", "image_size_px"}``: principal point and distance (px) and the 3×3 camera matrix."""
        s = self._system(system)
        xp, yp, c = s.iop_px
        return {
            "xp": xp,
            "yp": yp,
            "c": c,
            "K": camera_matrix(s.iop_px),
            "image_size_px": s.image_size_px,
        }

    def pose(self, system: str, exposure: int) -> tuple[np.ndarray, np.ndarray]:
        """``(q, T)`` of ``system`` at a training ``exposure``: the reference pose composed with the ROP."""
        s = self._system(system)
        if exposure not in self.exposures:
            raise InputError(f"exposure {exposure} is not a training exposure of this calibration")
        q0, T0 = self.exposures[exposure]
        q = quat_normalize(quat_multiply(s.rop_q, q0))
        return q, T0 + quat_to_matrix(q0).T @ s.rop_source_mm

    def project(self, system: str, exposure: int, xyz_mm) -> np.ndarray:
        """Where object points ``(N, 3)`` mm appear in ``system``'s measured (distorted) image at ``exposure``, px."""
        q, T = self.pose(system, exposure)
        return self.distort_points(
            system, project(check_points("xyz_mm", xyz_mm, 3), q, T, self._system(system).iop_px)
        )

    def rays(self, system: str, xy, *, exposure: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Origins ``(3,)`` and unit directions ``(N, 3)`` of the rays through measured points.

        In object space at a training ``exposure``; without one, in the
        reference system's camera frame (the rig frame of a biplanar pair).
        """
        s = self._system(system)
        ideal = self.undistort_points(system, xy)
        # the ROP is the system's pose in the reference camera frame
        q, origin = (s.rop_q, s.rop_source_mm) if exposure is None else self.pose(system, exposure)
        return image_rays(ideal, s.iop_px, q, origin)

    def intersect(self, observations: dict, *, exposure: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Multi-ray spatial intersection of corresponding points seen by several systems.

        Parameters
        ----------
        observations : dict of str to (N, 2) array_like, px
            Measured coordinates of the same N points in each system's frame.
        exposure : int, optional
            A training exposure: the result is in the phantom's object space.
            Without it, the result is in the reference system's camera frame.

        Returns
        -------
        xyz_mm : (N, 3) float64 ndarray, mm
            Least-squares intersection of the rays.
        miss_mm : (N,) float64 ndarray, mm
            RMS distance of the point from its rays (a consistency check).
        """
        if len(observations) < 2:
            raise InputError(f"intersect needs the same points seen by >= 2 systems; got {list(observations)}")
        rays = [self.rays(name, xy, exposure=exposure) for name, xy in observations.items()]
        n = {len(d) for _, d in rays}
        if len(n) != 1:
            raise InputError(f"every system must give the same number of points; got {sorted(n)}")
        return intersect_rays(rays)
