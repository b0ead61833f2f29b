"""Radiograph simulator with ground truth: phantom, acquisition, distortion and image formation.

Everything here is a pure function of :class:`SimulateParams` (randomness only
from ``np.random.default_rng`` seeded by ``params.seed``, one stream per
purpose, so the geometry does not depend on whether frames are rendered);
file writing lives in ``pipeline/cmd_simulate.py``.

Model, in the order light travels (conventions: ``stages/_geometry.py``):

1. **Phantom** (:func:`make_phantom`). ``"cube"``: 3.5 mm steel beads set in
   the mid-planes of the four vertical walls of an open acrylic box (no lid
   or floor), one grid per wall, neighbouring walls' rows offset by half a
   row pitch (in an oblique view the walls that overlap in projection are
   neighbours), plus larger ``marker`` beads. ``"grid"``: a steel plate with
   holes on a hexagonal lattice. Three coordinate sets: nominal (design),
   true (nominal + fabrication error) and reference (true + survey noise).
2. **Acquisition** (:func:`make_acquisition`). The phantom stands on a
   turntable (rotation about the vertical lab axis, with translations and
   height changes); each system is a source and a detector fixed in the lab,
   looking horizontally at the isocentre; system B sits ``system_angle_deg``
   from A and exposes at the same instants. Camera poses ``(q, T)`` are
   expressed in the phantom (object) frame.
3. **Distortion** (:class:`ImageDistortion`, forward ideal -> distorted):
   pincushion radial, S-distortion (rotation growing with r²), decentring and
   a smooth random field (cubic B-spline of random coefficients).
4. **Image formation** (:func:`render_frame`). Each output pixel centre is
   mapped through the *inverse* distortion to its ideal ray (Newton, to
   1e-7 px; :func:`ideal_pixel_map`); an ideal image is never warped.
   Line integrals: exact chord lengths through every sphere (or hole
   cylinder) and through the acrylic walls (or plate), Beer–Lambert. Pixels
   within a pixel of a bead outline are integrated over 21 sub-samples (a
   Fibonacci lattice), mapped to ideal rays by the local first-order inverse
   map (error < 3e-4 px, tested; far below the sub-sample spacing). Then heel
   effect, focal-spot + intensifier blur (Gaussian), veiling glare,
   vignetting, round field of view, quantum (normal approximation of
   Poisson) + electronic noise and 12-bit quantisation.

"Outline centre": the silhouette of a sphere is the ellipse where the cone
from the source tangent to the sphere meets the image plane (for a hole: the
perspective image of its mid-plane circle). Its ideal centre is the exact
centre of that conic. Through the distortion the outline is no longer an
ellipse; its *distorted outline centre* is the area centroid of the region
it bounds (the centroid an opaque flat silhouette would have), computed from
``N_OUTLINE`` points spaced uniformly in the ideal ellipse's parameter, so
that with no distortion it equals the conic centre exactly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, fields

import numpy as np
from fluorocal.stages._geometry import check_points, matrix_to_quat, project, quat_to_matrix, to_camera
from fluorocal.stages.artifacts import Phantom, Radiograph, freeze
from fluorocal.stages.errors import InputError

log = logging.getLogger(__name__)

VERSION = 1
SYSTEM_NAMES = ("A", "B")
#: points on each outline used for the distorted outline centre and apparent diameter
N_OUTLINE = 256
#: Fibonacci numbers allowed as sub-sample counts of edge pixels
_FIBONACCI = (5, 8, 13, 21, 34, 55, 89, 144)

# seed-sequence tags, so each random quantity has its own stream and the
# geometry does not depend on whether frames were rendered
_RNG_PHANTOM, _RNG_ACQ, _RNG_DIST, _RNG_NOISE = 1, 2, 3, 4


@dataclass(frozen=True)
class SimulateParams:
    """Parameters of a simulated acquisition (defaults give ARCADIS-like 1024² frames).

    Lengths in mm are physical (detector plane or object space); px values
    derived from them scale with ``image_size_px``. Distortion amplitudes are
    quoted in px for a 1024-px image and scale with the image size.

    Attributes
    ----------
    n_frames : int, default 12
        Exposures per system.
    n_systems : int, default 1
        1 (monoplanar) or 2 (biplanar, synchronised exposures).
    image_size_px : int, default 1024
        Square image side.
    detector_size_mm : float, default 256.0
        Detector side at the image plane; pixel pitch = detector_size_mm / image_size_px.
    source_image_distance_mm : float, default 1100.0
    magnification : float, default 1.35
        At the isocentre (source–isocentre distance = SID / magnification).
    system_angle_deg : float, default 75.0
        Azimuth of system B from system A (biplanar only).
    phantom : str, default "cube"
        ``"cube"`` (3D bead phantom) or ``"grid"`` (perforated hex plate, monoplanar only).
    distortion : str, default "strong"
        ``"none"``, ``"mild"`` (radial ~5 px at the field edge) or ``"strong"`` (~15 px).
    noise_scale : float, default 1.0
        Multiplies quantum and electronic noise; 0 gives noise-free frames.
    seed : int, default 0
    cube_side_mm, wall_thickness_mm : float, default 120.0, 5.0
        Acrylic box; bead centres lie in the walls' mid-planes.
    bead_diameter_mm, marker_diameter_mm : float, default 3.5, 5.0
    bead_row_pitch_mm, bead_column_pitch_mm : float, default 12.0, 9.0
        Bead grid on each wall (9 or 10 rows × 13 columns on the default cube,
        494 beads); neighbouring walls' rows are offset by half a row pitch.
    grid_pitch_mm, grid_hole_diameter_mm, grid_thickness_mm : float, default 3.6, 1.8, 1.0
    grid_size_mm : float, default 250.0
        Diameter of the perforated region of the plate.
    grid_magnification : float, default 1.05
        The plate sits near the detector face.
    fabrication_error_mm : float, default 0.1
        3D RMS of true - nominal bead positions.
    reference_error_mm : float, default 0.025
        3D RMS of reference - true (survey noise of the check points).
    turntable_translation_mm, turntable_height_mm : float, default 10.0, 15.0
        Half-ranges of the horizontal shifts and height changes of the turntable.
    min_face_angle_deg : float, default 30.0
        Turntable angles keep every system at least this far from viewing a wall edge-on.
    system_misalignment_deg : float, default 1.0
        Random tilt of each system from its nominal orientation.
    principal_point_offset_px : float, default 6.0
        Half-range of the principal point's offset from the image centre (at 1024 px).
    fov_radius_frac : float, default 0.47
        Radius of the round field of view as a fraction of the image side.
    overlap_margin_px : float, default 2.0
        Outlines closer than this (about half a blurred edge) count as overlapping.
    mu_steel_per_mm, mu_acrylic_per_mm : float, default 0.9, 0.015
        Effective linear attenuation coefficients (~60 keV).
    open_field_dn : float, default 2000.0
        Unattenuated signal at the field centre.
    dark_dn : float, default 8.0
        Signal outside the field of view.
    focal_spot_mm : float, default 0.6
        FWHM of the focal spot; blurs by ``focal_spot_mm * (M - 1)`` at the detector.
    intensifier_blur_mm : float, default 0.32
        Gaussian sigma of the intensifier + camera blur at the detector.
    glare_fraction : float, default 0.06
    glare_sigma_mm : float, default 30.0
        Veiling glare: this fraction of the signal is spread by a Gaussian of this sigma.
    vignetting : float, default 0.2
        Relative fall-off of the signal from the field centre to its rim.
    heel : float, default 0.04
        Relative fluence gradient (heel effect) from the field centre to the rim along y.
    gain_dn_per_quantum : float, default 0.14
        Quantum noise variance = gain * signal (DN²).
    electronic_noise_dn : float, default 4.0
    supersample : int, default 21
        Sub-samples per pixel on bead edges, on a Fibonacci lattice (a Fibonacci number: 5, 8, 13, 21, 34, 55, ...).
    bit_depth : int, default 12
    """

    n_frames: int = 12
    n_systems: int = 1
    image_size_px: int = 1024
    detector_size_mm: float = 256.0
    source_image_distance_mm: float = 1100.0
    magnification: float = 1.35
    system_angle_deg: float = 75.0
    phantom: str = "cube"
    distortion: str = "strong"
    noise_scale: float = 1.0
    seed: int = 0
    cube_side_mm: float = 120.0
    wall_thickness_mm: float = 5.0
    bead_diameter_mm: float = 3.5
    marker_diameter_mm: float = 5.0
    bead_row_pitch_mm: float = 12.0
    bead_column_pitch_mm: float = 9.0
    grid_pitch_mm: float = 3.6
    grid_hole_diameter_mm: float = 1.8
    grid_thickness_mm: float = 1.0
    grid_size_mm: float = 250.0
    grid_magnification: float = 1.05
    fabrication_error_mm: float = 0.1
    reference_error_mm: float = 0.025
    turntable_translation_mm: float = 10.0
    turntable_height_mm: float = 15.0
    min_face_angle_deg: float = 30.0
    system_misalignment_deg: float = 1.0
    principal_point_offset_px: float = 6.0
    fov_radius_frac: float = 0.47
    overlap_margin_px: float = 2.0
    mu_steel_per_mm: float = 0.9
    mu_acrylic_per_mm: float = 0.015
    open_field_dn: float = 2000.0
    dark_dn: float = 8.0
    focal_spot_mm: float = 0.6
    intensifier_blur_mm: float = 0.32
    glare_fraction: float = 0.06
    glare_sigma_mm: float = 30.0
    vignetting: float = 0.2
    heel: float = 0.04
    gain_dn_per_quantum: float = 0.14
    electronic_noise_dn: float = 4.0
    supersample: int = 21
    bit_depth: int = 12

    def __post_init__(self):
        for name, allowed in (("phantom", ("cube", "grid")), ("distortion", ("none", "mild", "strong"))):
            if getattr(self, name) not in allowed:
                raise InputError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        if self.n_systems not in (1, 2):
            raise InputError(f"n_systems must be 1 or 2; got {self.n_systems}")
        if self.phantom == "grid" and self.n_systems != 1:
            raise InputError("n_systems must be 1 for phantom='grid' (the plate sits on one detector)")
        if self.supersample not in _FIBONACCI:
            raise InputError(f"supersample must be one of {', '.join(map(str, _FIBONACCI))}; got {self.supersample}")
        for name in ("n_frames", "image_size_px"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be >= 1; got {getattr(self, name)}")
        if self.image_size_px < 16:
            raise InputError(f"image_size_px must be >= 16; got {self.image_size_px}")
        if not 1.0 < self.magnification < 3.0:
            raise InputError(f"magnification must lie in (1, 3); got {self.magnification}")
        if not 0 < self.fov_radius_frac <= 0.75:
            raise InputError(f"fov_radius_frac must lie in (0, 0.75]; got {self.fov_radius_frac}")
        if not 0 < self.bit_depth <= 16:
            raise InputError(f"bit_depth must lie in 1..16; got {self.bit_depth}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, float) and not (np.isfinite(value) and value >= 0):
                raise InputError(f"{f.name} must be a finite number >= 0; got {value}")

    @property
    def pixel_pitch_mm(self) -> float:
        """Detector pixel pitch (mm)."""
        return self.detector_size_mm / self.image_size_px

    @property
    def px_scale(self) -> float:
        """Image size relative to 1024 px (px amplitudes are quoted for 1024)."""
        return self.image_size_px / 1024.0

    @property
    def fov_radius_px(self) -> float:
        return self.fov_radius_frac * self.image_size_px

    @property
    def image_centre_xy_px(self) -> np.ndarray:
        return np.full(2, (self.image_size_px - 1) / 2.0)


# --------------------------------------------------------------------------- phantom


def make_phantom(params: SimulateParams) -> tuple[Phantom, np.ndarray, np.ndarray]:
    """Design the phantom and draw its true and reference coordinates.

    Returns
    -------
    nominal : Phantom
        Design coordinates (what ``phantom.csv`` holds).
    true_xyz_mm : (N, 3) float64 ndarray, mm
        Nominal + fabrication error (``fabrication_error_mm`` 3D RMS; in-plane only for a plate).
    reference_xyz_mm : (N, 3) float64 ndarray, mm
        True + survey noise (``reference_error_mm`` 3D RMS), the check points.

    Examples
    --------
    >>> nominal, true_xyz, ref_xyz = make_phantom(SimulateParams())
    >>> nominal.n_beads, int((nominal.role == "marker").sum())
    (494, 8)
    """
    nominal = _cube_phantom(params) if params.phantom == "cube" else _grid_phantom(params)
    rng = np.random.default_rng([params.seed, _RNG_PHANTOM])
    n = nominal.n_beads
    dims = 3 if params.phantom == "cube" else 2
    fab = np.zeros((n, 3))
    fab[:, :dims] = rng.normal(scale=params.fabrication_error_mm / np.sqrt(dims), size=(n, dims))
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
            f"bead_row_pitch_mm={params.bead_row_pitch_mm} and bead_column_pitch_mm={params.bead_column_pitch_mm} leave no bead grid on a {params.cube_side_mm} mm cube"
        )
    levels = (np.arange(n_levels) - (n_levels - 1) / 2) * step
    cols = (np.arange(n_cols) - (n_cols - 1) / 2) * params.bead_column_pitch_mm
    xyz, diam, role = [], [], []
    for wall in range(4):
        phi = wall * np.pi / 2
        normal = np.array([np.cos(phi), np.sin(phi), 0.0])
        tangent = np.array([-np.sin(phi), np.cos(phi), 0.0])
        for row, z in enumerate(levels[wall % 2 :: 2]):
            for col, u in enumerate(cols):
                xyz.append(normal * (half - params.wall_thickness_mm / 2) + tangent * u + np.array([0, 0, z]))
                is_marker = (wall, col, row) in _MARKER_SLOTS
                diam.append(params.marker_diameter_mm if is_marker else params.bead_diameter_mm)
                role.append("marker" if is_marker else "")
    n = len(xyz)
    return Phantom(np.arange(n), np.array(xyz), np.array(diam), np.array(role))


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


# --------------------------------------------------------------------------- distortion


@dataclass(frozen=True, eq=False)
class ImageDistortion:
    """Forward image distortion of one system: ideal (pinhole) -> distorted (measured) pixels.

    With ``ρ = (x - centre) / scale`` (normalised, ``r² = |ρ|²``)::

        ρ_d = Rot(s · r²) · (1 + k1 r² + k2 r⁴) ρ  +  decentring(p1, p2)(ρ)
        x_d = centre + scale · ρ_d + field(x)

    where ``decentring`` is Brown's tangential term and ``field`` a smooth random
    displacement: a bicubic B-spline with coefficients ``field_coeffs_px`` on a
    lattice of spacing ``field_spacing_px`` whose node ``[0, 0]`` sits at
    ``field_origin_xy_px``.

    Attributes
    ----------
    centre_xy_px : (2,) float64 ndarray, px
        Centre of the radial and S terms.
    scale_px : float, px
        Normalising radius (half the image side).
    k1, k2 : float
        Radial coefficients (pincushion when positive).
    s_rad : float, rad
        S-distortion: rotation angle at ``r = 1``; grows as ``r²``.
    p1, p2 : float
        Decentring coefficients.
    field_spacing_px : float, px
    field_origin_xy_px : (2,) float64 ndarray, px
    field_coeffs_px : (2, ny, nx) float64 ndarray, px
        B-spline coefficients of the x and y displacement.
    """

    centre_xy_px: np.ndarray
    scale_px: float
    k1: float = 0.0
    k2: float = 0.0
    s_rad: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    field_spacing_px: float = 64.0
    field_origin_xy_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    field_coeffs_px: np.ndarray = field(default_factory=lambda: np.zeros((2, 1, 1)))

    def __post_init__(self):
        object.__setattr__(self, "centre_xy_px", np.asarray(self.centre_xy_px, dtype=np.float64).reshape(2))
        object.__setattr__(self, "field_origin_xy_px", np.asarray(self.field_origin_xy_px, dtype=np.float64).reshape(2))
        coeffs = np.asarray(self.field_coeffs_px, dtype=np.float64)
        if coeffs.ndim != 3 or coeffs.shape[0] != 2:
            raise InputError(f"field_coeffs_px must have shape (2, ny, nx); got {coeffs.shape}")
        object.__setattr__(self, "field_coeffs_px", coeffs)
        if not self.scale_px > 0 or not self.field_spacing_px > 0:
            raise InputError(f"scale_px and field_spacing_px must be > 0; got {self.scale_px}, {self.field_spacing_px}")
        freeze(self)

    @classmethod
    def identity(cls, image_size_px: int) -> ImageDistortion:
        """No distortion, for an image of side ``image_size_px``."""
        return cls(np.full(2, (image_size_px - 1) / 2.0), image_size_px / 2.0)

    @property
    def is_identity(self) -> bool:
        return not (any((self.k1, self.k2, self.s_rad, self.p1, self.p2)) or np.any(self.field_coeffs_px))

    def _parametric(self, xy: np.ndarray, *, jacobian: bool = False):
        """Radial + S + decentring part of the forward map (no random field).

        Returns the mapped points ``(..., 2)`` and, if ``jacobian``, also their
        analytic derivative ``(..., 2, 2)`` (``[..., i, j] = ∂out_i / ∂xy_j``).
        """
        x = (xy[..., 0] - self.centre_xy_px[0]) / self.scale_px
        y = (xy[..., 1] - self.centre_xy_px[1]) / self.scale_px
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + self.k2 * r2)
        theta = self.s_rad * r2
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        ax, ay = radial * x, radial * y
        rot_x, rot_y = cos_t * ax - sin_t * ay, sin_t * ax + cos_t * ay
        out = np.empty(xy.shape)
        out[..., 0] = self.centre_xy_px[0] + self.scale_px * (rot_x + self.p1 * (r2 + 2 * x * x) + 2 * self.p2 * x * y)
        out[..., 1] = self.centre_xy_px[1] + self.scale_px * (rot_y + self.p2 * (r2 + 2 * y * y) + 2 * self.p1 * x * y)
        if not jacobian:
            return out
        # d(radial)/d(r²), then ∂(radial ρ)/∂ρ = radial I + 2 radial' ρ ρᵀ
        d_radial = self.k1 + 2 * self.k2 * r2
        a_xx, a_xy, a_yy = radial + 2 * d_radial * x * x, 2 * d_radial * x * y, radial + 2 * d_radial * y * y
        # ∂(Rot(θ) a)/∂ρ = Rot(θ) ∂a/∂ρ + Rot(θ + π/2) a (2 s ρ)ᵀ
        ds = 2 * self.s_rad
        jac = np.empty(xy.shape + (2,))
        jac[..., 0, 0] = cos_t * a_xx - sin_t * a_xy - rot_y * ds * x + 6 * self.p1 * x + 2 * self.p2 * y
        jac[..., 0, 1] = cos_t * a_xy - sin_t * a_yy - rot_y * ds * y + 2 * self.p1 * y + 2 * self.p2 * x
        jac[..., 1, 0] = sin_t * a_xx + cos_t * a_xy + rot_x * ds * x + 2 * self.p2 * x + 2 * self.p1 * y
        jac[..., 1, 1] = sin_t * a_xy + cos_t * a_yy + rot_x * ds * y + 6 * self.p2 * y + 2 * self.p1 * x
        return out, jac

    def _field(self, xy: np.ndarray) -> np.ndarray:
        if not np.any(self.field_coeffs_px):
            return np.zeros_like(xy)
        from scipy.ndimage import map_coordinates

        grid = (xy - self.field_origin_xy_px) / self.field_spacing_px
        coords = [grid[..., 1].ravel(), grid[..., 0].ravel()]
        # prefilter=False: the array holds B-spline coefficients, so this evaluates the spline exactly
        comps = [map_coordinates(c, coords, order=3, prefilter=False, mode="nearest") for c in self.field_coeffs_px]
        return np.stack(comps, axis=-1).reshape(xy.shape)

    def distort(self, xy_ideal: np.ndarray) -> np.ndarray:
        """Forward map: ideal pinhole coordinates ``(..., 2)`` px -> distorted (measured) px.

        Examples
        --------
        >>> d = ImageDistortion(np.array([50.0, 50.0]), 50.0, k1=0.01)
        >>> d.distort(np.array([[100.0, 50.0]]))
        array([[100.5,  50. ]])
        """
        xy = np.asarray(xy_ideal, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise InputError(f"xy_ideal must have shape (..., 2); got {xy.shape}")
        return self._parametric(xy) + self._field(xy)

    def undistort(self, xy_distorted: np.ndarray, *, tol_px: float = 1e-10, max_iter: int = 50) -> np.ndarray:
        """Inverse map: distorted (measured) ``(..., 2)`` px -> ideal px, by Newton iteration.

        The Jacobian omits the random field's gradient (|∇field| < 0.05), so
        convergence is linear with a factor below 0.05: about 8 iterations reach
        ``tol_px``.

        Raises
        ------
        EstimationError
            The iteration did not reach ``tol_px`` within ``max_iter`` steps.
        """
        from fluorocal.stages.errors import EstimationError

        target = np.asarray(xy_distorted, dtype=np.float64)
        if target.shape[-1:] != (2,):
            raise InputError(f"xy_distorted must have shape (..., 2); got {target.shape}")
        if self.is_identity:
            return target.copy()
        xy = target.copy()
        for _ in range(max_iter):
            mapped, jac = self._parametric(xy, jacobian=True)
            residual = mapped + self._field(xy) - target
            if np.max(np.abs(residual), initial=0.0) < tol_px:
                return xy
            xy = xy - _solve2(jac, residual)
        raise EstimationError(f"undistort did not converge to tol_px={tol_px} in {max_iter} iterations")

    def correction(self, xy_measured: np.ndarray) -> np.ndarray:
        """DESIGN's correction Δ on measured coordinates: ``ideal = measured - Δ(measured)``."""
        xy = np.asarray(xy_measured, dtype=np.float64)
        return xy - self.undistort(xy)

    def correction_grid(self, image_size_px: int, step_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Δ sampled on a regular grid of measured coordinates covering the image.

        Returns
        -------
        grid_x_px : (nx,) float64 ndarray, px
        grid_y_px : (ny,) float64 ndarray, px
        delta_px : (ny, nx, 2) float64 ndarray, px
            ``Δ(grid_x[j], grid_y[i])``; ideal = measured - Δ.
        """
        axis = np.arange(0.0, image_size_px - 1 + 1e-9, step_px)
        if axis[-1] < image_size_px - 1:
            axis = np.append(axis, image_size_px - 1.0)
        gx, gy = np.meshgrid(axis, axis)
        return axis, axis.copy(), self.correction(np.stack([gx, gy], axis=-1))

    def to_dict(self) -> dict:
        """JSON-serialisable parameters (floats kept exact)."""
        return {
            "model": "radial+S+decentring+bspline_field",
            "centre_xy_px": self.centre_xy_px.tolist(),
            "scale_px": float(self.scale_px),
            "k1": float(self.k1),
            "k2": float(self.k2),
            "s_rad": float(self.s_rad),
            "p1": float(self.p1),
            "p2": float(self.p2),
            "field_spacing_px": float(self.field_spacing_px),
            "field_origin_xy_px": self.field_origin_xy_px.tolist(),
            "field_coeffs_px": self.field_coeffs_px.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ImageDistortion:
        """Inverse of :meth:`to_dict`."""
        keys = (
            "centre_xy_px",
            "scale_px",
            "k1",
            "k2",
            "s_rad",
            "p1",
            "p2",
            "field_spacing_px",
            "field_origin_xy_px",
            "field_coeffs_px",
        )
        missing = [k for k in keys if k not in d]
        if missing:
            raise InputError(f"distortion dict misses keys: {', '.join(missing)}")
        return cls(**{k: (np.asarray(d[k], dtype=np.float64) if isinstance(d[k], list) else d[k]) for k in keys})


def _solve2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve 2×2 systems ``a (..., 2, 2) x = b (..., 2)`` by Cramer's rule (vectorised)."""
    det = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    out = np.empty(b.shape)
    out[..., 0] = (a[..., 1, 1] * b[..., 0] - a[..., 0, 1] * b[..., 1]) / det
    out[..., 1] = (a[..., 0, 0] * b[..., 1] - a[..., 1, 0] * b[..., 0]) / det
    return out


#: per level: (radial px at the field edge, S px at the edge, decentring px at the edge,
#: centre offset px, random-field RMS px), all for a 1024-px image
_DISTORTION_LEVELS = {
    "none": (0.0, 0.0, 0.0, 0.0, 0.0),
    "mild": (5.0, 2.0, 0.5, 3.0, 0.3),
    "strong": (15.0, 6.0, 1.5, 8.0, 0.6),
}
#: spacing of the random field's B-spline lattice at the detector (mm): correlation length ~64 px at 0.25 mm
_FIELD_SPACING_MM = 16.0


def make_distortion(params: SimulateParams, system: int) -> ImageDistortion:
    """Draw system ``system``'s distortion at level ``params.distortion`` (seeded, per system).

    Amplitudes vary by ±20 % between systems and the S and decentring
    directions are random; see ``_DISTORTION_LEVELS`` for the px amplitudes.
    """
    size = params.image_size_px
    radial_px, s_px, dec_px, centre_px, field_px = (v * params.px_scale for v in _DISTORTION_LEVELS[params.distortion])
    if params.distortion == "none":
        return ImageDistortion.identity(size)
    rng = np.random.default_rng([params.seed, _RNG_DIST, system])
    scale = size / 2.0
    amp = rng.uniform(0.8, 1.2, size=3)
    radial = radial_px * amp[0] / scale
    # tangential decentring at r = 1 has magnitude ~3 |p|
    dec_angle = rng.uniform(0, 2 * np.pi)
    p = dec_px * amp[2] / (3 * scale)
    spacing = _FIELD_SPACING_MM / params.pixel_pitch_mm
    n_nodes = int(np.ceil(size / spacing)) + 7
    origin = np.full(2, (size - 1) / 2.0 - spacing * (n_nodes - 1) / 2)
    coeffs = rng.normal(size=(2, n_nodes, n_nodes))
    base = ImageDistortion(
        np.zeros(2), scale, field_spacing_px=spacing, field_origin_xy_px=origin, field_coeffs_px=coeffs
    )
    g = np.linspace(0, size - 1, 48)
    sample = np.stack(np.meshgrid(g, g), axis=-1)
    rms = np.sqrt(np.mean(np.sum(base._field(sample) ** 2, axis=-1)))
    return ImageDistortion(
        centre_xy_px=np.full(2, (size - 1) / 2.0) + rng.uniform(-centre_px, centre_px, size=2),
        scale_px=scale,
        k1=0.8 * radial,
        k2=0.2 * radial,
        s_rad=rng.choice([-1.0, 1.0]) * s_px * amp[1] / scale,
        p1=p * np.cos(dec_angle),
        p2=p * np.sin(dec_angle),
        field_spacing_px=spacing,
        field_origin_xy_px=origin,
        field_coeffs_px=coeffs * (field_px / rms),
    )


# --------------------------------------------------------------------------- acquisition


@dataclass(frozen=True, eq=False)
class SystemTruth:
    """One imaging system's true geometry.

    Attributes
    ----------
    name : str
    iop_px : (3,) float64 ndarray, px
        ``(xp, yp, c)``.
    distortion : ImageDistortion
    lab_from_camera_q : (4,) float64 ndarray
        Quaternion rotating camera-frame vectors into the lab frame (z up).
    source_lab_mm : (3,) float64 ndarray, mm
        Source position in the lab frame (isocentre at the origin).
    source_image_distance_mm : float, mm
    """

    name: str
    iop_px: np.ndarray
    distortion: ImageDistortion
    lab_from_camera_q: np.ndarray
    source_lab_mm: np.ndarray
    source_image_distance_mm: float

    def __post_init__(self):
        freeze(self)


@dataclass(frozen=True, eq=False)
class Acquisition:
    """Systems and exposures: everything geometric except the phantom.

    Attributes
    ----------
    systems : tuple of SystemTruth
    turntable_angle_rad : (K,) float64 ndarray, rad
        Phantom rotation about the vertical lab axis at each exposure.
    turntable_translation_mm : (K, 3) float64 ndarray, mm
        Phantom origin in the lab frame at each exposure.
    lab_from_phantom_q : (K, 4) float64 ndarray
        Phantom orientation at each exposure (for a cube: the turntable rotation).
    q : (S, K, 4) float64 ndarray
        Camera pose rotation (object -> camera) of system s at exposure k.
    source_mm : (S, K, 3) float64 ndarray, mm
        X-ray source in object (phantom) coordinates.
    """

    systems: tuple
    turntable_angle_rad: np.ndarray
    turntable_translation_mm: np.ndarray
    lab_from_phantom_q: np.ndarray
    q: np.ndarray
    source_mm: np.ndarray

    def __post_init__(self):
        freeze(self)


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _small_rotation(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    return quat_to_matrix(np.concatenate([[1.0], np.radians(rng.uniform(-max_deg, max_deg, 3)) / 2]))


def _turntable_angles(params: SimulateParams) -> np.ndarray:
    """``n_frames`` angles spread evenly over those that keep every system off edge-on walls."""
    candidates = np.radians(np.arange(0.0, 360.0, 0.25))
    ok = np.ones(candidates.shape, dtype=bool)
    for s in range(params.n_systems):
        rel = np.degrees(np.radians(s * params.system_angle_deg) - candidates) % 90.0
        ok &= np.minimum(rel, 90.0 - rel) >= params.min_face_angle_deg
    allowed = candidates[ok]
    if allowed.size == 0:
        raise InputError(
            f"min_face_angle_deg={params.min_face_angle_deg} leaves no turntable angle for system_angle_deg={params.system_angle_deg}"
        )
    idx = ((np.arange(params.n_frames) + 0.5) * allowed.size / params.n_frames).astype(int)
    return allowed[idx]


def make_acquisition(params: SimulateParams) -> Acquisition:
    """Place the systems in the lab and the phantom on the turntable for every exposure.

    Lab frame: z up, isocentre at the origin. System s looks horizontally
    along azimuth ``s * system_angle_deg``; camera y points down (image rows).
    """
    rng = np.random.default_rng([params.seed, _RNG_ACQ])
    sod_mm = params.source_image_distance_mm / params.magnification
    systems = []
    for s in range(params.n_systems):
        phi = np.radians(s * params.system_angle_deg)
        view = np.array([np.cos(phi), np.sin(phi), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        # rows: camera x, y, z expressed in lab coordinates (camera_from_lab)
        nominal = np.stack([np.cross(down, view), down, view])
        camera_from_lab = _small_rotation(rng, params.system_misalignment_deg) @ nominal
        sid = params.source_image_distance_mm * rng.uniform(0.99, 1.01)
        offset = rng.uniform(-1, 1, 2) * params.principal_point_offset_px * params.px_scale
        iop = np.array([*(params.image_centre_xy_px + offset), sid / params.pixel_pitch_mm])
        systems.append(
            SystemTruth(
                SYSTEM_NAMES[s],
                iop,
                make_distortion(params, s),
                matrix_to_quat(camera_from_lab.T),
                -sod_mm * view,
                float(sid),
            )
        )
    k = params.n_frames
    if params.phantom == "cube":
        angles = _turntable_angles(params)
        heights = np.linspace(-1, 1, k) if k > 1 else np.zeros(1)
        heights = rng.permutation(heights) * params.turntable_height_mm
        shifts = rng.uniform(-1, 1, (k, 2)) * params.turntable_translation_mm
        translation = np.column_stack([shifts, heights])
        lab_from_phantom = np.stack([_rot_z(a) for a in angles])
    else:
        # plate on system A's detector face, normal along the beam, small tilts and shifts
        angles = rng.uniform(0, 2 * np.pi, k)
        view = quat_to_matrix(systems[0].lab_from_camera_q)
        lab_from_phantom = np.stack([view @ _small_rotation(rng, 5.0) @ _rot_z(a) for a in angles])
        depth = params.source_image_distance_mm / params.grid_magnification
        # shifts in camera coordinates: up to 5 mm across the beam, 1 mm along it
        shifts = (rng.uniform(-5, 5, (k, 3)) * [1.0, 1.0, 0.2]) @ view.T
        translation = systems[0].source_lab_mm + depth * view[:, 2] + shifts
    q = np.empty((params.n_systems, k, 4))
    source = np.empty((params.n_systems, k, 3))
    for s, system in enumerate(systems):
        camera_from_lab = quat_to_matrix(system.lab_from_camera_q).T
        for i in range(k):
            # p_cam = C (R_k P + t_k - S) = (C R_k) (P - R_kᵀ (S - t_k))
            q[s, i] = matrix_to_quat(camera_from_lab @ lab_from_phantom[i])
            source[s, i] = lab_from_phantom[i].T @ (system.source_lab_mm - translation[i])
    return Acquisition(
        tuple(systems), np.asarray(angles, dtype=np.float64), translation, matrix_to_quat(lab_from_phantom), q, source
    )


# --------------------------------------------------------------------------- projection truth


@dataclass(frozen=True, eq=False)
class FrameTruth:
    """Truth of one frame: the pose and every (at least partly) visible bead.

    Attributes
    ----------
    system : int
    exposure : int
    q : (4,) float64 ndarray
        Pose rotation (object -> camera).
    source_mm : (3,) float64 ndarray, mm
        X-ray source in object coordinates.
    ids : (N,) int64 ndarray
        Phantom ids of the beads whose outline meets the field of view.
    ideal_xy_px : (N, 2) float64 ndarray, px
        Pinhole projection of the sphere (or hole) centre.
    distorted_xy_px : (N, 2) float64 ndarray, px
        ``distortion.distort(ideal_xy_px)``.
    outline_ideal_xy_px : (N, 2) float64 ndarray, px
        Centre of the ideal outline ellipse (exact conic centre).
    outline_xy_px : (N, 2) float64 ndarray, px
        Distorted outline centre (area centroid of the distorted outline; see module docstring).
    diameter_px : (N,) float64 ndarray, px
        Equal-area diameter of the distorted outline.
    overlap : (N,) bool ndarray
        The outline comes within ``overlap_margin_px`` of another bead's outline.
    field_edge : (N,) bool ndarray
        The outline reaches within ``overlap_margin_px`` of the field-of-view rim or the image border.
    """

    system: int
    exposure: int
    q: np.ndarray
    source_mm: np.ndarray
    ids: np.ndarray
    ideal_xy_px: np.ndarray
    distorted_xy_px: np.ndarray
    outline_ideal_xy_px: np.ndarray
    outline_xy_px: np.ndarray
    diameter_px: np.ndarray
    overlap: np.ndarray
    field_edge: np.ndarray

    def __post_init__(self):
        freeze(self)

    def __len__(self) -> int:
        return len(self.ids)

    #: per-bead array fields, in the order of ``to_dict``
    BEAD_FIELDS = (
        "ids",
        "ideal_xy_px",
        "distorted_xy_px",
        "outline_ideal_xy_px",
        "outline_xy_px",
        "diameter_px",
        "overlap",
        "field_edge",
    )


def _circle_ellipse(
    centre_cam: np.ndarray, e1_cam: np.ndarray, e2_cam: np.ndarray, radius: np.ndarray, iop: np.ndarray
):
    """Perspective image of 3D circles as ellipses ``centre + L (cos t, sin t)``.

    Parameters
    ----------
    centre_cam, e1_cam, e2_cam : (N, 3) float64 ndarray
        Circle centres (mm, camera frame) and orthonormal bases of their planes.
    radius : (N,) float64 ndarray, mm
    iop : (3,) float64 ndarray, px

    Returns
    -------
    centre_xy_px : (N, 2) float64 ndarray, px
        Exact centres of the image conics.
    axes_px : (N, 2, 2) float64 ndarray, px
        Columns are the semi-axis vectors.

    Notes
    -----
    With ``H = K [e1 e2 c]`` mapping plane coordinates ``(α, β, 1)`` to the image,
    the circle ``α² + β² = r²`` images to the conic ``Q = H⁻ᵀ diag(1, 1, -r²) H⁻¹``.
    """
    xp, yp, c = iop
    K = np.array([[c, 0, xp], [0, c, yp], [0, 0, 1.0]])
    # shape (N, 3, 3)
    H = K @ np.stack([e1_cam, e2_cam, centre_cam], axis=-1)
    Hinv = np.linalg.inv(H)
    D = np.zeros((len(radius), 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = -(np.asarray(radius, dtype=np.float64) ** 2)
    Q = np.swapaxes(Hinv, -1, -2) @ D @ Hinv
    A, b, f = Q[:, :2, :2], Q[:, :2, 2], Q[:, 2, 2]
    centre = -np.linalg.solve(A, b[..., None])[..., 0]
    g = f + np.einsum("ni,ni->n", b, centre)
    lam, V = np.linalg.eigh(A / -g[:, None, None])
    return centre, V * (1.0 / np.sqrt(lam))[:, None, :]


def _sphere_outline_circles(centre_cam: np.ndarray, radius_mm: np.ndarray):
    """Circles of tangency of the cones from the source (camera origin) to spheres.

    Returns ``(centre, e1, e2, radius)`` as for :func:`_circle_ellipse`.
    """
    dist = np.linalg.norm(centre_cam, axis=1)
    u = centre_cam / dist[:, None]
    ratio2 = (radius_mm / dist) ** 2
    centre = centre_cam * (1.0 - ratio2)[:, None]
    helper = np.where(np.abs(u[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return centre, e1, e2, radius_mm * np.sqrt(1.0 - ratio2)


def _polygon_centroid_area(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area centroids ``(N, 2)`` and areas ``(N,)`` of closed polygons ``(N, M, 2)`` (shoelace)."""
    x, y = points[..., 0], points[..., 1]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * y1 - x1 * y
    area = cross.sum(-1) / 2
    cx = ((x + x1) * cross).sum(-1) / (6 * area)
    cy = ((y + y1) * cross).sum(-1) / (6 * area)
    return np.column_stack([cx, cy]), np.abs(area)


@dataclass(frozen=True, eq=False)
class _Outlines:
    """Every bead's projection in one frame (all beads, before selecting the visible ones)."""

    ideal_xy_px: np.ndarray
    distorted_xy_px: np.ndarray
    outline_ideal_xy_px: np.ndarray
    outline_xy_px: np.ndarray
    diameter_px: np.ndarray
    radius_max_px: np.ndarray  # largest distance from the distorted outline centre to the outline


def _project_outlines(
    xyz_mm, diameter_mm, q, source_mm, iop, distortion: ImageDistortion, *, hole_axis: bool
) -> _Outlines:
    ideal = project(xyz_mm, q, source_mm, iop)
    centre_cam = to_camera(xyz_mm, q, source_mm)
    radius = np.asarray(diameter_mm, dtype=np.float64) / 2
    if hole_axis:
        R = quat_to_matrix(q)
        n = len(radius)
        circles = (centre_cam, np.tile(R[:, 0], (n, 1)), np.tile(R[:, 1], (n, 1)), radius)
    else:
        circles = _sphere_outline_circles(centre_cam, radius)
    centre, axes = _circle_ellipse(*circles, iop)
    t = np.linspace(0, 2 * np.pi, N_OUTLINE, endpoint=False)
    # shape (N, N_OUTLINE, 2)
    ring = centre[:, None, :] + np.einsum("nij,mj->nmi", axes, np.column_stack([np.cos(t), np.sin(t)]))
    ring_d = distortion.distort(ring)
    outline_xy, area = _polygon_centroid_area(ring_d)
    radius_max = np.max(np.linalg.norm(ring_d - outline_xy[:, None, :], axis=-1), axis=1)
    return _Outlines(ideal, distortion.distort(ideal), centre, outline_xy, 2 * np.sqrt(area / np.pi), radius_max)


def project_beads(
    ids: np.ndarray,
    xyz_mm: np.ndarray,
    diameter_mm: np.ndarray,
    q: np.ndarray,
    source_mm: np.ndarray,
    iop: np.ndarray,
    distortion: ImageDistortion,
    *,
    image_size_px: int,
    fov_radius_px: float,
    overlap_margin_px: float = 2.0,
    holes: bool = False,
    system: int = 0,
    exposure: int = 0,
) -> FrameTruth:
    """Truth of one frame: project beads (spheres, or plate holes if ``holes``) through pose, IOP and distortion.

    Parameters
    ----------
    ids : (N,) int ndarray
    xyz_mm : (N, 3) float64 ndarray, mm
        True centres in object coordinates.
    diameter_mm : (N,) float64 ndarray, mm
    q, source_mm, iop : pose ``(q, T)`` and interior orientation ``(xp, yp, c)`` px
    distortion : ImageDistortion
    image_size_px : int
    fov_radius_px : float, px
        Round field of view centred on the image centre.
    overlap_margin_px : float, px
    holes : bool
        Holes of a plate whose normal is the object z axis (outline = mid-plane circle).

    Returns
    -------
    FrameTruth
        Beads whose distorted outline meets the field of view, in id order.
    """
    xyz_mm = check_points("xyz_mm", xyz_mm, 3)
    ids = np.asarray(ids, dtype=np.int64)
    diameter_mm = np.asarray(diameter_mm, dtype=np.float64)
    if ids.shape != (len(xyz_mm),) or diameter_mm.shape != (len(xyz_mm),):
        raise InputError(
            f"ids and diameter_mm must have shape ({len(xyz_mm)},); got {ids.shape} and {diameter_mm.shape}"
        )
    o = _project_outlines(xyz_mm, diameter_mm, q, source_mm, iop, distortion, hole_axis=holes)
    centre = np.full(2, (image_size_px - 1) / 2.0)
    r_fov = np.linalg.norm(o.outline_xy_px - centre, axis=1)
    rad = o.radius_max_px
    lo, hi = o.outline_xy_px - rad[:, None], o.outline_xy_px + rad[:, None]
    in_image = np.all((hi >= -0.5) & (lo <= image_size_px - 0.5), axis=1)
    visible = (r_fov < fov_radius_px + rad) & in_image
    margin = overlap_margin_px
    field_edge = (r_fov > fov_radius_px - rad - margin) | np.any(
        (lo < -0.5 + margin) | (hi > image_size_px - 0.5 - margin), axis=1
    )
    overlap = np.zeros(len(ids), dtype=bool)
    if len(ids) > 1:
        from scipy.spatial import cKDTree

        tree = cKDTree(o.outline_xy_px)
        pairs = tree.query_pairs(2 * rad.max() + margin, output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
        close = np.linalg.norm(o.outline_xy_px[i] - o.outline_xy_px[j], axis=1) < rad[i] + rad[j] + margin
        overlap[i[close]] = True
        overlap[j[close]] = True
    sel = np.flatnonzero(visible)
    sel = sel[np.argsort(ids[sel], kind="stable")]
    return FrameTruth(
        system,
        exposure,
        np.asarray(q, dtype=np.float64),
        np.asarray(source_mm, dtype=np.float64),
        ids[sel],
        o.ideal_xy_px[sel],
        o.distorted_xy_px[sel],
        o.outline_ideal_xy_px[sel],
        o.outline_xy_px[sel],
        o.diameter_px[sel],
        overlap[sel],
        field_edge[sel],
    )


# --------------------------------------------------------------------------- rendering


@dataclass(frozen=True, eq=False)
class _SystemRaster:
    """Per-system pixel geometry, shared by all of that system's frames.

    Attributes
    ----------
    ideal_xy : (H, W, 2) float64 ndarray, px
        Ideal (undistorted) coordinates of every output pixel centre.
    rays : (3, H*W) float32 ndarray
        Unit ray directions of the pixel centres in the camera frame (components first, for speed).
    fov : (H, W) float32 ndarray
        Intensifier input disc with a one-pixel linear rim (1 inside, 0 outside).
    radial2 : (H, W) float32 ndarray
        ``(r / fov_radius)²`` about the image centre.
    """

    ideal_xy: np.ndarray
    rays: np.ndarray
    fov: np.ndarray
    radial2: np.ndarray


def ideal_pixel_map(distortion: ImageDistortion, image_size_px: int) -> np.ndarray:
    """Ideal coordinates ``(H, W, 2)`` px of every pixel centre of the distorted image.

    The inverse distortion is solved exactly (Newton) on a lattice every 1-8 px,
    interpolated by a bicubic spline as a starting point and polished by Newton
    steps on every pixel until the forward map returns each pixel centre to
    1e-7 px (tested against :meth:`ImageDistortion.undistort`: < 1e-6 px).
    """
    from scipy.interpolate import RectBivariateSpline

    axis = np.arange(image_size_px, dtype=np.float64)
    gx, gy = np.meshgrid(axis, axis)
    target = np.stack([gx, gy], axis=-1)
    if distortion.is_identity:
        return target
    # lattice step: 1/16 of the random field's spacing (4 px at 1024 px), so the spline start is within ~1e-4 px
    step = float(np.clip(distortion.field_spacing_px / 16, 1.0, 8.0))
    coarse = np.unique(np.append(np.arange(-4 * step, image_size_px + 4 * step, step), image_size_px - 1))
    cx, cy = np.meshgrid(coarse, coarse)
    ideal_coarse = distortion.undistort(np.stack([cx, cy], axis=-1))
    guess = np.stack([RectBivariateSpline(coarse, coarse, ideal_coarse[..., i])(axis, axis) for i in range(2)], axis=-1)
    # Newton polish: the spline start is within ~1e-4 px and each step gains a factor |∇field| < 0.05.
    # The Jacobian of the first step is reused: over 1e-4 px it changes by far less than that factor.
    _, jac = distortion._parametric(guess, jacobian=True)
    for _ in range(5):
        residual = distortion.distort(guess) - target
        if np.max(np.abs(residual)) < 1e-7:
            break
        guess = guess - _solve2(jac, residual)
    return guess


def _pixel_rays(ideal_xy: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """Unit camera-frame rays ``(..., 3)`` through ideal image points ``(..., 2)``."""
    xp, yp, c = iop
    d = np.stack([(ideal_xy[..., 0] - xp) / c, (ideal_xy[..., 1] - yp) / c, np.ones(ideal_xy.shape[:-1])], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _system_raster(params: SimulateParams, system: SystemTruth) -> _SystemRaster:
    size = params.image_size_px
    ideal = ideal_pixel_map(system.distortion, size)
    axis = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    r = np.hypot(axis[None, :], axis[:, None])
    fov = np.clip(params.fov_radius_px - r + 0.5, 0.0, 1.0).astype(np.float32)
    rays = np.ascontiguousarray(_pixel_rays(ideal, system.iop_px).reshape(-1, 3).T, dtype=np.float32)
    return _SystemRaster(ideal, rays, fov, ((r / params.fov_radius_px) ** 2).astype(np.float32))


def _box_chord(a: tuple, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Length of each ray inside an axis-aligned box.

    ``a`` : three ``(M,)`` arrays, the unit rays' components along the box
    axes; ``lo``, ``hi`` : (3,) box bounds relative to the ray origin.
    """
    enter = leave = None
    with np.errstate(divide="ignore", invalid="ignore"):
        for a_i, lo_i, hi_i in zip(a, lo, hi):
            inv = 1.0 / a_i
            s1, s2 = lo_i * inv, hi_i * inv
            near, far = np.minimum(s1, s2), np.maximum(s1, s2)
            enter = near if enter is None else np.maximum(enter, near)
            leave = far if leave is None else np.minimum(leave, far)
    return np.maximum(leave - enter, 0.0)


def _background_line_integral(
    params: SimulateParams, rays: np.ndarray, q: np.ndarray, source_mm: np.ndarray
) -> np.ndarray:
    """μ·length through the acrylic walls (cube) or the steel plate (grid) along each ray ``(M,)``.

    ``rays`` : (3, M) float32 unit rays in the camera frame.
    """
    R = quat_to_matrix(q).astype(np.float32)
    # components of each ray along the object axes: a_j = rays · (R e_j)
    a = tuple(R[0, j] * rays[0] + R[1, j] * rays[1] + R[2, j] * rays[2] for j in range(3))
    T = np.asarray(source_mm, dtype=np.float32)
    if params.phantom == "grid":
        with np.errstate(divide="ignore"):
            return params.mu_steel_per_mm * params.grid_thickness_mm / np.abs(a[2])
    half = params.cube_side_mm / 2
    inner = half - params.wall_thickness_mm
    outer_len = _box_chord(
        a, np.array([-half, -half, -half], np.float32) - T, np.array([half, half, half], np.float32) - T
    )
    inner_len = _box_chord(
        a, np.array([-inner, -inner, -half], np.float32) - T, np.array([inner, inner, half], np.float32) - T
    )
    return params.mu_acrylic_per_mm * (outer_len - inner_len)


def _dot3(a: tuple, b: tuple) -> np.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _sphere_chords(rays: tuple, centre_cam: tuple, radius_mm: np.ndarray, c_px: float):
    """Chord lengths (mm) of unit rays from the origin through spheres, and the px distance to the outline.

    ``rays`` and ``centre_cam`` are triples of broadcastable component arrays; ``radius_mm`` broadcasts with them.
    """
    b = _dot3(rays, centre_cam)
    dist2 = np.maximum(_dot3(centre_cam, centre_cam) - b * b, 0.0)
    chord = 2.0 * np.sqrt(np.maximum(radius_mm**2 - dist2, 0.0))
    # mm per px at the sphere's distance is |C| / c
    edge_px = np.abs(np.sqrt(dist2) - radius_mm) * c_px / np.sqrt(b * b + dist2)
    return chord, edge_px


def _hole_chords(rays: tuple, centre_cam: tuple, radius_mm, c_px: float, *, axis_cam: np.ndarray, thickness_mm: float):
    """Lengths (mm) of unit rays inside cylindrical holes through a plate, and the px distance to the outline.

    The holes' axis is ``axis_cam`` (the plate normal, camera frame); the plate
    spans ``±thickness_mm / 2`` about each centre along it. ``rays`` and
    ``centre_cam`` are triples of broadcastable component arrays.
    """
    dn = _dot3(rays, axis_cam)
    cn = _dot3(centre_cam, axis_cam)
    d_perp = tuple(r - dn * n for r, n in zip(rays, axis_cam))
    c_perp = tuple(c - cn * n for c, n in zip(centre_cam, axis_cam))
    A = _dot3(d_perp, d_perp)
    B = _dot3(d_perp, c_perp)
    disc = B * B - A * (_dot3(c_perp, c_perp) - radius_mm**2)
    root = np.sqrt(np.maximum(disc, 0.0))
    safe_A = np.maximum(A, 1e-30)
    # ray parameter interval inside the (infinite) cylinder, and inside the plate
    c_lo = np.where(disc > 0, (B - root) / safe_A, 0.0)
    c_hi = np.where(disc > 0, (B + root) / safe_A, 0.0)
    p1, p2 = (cn - thickness_mm / 2) / dn, (cn + thickness_mm / 2) / dn
    length = np.maximum(np.minimum(c_hi, np.maximum(p1, p2)) - np.maximum(c_lo, np.minimum(p1, p2)), 0.0)
    s_mid = cn / dn
    dist_mid = np.sqrt(_dot3(*[tuple(s_mid * d - c for d, c in zip(d_perp, c_perp))] * 2))
    px_per_mm = c_px / s_mid
    slant_px = thickness_mm / 2 * np.sqrt(A) / np.abs(dn) * px_per_mm
    return length, np.maximum(np.abs(dist_mid - radius_mm) * px_per_mm - slant_px, 0.0)


def _subsample_offsets(n: int) -> np.ndarray:
    """``(n, 2)`` sub-pixel offsets in ``[-0.5, 0.5)²`` on a Fibonacci lattice of ``n`` points.

    A Fibonacci lattice covers the square more evenly than a regular grid of
    similar size: on an opaque bead's edge, 21 points leave the centroid within
    ~0.01 px of the outline centre where a 4 × 4 grid leaves ~0.02 px.
    """
    generator = _FIBONACCI[_FIBONACCI.index(n) - 1] if n in _FIBONACCI[1:] else 3
    i = np.arange(n)
    return np.column_stack([(i + 0.5) / n - 0.5, ((i * generator) / n + 0.5 / n) % 1.0 - 0.5])


def _local_jacobian(ideal_xy: np.ndarray, flat_idx: np.ndarray) -> np.ndarray:
    """``(M, 2, 2)`` derivative of the ideal map at pixels ``flat_idx`` (central differences)."""
    h, w = ideal_xy.shape[:2]
    y, x = np.divmod(flat_idx, w)
    cols = []
    for dx, dy in ((1, 0), (0, 1)):
        x1, x0 = np.minimum(x + dx, w - 1), np.maximum(x - dx, 0)
        y1, y0 = np.minimum(y + dy, h - 1), np.maximum(y - dy, 0)
        span = (x1 - x0) + (y1 - y0)
        cols.append((ideal_xy[y1, x1] - ideal_xy[y0, x0]) / span[:, None])
    return np.stack(cols, axis=-1)


def _feature_line_integrals(params, raster: _SystemRaster, system: SystemTruth, q, source_mm, xyz_mm, diameter_mm):
    """Per-pixel μ·length of the beads (holes) and supersampled transmission on their edges.

    Returns
    -------
    line : (H*W,) float64 ndarray
        Sum over features of Δμ · chord at pixel centres.
    edge_idx : (E,) int64 ndarray
        Flat indices of the pixels on a feature edge.
    edge_line : (E, S) float64 ndarray
        The same sum at S sub-samples of each edge pixel.
    """
    size = params.image_size_px
    iop = system.iop_px
    c_px = iop[2]
    holes = params.phantom == "grid"
    centre_cam = to_camera(xyz_mm, q, source_mm)
    radius = np.asarray(diameter_mm, dtype=np.float64) / 2
    if holes:
        axis_cam = quat_to_matrix(q)[:, 2]
        delta_mu = np.full(len(radius), -params.mu_steel_per_mm)

        def chords(rays, centres, radii):
            return _hole_chords(rays, centres, radii, c_px, axis_cam=axis_cam, thickness_mm=params.grid_thickness_mm)
    else:
        delta_mu = np.full(len(radius), params.mu_steel_per_mm - params.mu_acrylic_per_mm)

        def chords(rays, centres, radii):
            return _sphere_chords(rays, centres, radii, c_px)

    # box around each feature's distorted centre: radius in px with 10 % for distortion and obliquity, + 2 px
    centre_px = system.distortion.distort(project(xyz_mm, q, source_mm, iop))
    half_px = np.ceil(c_px * radius / np.linalg.norm(centre_cam, axis=1) * 1.1 + 2).astype(np.int64)
    pix_list, feat_list = [], []
    for h in np.unique(half_px):
        sel = np.flatnonzero(half_px == h)
        off = np.arange(-h, h + 1)
        # shape (n_sel, 2h+1, 2h+1)
        cx = np.rint(centre_px[sel, 0]).astype(np.int64)[:, None, None] + off[None, None, :]
        cy = np.rint(centre_px[sel, 1]).astype(np.int64)[:, None, None] + off[None, :, None]
        cx, cy = np.broadcast_arrays(cx, cy)
        ok = (cx >= 0) & (cx < size) & (cy >= 0) & (cy < size)
        pix_list.append((cy * size + cx)[ok])
        feat_list.append(np.broadcast_to(sel[:, None, None], ok.shape)[ok])
    pix = np.concatenate(pix_list)
    feat = np.concatenate(feat_list)
    rays = tuple(r[pix].astype(np.float64) for r in raster.rays)
    # contiguous per-component gathers (a transposed (M, 3) gather would be strided and slow)
    centres = tuple(np.ascontiguousarray(centre_cam[:, j])[feat] for j in range(3))
    chord, edge_px = chords(rays, centres, radius[feat])
    line = np.bincount(pix, weights=delta_mu[feat] * chord, minlength=size * size)

    # pixels within a pixel of any outline: integrate the transmission over sub-samples
    edge_idx = np.unique(pix[edge_px < 1.0])
    is_edge = np.zeros(size * size, dtype=bool)
    is_edge[edge_idx] = True
    # pairs more than a pixel outside their feature contribute nothing to any sub-sample
    in_edge = is_edge[pix] & ((chord > 0) | (edge_px < 1.0))
    rows = np.searchsorted(edge_idx, pix[in_edge])
    offsets = _subsample_offsets(params.supersample)
    pair_pix = pix[in_edge]
    # ray slopes (x - xp) / c of each pair's pixel centre and their derivatives by the pixel offset
    slope = (raster.ideal_xy.reshape(-1, 2)[pair_pix] - iop[:2]) / iop[2]
    d_slope = _local_jacobian(raster.ideal_xy, pair_pix) / iop[2]
    # shape (P, S) per component: first-order map of the sub-sample offsets through the inverse distortion
    u = slope[:, 0, None] + d_slope[:, 0, 0, None] * offsets[:, 0] + d_slope[:, 0, 1, None] * offsets[:, 1]
    v = slope[:, 1, None] + d_slope[:, 1, 0, None] * offsets[:, 0] + d_slope[:, 1, 1, None] * offsets[:, 1]
    inv_norm = 1.0 / np.sqrt(u * u + v * v + 1.0)
    f = feat[in_edge]
    in_centres = tuple(c_j[in_edge][:, None] for c_j in centres)
    sub_chord, _ = chords((u * inv_norm, v * inv_norm, inv_norm), in_centres, radius[f][:, None])
    n_sub = len(offsets)
    flat = (rows[:, None] * n_sub + np.arange(n_sub)).ravel()
    edge_line = np.bincount(flat, weights=(delta_mu[f][:, None] * sub_chord).ravel(), minlength=len(edge_idx) * n_sub)
    return line, edge_idx, edge_line.reshape(len(edge_idx), n_sub)


def _blur_sigma_px(params: SimulateParams) -> float:
    """Gaussian sigma (px) of focal-spot penumbra (at the isocentre's magnification) and intensifier blur."""
    focal = params.focal_spot_mm * (params.magnification - 1.0) / 2.3548
    return float(np.hypot(focal, params.intensifier_blur_mm) / params.pixel_pitch_mm)


def _form_image(
    params: SimulateParams, raster: _SystemRaster, transmission: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Detector chain from transmission ``(H, W)`` to quantised DN ``(H, W) uint16``."""
    import cv2

    size = params.image_size_px
    y = (np.arange(size, dtype=np.float32) - (size - 1) / 2.0) / np.float32(params.fov_radius_px)
    heel = (1.0 + params.heel * y)[:, None]
    primary = (transmission * heel * raster.fov).astype(np.float32)
    sigma = _blur_sigma_px(params)
    if sigma > 0.05:
        primary = cv2.GaussianBlur(primary, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    if params.glare_fraction > 0:
        # veiling glare: a wide Gaussian, computed at 1/8 resolution (it has no fine detail)
        f = 8 if size >= 64 else 1
        low = cv2.resize(primary, (size // f, size // f), interpolation=cv2.INTER_AREA) if f > 1 else primary
        low = cv2.GaussianBlur(
            low, (0, 0), params.glare_sigma_mm / params.pixel_pitch_mm / f, borderType=cv2.BORDER_CONSTANT
        )
        glare = cv2.resize(low, (size, size), interpolation=cv2.INTER_LINEAR) if f > 1 else low
        primary = (1.0 - params.glare_fraction) * primary + params.glare_fraction * glare
    signal = params.open_field_dn * primary * (1.0 - params.vignetting * raster.radial2)
    image = signal + params.dark_dn
    if params.noise_scale > 0:
        # quantum noise by its normal approximation (>= ~500 quanta per pixel inside the field)
        std = params.noise_scale * np.sqrt(
            params.gain_dn_per_quantum * np.maximum(signal, 0) + params.electronic_noise_dn**2
        )
        image = image + std * rng.standard_normal(image.shape, dtype=np.float32)
    return np.clip(np.rint(image), 0, 2**params.bit_depth - 1).astype(np.uint16)


def render_frame(
    params: SimulateParams,
    system: SystemTruth,
    q: np.ndarray,
    source_mm: np.ndarray,
    xyz_mm: np.ndarray,
    diameter_mm: np.ndarray,
    *,
    rng: np.random.Generator,
    raster: _SystemRaster | None = None,
) -> np.ndarray:
    """Render one radiograph of beads (or plate holes) at true positions ``xyz_mm``.

    Parameters
    ----------
    params : SimulateParams
    system : SystemTruth
        IOP and distortion of the imaging system.
    q, source_mm : pose ``(q, T)`` of the exposure (object -> camera).
    xyz_mm : (N, 3) float64 ndarray, mm
    diameter_mm : (N,) float64 ndarray, mm
    rng : numpy Generator
        Noise source.
    raster : optional
        The system's cached pixel geometry (computed if None).

    Returns
    -------
    image : (H, W) uint16 ndarray, DN
        Values in ``0 .. 2**bit_depth - 1``.
    """
    xyz_mm = check_points("xyz_mm", xyz_mm, 3)
    raster = raster or _system_raster(params, system)
    size = params.image_size_px
    background = _background_line_integral(params, raster.rays, q, source_mm).astype(np.float64)
    line, edge_idx, edge_line = _feature_line_integrals(params, raster, system, q, source_mm, xyz_mm, diameter_mm)
    transmission = np.exp(-(background + line))
    transmission[edge_idx] = np.mean(np.exp(-(background[edge_idx, None] + edge_line)), axis=1)
    return _form_image(params, raster, transmission.reshape(size, size), rng)


# --------------------------------------------------------------------------- simulate


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth of a simulated data set.

    Attributes
    ----------
    true_xyz_mm : (N, 3) float64 ndarray, mm
        True bead (hole) centres in phantom coordinates, in ``phantom.ids`` order.
    reference_xyz_mm : (N, 3) float64 ndarray, mm
        Reference check points (true + survey noise).
    acquisition : Acquisition
        Systems (IOP, distortion, lab placement) and per-exposure poses.
    frames : tuple of tuple of FrameTruth
        ``frames[system][exposure]``.
    """

    true_xyz_mm: np.ndarray
    reference_xyz_mm: np.ndarray
    acquisition: Acquisition
    frames: tuple

    def __post_init__(self):
        freeze(self)

    @property
    def systems(self) -> tuple:
        return self.acquisition.systems


@dataclass(frozen=True, eq=False)
class SimulatedData:
    """A simulated acquisition: frames, nominal phantom and ground truth.

    Attributes
    ----------
    params : SimulateParams
    phantom : Phantom
        Nominal (design) phantom, as written to ``phantom.csv``.
    truth : Truth
    frames : tuple of tuple of Radiograph
        ``frames[system][exposure]``; empty tuples when simulated with ``render=False``.
    """

    params: SimulateParams
    phantom: Phantom
    truth: Truth
    frames: tuple

    @property
    def system_names(self) -> tuple:
        return tuple(s.name for s in self.truth.systems)


def simulate(
    params: SimulateParams, *, render: bool = True, phantom: Phantom | None = None, on_frame=None
) -> SimulatedData:
    """Simulate an acquisition with its ground truth.

    Parameters
    ----------
    params : SimulateParams
    render : bool
        False skips image formation (geometry and truth only: fast).
    phantom : Phantom, optional
        Use these beads instead of ``make_phantom(params)``; its coordinates are
        then taken as exact (true = reference = nominal). Spheres for
        ``params.phantom == "cube"`` (the acrylic box is still present unless
        ``mu_acrylic_per_mm`` is 0), plate holes for ``"grid"``.
    on_frame : callable, optional
        Called as ``on_frame(system, exposure)`` after each rendered frame (progress reporting).

    Returns
    -------
    SimulatedData

    Examples
    --------
    >>> data = simulate(SimulateParams(n_frames=2, image_size_px=128), render=False)
    >>> data.system_names, len(data.truth.frames[0]), data.frames
    (('A',), 2, ((),))
    """
    if phantom is None:
        nominal, true_xyz, reference_xyz = make_phantom(params)
    else:
        nominal = phantom
        true_xyz = reference_xyz = phantom.xyz_mm.copy()
    default_mm = params.grid_hole_diameter_mm if params.phantom == "grid" else params.bead_diameter_mm
    diameter = np.where(np.isfinite(nominal.diameter_mm), nominal.diameter_mm, default_mm)
    acq = make_acquisition(params)
    holes = params.phantom == "grid"
    truth_frames, frames = [], []
    for s, system in enumerate(acq.systems):
        per_system = []
        for k in range(params.n_frames):
            per_system.append(
                project_beads(
                    nominal.ids,
                    true_xyz,
                    diameter,
                    acq.q[s, k],
                    acq.source_mm[s, k],
                    system.iop_px,
                    system.distortion,
                    image_size_px=params.image_size_px,
                    fov_radius_px=params.fov_radius_px,
                    overlap_margin_px=params.overlap_margin_px,
                    holes=holes,
                    system=s,
                    exposure=k,
                )
            )
        truth_frames.append(tuple(per_system))
        log.debug(
            "system %s: %d exposures, %.0f visible beads per frame",
            system.name,
            params.n_frames,
            np.mean([len(f) for f in per_system]),
        )
        rendered = []
        if render:
            raster = _system_raster(params, system)
            for k in range(params.n_frames):
                rng = np.random.default_rng([params.seed, _RNG_NOISE, s, k])
                image = render_frame(
                    params, system, acq.q[s, k], acq.source_mm[s, k], true_xyz, diameter, rng=rng, raster=raster
                )
                meta = {
                    "format": "simulated",
                    "system": system.name,
                    "exposure": k,
                    "ImagerPixelSpacing": [params.pixel_pitch_mm, params.pixel_pitch_mm],
                    "DistanceSourceToDetector": system.source_image_distance_mm,
                }
                rendered.append(
                    Radiograph(
                        image.astype(np.float32), params.bit_depth, f"simulated/{system.name}/frame_{k:03d}", 0, meta
                    )
                )
                if on_frame is not None:
                    on_frame(s, k)
        frames.append(tuple(rendered))
    truth = Truth(
        np.asarray(true_xyz, dtype=np.float64), np.asarray(reference_xyz, dtype=np.float64), acq, tuple(truth_frames)
    )
    return SimulatedData(params, nominal, truth, tuple(frames))


def truth_to_dict(data: SimulatedData, *, grid_step_px: float | None = None) -> dict:
    """JSON-serialisable ground truth (the content of ``truth.json``).

    Floats are kept at full precision (Python's ``json`` writes them exactly).
    The schema is documented in ``pipeline/cmd_simulate.py``.

    Parameters
    ----------
    data : SimulatedData
    grid_step_px : float, optional
        Spacing of the dense correction grid (default 16 px at 1024, scaled with the image, at least 8 px).
    """
    from dataclasses import asdict

    params = data.params
    step = grid_step_px or max(8.0, 16.0 * params.px_scale)
    acq = data.truth.acquisition
    systems = []
    for s, system in enumerate(acq.systems):
        gx, gy, delta = system.distortion.correction_grid(params.image_size_px, step)
        systems.append(
            {
                "name": system.name,
                "iop_px": system.iop_px.tolist(),
                "source_image_distance_mm": system.source_image_distance_mm,
                "pixel_pitch_mm": params.pixel_pitch_mm,
                "lab_from_camera_q": system.lab_from_camera_q.tolist(),
                "source_lab_mm": system.source_lab_mm.tolist(),
                "distortion": system.distortion.to_dict(),
                "correction_grid": {"x_px": gx.tolist(), "y_px": gy.tolist(), "delta_px": delta.tolist()},
            }
        )
    exposures = [
        {
            "turntable_angle_rad": float(acq.turntable_angle_rad[k]),
            "turntable_translation_mm": acq.turntable_translation_mm[k].tolist(),
            "lab_from_phantom_q": acq.lab_from_phantom_q[k].tolist(),
        }
        for k in range(params.n_frames)
    ]
    frames = []
    for s, per_system in enumerate(data.truth.frames):
        for ft in per_system:
            entry = {
                "system": acq.systems[s].name,
                "exposure": ft.exposure,
                "q": ft.q.tolist(),
                "source_mm": ft.source_mm.tolist(),
            }
            entry["beads"] = {name: getattr(ft, name).tolist() for name in FrameTruth.BEAD_FIELDS}
            frames.append(entry)
    return {
        "schema": "fluorocal-simulation-truth",
        "schema_version": 1,
        "simulator_version": VERSION,
        "params": asdict(params),
        "image_size_px": params.image_size_px,
        "fov": {"centre_xy_px": params.image_centre_xy_px.tolist(), "radius_px": params.fov_radius_px},
        "phantom": {
            "kind": params.phantom,
            "ids": data.phantom.ids.tolist(),
            "diameter_mm": data.phantom.diameter_mm.tolist(),
            "role": data.phantom.role.tolist(),
            "nominal_xyz_mm": data.phantom.xyz_mm.tolist(),
            "true_xyz_mm": data.truth.true_xyz_mm.tolist(),
            "reference_xyz_mm": data.truth.reference_xyz_mm.tolist(),
        },
        "systems": systems,
        "exposures": exposures,
        "frames": frames,
    }
