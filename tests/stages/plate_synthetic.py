"""A synthetic grid plate for the plate-calibration tests: known plate errors, poses, distortion and noise.

Point data, no rendering: each frame sees the holes of a hex plate (pitch 3.6 mm) through a homography
(the plate turned and shifted between frames), the correction field of a smooth analytic distortion
(radial + S-shaped, a few px at the edge, plus a term that changes with the frame's orientation), and
Gaussian centroid noise.
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.field import CorrectionField
from fluorocal.stages.label.lattice import lattice_id, lattice_xyz_mm
from fluorocal.stages.plate.solve import PlateProblem

SIZE = 512
PITCH_MM = 3.6
PX_PER_MM = 4.0
FOV_RADIUS = 240.0


def distortion_px(xy: np.ndarray, angle: float = 0.0) -> np.ndarray:
    """The true correction ``Δ(measured)`` (px): ideal = measured - Δ. ``angle`` (rad) turns an S-term on."""
    c = (SIZE - 1) / 2
    u, v = (xy[:, 0] - c) / c, (xy[:, 1] - c) / c
    r2 = u * u + v * v
    radial = 3.0 * r2 + 0.8 * np.sin(3 * u) * np.cos(2 * v)
    s = 1.5 * np.sin(angle) * r2 * r2
    return np.column_stack([radial * u - s * v, radial * v + s * u])


def true_field(angle: float = 0.0, spacing: float = 8.0) -> CorrectionField:
    """:func:`distortion_px` sampled on a grid (for comparisons)."""
    field = CorrectionField.constant(SIZE, SIZE, spacing_px=spacing)
    return field.with_delta(distortion_px(field.nodes_px, angle).reshape(field.delta_px.shape))


def make_plate(
    seed: int, n_frames: int, *, turn_deg: float, shift_mm: float, plate_error_mm: float, noise_px: float, angles=None
):
    """Observations of a synthetic plate; returns ``(problem, ids, true_error_mm)``.

    Frame ``f`` turns the plate by up to ``turn_deg`` and shifts it by up to ``shift_mm``; its orientation is
    ``f`` (a field each) with angle ``angles[f]`` (rad, default all 0).
    """
    rng = np.random.default_rng(seed)
    ij = np.array([(i, j) for i in range(-45, 46) for j in range(-40, 41)])
    nominal = lattice_xyz_mm(ij, "hex", PITCH_MM)[:, :2]
    keep = np.linalg.norm(nominal, axis=1) < 1.4 * FOV_RADIUS / PX_PER_MM
    ij, nominal = ij[keep], nominal[keep]
    error = rng.normal(scale=plate_error_mm / np.sqrt(2), size=nominal.shape)
    true = nominal + error
    angles = np.zeros(n_frames) if angles is None else np.asarray(angles, float)
    frames, holes, xy = [], [], []
    c = (SIZE - 1) / 2
    for f in range(n_frames):
        a = np.radians(rng.uniform(-turn_deg, turn_deg))
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        ideal = (true @ R.T + rng.uniform(-shift_mm, shift_mm, 2)) * PX_PER_MM + c
        inside = np.linalg.norm(ideal - c, axis=1) < FOV_RADIUS
        measured = _distort(ideal[inside], angles[f]) + rng.normal(scale=noise_px, size=(int(inside.sum()), 2))
        frames.append(np.full(int(inside.sum()), f))
        holes.append(np.flatnonzero(inside))
        xy.append(measured)
    n = sum(len(h) for h in holes)
    sigma = np.column_stack([np.full(n, noise_px), np.full(n, noise_px), np.zeros(n)])
    problem = PlateProblem(
        np.concatenate(frames), np.arange(n_frames), np.concatenate(holes), nominal, np.vstack(xy), sigma, (SIZE, SIZE)
    )
    return problem, lattice_id(ij), error


def _distort(ideal: np.ndarray, angle: float) -> np.ndarray:
    """Measured points whose correction gives ``ideal``: ``m - Δ(m) = ideal`` by fixed-point iteration."""
    m = ideal.copy()
    for _ in range(50):
        m = ideal + distortion_px(m, angle)
    return m
