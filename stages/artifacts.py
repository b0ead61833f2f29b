"""Artifacts shared by several stages: frozen dataclasses of numpy arrays plus metadata.

Every artifact is a ``@dataclass(frozen=True)`` whose fields are numpy arrays,
JSON-serialisable scalars/strings/dicts, or tuples of those. ``__post_init__``
checks shapes and makes arrays read-only. The pipeline stores any such
dataclass generically (arrays to ``.npz``, the rest to a JSON manifest), so a
stage's own output type can live in its own module.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from fluorocal.stages.errors import ShapeError

SCHEMA_VERSION = 1


def freeze(obj) -> None:
    """Make every ndarray field of a dataclass instance read-only (call from ``__post_init__``)."""
    for f in fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, np.ndarray):
            value.flags.writeable = False


def as_arrays(obj, dtype, *names: str, shape: tuple | None = (-1,)) -> None:
    """Set the named fields of a frozen dataclass instance to ndarrays of ``dtype`` (call from ``__post_init__``).

    Each is reshaped to ``shape`` (default: 1-D); ``shape=None`` keeps the shape given.
    """
    for name in names:
        value = np.asarray(getattr(obj, name), dtype=dtype)
        object.__setattr__(obj, name, value if shape is None else value.reshape(shape))


def check_shape(name: str, arr: np.ndarray, shape: tuple) -> None:
    """Raise :class:`ShapeError` unless ``arr.shape`` matches ``shape`` (``None`` = any size)."""
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ShapeError(f"{name} must have shape {want}; got {arr.shape}")


@dataclass(frozen=True)
class Radiograph:
    """One frame, as float32 intensities in the source's own units (DN).

    Attributes
    ----------
    image : (H, W) float32 ndarray, DN
        Monochrome with larger = brighter (MONOCHROME1 inputs are inverted on read).
    bit_depth : int
        Bits per sample of the source (12 for the ARCADIS frames, 16 for 16-bit TIFF).
    source : str
        File name the frame came from.
    frame_index : int
        Index within a multi-frame source (0 for stills).
    metadata : dict
        JSON-serialisable facts read from the file (modality, pixel spacing, ...).
    """

    image: np.ndarray
    bit_depth: int
    source: str = ""
    frame_index: int = 0
    metadata: dict = field(default_factory=dict)
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        if not isinstance(self.image, np.ndarray) or self.image.dtype != np.float32:
            object.__setattr__(self, "image", np.asarray(self.image, dtype=np.float32))
        check_shape("image", self.image, (None, None))
        if not np.all(np.isfinite(self.image)):
            raise ShapeError(f"image of {self.source or 'frame'} has non-finite values")
        freeze(self)

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape

    @property
    def full_scale(self) -> float:
        """Largest representable value of the source bit depth."""
        return float(2**self.bit_depth - 1)


MIN_PHANTOM_BEADS = 4  # a 3D bead phantom's fewest beads: a pose needs four points


@dataclass(frozen=True)
class Phantom:
    """A calibration phantom's beads in its nominal (design) coordinates.

    Attributes
    ----------
    ids : (N,) int64 ndarray
    xyz_mm : (N, 3) float64 ndarray, mm
    diameter_mm : (N,) float64 ndarray, mm
        NaN where the CSV gave none.
    role : (N,) str ndarray
        ``""`` or ``"marker"`` (distinctive beads used to find the pose for labelling).
    lattice : str
        ``""`` for a 3D bead phantom, ``"hex"`` or ``"square"`` for a grid plate.
    pitch_mm : float
        Lattice pitch of a grid plate (0 for a bead phantom).
    """

    ids: np.ndarray
    xyz_mm: np.ndarray
    diameter_mm: np.ndarray
    role: np.ndarray
    lattice: str = ""
    pitch_mm: float = 0.0
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        as_arrays(self, np.int64, "ids", shape=None)
        as_arrays(self, np.float64, "xyz_mm", shape=(-1, 3))
        as_arrays(self, np.float64, "diameter_mm", shape=None)
        as_arrays(self, str, "role", shape=None)
        n = len(self.ids)
        check_shape("xyz_mm", self.xyz_mm, (n, 3))
        check_shape("diameter_mm", self.diameter_mm, (n,))
        check_shape("role", self.role, (n,))
        if len(np.unique(self.ids)) != n:
            raise ShapeError("phantom ids must be unique")
        freeze(self)

    @property
    def n_beads(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Observations:
    """Labelled bead observations: the table the adjustment consumes.

    One row per labelled detection. ``exposure`` is the epoch index within the
    acquisition: frames of different systems with the same ``exposure`` were
    taken at the same time (biplanar pairs, paired in sorted order).

    Attributes
    ----------
    system : (N,) int64 ndarray
        Index into ``system_names``.
    exposure : (N,) int64 ndarray
    bead_id : (N,) int64 ndarray
        Phantom bead id.
    xy_px : (N, 2) float64 ndarray, px
        Measured (distorted) image coordinates.
    sigma_px : (N, 3) float64 ndarray
        ``(sigma_x px, sigma_y px, rho)`` of each centre, from the centroid stage.
    system_names : tuple of str
    """

    system: np.ndarray
    exposure: np.ndarray
    bead_id: np.ndarray
    xy_px: np.ndarray
    sigma_px: np.ndarray
    system_names: tuple = ("A",)
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        as_arrays(self, np.int64, "system", "exposure", "bead_id")
        as_arrays(self, np.float64, "xy_px", shape=(-1, 2))
        as_arrays(self, np.float64, "sigma_px", shape=(-1, 3))
        object.__setattr__(self, "system_names", tuple(self.system_names))
        n = len(self.system)
        for name in ("exposure", "bead_id"):
            check_shape(name, getattr(self, name), (n,))
        check_shape("xy_px", self.xy_px, (n, 2))
        check_shape("sigma_px", self.sigma_px, (n, 3))
        if not (np.all(np.isfinite(self.xy_px)) and np.all(np.isfinite(self.sigma_px))):
            raise ShapeError("observations hold non-finite coordinates or sigmas")
        if n and (self.system.min() < 0 or self.system.max() >= len(self.system_names)):
            lo, hi = self.system.min(), self.system.max()
            raise ShapeError(f"system indices must lie in [0, {len(self.system_names)}); got {lo}..{hi}")
        freeze(self)

    def __len__(self) -> int:
        return len(self.system)
