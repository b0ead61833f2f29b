"""Line integrals of attenuation: exact chords through the acrylic box or plate, beads or holes, edge sub-samples."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from fluorocal.stages.geometry import project, quat_to_matrix, to_camera
from fluorocal.stages.simulate.acquisition import SystemTruth
from fluorocal.stages.simulate.params import FIBONACCI, SimulateParams
from fluorocal.stages.simulate.raster import SystemRaster, local_jacobian


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


def background_line_integral(
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

    The holes' axis is ``axis_cam`` (the plate normal, a unit vector, camera frame); the plate
    spans ``±thickness_mm / 2`` about each centre along it. ``rays`` and
    ``centre_cam`` are triples of broadcastable component arrays.
    """
    dn = _dot3(rays, axis_cam)
    cn = _dot3(centre_cam, axis_cam)
    # the rays' and centres' parts across the axis enter only through their dot products (no vectors of their own:
    # these are arrays of a ray per pixel and sub-sample)
    A = np.maximum(_dot3(rays, rays) - dn * dn, 0.0)
    B = _dot3(rays, centre_cam) - dn * cn
    cc = _dot3(centre_cam, centre_cam) - cn * cn
    disc = B * B - A * (cc - radius_mm**2)
    root = np.sqrt(np.maximum(disc, 0.0))
    safe_A = np.maximum(A, 1e-30)
    # ray parameter interval inside the (infinite) cylinder, and inside the plate
    c_lo = np.where(disc > 0, (B - root) / safe_A, 0.0)
    c_hi = np.where(disc > 0, (B + root) / safe_A, 0.0)
    p1, p2 = (cn - thickness_mm / 2) / dn, (cn + thickness_mm / 2) / dn
    length = np.maximum(np.minimum(c_hi, np.maximum(p1, p2)) - np.maximum(c_lo, np.minimum(p1, p2)), 0.0)
    s_mid = cn / dn
    # distance from the hole's axis where the ray crosses the plate's mid-plane: |s_mid d_perp - c_perp|
    dist_mid = np.sqrt(np.maximum(s_mid * (s_mid * A - 2 * B) + cc, 0.0))
    px_per_mm = c_px / s_mid
    slant_px = thickness_mm / 2 * np.sqrt(A) / np.abs(dn) * px_per_mm
    return length, np.maximum(np.abs(dist_mid - radius_mm) * px_per_mm - slant_px, 0.0)


def _subsample_offsets(n: int) -> np.ndarray:
    """``(n, 2)`` sub-pixel offsets in ``[-0.5, 0.5)²`` on a Fibonacci lattice of ``n`` points.

    A Fibonacci lattice covers the square more evenly than a regular grid of
    similar size: on an opaque bead's edge, 21 points leave the centroid within
    ~0.01 px of the outline centre where a 4 × 4 grid leaves ~0.02 px.
    """
    generator = FIBONACCI[FIBONACCI.index(n) - 1] if n in FIBONACCI[1:] else 3
    i = np.arange(n)
    return np.column_stack([(i + 0.5) / n - 0.5, ((i * generator) / n + 0.5 / n) % 1.0 - 0.5])


#: (pixel, feature) pairs per chunk of the chord evaluations: each temporary is 0.25 MB at the pixel centres and
#: 5.5 MB at 21 sub-samples, not a GB of them at once
_CHUNK = 1 << 15


def _chunks(n: int) -> Iterator[slice]:
    """Slices of ``range(n)`` of ``_CHUNK`` (the last one shorter), in order."""
    return (slice(a, min(a + _CHUNK, n)) for a in range(0, n, _CHUNK))


def _feature_pixels(centre_px: np.ndarray, half_px: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """The (pixel, feature) pairs ``(P,)`` of each feature's box of half side ``half_px`` about ``centre_px``."""
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
    return np.concatenate(pix_list), np.concatenate(feat_list)


def feature_line_integrals(params, raster: SystemRaster, system: SystemTruth, q, source_mm, xyz_mm, diameter_mm):
    """Per-pixel Δμ·length of the beads (holes) at the pixel centres, and at sub-samples of their edge pixels.

    Parameters
    ----------
    params : SimulateParams
    raster : SystemRaster
        The system's pixel geometry (ideal coordinates and rays of every pixel).
    system : SystemTruth
        Its IOP and distortion.
    q, source_mm : pose ``(q, T)`` of the exposure (object -> camera).
    xyz_mm : (N, 3) float64 ndarray, mm
    diameter_mm : (N,) float64 ndarray, mm

    Returns
    -------
    line : (H*W,) float64 ndarray
        Sum over features of Δμ · chord at pixel centres.
    edge_idx : (E,) int64 ndarray
        Flat indices of the pixels on a feature edge, ascending (the rows of ``edge_line``).
    edge_line : (E, S) float64 ndarray
        The same sum at S sub-samples of each edge pixel (``params.supersample``).
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
    centre_px = system.distortion.distort_points(project(xyz_mm, q, source_mm, iop))
    half_px = np.ceil(c_px * radius / np.linalg.norm(centre_cam, axis=1) * 1.1 + 2).astype(np.int64)
    pix, feat = _feature_pixels(centre_px, half_px, size)
    # contiguous per-component gathers (a transposed (M, 3) gather would be strided and slow)
    centre_parts = tuple(np.ascontiguousarray(centre_cam[:, j]) for j in range(3))
    chord, edge_px = np.empty(len(pix)), np.empty(len(pix))
    for part in _chunks(len(pix)):
        rays = tuple(r[pix[part]].astype(np.float64) for r in raster.rays)
        chord[part], edge_px[part] = chords(rays, tuple(c[feat[part]] for c in centre_parts), radius[feat[part]])
    line = np.bincount(pix, weights=delta_mu[feat] * chord, minlength=size * size)

    # pixels within a pixel of any outline: integrate the transmission over sub-samples
    is_edge = np.zeros(size * size, dtype=bool)
    is_edge[pix[edge_px < 1.0]] = True
    edge_idx = np.flatnonzero(is_edge)
    # pairs more than a pixel outside their feature contribute nothing to any sub-sample
    in_edge = np.flatnonzero(is_edge[pix] & ((chord > 0) | (edge_px < 1.0)))
    edge_line = np.zeros(len(edge_idx) * params.supersample)
    for part in _chunks(len(in_edge)):
        pairs = in_edge[part]
        rows = np.searchsorted(edge_idx, pix[pairs])
        weights = _subsample_line(params, raster, iop, pix[pairs], feat[pairs], centre_parts, radius, delta_mu, chords)
        # np.add.at adds in the pairs' order, as one bincount over all of them would
        np.add.at(edge_line, (rows[:, None] * params.supersample + np.arange(params.supersample)).ravel(), weights)
    return line, edge_idx, edge_line.reshape(len(edge_idx), params.supersample)


def _subsample_line(params, raster: SystemRaster, iop, pair_pix, pair_feat, centre_parts, radius, delta_mu, chords):
    """Δμ · chord ``(P * S,)`` at the S sub-samples of each (pixel, feature) pair, pair by pair."""
    offsets = _subsample_offsets(params.supersample)
    # ray slopes (x - xp) / c of each pair's pixel centre and their derivatives by the pixel offset
    slope = (raster.ideal_xy.reshape(-1, 2)[pair_pix] - iop[:2]) / iop[2]
    d_slope = local_jacobian(raster.ideal_xy, pair_pix) / iop[2]
    # shape (P, S) per component: first-order map of the sub-sample offsets through the inverse distortion
    u = slope[:, 0, None] + d_slope[:, 0, 0, None] * offsets[:, 0] + d_slope[:, 0, 1, None] * offsets[:, 1]
    v = slope[:, 1, None] + d_slope[:, 1, 0, None] * offsets[:, 0] + d_slope[:, 1, 1, None] * offsets[:, 1]
    inv_norm = 1.0 / np.sqrt(u * u + v * v + 1.0)
    in_centres = tuple(c[pair_feat][:, None] for c in centre_parts)
    sub_chord, _ = chords((u * inv_norm, v * inv_norm, inv_norm), in_centres, radius[pair_feat][:, None])
    return (delta_mu[pair_feat][:, None] * sub_chord).ravel()
