"""C-arm orientations: their names, the earth's field across the intensifier and the distortion it adds.

An image intensifier's electrons are bent by the earth's magnetic field, so
its distortion depends on how the C-arm is turned in that field. Model (all
amplitudes in px for a 1024-px image, scaled with the image):

- Orientation ``(orbit, tilt)`` in degrees: the C-arm turned from its centred
  orientation by ``lab_from_camera = R_x(tilt) R_y(orbit)``, axes of the
  camera frame at the centred orientation (orbit about the image's y axis,
  then tilt about its x axis).
- The earth's field, a unit vector ``b0 = (cos I cos h, cos I sin h, -sin I)``
  in that frame (inclination ``I``, heading ``h``; z along the beam), reads
  ``b = Rᵀ b0`` in the turned intensifier's frame; ``Δb = b - b0``.
- The distortion at an orientation is the system's (centred) distortion plus
  a cubic displacement in ``ρ = (x - centre) / scale`` (the distortion's own
  centre and scale), with ``t(ρ) = (-ρy, ρx)`` the tangential direction::

      u(ρ) = a_z Δb_z r² (t(ρ) + 0.3 ρ)         axial change: S-distortion (and a little radial)
           + a_t (Δb_x ρx + Δb_y ρy) t(ρ)       change across the axis: a twist growing across the field
           + s (-Δb_y, Δb_x)                    change across the axis: the whole image shifts

  Both non-uniform terms are tangential, apart from the small radial part;
  no homography absorbs them. ``a_t`` makes the RMS over the disc
  ``|ρ| <= 0.94`` (the default field of view), modulo a homography, of the
  twist term ``orientation_distortion_px`` per unit ``|Δb_xy|``, ``a_z`` that
  of the axial term ``_AXIAL_RATIO`` times as much per unit ``|Δb_z|``; ``s``
  is ``_SHIFT_PX`` px per unit ``|Δb_xy|``. ``ρ`` is in ideal coordinates, so
  under a pincushion the measured field of view sees a little less.

With the default field (dip 65°, heading 315°) and strong distortion, the
centred orientation's correction leaves, modulo a homography over the field
of view (truth correction grids, seeds 0-4), 0.20-0.21 px at 15° (orbit or
tilt), 0.37-0.39 px at 30°, 0.52-0.54 px at 45° and 0.62-0.66 px at 60°: the
real C-arm's figures (``../shared/data/README.md``). Turning the other way
gives more (0.8 px at -60°): the field is not symmetric about the centred
orientation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.simulate.distortion import MONOMIALS, ImageDistortion
from fluorocal.stages.simulate.params import SimulateParams

#: RMS (px per px of coefficient) over the disc |ρ| <= 0.94 (the default field of view), modulo a
#: (linearised) homography, of r² t(ρ) (equally r² ρ) and of (e · ρ) t(ρ) for a unit vector e
_RMS_R2, _RMS_TWIST = 0.13837, 0.22807
#: the axial change's RMS per unit |Δb_z| relative to the twist's per unit |Δb_xy|, its radial share,
#: and the image shift per unit |Δb_xy| (px at 1024): fitted to the real C-arm's figures
_AXIAL_RATIO, _RADIAL_SHARE, _SHIFT_PX = 0.475, 0.3, 4.0


def orientation_name(orbit_deg: float, tilt_deg: float) -> str:
    """A file-name-safe name: ``"centred"``, ``"orbit30"``, ``"tilt-15"``, ``"orbit30_tilt7.5"``.

    Examples
    --------
    >>> orientation_name(0, 0), orientation_name(30, 0), orientation_name(0, -15), orientation_name(30, 7.5)
    ('centred', 'orbit30', 'tilt-15', 'orbit30_tilt7.5')
    """
    parts = [f"{label}{angle:g}" for label, angle in (("orbit", orbit_deg), ("tilt", tilt_deg)) if angle != 0]
    return "_".join(parts) or "centred"


def angle_codes(orbit_deg: float, tilt_deg: float) -> list:
    """Non-negative integers naming an orientation to 1e-3 degree: seed-sequence entries."""
    return [int(round((angle + 360.0) * 1000)) for angle in (orbit_deg, tilt_deg)]


def _rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def field_change(params: SimulateParams, orbit_deg: float, tilt_deg: float) -> np.ndarray:
    """``Δb`` (3,): the change of the unit earth field in the intensifier's frame from the centred orientation.

    Examples
    --------
    >>> bool(np.all(field_change(SimulateParams(), 0, 0) == 0))
    True
    >>> # a 60° turn about x moves the field by 2 sin 30° times its part across x: sqrt(1 - (cos 65° cos 315°)²)
    >>> round(float(np.linalg.norm(field_change(SimulateParams(), 0, 60))), 3)
    0.954
    """
    dip, heading = np.radians(params.earth_field_inclination_deg), np.radians(params.earth_field_heading_deg)
    b0 = np.array([np.cos(dip) * np.cos(heading), np.cos(dip) * np.sin(heading), -np.sin(dip)])
    lab_from_camera = _rot_x(np.radians(tilt_deg)) @ _rot_y(np.radians(orbit_deg))
    return lab_from_camera.T @ b0 - b0


def orientation_poly_px(params: SimulateParams, delta_b: np.ndarray) -> np.ndarray:
    """Coefficients ``(2, 10)`` px of the displacement ``u(ρ)`` (module docstring) on :data:`MONOMIALS`."""
    bx, by, bz = np.asarray(delta_b, dtype=np.float64)
    k = params.orientation_distortion_px * params.px_scale
    a_z = k * _AXIAL_RATIO / (_RMS_R2 * np.hypot(1.0, _RADIAL_SHARE)) * bz
    a_r = _RADIAL_SHARE * a_z
    a_t = k / _RMS_TWIST
    s = _SHIFT_PX * params.px_scale
    c = np.zeros((2, len(MONOMIALS)))
    col = {m: i for i, m in enumerate(MONOMIALS)}
    # r² t(ρ) = (-x²y - y³, x³ + xy²) and r² ρ = (x³ + xy², x²y + y³)
    c[0, col[2, 1]] += -a_z + a_r
    c[0, col[0, 3]] += -a_z
    c[0, col[3, 0]] += a_r
    c[0, col[1, 2]] += a_r
    c[1, col[3, 0]] += a_z
    c[1, col[1, 2]] += a_z + a_r
    c[1, col[2, 1]] += a_r
    c[1, col[0, 3]] += a_r
    # (bx x + by y) t(ρ) = (-bx xy - by y², bx x² + by xy)
    c[0, col[1, 1]] += -a_t * bx
    c[0, col[0, 2]] += -a_t * by
    c[1, col[2, 0]] += a_t * bx
    c[1, col[1, 1]] += a_t * by
    c[0, col[0, 0]] += -s * by
    c[1, col[0, 0]] += s * bx
    return c


@dataclass(frozen=True, eq=False)
class Orientation:
    """One C-arm orientation of a grid sequence.

    Attributes
    ----------
    name : str
        :func:`orientation_name` of the angles.
    orbit_deg, tilt_deg : float, degrees
    field_change : (3,) float64 ndarray
        ``Δb`` (:func:`field_change`).
    distortion : ImageDistortion
        The system's distortion at this orientation (forward, ideal -> distorted).
    """

    name: str
    orbit_deg: float
    tilt_deg: float
    field_change: np.ndarray
    distortion: ImageDistortion

    def __post_init__(self):
        freeze(self)


def make_orientations(params: SimulateParams, base: ImageDistortion) -> tuple:
    """The :class:`Orientation` of each of ``params.orientations_deg``, with ``base`` the centred distortion.

    Examples
    --------
    >>> from fluorocal.stages.simulate.distortion import make_distortion
    >>> p = SimulateParams(phantom="grid", image_size_px=256, orientations_deg=((0, 0), (0, 30)))
    >>> [o.name for o in make_orientations(p, make_distortion(p, 0))]
    ['centred', 'tilt30']
    """
    out = []
    for orbit, tilt in params.orientations_deg:
        delta_b = field_change(params, orbit, tilt)
        poly = base.poly_coeffs_px + orientation_poly_px(params, delta_b)
        out.append(Orientation(orientation_name(orbit, tilt), orbit, tilt, delta_b, replace(base, poly_coeffs_px=poly)))
    return tuple(out)
