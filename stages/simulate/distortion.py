"""The image-intensifier distortion model: forward and inverse maps, correction grid, per-system draw, pixel map."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.errors import InputError
from fluorocal.stages.simulate.params import RNG_DIST, SimulateParams

#: exponents (i, j) of the monomials ρx^i ρy^j of ``ImageDistortion.poly_coeffs_px``
MONOMIALS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3))


@dataclass(frozen=True, eq=False)
class ImageDistortion:
    """Forward image distortion of one system: ideal (pinhole) -> distorted (measured) pixels.

    With ``ρ = (x - centre) / scale`` (normalised, ``r² = |ρ|²``)::

        ρ_d = Rot(s · r²) · (1 + k1 r² + k2 r⁴) ρ  +  decentring(p1, p2)(ρ)
        x_d = centre + scale · ρ_d + poly(ρ) + field(x)

    where ``decentring`` is Brown's tangential term, ``poly`` a cubic
    displacement in px (the C-arm orientation's part, :mod:`.orientation`) and
    ``field`` a smooth random displacement: a bicubic B-spline with coefficients
    ``field_coeffs_px`` on a lattice of spacing ``field_spacing_px`` whose node
    ``[0, 0]`` sits at ``field_origin_xy_px``.

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
    poly_coeffs_px : (2, 10) float64 ndarray, px
        Coefficients of the x and y displacement on the monomials ``ρx^i ρy^j`` with
        ``(i, j)`` in ``(0,0), (1,0), (0,1), (2,0), (1,1), (0,2), (3,0), (2,1), (1,2), (0,3)``.
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
    poly_coeffs_px: np.ndarray = field(default_factory=lambda: np.zeros((2, len(MONOMIALS))))

    def __post_init__(self):
        object.__setattr__(self, "centre_xy_px", np.asarray(self.centre_xy_px, dtype=np.float64).reshape(2))
        poly = np.asarray(self.poly_coeffs_px, dtype=np.float64)
        if poly.shape != (2, len(MONOMIALS)):
            raise InputError(f"poly_coeffs_px must have shape (2, {len(MONOMIALS)}); got {poly.shape}")
        object.__setattr__(self, "poly_coeffs_px", poly)
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
        return not (
            any((self.k1, self.k2, self.s_rad, self.p1, self.p2))
            or np.any(self.field_coeffs_px)
            or np.any(self.poly_coeffs_px)
        )

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
        has_poly = bool(np.any(self.poly_coeffs_px))
        if has_poly:
            out += self._poly(x, y)
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
        if has_poly:
            jac += self._poly(x, y, derivative=True) / self.scale_px
        return out, jac

    def _poly(self, x: np.ndarray, y: np.ndarray, *, derivative: bool = False) -> np.ndarray:
        """The cubic displacement ``(..., 2)`` px at normalised ``(x, y)``, or its derivative ``(..., 2, 2)``."""
        if not derivative:
            return np.stack([x**i * y**j for i, j in MONOMIALS], axis=-1) @ self.poly_coeffs_px.T
        d_x = np.stack([i * x ** max(i - 1, 0) * y**j for i, j in MONOMIALS], axis=-1)
        d_y = np.stack([j * x**i * y ** max(j - 1, 0) for i, j in MONOMIALS], axis=-1)
        return np.stack([d_x @ self.poly_coeffs_px.T, d_y @ self.poly_coeffs_px.T], axis=-1)

    def _field(self, xy: np.ndarray) -> np.ndarray:
        if not np.any(self.field_coeffs_px):
            return np.zeros_like(xy)
        from scipy.ndimage import map_coordinates

        grid = (xy - self.field_origin_xy_px) / self.field_spacing_px
        coords = [grid[..., 1].ravel(), grid[..., 0].ravel()]
        # prefilter=False: the array holds B-spline coefficients, so this evaluates the spline exactly
        comps = [map_coordinates(c, coords, order=3, prefilter=False, mode="nearest") for c in self.field_coeffs_px]
        return np.stack(comps, axis=-1).reshape(xy.shape)

    def distort_points(self, xy_ideal: np.ndarray) -> np.ndarray:
        """Forward map: ideal pinhole coordinates ``(..., 2)`` px -> distorted (measured) px.

        Examples
        --------
        >>> d = ImageDistortion(np.array([50.0, 50.0]), 50.0, k1=0.01)
        >>> d.distort_points(np.array([[100.0, 50.0]]))
        array([[100.5,  50. ]])
        """
        xy = np.asarray(xy_ideal, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise InputError(f"xy_ideal must have shape (..., 2); got {xy.shape}")
        return self._parametric(xy) + self._field(xy)

    def undistort_points(self, xy_distorted: np.ndarray, *, tol_px: float = 1e-10, max_iter: int = 50) -> np.ndarray:
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

    def correction_at(self, xy_measured: np.ndarray) -> np.ndarray:
        """DESIGN's correction Δ on measured coordinates: ``ideal = measured - Δ(measured)``."""
        xy = np.asarray(xy_measured, dtype=np.float64)
        return xy - self.undistort_points(xy)

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
        return axis, axis.copy(), self.correction_at(np.stack([gx, gy], axis=-1))

    def to_dict(self) -> dict:
        """JSON-serialisable parameters (floats kept exact); ``poly_coeffs_px`` only when not zero."""
        has_poly = bool(np.any(self.poly_coeffs_px))
        out = {
            "model": "radial+S+decentring+bspline_field" + ("+cubic" if has_poly else ""),
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
        if has_poly:
            out["poly_coeffs_px"] = self.poly_coeffs_px.tolist()
        return out

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
        optional = tuple(k for k in ("poly_coeffs_px",) if k in d)
        return cls(
            **{k: (np.asarray(d[k], dtype=np.float64) if isinstance(d[k], list) else d[k]) for k in keys + optional}
        )


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
    rng = np.random.default_rng([params.seed, RNG_DIST, system])
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


def ideal_pixel_map(distortion: ImageDistortion, image_size_px: int) -> np.ndarray:
    """Ideal coordinates ``(H, W, 2)`` px of every pixel centre of the distorted image.

    The inverse distortion is solved exactly (Newton) on a lattice every 1-8 px,
    interpolated by a bicubic spline as a starting point and polished by Newton
    steps on every pixel until the forward map returns each pixel centre to
    1e-7 px (tested against :meth:`ImageDistortion.undistort_points`: < 1e-6 px).
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
    ideal_coarse = distortion.undistort_points(np.stack([cx, cy], axis=-1))
    guess = np.stack([RectBivariateSpline(coarse, coarse, ideal_coarse[..., i])(axis, axis) for i in range(2)], axis=-1)
    # Newton polish: the spline start is within ~1e-4 px and each step gains a factor |∇field| < 0.05.
    # The Jacobian of the first step is reused: over 1e-4 px it changes by far less than that factor.
    _, jac = distortion._parametric(guess, jacobian=True)
    for _ in range(5):
        residual = distortion.distort_points(guess) - target
        if np.max(np.abs(residual)) < 1e-7:
            break
        guess = guess - _solve2(jac, residual)
    return guess
