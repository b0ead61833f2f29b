"""Phantom designs (bead cube, perforated hex plate) and their true and reference coordinates."""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.simulate.params import RNG_MARKERS, RNG_PHANTOM, SimulateParams


def make_phantom(params: SimulateParams) -> tuple[Phantom, np.ndarray, np.ndarray]:
    """Design the phantom and draw its true and reference coordinates.

    Returns
    -------
    nominal : Phantom
        Design coordinates (what ``phantom.csv`` holds).
    true_xyz_mm : (N, 3) float64 ndarray, mm
        Nominal + fabrication error: for a cube, independent per bead (``fabrication_error_mm``
        3D RMS); for a plate, in-plane and structured (:func:`plate_errors`, ``plate_error_mm`` 2D RMS).
    reference_xyz_mm : (N, 3) float64 ndarray, mm
        True + survey noise (``reference_error_mm`` 3D RMS), the check points.

    Examples
    --------
    >>> nominal, true_xyz, ref_xyz = make_phantom(SimulateParams())
    >>> nominal.n_beads, int((nominal.role == "marker").sum())
    (494, 8)
    """
    rng = np.random.default_rng([params.seed, RNG_PHANTOM])
    if params.phantom == "cube":
        nominal = _cube_phantom(params)
        fab = rng.normal(scale=params.fabrication_error_mm / np.sqrt(3), size=(nominal.n_beads, 3))
    else:
        nominal = _grid_phantom(params)
        fab = np.zeros((nominal.n_beads, 3))
        fab[:, :2] = plate_errors(nominal.xyz_mm[:, :2], params.grid_pitch_mm, params.plate_error_mm, rng)
    n = nominal.n_beads
    true_xyz = nominal.xyz_mm + fab
    reference_xyz = true_xyz + rng.normal(scale=params.reference_error_mm / np.sqrt(3), size=(n, 3))
    return nominal, true_xyz, reference_xyz


# (wall, column, row) of the grid beads replaced by larger markers: two per wall,
# near the wall's centre (visible in every view) and placed asymmetrically so the pose is unambiguous
_MARKER_SLOTS = ((0, 4, 3), (0, 8, 6), (1, 5, 5), (1, 9, 2), (2, 3, 6), (2, 7, 2), (3, 6, 3), (3, 8, 6))
#: distance from a bead centre to the cube's edges (mm)
_EDGE_CLEARANCE_MM = 6.0


def _cube_phantom(params: SimulateParams) -> Phantom:
    """Beads in the mid-planes of the four vertical walls, on one grid per wall.

    In an oblique view the walls that overlap in projection are neighbours
    (they meet at the corner on that side of the image), so neighbouring
    walls' rows are offset by half ``bead_row_pitch_mm``: their beads fall
    between each other's rows, up to perspective. Opposite walls share row
    heights; they project onto different halves of the image.
    """
    half = params.cube_side_mm / 2
    extent = params.cube_side_mm - 2 * _EDGE_CLEARANCE_MM
    step = params.bead_row_pitch_mm / 2
    n_levels = int(np.floor(extent / step)) + 1
    n_cols = int(np.floor(extent / params.bead_column_pitch_mm)) + 1
    if n_levels < 2 or n_cols < 2:
        raise InputError(
            f"bead_row_pitch_mm={params.bead_row_pitch_mm} and bead_column_pitch_mm={params.bead_column_pitch_mm}"
            f" leave no bead grid on a {params.cube_side_mm} mm cube"
        )
    levels = (np.arange(n_levels) - (n_levels - 1) / 2) * step
    cols = (np.arange(n_cols) - (n_cols - 1) / 2) * params.bead_column_pitch_mm
    xyz, slots = [], []
    for wall in range(4):
        phi = wall * np.pi / 2
        normal = np.array([np.cos(phi), np.sin(phi), 0.0])
        tangent = np.array([-np.sin(phi), np.cos(phi), 0.0])
        for row, z in enumerate(levels[wall % 2 :: 2]):
            for col, u in enumerate(cols):
                xyz.append(normal * (half - params.wall_thickness_mm / 2) + tangent * u + np.array([0, 0, z]))
                slots.append((wall, col, row))
    n = len(xyz)
    marker = _markers(params, slots)
    diam = np.where(marker, params.marker_diameter_mm, params.bead_diameter_mm)
    return Phantom(np.arange(n), np.array(xyz), diam, np.where(marker, "marker", ""))


def _markers(params: SimulateParams, slots: list) -> np.ndarray:
    """``(N,) bool``: the beads (at ``(wall, column, row)`` ``slots``) that are markers (``params.marker_layout``)."""
    marker = np.zeros(len(slots), dtype=bool)
    if params.marker_layout == "fixed":
        chosen = set(_MARKER_SLOTS[: params.n_markers])
        marker[[i for i, slot in enumerate(slots) if slot in chosen]] = True
        return marker
    if params.n_markers > len(slots):
        raise InputError(f"n_markers={params.n_markers} exceeds the cube's {len(slots)} beads")
    rng = np.random.default_rng([params.seed, RNG_MARKERS])
    marker[rng.choice(len(slots), size=params.n_markers, replace=False)] = True
    return marker


def _grid_phantom(params: SimulateParams) -> Phantom:
    pitch = params.grid_pitch_mm
    radius = params.grid_size_mm / 2
    n_rows = int(np.ceil(radius / (pitch * np.sqrt(3) / 2)))
    rows = np.arange(-n_rows, n_rows + 1)
    n_cols = int(np.ceil(radius / pitch)) + 1
    cols = np.arange(-n_cols, n_cols + 1)
    # shape (n_rows, n_cols): hex lattice, odd rows shifted by half a pitch
    x = (cols[None, :] + 0.5 * (rows[:, None] % 2)) * pitch
    y = np.broadcast_to(rows[:, None] * pitch * np.sqrt(3) / 2, x.shape)
    keep = x**2 + y**2 <= radius**2
    xyz = np.column_stack([x[keep], y[keep], np.zeros(keep.sum())])
    n = len(xyz)
    return Phantom(np.arange(n), xyz, np.full(n, params.grid_hole_diameter_mm), np.full(n, ""), "hex", pitch)


#: shares of the plate error's variance, as measured on the real ARCADIS plate (0.19 px RMS in all):
#: a displacement per lattice row (~0.1 px), alternate rows offset along the rows (±0.07 px), per-hole jitter
PLATE_ERROR_SHARES = {"row": 0.28, "alternate": 0.14, "hole": 0.58}


def plate_errors(xy_mm: np.ndarray, pitch_mm: float, rms_mm: float, rng: np.random.Generator) -> np.ndarray:
    """In-plane manufacturing errors ``(N, 2)`` mm of a drilled hex plate's holes at nominal ``xy_mm``.

    Three parts, each scaled to its share of the variance
    (:data:`PLATE_ERROR_SHARES`) over the plate's holes: every lattice row
    (constant nominal y) displaced as a whole by a random 2D vector, odd rows
    offset along the rows against even ones (``±a``, the half-pitch shift of
    the hex lattice a little off), and independent 2D jitter per hole. The
    sum's best-fit similarity (shift, turn, scale) is removed, so the plate
    keeps its nominal place and size, and it is rescaled to exactly
    ``rms_mm`` 2D RMS.

    Examples
    --------
    >>> xy = np.array([[x + 0.5 * (r % 2), r * 0.866] for r in range(20) for x in range(20)])
    >>> err = plate_errors(xy, 1.0, 0.02, np.random.default_rng(0))
    >>> round(float(np.sqrt(np.mean(np.sum(err**2, axis=1)))), 6)
    0.02
    """
    n = len(xy_mm)
    if n == 0 or rms_mm == 0:
        return np.zeros((n, 2))
    row = np.rint(xy_mm[:, 1] / (pitch_mm * np.sqrt(3) / 2)).astype(np.int64)
    _, row_index = np.unique(row, return_inverse=True)
    parts = {
        "row": rng.standard_normal((row_index.max() + 1, 2))[row_index],
        "alternate": np.column_stack([np.where(row % 2 == 1, 1.0, -1.0) * rng.choice([-1.0, 1.0]), np.zeros(n)]),
        "hole": rng.standard_normal((n, 2)),
    }
    err = sum(np.sqrt(PLATE_ERROR_SHARES[k]) * v / np.sqrt(np.mean(np.sum(v**2, axis=1))) for k, v in parts.items())
    # remove the best-fit similarity: err ≈ t + [[a, -b], [b, a]] xy
    x, y = xy_mm[:, 0], xy_mm[:, 1]
    one, zero = np.ones(n), np.zeros(n)
    design = np.concatenate([np.column_stack([one, zero, x, -y]), np.column_stack([zero, one, y, x])])
    coef, *_ = np.linalg.lstsq(design, err.T.ravel(), rcond=None)
    err = err - (design @ coef).reshape(2, n).T
    return err * (rms_mm / np.sqrt(np.mean(np.sum(err**2, axis=1))))
