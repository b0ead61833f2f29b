"""Correction fields per C-arm orientation: interpolation between them, and how much they differ.

An image intensifier's distortion changes with the C-arm's orientation (the
earth's magnetic field bends the electron paths), so a calibration holds one
:class:`~fluorocal.stages.field.CorrectionField` per orientation, all of one
system's on the same grid of nodes. An orientation may carry its C-arm angles
in degrees: the orbit (DICOM ``PositionerPrimaryAngle``) and the tilt
(``PositionerSecondaryAngle``).

- :class:`OrientationField`: a named field with its angles (or none).
- :func:`interpolate_field`: the field at angles between calibrated ones. The
  node values are interpolated: a cubic spline (quadratic through three
  orientations, linear through two) along the line when the calibrated angles
  lie on one, else a thin-plate spline within their convex hull. Beyond the
  calibrated angles it refuses, naming them.
- :func:`field_change`: how one field differs from another at the nodes both
  support, as is and modulo a homography (what a change of pose or interior
  orientation would absorb).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import check_shape, freeze
from fluorocal.stages.errors import InputError
from fluorocal.stages.field import CorrectionField

#: how far, in degrees, a requested orientation may lie off the calibrated ones and still be interpolated:
#: a C-arm's angle read-out resolution (DICOM gives 0.1°)
ANGLE_TOL_DEG = 0.05
#: largest |angle| accepted, degrees
MAX_ANGLE_DEG = 180.0


def check_angle(value, what: str) -> float:
    """``value`` as a float if it is a finite angle within ±180°, else :class:`InputError` naming ``what``.

    Examples
    --------
    >>> check_angle(30, "orbit")
    30.0
    >>> check_angle(200.0, "orbit")
    Traceback (most recent call last):
    ...
    fluorocal.stages.errors.InputError: orbit must be a finite angle in -180..180 degrees; got 200.0
    """
    ok = isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool)
    if not ok or not math.isfinite(value) or abs(value) > MAX_ANGLE_DEG:
        raise InputError(f"{what} must be a finite angle in -180..180 degrees; got {value!r}")
    return float(value)


@dataclass(frozen=True)
class OrientationField:
    """One calibrated C-arm orientation of a system: its name, its angles (or none) and its field.

    Attributes
    ----------
    name : str
        The orientation's name (a group's name in the config, or by default the frame's file stem).
    orbit_deg, tilt_deg : float or None, degrees
        The C-arm's orbit (DICOM ``PositionerPrimaryAngle``) and tilt (``PositionerSecondaryAngle``);
        both or neither.
    field : CorrectionField
        The correction at this orientation.
    """

    name: str
    orbit_deg: float | None
    tilt_deg: float | None
    field: CorrectionField

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"an orientation's name must be a non-empty string; got {self.name!r}")
        if (self.orbit_deg is None) != (self.tilt_deg is None):
            raise InputError(f"orientation {self.name!r}: give both orbit_deg and tilt_deg, or neither")
        if self.orbit_deg is not None:
            object.__setattr__(self, "orbit_deg", check_angle(self.orbit_deg, f"orientation {self.name!r}: orbit"))
            object.__setattr__(self, "tilt_deg", check_angle(self.tilt_deg, f"orientation {self.name!r}: tilt"))
        if not isinstance(self.field, CorrectionField):
            raise InputError(f"orientation {self.name!r}: field must be a CorrectionField; got {type(self.field)}")

    @property
    def has_angles(self) -> bool:
        return self.orbit_deg is not None

    def describe(self) -> str:
        """``name (orbit 30°, tilt 0°)``, or the name alone."""
        if not self.has_angles:
            return self.name
        return f"{self.name} (orbit {self.orbit_deg:g}°, tilt {self.tilt_deg:g}°)"


def check_same_grid(fields: list[CorrectionField], what: str) -> None:
    """Refuse fields that are not on one grid of nodes over one image size (:class:`InputError` naming ``what``)."""
    first = fields[0]
    for f in fields[1:]:
        same = (
            np.array_equal(f.x_nodes_px, first.x_nodes_px)
            and np.array_equal(f.y_nodes_px, first.y_nodes_px)
            and (f.width_px, f.height_px) == (first.width_px, first.height_px)
        )
        if not same:
            raise InputError(f"{what}: the fields of the orientations are on different grids of nodes")


def interpolate_field(
    orientations, orbit_deg: float, tilt_deg: float, *, what: str = "the calibration"
) -> CorrectionField:
    """The correction field at C-arm angles ``(orbit_deg, tilt_deg)``, interpolated between calibrated orientations.

    Parameters
    ----------
    orientations : sequence of OrientationField
        The calibrated orientations; those without angles are left out.
    orbit_deg, tilt_deg : float, degrees
        The orientation wanted.
    what : str
        Names the calibration (and system) in messages.

    Returns
    -------
    CorrectionField
        On the calibrated fields' grid. At a calibrated orientation, its own field. Else the node
        values ``delta_px`` interpolated; ``support`` is where every calibrated field is supported and
        ``sigma_px`` the largest of theirs (the interpolation's own error is not included).

    Raises
    ------
    InputError
        No orientation has angles; two have the same angles; the fields are on different grids; or the
        angles lie beyond the calibrated ones (by more than :data:`ANGLE_TOL_DEG`): off the line of
        collinear orientations, outside their segment, or outside the convex hull. fluorocal does not
        extrapolate; the message names the calibrated orientations.

    Notes
    -----
    Angles are taken as coordinates in a plane (orbit, tilt), degrees. When the calibrated angles lie
    on a line, the values are a function of the position ``t`` along it and are interpolated by
    :class:`scipy.interpolate.CubicSpline` with not-a-knot ends: a cubic spline through four or more
    orientations, the parabola through three, the line through two. Otherwise they are interpolated
    by :class:`scipy.interpolate.RBFInterpolator`'s thin-plate spline with a linear polynomial term
    (exact at the calibrated orientations, independent of the angles' scale), inside the convex hull.

    Examples
    --------
    >>> f = [CorrectionField.constant(32, 32, (d, 0.0)) for d in (0.0, 1.0, 4.0)]
    >>> cal = [OrientationField(f"o{a}", a, 0.0, g) for a, g in zip((0, 30, 60), f)]
    >>> interpolate_field(cal, 45.0, 0.0).delta_px[0, 0]  # the parabola through (0, 0), (30, 1), (60, 4)
    array([2.25, 0.  ])
    """
    orbit_deg = check_angle(orbit_deg, "orbit")
    tilt_deg = check_angle(tilt_deg, "tilt")
    known, angles = _with_angles(orientations, what)
    query = np.array([orbit_deg, tilt_deg])
    distance = np.linalg.norm(angles - query, axis=1)
    if distance.min() <= 1e-9:
        return known[int(np.argmin(distance))].field
    centred = angles - angles.mean(axis=0)
    _, singular, axes = np.linalg.svd(centred, full_matrices=False)
    values = np.stack([o.field.delta_px.ravel() for o in known])  # shape (K, H_g * W_g * 2)
    if len(known) == 1 or singular[0] <= 1e-12:
        delta = None
    elif len(known) == 2 or np.abs(centred @ axes[1]).max() <= ANGLE_TOL_DEG:
        delta = _along_line(angles, values, query, axes[0])
    else:
        delta = _in_hull(angles, values, query)
    if delta is None:
        raise InputError(
            f"{what}: orientation (orbit {orbit_deg:g}°, tilt {tilt_deg:g}°) lies beyond the calibrated "
            f"orientations ({_calibrated_range(known, angles)}); fluorocal does not extrapolate: "
            "calibrate at that orientation, or choose a calibrated one by name"
        )
    first = known[0].field
    return first.with_delta(
        delta.reshape(first.delta_px.shape),
        sigma_px=np.max([o.field.sigma_px for o in known], axis=0),
        support=np.all([o.field.support for o in known], axis=0),
    )


def _with_angles(orientations, what: str) -> tuple[list, np.ndarray]:
    """The orientations with angles and their ``(K, 2)`` angles, deg, refused unless distinct and on one grid."""
    known = [o for o in orientations if o.has_angles]
    if not known:
        names = ", ".join(o.name for o in orientations)
        raise InputError(
            f"{what}: no calibrated orientation has C-arm angles, so none can be interpolated; "
            f"choose one by name ({names}) or give orbit and tilt in the config's orientations"
        )
    check_same_grid([o.field for o in known], what)
    angles = np.array([[o.orbit_deg, o.tilt_deg] for o in known])
    _check_distinct(known, angles, what)
    return known, angles


def _check_distinct(known, angles: np.ndarray, what: str) -> None:
    for i in range(len(known)):
        for j in range(i):
            if np.linalg.norm(angles[i] - angles[j]) <= ANGLE_TOL_DEG:
                raise InputError(
                    f"{what}: orientations {known[j].name!r} and {known[i].name!r} are both at "
                    f"orbit {angles[i, 0]:g}°, tilt {angles[i, 1]:g}°; interpolation needs distinct angles: "
                    "make their frames one orientation in the config"
                )


def _along_line(angles, values, query, direction) -> np.ndarray | None:
    """The cubic-spline value at ``query`` along the calibrated line, or None when it is off the segment."""
    from scipy.interpolate import CubicSpline

    centre = angles.mean(axis=0)
    t = (angles - centre) @ direction
    t_query = float((query - centre) @ direction)
    off_line = np.linalg.norm(query - centre - t_query * direction)
    if off_line > ANGLE_TOL_DEG or not t.min() - ANGLE_TOL_DEG <= t_query <= t.max() + ANGLE_TOL_DEG:
        return None
    order = np.argsort(t)
    return CubicSpline(t[order], values[order], axis=0)(np.clip(t_query, t.min(), t.max()))


def _in_hull(angles, values, query) -> np.ndarray | None:
    """The thin-plate spline's value at ``query``, or None when it is outside the convex hull of ``angles``."""
    from scipy.interpolate import RBFInterpolator
    from scipy.spatial import ConvexHull

    # each facet's equation is (unit outward normal, offset): positive outside, the distance in degrees
    hull = ConvexHull(angles)
    if np.max(hull.equations[:, :2] @ query + hull.equations[:, 2]) > ANGLE_TOL_DEG:
        return None
    return RBFInterpolator(angles, values, kernel="thin_plate_spline", degree=1)(query[None])[0]


def _calibrated_range(known, angles: np.ndarray) -> str:
    lo, hi = angles.min(axis=0), angles.max(axis=0)
    span = ", ".join(
        f"{axis} {a:g}°" if a == b else f"{axis} {a:g}..{b:g}°" for axis, a, b in zip(("orbit", "tilt"), lo, hi)
    )
    listed = ", ".join(o.describe() for o in known)
    return f"{span}: {listed}"


# --- how the field changes with orientation -----------------------------------------------------


@dataclass(frozen=True)
class FieldChange:
    """How a field differs from a reference field at the nodes both support.

    Attributes
    ----------
    rms_px, max_px : float, px
        RMS (per coordinate) and largest magnitude of ``Δ - Δ_ref``.
    rms_mod_h_px, max_mod_h_px : float, px
        The same after the best homography between the two fields' ideal node positions: the part
        of the change that no change of pose or interior orientation absorbs.
    difference_mod_h_px : (H_g, W_g, 2) float64 ndarray, px
        That part per node; NaN where a field is unsupported (or fewer than 4 nodes are).
    support : (H_g, W_g) bool ndarray
        Where both fields are supported.
    """

    rms_px: float
    max_px: float
    rms_mod_h_px: float
    max_mod_h_px: float
    difference_mod_h_px: np.ndarray
    support: np.ndarray

    def __post_init__(self):
        check_shape("difference_mod_h_px", self.difference_mod_h_px, self.support.shape + (2,))
        freeze(self)


def field_change(reference: CorrectionField, other: CorrectionField) -> FieldChange:
    """How ``other`` differs from ``reference`` (same grid), as is and modulo a homography.

    The homography maps the reference's ideal node positions ``n - Δ_ref(n)`` onto the other's
    ``n - Δ(n)`` by least squares (:func:`fluorocal.stages.geometry.homography_fit`); what remains is
    ``H(n - Δ_ref) - (n - Δ)``, equal to ``Δ - Δ_ref`` when ``H`` is the identity.

    Examples
    --------
    >>> a = CorrectionField.constant(64, 64, (0.0, 0.0))
    >>> c = field_change(a, CorrectionField.constant(64, 64, (0.3, -0.4)))  # a shift: a homography
    >>> round(c.max_px, 4), round(c.max_mod_h_px, 4)
    (0.5, 0.0)
    """
    from fluorocal.stages.geometry import homography_fit

    check_same_grid([reference, other], "field_change")
    support = reference.support & other.support
    diff = (other.delta_px - reference.delta_px)[support]
    nodes = reference.nodes_px.reshape(support.shape + (2,))[support]
    ideal_ref = nodes - reference.delta_px[support]
    ideal = nodes - other.delta_px[support]
    mod_h = np.full(support.shape + (2,), np.nan)
    fit = homography_fit(ideal_ref, ideal)
    if fit is not None:  # None: too few or degenerate nodes
        mod_h[support] = -fit[1]
    rest = mod_h[support]

    def rms(d):
        return float(np.sqrt(np.mean(d**2))) if len(d) else float("nan")

    def largest(d):
        return float(np.linalg.norm(d, axis=1).max()) if len(d) else float("nan")

    return FieldChange(rms(diff), largest(diff), rms(rest), largest(rest), mod_h, support)


def reference_orientation(orientations) -> int:
    """Index of the orientation to compare the others with: the one nearest orbit 0°, tilt 0°, else the first.

    Examples
    --------
    >>> f = CorrectionField.constant(16, 16)
    >>> reference_orientation([OrientationField("a", 30, 0, f), OrientationField("b", -5, 5, f)])
    1
    """
    known = [(math.hypot(o.orbit_deg, o.tilt_deg), i) for i, o in enumerate(orientations) if o.has_angles]
    return min(known)[1] if known else 0


__all__ = [
    "ANGLE_TOL_DEG",
    "FieldChange",
    "OrientationField",
    "check_angle",
    "check_same_grid",
    "field_change",
    "interpolate_field",
    "reference_orientation",
]
