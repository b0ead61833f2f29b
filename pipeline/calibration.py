"""The calibration file and the public Python API.

``calibration.json`` (schema ``fluorocal-calibration``, version 2; version 1
files are read too) holds, per imaging system, the image size, the interior
orientation and the ``.npz`` file(s) beside it with the correction field on
its grid: one field, or one per C-arm orientation (an image intensifier's
distortion changes with the orientation), each with its name and its angles
when known; the relative orientation of a biplanar pair; each training
exposure's pose; the scheme and the statistics of the solve. docs/calibration-file.md
documents every key. Usage::

    from fluorocal import Calibration
    cal = Calibration.load("out/calibration.json")
    ideal_xy = cal.undistort_points("A", [[512.3, 100.7]])
    ideal_xy = cal.undistort_points("A", [[512.3, 100.7]], orientation="orbit30")
    ideal_xy = cal.undistort_points("A", [[512.3, 100.7]], orientation={"orbit": 15, "tilt": 0})
    map_x, map_y = cal.remap_maps("A")  # as cv2.initUndistortRectifyMap's: cv2.remap(frame, map_x, map_y, ...)
    ideal_frame = cal.undistort_image("A", frame)  # the same, with the maps cached beside the calibration
"""

from __future__ import annotations

import hashlib
import json
import operator
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fluorocal.calibration_doc import (
    DOCUMENT_SHA256,
    FIELD_ARRAYS,
    MAX_IMAGE_SIDE_PX,
    angle,
    check_document_sha256,
    checked_name,
    document_sha256,
    field_file,
    image_size,
    quaternion,
    read_checked_field,
    vector,
)
from fluorocal.maps import cached_maps, orientation_key
from fluorocal.outputs import inside, safe_name
from fluorocal.stages.errors import ArtifactError, InputError, ShapeError
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
from fluorocal.stages.orientation import OrientationField, interpolate_field
from fluorocal.stages.undistort import UndistortParams, check_maps, check_shift, remap_image

SCHEMA = "fluorocal-calibration"
#: the version written; version 1 (one field per system, no orientations) is read as well
SCHEMA_VERSION = 2
READ_VERSIONS = (1, 2)
#: the frame dtypes cv2.remap resamples
_REMAP_DTYPES = tuple(np.dtype(t) for t in (np.uint8, np.uint16, np.int16, np.float32, np.float64))


@dataclass(frozen=True)
class SystemCalibration:
    """One imaging system: image size, IOP ``(xp, yp, c)`` px, ROP relative to the reference system, field(s).

    Give either ``field`` (one field, no named orientation: a bead phantom's calibration) or
    ``orientations`` (one :class:`~fluorocal.stages.orientation.OrientationField` per C-arm
    orientation, all on one grid of nodes). With exactly one orientation, ``field`` is set to its
    field; with several, ``field`` is None: ask :meth:`Calibration.field` for one.
    """

    name: str
    image_size_px: tuple[int, int]
    iop_px: np.ndarray
    iop_std_px: np.ndarray
    rop_q: np.ndarray
    rop_source_mm: np.ndarray
    field: CorrectionField | None = None
    orientations: tuple[OrientationField, ...] = ()

    def __post_init__(self):
        orientations = tuple(self.orientations)
        object.__setattr__(self, "orientations", orientations)
        names = [o.name for o in orientations]
        if len(set(names)) != len(names):
            raise InputError(f"system {self.name!r}: orientation names must differ; got {names}")
        if not orientations:
            if not isinstance(self.field, CorrectionField):
                raise InputError(f"system {self.name!r}: give its field or its orientations; got neither")
        elif len(orientations) == 1 and self.field is None:
            object.__setattr__(self, "field", orientations[0].field)
        elif self.field is not (orientations[0].field if len(orientations) == 1 else None):
            raise InputError(
                f"system {self.name!r}: give its field or its orientations, not both "
                f"({len(orientations)} orientation(s): {', '.join(names)})"
            )

    @property
    def orientation_names(self) -> list[str]:
        return [o.name for o in self.orientations]


def _output_size(value) -> tuple[int, int]:
    """``(width, height)``: two integers in 1..:data:`MAX_IMAGE_SIDE_PX`, else InputError."""
    try:
        w, h = (operator.index(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"image_size must be (width, height) in px, two integers; got {value!r}") from None
    if not (1 <= w <= MAX_IMAGE_SIDE_PX and 1 <= h <= MAX_IMAGE_SIDE_PX):
        raise InputError(f"image_size must be (width, height) in 1..{MAX_IMAGE_SIDE_PX} px; got {value!r}")
    return w, h


def _system_from_doc(s: dict, path: Path) -> "SystemCalibration":
    w, h = image_size(s["image_size_px"], path)
    read: dict[str, CorrectionField] = {}  # by file name: a single orientation shares the system's field file

    def field_of(entry) -> CorrectionField:
        name = entry["file"]
        if name not in read:
            read[name] = read_checked_field(path, entry, w, h)
        return read[name]

    name = checked_name(s["name"], path, "system name")
    iop = vector([s["iop_px"][k] for k in ("xp", "yp", "c")], 3, f"system {name}: iop_px", path)
    if not iop[2] > 0:
        raise ArtifactError(f"{path}: system {s['name']}: iop_px must be finite with c > 0; got {iop.tolist()}")
    orientations = tuple(_orientation_from_doc(o, path, field_of) for o in s.get("orientations", []))
    field = field_of(s["field"]) if "field" in s or not orientations else None
    return SystemCalibration(
        name,
        (w, h),
        iop,
        vector(s.get("iop_std_px", [0.0, 0.0, 0.0]), 3, f"system {name}: iop_std_px", path, nulls=True),
        quaternion(s["rop"]["q_cam_from_ref"], f"system {name}: rop q_cam_from_ref", path),
        vector(s["rop"]["source_in_ref_camera_mm"], 3, f"system {name}: rop source_in_ref_camera_mm", path),
        field,
        orientations,
    )


def _orientation_from_doc(o: dict, path: Path, field_of) -> OrientationField:
    name = checked_name(o["name"], path, "orientation name")
    orbit, tilt = (angle(o.get(k), f"orientation {name}: {k}", path) for k in ("orbit_deg", "tilt_deg"))
    return OrientationField(name, orbit, tilt, field_of(o["field"]))


def _exposure_from_doc(e: dict, path: Path) -> tuple[int, tuple[np.ndarray, np.ndarray]]:
    if isinstance(e["exposure"], bool) or not isinstance(e["exposure"], int):
        raise ArtifactError(f"{path}: an exposure's number must be an integer; got {e['exposure']!r}")
    where = f"exposure {e['exposure']}"
    q = quaternion(e["q_cam_from_obj"], f"{where}: q_cam_from_obj", path)
    return e["exposure"], (q, vector(e["source_mm"], 3, f"{where}: source_mm", path))


def _content_sha256(path: Path, raw: bytes, doc: dict) -> str:
    """SHA-256 of a calibration's JSON bytes and of each field file it names, in sorted order of name."""
    names = set()
    for s in doc["systems"]:
        names.update(
            entry["file"] for entry in [s.get("field")] + [o["field"] for o in s.get("orientations", [])] if entry
        )
    digest = hashlib.sha256(raw)
    for name in sorted(names):
        digest.update(name.encode() + b"\0" + field_file(path, name).read_bytes())
    return digest.hexdigest()


def _field_entry(field: CorrectionField, file: Path) -> dict:
    """A field's entry in ``calibration.json``: its (written) file, its SHA-256, a summary over the supported nodes."""
    magnitude = np.linalg.norm(field.delta_px, axis=-1)[field.support] if field.support.any() else np.zeros(1)
    return {
        "file": file.name,
        "sha256": hashlib.sha256(file.read_bytes()).hexdigest(),
        "grid_nodes": [len(field.x_nodes_px), len(field.y_nodes_px)],
        "max_correction_px": float(magnitude.max()),
        "rms_correction_px": float(np.sqrt(np.mean(magnitude**2))),
        "supported_fraction": float(field.support.mean()),
    }


def _field_files(s: SystemCalibration) -> list[tuple[CorrectionField, str]]:
    """``(field, file name)`` of each field a system stores.

    ``field_<system>.npz`` for its one field, else ``field_<system>_<orientation>.npz`` per
    orientation; both names are checked by :func:`safe_name`.
    """
    system = safe_name(s.name, what="system name")
    if len(s.orientations) <= 1:
        return [(s.field, f"field_{system}.npz")]
    return [(o.field, f"field_{system}_{safe_name(o.name, what='orientation name')}.npz") for o in s.orientations]


class Calibration:
    """A loaded calibration.

    Methods take a system by name and points as ``(N, 2)`` px arrays
    (docs/concepts.md, "Conventions").
    """

    def __init__(self, systems: list[SystemCalibration], exposures: dict, meta: dict):
        self.systems = {s.name: s for s in systems}
        self._order = [s.name for s in systems]
        self.exposures = exposures  # epoch -> (q (4,), source_mm (3,)) of the reference system
        self.meta = meta
        self.path: Path | None = None  # the file it was loaded from: its map cache lies beside it
        self._content_sha256: str | None = None  # of that file and its field files
        self._maps: dict = {}  # (system, orientation, size) -> read-only (2, H, W) float32 maps

    # --- files -------------------------------------------------------------------------------

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read ``calibration.json`` (version 1 or 2) and the field files beside it.

        Each field's ``file`` is a bare file name, read from the calibration's own
        folder: an absolute path, a folder or ``..`` is refused.

        Raises
        ------
        ArtifactError
            Missing, unreadable or corrupt file (the JSON or a field ``.npz``), another schema, a schema
            version this fluorocal does not know, or values out of range; the message names the file.
        """
        path = Path(path)
        try:
            raw = path.read_bytes()
            doc = json.loads(raw)
        except (OSError, ValueError, RecursionError) as exc:  # RecursionError: JSON nested too deeply
            raise ArtifactError(f"{path}: cannot read calibration ({exc})") from exc
        if not isinstance(doc, dict):
            raise ArtifactError(f"{path}: not a {SCHEMA} file (a JSON {type(doc).__name__}, not an object)")
        if doc.get("schema") != SCHEMA or doc.get("schema_version") not in READ_VERSIONS:
            raise ArtifactError(
                f"{path}: not a {SCHEMA} file of version {' or '.join(map(str, READ_VERSIONS))} "
                f"(schema {doc.get('schema')!r} v{doc.get('schema_version')!r})"
            )
        try:
            systems = [_system_from_doc(s, path) for s in doc["systems"]]
            exposures = dict(_exposure_from_doc(e, path) for e in doc.get("exposures", []))
        except (KeyError, TypeError, ValueError, OverflowError, OSError) as exc:  # OverflowError: an integer of 10**400
            if isinstance(exc, ArtifactError):
                raise
            raise ArtifactError(f"{path}: malformed calibration ({type(exc).__name__}: {exc})") from exc
        names = [s.name for s in systems]
        if len(set(names)) != len(names):
            raise ArtifactError(f"{path}: malformed calibration (system names must differ; got {names})")
        check_document_sha256(doc, path)
        meta = {k: v for k, v in doc.items() if k not in ("systems", "exposures", DOCUMENT_SHA256)}
        cal = cls(systems, exposures, meta)
        cal.path, cal._content_sha256 = path, _content_sha256(path, raw, doc)
        return cal

    def save(self, path: str | Path) -> list[Path]:
        """Write ``calibration.json`` and its field files atomically; return the paths.

        Raises
        ------
        InputError
            A system or orientation name cannot be part of a file name, or two fields would share a file.
        """
        path = Path(path)
        files = {s: _field_files(self.systems[s]) for s in self._order}
        names = [name for pairs in files.values() for _, name in pairs]
        clash = next((n for n in names if names.count(n) > 1), None)
        if clash is not None:
            raise InputError(f"two fields would both be written as {clash}; rename a system or an orientation")
        written, systems = [], []
        for name in self._order:
            s = self.systems[name]
            entries = []
            for field, file_name in files[name]:
                file = inside(path.parent, file_name)
                atomic_write(file, lambda tmp, f=field: np.savez(tmp, **{k: getattr(f, k) for k in FIELD_ARRAYS}))
                written.append(file)
                entries.append(_field_entry(field, file))
            doc_s = {
                "name": name,
                "image_size_px": list(s.image_size_px),
                "iop_px": dict(zip(("xp", "yp", "c"), map(float, s.iop_px))),
                "iop_std_px": [float(v) if np.isfinite(v) else None for v in s.iop_std_px],
                "rop": {
                    "q_cam_from_ref": [float(v) for v in s.rop_q],
                    "source_in_ref_camera_mm": [float(v) for v in s.rop_source_mm],
                },
            }
            if len(s.orientations) <= 1:
                doc_s["field"] = entries[0]
            doc_s["orientations"] = [  # a single orientation's entry names the system's one field file
                {"name": o.name, "orbit_deg": o.orbit_deg, "tilt_deg": o.tilt_deg, "field": entry}
                for o, entry in zip(s.orientations, entries)
            ]
            systems.append(doc_s)
        doc = {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            **{k: v for k, v in self.meta.items() if k not in ("schema", "schema_version", DOCUMENT_SHA256)},
            "systems": systems,
            "exposures": [
                {"exposure": e, "q_cam_from_obj": q.tolist(), "source_mm": t.tolist()}
                for e, (q, t) in sorted(self.exposures.items())
            ],
        }
        doc[DOCUMENT_SHA256] = document_sha256(doc)
        atomic_write(path, lambda tmp: Path(tmp).write_text(json.dumps(doc, indent=1), encoding="utf-8"))
        return written + [path]

    @property
    def content_sha256(self) -> str | None:
        """SHA-256 (hex) of the loaded file and its field files: this calibration's content; None in memory."""
        return self._content_sha256

    # --- the API -----------------------------------------------------------------------------

    def _check_geometry(self) -> None:
        """Refuse geometry (IOP, poses, rays) from a calibration that estimated none: a grid plate's."""
        if self.meta.get("geometry_estimated", True) is False:
            raise InputError(
                "this calibration comes from a grid plate: it holds the distortion only, no interior "
                "orientation, pose or relative orientation; calibrate with a 3D bead phantom for those"
            )

    def _system(self, system: str) -> SystemCalibration:
        if system not in self.systems:
            raise InputError(f"system {system!r} is not in this calibration; it has {', '.join(self._order)}")
        return self.systems[system]

    @property
    def system_names(self) -> list[str]:
        return list(self._order)

    def orientation_names(self, system: str) -> list[str]:
        """The names of ``system``'s calibrated orientations (empty for one field without a name)."""
        return self._system(system).orientation_names

    def field(self, system: str, orientation=None) -> CorrectionField:
        """The correction field of ``system`` at an orientation.

        Parameters
        ----------
        system : str
            A system name.
        orientation : None, str or dict
            None: the system's one field (refused when it has several orientations). A name: that
            calibrated orientation. ``{"orbit": deg, "tilt": deg}``: interpolated between the
            calibrated orientations with angles (:func:`fluorocal.stages.orientation.interpolate_field`),
            refused beyond them.

        Raises
        ------
        InputError
            An unknown system or orientation name, a missing orientation where several are
            calibrated, a malformed dict, or angles beyond the calibrated ones; the message lists
            what the calibration has.
        """
        s = self._system(system)
        names = ", ".join(s.orientation_names)
        if orientation is None:
            if len(s.orientations) <= 1:
                return s.field
            raise InputError(
                f"system {system!r} is calibrated at {len(s.orientations)} orientations ({names}); "
                'choose one with orientation="NAME", or interpolate with orientation={"orbit": deg, "tilt": deg}'
            )
        if isinstance(orientation, str):
            found = next((o for o in s.orientations if o.name == orientation), None)
            if found is None:
                has = f"its orientations are {names}" if names else "it has one field and no named orientations"
                raise InputError(f"orientation {orientation!r} is not calibrated for system {system!r}; {has}")
            return found.field
        if isinstance(orientation, Mapping) and set(orientation) == {"orbit", "tilt"}:
            if not s.orientations:
                raise InputError(
                    f"system {system!r} has one field without C-arm angles; leave orientation out to use it"
                )
            return interpolate_field(
                s.orientations, orientation["orbit"], orientation["tilt"], what=f"system {system!r}"
            )
        raise InputError(f'orientation must be None, a name or {{"orbit": deg, "tilt": deg}}; got {orientation!r}')

    def undistort_points(self, system: str, xy, orientation=None) -> np.ndarray:
        """Measured (distorted) ``(N, 2)`` px -> ideal pinhole ``(N, 2)`` px: ``xy - Δ(xy)``.

        ``orientation`` as in :meth:`field`: None (the one field), a name, or ``{"orbit": deg, "tilt": deg}``.
        """
        return self.field(system, orientation).undistort_points(check_points("xy", xy, 2))

    def distort_points(self, system: str, xy, orientation=None) -> np.ndarray:
        """Ideal pinhole ``(N, 2)`` px -> measured ``(N, 2)`` px (the inverse of :meth:`undistort_points`)."""
        return self.field(system, orientation).distort_points(check_points("xy", xy, 2))

    def remap_maps(self, system: str, image_size=None, orientation=None) -> tuple[np.ndarray, np.ndarray]:
        """Inverse maps that undistort ``system``'s frames with ``cv2.remap``, as ``cv2.initUndistortRectifyMap``'s.

        ``cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR)`` resamples a measured frame onto the
        ideal pinhole image. The maps are computed once per (calibration, system, orientation,
        size): kept in memory, and cached on disk beside a loaded calibration (:mod:`fluorocal.maps`).

        Parameters
        ----------
        system : str
            A system name.
        image_size : (int, int), optional
            ``(width, height)`` px of the undistorted output (default: the calibrated image size), as
            ``newImageSize``; the source is always a frame of the calibrated size.
        orientation : None, str or dict
            As in :meth:`field`: None (the one field), a name, or ``{"orbit": deg, "tilt": deg}``.

        Returns
        -------
        map_x, map_y : (H, W) float32 ndarray, px, read-only
            The measured (distorted) source coordinate of each output pixel centre (docs/concepts.md,
            "Conventions"). Float32 maps are OpenCV's fastest here and exact; ``cv2.convertMaps``'s
            fixed-point pair is slower (``benchmarks/undistort.py``).

        Raises
        ------
        InputError
            An unknown system or orientation (:meth:`field`), a size that is not two positive
            integers, or a field that moves pixels beyond the image (naming the system).
        """
        s = self._system(system)
        w, h = _output_size(s.image_size_px if image_size is None else image_size)
        try:
            memo = (system, json.dumps(orientation_key(orientation)), (w, h))
        except (TypeError, ValueError):
            memo = None  # not an orientation: self.field says why
        if memo not in self._maps:
            field = self.field(system, orientation)  # refuses a bad orientation before any cache is touched
            compute = lambda: self._computed_maps(system, field, orientation, (w, h))  # noqa: E731
            self._maps[memo] = cached_maps(self.path, self._content_sha256, system, orientation, (w, h), compute)
        map_x, map_y = self._maps[memo]  # a memo hit skips the field: interpolating one costs milliseconds
        return map_x, map_y

    def _computed_maps(self, system: str, field: CorrectionField, orientation, size: tuple[int, int]) -> np.ndarray:
        """The ``(2, H, W)`` float32 maps of ``field``, after refusing a field that moves pixels beyond the image."""
        try:
            check_shift(field.delta_px, *self.systems[system].image_size_px)  # before a huge field overflows maps
            maps = np.stack(field.remap_maps(*size))
            check_maps(*maps)
        except InputError as exc:
            where = f"{self.path or 'calibration'}: system {system}"
            raise InputError(
                where + ("" if orientation is None else f", orientation {orientation}") + f": {exc}"
            ) from exc
        return maps

    def undistort_image(
        self, system: str, image, orientation=None, *, interpolation: str = "linear", border_value: float = 0.0
    ) -> np.ndarray:
        """A frame of ``system`` resampled onto its ideal pinhole image: :meth:`remap_maps` + ``cv2.remap``.

        Parameters
        ----------
        system : str
            A system name.
        image : (H, W) ndarray, uint8, uint16, int16, float32 or float64
            A measured frame of the calibrated size, in its own dtype (kept; no float copy is made).
        orientation : None, str or dict
            As in :meth:`field`.
        interpolation : str
            ``"linear"`` (default), ``"cubic"``, ``"lanczos"`` or ``"nearest"``.
        border_value : float
            Output pixels whose source falls outside the frame (default 0).

        Returns
        -------
        (H, W) ndarray of ``image``'s dtype
            As :func:`fluorocal.stages.undistort.remap_image` gives it (cubic and Lanczos clipped to the
            frame's value range).

        Raises
        ------
        InputError
            Not a 2-D frame of the calibrated size or of a dtype OpenCV remaps, or as :meth:`remap_maps`.
        """
        image = np.asarray(image)
        s = self._system(system)
        if image.ndim != 2 or image.shape != (s.image_size_px[1], s.image_size_px[0]):
            raise ShapeError(
                f"image must be one frame of system {system}'s calibrated size, shape "
                f"({s.image_size_px[1]}, {s.image_size_px[0]}); got {image.shape}"
            )
        if image.dtype not in _REMAP_DTYPES:
            raise InputError(f"image dtype must be one of {', '.join(map(str, _REMAP_DTYPES))}; got {image.dtype}")
        map_x, map_y = self.remap_maps(system, orientation=orientation)
        return remap_image(image, map_x, map_y, UndistortParams(interpolation, float(border_value)))

    def intrinsics(self, system: str) -> dict:
        """``{"xp", "yp", "c", "K", "image_size_px"}``: principal point and distance (px) and the 3×3 camera matrix."""
        self._check_geometry()
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
        self._check_geometry()
        s = self._system(system)
        if exposure not in self.exposures:
            raise InputError(f"exposure {exposure} is not a training exposure of this calibration")
        q0, T0 = self.exposures[exposure]
        q = quat_normalize(quat_multiply(s.rop_q, q0))
        return q, T0 + quat_to_matrix(q0).T @ s.rop_source_mm

    def project(self, system: str, exposure: int, xyz_mm, *, orientation=None) -> np.ndarray:
        """Where object points ``(N, 3)`` mm appear in ``system``'s measured (distorted) image at ``exposure``, px.

        ``orientation`` chooses the field as in :meth:`field`.
        """
        self._check_geometry()
        q, T = self.pose(system, exposure)
        return self.distort_points(
            system, project(check_points("xyz_mm", xyz_mm, 3), q, T, self._system(system).iop_px), orientation
        )

    def rays(self, system: str, xy, *, exposure: int | None = None, orientation=None) -> tuple[np.ndarray, np.ndarray]:
        """Origins ``(3,)`` and unit directions ``(N, 3)`` of the rays through measured points.

        In object space at a training ``exposure``; without one, in the
        reference system's camera frame (the rig frame of a biplanar pair).
        ``orientation`` chooses the field as in :meth:`field`.
        """
        self._check_geometry()
        s = self._system(system)
        ideal = self.undistort_points(system, xy, orientation)
        # the ROP is the system's pose in the reference camera frame
        q, origin = (s.rop_q, s.rop_source_mm) if exposure is None else self.pose(system, exposure)
        return image_rays(ideal, s.iop_px, q, origin)

    def intersect(
        self, observations: dict, *, exposure: int | None = None, orientations: dict | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Multi-ray spatial intersection of corresponding points seen by several systems.

        Parameters
        ----------
        observations : dict of str to (N, 2) array_like, px
            Measured coordinates of the same N points in each system's frame.
        exposure : int, optional
            A training exposure: the result is in the phantom's object space.
            Without it, the result is in the reference system's camera frame.
        orientations : dict of str to orientation, optional
            Per system, the orientation as in :meth:`field` (default: each system's one field).

        Returns
        -------
        xyz_mm : (N, 3) float64 ndarray, mm
            Least-squares intersection of the rays.
        miss_mm : (N,) float64 ndarray, mm
            RMS distance of the point from its rays (a consistency check).
        """
        self._check_geometry()
        if len(observations) < 2:
            raise InputError(f"intersect needs the same points seen by >= 2 systems; got {list(observations)}")
        orientations = orientations or {}
        rays = [
            self.rays(name, xy, exposure=exposure, orientation=orientations.get(name))
            for name, xy in observations.items()
        ]
        n = {len(d) for _, d in rays}
        if len(n) != 1:
            raise InputError(f"every system must give the same number of points; got {sorted(n)}")
        return intersect_rays(rays)
