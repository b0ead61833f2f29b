"""Sub-pixel bead centres: robust ellipse fits to sub-pixel edge points, with the centre's covariance.

For each accepted candidate of :mod:`stages.detect`:

1. **Edge points.** The frame, flattened (step 4), is differentiated with
   derivative-of-Gaussian filters of scale ``edge_sigma_px``. Around each
   bead, a pixel is an edge pixel when its gradient magnitude is a maximum
   along the gradient's dominant axis (non-maximum suppression); the maximum
   is located to sub-pixel precision by a parabola through the logarithms of
   the three magnitudes (exact for a Gaussian-shaped gradient profile, the
   profile of an edge blurred by a Gaussian-like spread function) [1]_. Only
   points in an annulus around the candidate's radius whose gradient points
   across the bead's edge in the bead's polarity, and whose magnitude is at
   least ``min_gradient_fraction`` of the bead's strongest, are kept. A
   gradient maximum is unmoved by a linear background (vignetting, the heel
   effect), so intensities are used as they are (not their logarithm).
2. **Direct fit.** A conic ``A x^2 + 2B xy + C y^2 + D x + E y = 1`` in
   coordinates relative to the candidate centre (the origin is inside the
   bead, so the constant term can be fixed) is fitted by linear least squares
   for all beads at once [2]_.
3. **Robust geometric refinement.** The centre ``c`` and the ellipse's
   quadratic form ``Q`` (``(p - c)^T Q (p - c) = 1``) are refined by
   Gauss-Newton on the radial distance of each point from the ellipse,
   ``r = |u| (1 - (u^T Q u)^(-1/2))`` with ``u = p - c``; points beyond
   ``outlier_sigma`` robust standard deviations (from the mean absolute
   residual of the previous round's inliers) are dropped and the fit repeated.
4. **Neighbours.** Edge points within ``neighbour_margin_px`` of another
   blob's outline are dropped before the fit (a neighbour's edge pulls the
   gradient maximum); the frame is first flattened by a top-hat so that steps
   in the background (a phantom wall next to a bead) do not pull either.
5. **Covariance.** A delete-one-arc jackknife over ``n_arcs`` arcs of the
   outline: unlike ``s^2 (J^T J)^-1`` it keeps the correlation of
   neighbouring edge points (they share smoothed pixels, and an intensifier's
   noise is itself correlated). Checked against a Monte-Carlo run in
   ``tests/stages/test_centroid.py``.

Every bead is fitted together with every other (arrays of points tagged by
bead), so a frame of hundreds of beads costs a handful of array operations.

Coordinates follow ``stages/_geometry.py``: ``(x, y)`` with x = column, y = row,
the centre of the top-left pixel at ``(0, 0)``; angles in radians from +x
toward +y.

References
----------
.. [1] F. Devernay, "A non-maxima suppression method for edge detection with
   sub-pixel accuracy", INRIA RR-2724, 1995.
.. [2] A. Fitzgibbon, M. Pilu, R. Fisher, "Direct least square fitting of
   ellipses", IEEE PAMI 21(5), 1999 (here without the ellipse constraint,
   which a well-sampled closed outline does not need).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from stages.artifacts import SCHEMA_VERSION, Radiograph, check_shape, freeze
from stages.detect import BeadCandidates
from stages.errors import InputError

VERSION = 1

log = logging.getLogger(__name__)

#: fit failure reasons
REASONS = ("few_edges", "no_fit", "shape", "moved", "rmse")


@dataclass(frozen=True)
class CentroidParams:
    """Parameters of :func:`centroid_beads`.

    Attributes
    ----------
    edge_sigma_px : float
        Scale of the derivative-of-Gaussian filters, px. Default 1.5 (larger
        averages more noise, smaller lets a neighbour's edge pull less).
    annulus_fraction : float
        Edge points are searched at radii ``R (1 +- annulus_fraction)`` of the
        candidate radius ``R``, at least ``min_annulus_px`` either side.
        Default 0.3.
    min_annulus_px : float
        Default 3.0.
    min_gradient_fraction : float
        Edge points weaker than this fraction of the bead's strongest are
        noise or another structure's edge. Default 0.5.
    min_cos_radial : float
        Cosine between the gradient and the radial direction below which an
        edge point is not on the bead's outline. Default 0.8.
    outlier_sigma : float
        Points farther than this many robust standard deviations from
        the ellipse are dropped. Default 3.0.
    n_iterations : int
        Gauss-Newton iterations in each robust round (the direct fit starts close). Default 1.
    n_rounds : int
        Robust rounds: outliers are re-identified from the current fit, then
        the fit is refined. Default 2.
    min_edge_fraction : float
        A fit needs at least this fraction of the ``2 pi R`` points a full
        outline gives (beads crowded by neighbours keep only part of theirs). Default 0.3.
    max_axis_ratio : float
        Major over minor semi-axis beyond which a fit is not a bead. Default 1.6.
    max_rmse_px : float
        Inlier RMS distance from the ellipse beyond which the outline is not an
        ellipse (something else's edge was fitted). Default 0.5.
    neighbour_margin_px : float
        Edge points closer than this (at most 0.6 of the neighbour's radius)
        to another blob's outline are dropped (a neighbour's edge pulls the
        gradient maximum; about ``3 sqrt(edge_sigma_px^2 + blur^2)``). Default 6.
    n_arcs : int
        Arcs of the delete-one-arc jackknife that estimates the centre's
        covariance. Default 6 (checked against Monte-Carlo in the tests).
    """

    edge_sigma_px: float = 1.5
    annulus_fraction: float = 0.3
    min_annulus_px: float = 3.0
    min_gradient_fraction: float = 0.5
    min_cos_radial: float = 0.8
    outlier_sigma: float = 3.0
    n_iterations: int = 1
    n_rounds: int = 2
    min_edge_fraction: float = 0.3
    max_axis_ratio: float = 1.6
    max_rmse_px: float = 0.5
    n_arcs: int = 6
    neighbour_margin_px: float = 6.0

    def __post_init__(self):
        for name in ("edge_sigma_px", "annulus_fraction", "min_annulus_px", "outlier_sigma", "max_axis_ratio", "max_rmse_px", "neighbour_margin_px"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0; got {getattr(self, name)}")
        for name in ("min_gradient_fraction", "min_cos_radial", "min_edge_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"{name} must be in [0, 1]; got {getattr(self, name)}")
        for name, low in (("n_iterations", 1), ("n_rounds", 1), ("n_arcs", 4)):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= low):
                raise InputError(f"{name} must be an int >= {low}; got {getattr(self, name)!r}")


@dataclass(frozen=True)
class Centroids:
    """Sub-pixel centres of the accepted candidates of one frame; failed fits are kept, with a reason.

    Attributes
    ----------
    xy_px : (N, 2) float64 ndarray, px
        Fitted ellipse centre ``(x, y)`` (the candidate's centre where the fit failed).
    sigma_x, sigma_y : (N,) float64 ndarray, px
        Standard deviations of the centre (``inf`` where the fit failed).
    rho : (N,) float64 ndarray
        Correlation of the centre's x and y.
    major_px, minor_px : (N,) float64 ndarray, px
        Semi-axes of the fitted ellipse.
    angle_rad : (N,) float64 ndarray, rad
        Direction of the major axis, from +x toward +y, in ``[-pi/2, pi/2)``.
    fit_rmse_px : (N,) float64 ndarray, px
        RMS radial distance of the inlier edge points from the ellipse.
    n_edges : (N,) int64 ndarray
        Inlier edge points used by the fit.
    score : (N,) float64 ndarray
        The candidate's detection score (contrast over noise).
    ok : (N,) bool ndarray
    reason : (N,) str ndarray
        ``""`` where ok, else one of :data:`REASONS`.
    candidate_index : (N,) int64 ndarray
        Row of each bead in the :class:`~stages.detect.BeadCandidates` it came from.
    source : str
    frame_index : int
    """

    xy_px: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    rho: np.ndarray
    major_px: np.ndarray
    minor_px: np.ndarray
    angle_rad: np.ndarray
    fit_rmse_px: np.ndarray
    n_edges: np.ndarray
    score: np.ndarray
    ok: np.ndarray
    reason: np.ndarray
    candidate_index: np.ndarray
    source: str = ""
    frame_index: int = 0
    schema_version: int = SCHEMA_VERSION

    _FLOATS = ("sigma_x", "sigma_y", "rho", "major_px", "minor_px", "angle_rad", "fit_rmse_px", "score")

    def __post_init__(self):
        object.__setattr__(self, "xy_px", np.asarray(self.xy_px, dtype=np.float64).reshape(-1, 2))
        for name in self._FLOATS:
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))
        for name in ("n_edges", "candidate_index"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.int64).reshape(-1))
        object.__setattr__(self, "ok", np.asarray(self.ok, dtype=bool).reshape(-1))
        object.__setattr__(self, "reason", np.asarray(self.reason, dtype="<U16").reshape(-1))
        n = len(self.xy_px)
        for name in self._FLOATS + ("n_edges", "candidate_index", "ok", "reason"):
            check_shape(name, getattr(self, name), (n,))
        if np.any(self.ok != (self.reason == "")):
            raise InputError("reason must be '' exactly where ok is True")
        if not np.all(np.isfinite(self.xy_px[self.ok])):
            raise InputError("xy_px of a successful fit is not finite")
        freeze(self)

    def __len__(self) -> int:
        return len(self.xy_px)

    @property
    def sigma_px(self) -> np.ndarray:
        """``(sigma_x, sigma_y, rho)`` per bead, (N, 3) float64, as :class:`~stages.artifacts.Observations` stores it."""
        return np.column_stack([self.sigma_x, self.sigma_y, self.rho])


def centroid_beads(radiograph: Radiograph, candidates: BeadCandidates, params: CentroidParams) -> Centroids:
    """Fit an ellipse to the outline of every accepted candidate.

    Parameters
    ----------
    radiograph : Radiograph
        The frame the candidates were detected in.
    candidates : BeadCandidates
    params : CentroidParams

    Returns
    -------
    Centroids
        One row per accepted candidate, in candidate order.

    Raises
    ------
    InputError
        ``candidates`` came from a frame of another size (a candidate lies outside ``radiograph``).

    Examples
    --------
    >>> from stages.detect import DetectParams, detect_beads
    >>> yy, xx = np.mgrid[0:128, 0:128]
    >>> image = np.where((xx - 60.3) ** 2 + (yy - 70.6) ** 2 < 8.0**2, 150.0, 1400.0)
    >>> frame = Radiograph(image, 12)
    >>> beads = centroid_beads(frame, detect_beads(frame, DetectParams()), CentroidParams())
    >>> bool(beads.ok[0]), np.round(beads.xy_px[0], 1).tolist(), round(float(beads.major_px[0]), 0)
    (True, [60.3, 70.6], 8.0)
    """
    index = np.flatnonzero(candidates.accepted)
    centre0 = candidates.xy_px[index]
    radius0 = candidates.radius_px[index]
    height, width = radiograph.shape
    if len(index) and (np.any(centre0 < 0) or np.any(centre0[:, 0] > width - 1) or np.any(centre0[:, 1] > height - 1)):
        raise InputError(f"candidates lie outside the {width}x{height} radiograph {radiograph.source or ''}: detected in another frame?")
    n = len(index)
    if n == 0:
        return _result(candidates, index, np.empty((0, 2)), np.empty((0, 5)), np.empty((0, 2, 2)), np.empty(0), np.empty(0, np.int64), np.empty(0, "<U16"))

    points_xy, owner = _edge_points(radiograph.image, centre0, radius0, candidates.polarity, params)
    # every blob the detector saw, accepted or not, can bend the edges of a bead next to it
    points_xy, owner = _drop_near_neighbours(points_xy, owner, index, candidates.xy_px, candidates.radius_px, params)
    params_fit, rmse, n_inliers, covariance = _fit_ellipses(points_xy, owner, centre0, radius0, params)
    reason = _fit_reasons(params_fit, centre0, radius0, n_inliers, covariance, params)
    reason[(reason == "") & ~(rmse <= params.max_rmse_px)] = "rmse"
    log.debug("%s[%d]: %d of %d beads fitted, %d edge points", candidates.source, candidates.frame_index, int(np.sum(reason == "")), n, len(owner))
    return _result(candidates, index, centre0, params_fit, covariance, rmse, n_inliers, reason)


def _result(candidates, index, centre0, fit, covariance, rmse, n_inliers, reason) -> Centroids:
    """Assemble the artifact from the fitted ``(cx, cy, A, B, C)`` and the centres' (n, 2, 2) covariance."""
    n = len(index)
    ok = reason == ""
    xy = np.where(ok[:, None], fit[:, :2], centre0) if n else np.empty((0, 2))
    major, minor, angle = _axes(fit[:, 2:]) if n else (np.empty(0),) * 3
    sx, sy, rho = np.full(n, np.inf), np.full(n, np.inf), np.zeros(n)
    if ok.any():
        sx[ok], sy[ok] = np.sqrt(covariance[ok, 0, 0]), np.sqrt(covariance[ok, 1, 1])
        rho[ok] = covariance[ok, 0, 1] / (sx[ok] * sy[ok])
    return Centroids(
        xy_px=xy,
        sigma_x=sx,
        sigma_y=sy,
        rho=rho,
        major_px=major,
        minor_px=minor,
        angle_rad=angle,
        fit_rmse_px=rmse,
        n_edges=n_inliers,
        score=candidates.score[index],
        ok=ok,
        reason=reason,
        candidate_index=index,
        source=candidates.source,
        frame_index=candidates.frame_index,
    )


def _axes(quadratic: np.ndarray):
    """Semi-axes and major-axis angle of ``(p - c)^T Q (p - c) = 1`` with ``Q = [[A, B], [B, C]]``.

    Parameters
    ----------
    quadratic : (N, 3) float64 ndarray
        ``(A, B, C)``, px^-2.

    Returns
    -------
    major_px, minor_px, angle_rad : (N,) float64 ndarray
    """
    a, b, c = quadratic.T
    half_trace, root = (a + c) / 2, np.sqrt(((a - c) / 2) ** 2 + b**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        major = 1 / np.sqrt(half_trace - root)  # the smaller eigenvalue of Q belongs to the major axis
        minor = 1 / np.sqrt(half_trace + root)
    # eigenvector of the smaller eigenvalue: angle 0.5 atan2(2B, A - C) is the larger one's direction
    angle = 0.5 * np.arctan2(2 * b, a - c) + np.pi / 2
    angle = (angle + np.pi / 2) % np.pi - np.pi / 2
    return major, minor, angle


def _flatten(image: np.ndarray, max_diameter_px: float, polarity: str) -> np.ndarray:
    """The beads alone: a black (dark beads) or white (bright) top-hat with a square wider than any bead; (H, W) float32.

    A flat closing (opening) restores monotone edges, so the top-hat removes
    steps such as the edge of a phantom wall next to a bead, which would
    otherwise pull the gradient maxima on that side.
    """
    import cv2

    height, width = image.shape
    # the background is smooth but for steps: a closing (opening) on a 2x-reduced copy, brought back by
    # bilinear interpolation, is as good within a pixel and 4x cheaper
    small = cv2.resize(image, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    side = int(2 * np.ceil((1.25 * max_diameter_px / 2 + 4 - 1) / 2) + 1)
    op = cv2.MORPH_CLOSE if polarity == "dark" else cv2.MORPH_OPEN
    background = cv2.morphologyEx(small, op, cv2.getStructuringElement(cv2.MORPH_RECT, (side, side)))
    background = cv2.resize(background, (width, height), interpolation=cv2.INTER_LINEAR)
    return image - background


def _gaussian_gradient(image: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives along x and y of the image smoothed by a Gaussian of ``sigma_px``; two (H, W) float32, DN/px."""
    import cv2

    half = int(np.ceil(3.5 * sigma_px))  # the Gaussian's tails beyond 3.5 sigma hold 0.05 % of it
    t = np.arange(-half, half + 1, dtype=np.float64)
    g = np.exp(-0.5 * (t / sigma_px) ** 2)
    g /= g.sum()
    # normalised so that a ramp of unit slope gives 1 (cv2 correlates: sum_t dg(t) f(x + t))
    dg = t * g
    dg /= np.sum(t * dg)
    gx = cv2.sepFilter2D(image, cv2.CV_32F, dg.astype(np.float32), g.astype(np.float32), borderType=cv2.BORDER_REPLICATE)
    gy = cv2.sepFilter2D(image, cv2.CV_32F, g.astype(np.float32), dg.astype(np.float32), borderType=cv2.BORDER_REPLICATE)
    return gx, gy


def _edge_points(image, centre0, radius0, polarity, params: CentroidParams):
    """Sub-pixel edge points around every bead.

    Returns
    -------
    points_xy : (P, 2) float64 ndarray, px
    owner : (P,) int64 ndarray
        Bead (row of ``centre0``) each point belongs to; sorted ascending.
    """
    import cv2

    height, width = image.shape
    gx, gy = _gaussian_gradient(_flatten(image, 2 * radius0.max(), polarity), params.edge_sigma_px)
    magnitude = cv2.magnitude(gx, gy)

    # owner image: each bead's search annulus, labelled bead + 1; smaller beads drawn last so they keep overlaps
    half_width = np.maximum(params.annulus_fraction * radius0, params.min_annulus_px)
    r_in, r_out = np.maximum(radius0 - half_width, 0.0), radius0 + half_width
    owner_image = np.zeros((height, width), np.int32)
    centre_int = np.round(centre0).astype(int).tolist()
    outer, inner = (np.ceil(r_out) + 1).astype(int).tolist(), (np.floor(r_in) - 2).astype(int).tolist()
    # filled discs are fast to draw (thick circles are polygons); the holes only cover a bead's own inside
    for i in np.argsort(-r_out).tolist():
        cv2.circle(owner_image, centre_int[i], outer[i], i + 1, -1)
    for i in np.flatnonzero(np.array(inner) > 0).tolist():
        cv2.circle(owner_image, centre_int[i], inner[i], 0, -1)
    owner_image[[0, -1], :] = 0
    owner_image[:, [0, -1]] = 0
    # non-maximum suppression along the gradient's dominant axis, with OpenCV's vectorised comparisons
    inner_mag = magnitude[1:-1, 1:-1]
    horizontal_map = cv2.compare(np.abs(gx[1:-1, 1:-1]), np.abs(gy[1:-1, 1:-1]), cv2.CMP_GE)
    peak_h = cv2.bitwise_and(cv2.compare(inner_mag, magnitude[1:-1, :-2], cv2.CMP_GT), cv2.compare(inner_mag, magnitude[1:-1, 2:], cv2.CMP_GE))
    peak_v = cv2.bitwise_and(cv2.compare(inner_mag, magnitude[:-2, 1:-1], cv2.CMP_GT), cv2.compare(inner_mag, magnitude[2:, 1:-1], cv2.CMP_GE))
    peak = cv2.bitwise_or(cv2.bitwise_and(peak_h, horizontal_map), cv2.bitwise_and(peak_v, cv2.bitwise_not(horizontal_map)))
    peak = cv2.bitwise_and(peak, cv2.compare(owner_image[1:-1, 1:-1], 0, cv2.CMP_GT))
    found = cv2.findNonZero(peak)
    # shape (K, 2): (x, y) of the peaks in the full frame (``peak`` starts at pixel (1, 1))
    found_xy = found.reshape(-1, 2).astype(np.int64) + 1 if found is not None else np.empty((0, 2), np.int64)
    flat = found_xy[:, 1] * width + found_xy[:, 0]
    gx_p, gy_p, centre_mag = gx.ravel()[flat], gy.ravel()[flat], magnitude.ravel()[flat]
    horizontal = np.abs(gx_p) >= np.abs(gy_p)
    step = np.where(horizontal, 1, width)
    before, after = magnitude.ravel()[flat - step], magnitude.ravel()[flat + step]
    owner = owner_image.ravel()[flat] - 1
    rows, cols = np.divmod(flat, width)
    # radial direction from the candidate centre; the gradient of a dark bead points outward, of a bright one inward
    ux, uy = cols - centre0[owner, 0], rows - centre0[owner, 1]
    sign = 1.0 if polarity == "dark" else -1.0
    keep = sign * (gx_p * ux + gy_p * uy) >= params.min_cos_radial * centre_mag * np.hypot(ux, uy)
    flat, owner, rows, cols, centre_mag, before, after, horizontal = (v[keep] for v in (flat, owner, rows, cols, centre_mag, before, after, horizontal))

    # a parabola through the log magnitudes: the exact peak of a Gaussian profile
    log_b, log_c, log_a = np.log(np.maximum(before, 1e-12)), np.log(np.maximum(centre_mag, 1e-12)), np.log(np.maximum(after, 1e-12))
    denominator = log_b - 2 * log_c + log_a
    offset = np.where(denominator < 0, 0.5 * (log_b - log_a) / np.where(denominator < 0, denominator, -1.0), 0.0)
    offset = np.clip(offset, -0.5, 0.5)
    x = cols + np.where(horizontal, offset, 0.0)
    y = rows + np.where(horizontal, 0.0, offset)

    # sorted by bead, then around each bead's outline (the covariance estimate cuts outlines into arcs)
    # one sort key: the bead, plus the angle mapped into [0, 1)
    order = np.argsort(owner + (np.arctan2(y - centre0[owner, 1], x - centre0[owner, 0]) + np.pi) / (2 * np.pi + 1e-9))
    x, y, owner, centre_mag = x[order], y[order], owner[order], centre_mag[order]
    # per bead: drop weak maxima (noise) and points outside the annulus
    strongest = np.zeros(len(centre0))
    if len(owner):
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        strongest[owner[starts]] = np.maximum.reduceat(centre_mag, starts)
    dist = np.hypot(x - centre0[owner, 0], y - centre0[owner, 1])
    keep = (centre_mag >= params.min_gradient_fraction * strongest[owner]) & (dist >= r_in[owner]) & (dist <= r_out[owner])
    return np.column_stack([x[keep], y[keep]]), owner[keep]


def _drop_near_neighbours(points_xy, owner, index, all_xy, all_radius, params: CentroidParams):
    """Drop edge points within reach of another blob's outline.

    A neighbouring outline closer than a few smoothing lengths pulls the
    gradient maximum towards it; points within ``R_j + neighbour_margin_px``
    of another blob ``j`` (radius ``R_j``) are dropped, the rest of the
    outline still determines the ellipse. A bead that would keep too few
    points for a fit keeps them all.

    Parameters
    ----------
    points_xy : (P, 2) float64 ndarray, px
    owner : (P,) int64 ndarray
        Row of the fitted beads (``index``) each point belongs to, sorted.
    index : (n,) int64 ndarray
        Rows of ``all_xy`` that are fitted.
    all_xy : (M, 2) float64 ndarray, px
        Centres of every candidate blob.
    all_radius : (M,) float64 ndarray, px
    """
    from scipy.spatial import cKDTree

    if len(all_xy) < 2 or len(points_xy) == 0:
        return points_xy, owner
    # a point of bead i lies within R_i (1 + annulus_fraction) + min_annulus_px of its centre
    point_reach = all_radius.max() * (1 + params.annulus_fraction) + params.min_annulus_px
    tree = cKDTree(all_xy)
    # shape (M, K): up to K other blobs near each blob, padded with M (no blob)
    k = min(len(all_xy), 8)
    dist, near = tree.query(all_xy[index], k=k, distance_upper_bound=point_reach + all_radius.max() + params.neighbour_margin_px)
    near = np.where(np.isfinite(dist) & (near != index[:, None]), near, len(all_xy))
    crowded_bead = np.any(near < len(all_xy), axis=1)
    keep = np.ones(len(owner), bool)
    check = crowded_bead[owner]
    if not check.any():
        return points_xy, owner
    padded_xy = np.vstack([all_xy, np.full((1, 2), np.inf)])
    # the margin shrinks for small blobs: their edges are as sharp, relative to their size, as their image allows
    padded_reach = np.append(all_radius + np.minimum(params.neighbour_margin_px, 0.6 * all_radius), 0.0)
    neighbours = near[owner[check]]  # shape (P', K)
    gap = np.hypot(points_xy[check, None, 0] - padded_xy[neighbours, 0], points_xy[check, None, 1] - padded_xy[neighbours, 1])
    keep[check] = np.all(gap >= padded_reach[neighbours], axis=1)
    # a bead surrounded on all sides (a grid plate) keeps all its points: its neighbours pull symmetrically
    n = len(index)
    needed = np.maximum(params.min_edge_fraction * 2 * np.pi * all_radius[index], 6)
    crowded = np.bincount(owner, keep, n) < needed
    keep |= crowded[owner]
    return points_xy[keep], owner[keep]


def _solve(matrices: np.ndarray, rhs: np.ndarray, damping: float = 1e-10) -> np.ndarray:
    """Solve stacks of small symmetric systems ``(..., k, k) x = (..., k)``, Marquardt-damped; (..., k).

    ``damping`` times each diagonal is added (plus a tiny absolute ridge), so
    a bead without points gives a zero step instead of an exception;
    singular stacks fall back to the pseudo-inverse.
    """
    diagonal = np.einsum("...ii->...i", matrices)
    damped = matrices + (damping * diagonal + 1e-300)[..., None] * np.eye(matrices.shape[-1])
    try:
        return np.linalg.solve(damped, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return (np.linalg.pinv(damped) @ rhs[..., None])[..., 0]


_UPPER = np.triu_indices(5)


def _group_normal(owner: np.ndarray, left: np.ndarray, right: np.ndarray, n: int) -> np.ndarray:
    """Per-bead ``sum left^T right`` of (P, 5) rows, for symmetric results; (n, 5, 5).

    Only the 15 products of the upper triangle are summed.
    """
    upper = _group_sum(owner, left[:, _UPPER[0]] * right[:, _UPPER[1]], n)
    out = np.empty((n, 5, 5))
    out[:, _UPPER[0], _UPPER[1]] = upper
    out[:, _UPPER[1], _UPPER[0]] = upper
    return out


def _group_sum(owner: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum ``values`` (P, ...) over the points of each of ``n`` beads; (n, ...). ``owner`` must be sorted."""
    out = np.zeros((n,) + values.shape[1:])
    if len(owner) == 0:
        return out
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    out[owner[starts]] = np.add.reduceat(values, starts, axis=0)
    return out


def _algebraic_fit(points_xy, owner, centre0, n):
    """Direct linear fit of ``A u^2 + 2B uv + C v^2 + D u + E v = 1`` (u, v relative to ``centre0``).

    Returns
    -------
    (n, 5) float64 ndarray
        ``(cx, cy, A, B, C)``: centre and quadratic form; NaN where singular.
    """
    u = points_xy - centre0[owner]
    # shape (P, 5): one row of the design matrix per point
    design = np.column_stack([u[:, 0] ** 2, 2 * u[:, 0] * u[:, 1], u[:, 1] ** 2, u[:, 0], u[:, 1]])
    normal = _group_normal(owner, design, design, n)
    rhs = _group_sum(owner, design, n)
    solvable = np.abs(np.linalg.det(normal)) > 1e-300
    coef = np.full((n, 5), np.nan)
    if solvable.any():
        coef[solvable] = _solve(normal[solvable], rhs[solvable])
    m = np.stack([coef[:, [0, 1]], coef[:, [1, 2]]], axis=1)  # shape (n, 2, 2)
    g = coef[:, 3:]
    out = np.full((n, 5), np.nan)
    good = solvable & np.all(np.isfinite(coef), axis=1)
    good[good] = np.linalg.det(m[good]) > 0
    if good.any():
        # x^T M x + g^T x = 1  <=>  (x - c)^T M (x - c) = 1 + c^T M c  with  c = -M^-1 g / 2
        c = -0.5 * np.linalg.solve(m[good], g[good][:, :, None])[:, :, 0]
        scale = 1 + np.einsum("ni,nij,nj->n", c, m[good], c)
        q = m[good] / scale[:, None, None]
        out[good] = np.column_stack([centre0[good] + c, q[:, 0, 0], q[:, 0, 1], q[:, 1, 1]])
    return out


def _radial_residuals(points_xy, owner, fit, with_jacobian: bool):
    """Radial distance of each point from its bead's ellipse and its derivative.

    ``r = |u| (1 - s^(-1/2))``, ``u = p - c``, ``s = u^T Q u``: the distance from
    the point to where the ray from the centre through it crosses the ellipse.

    Returns
    -------
    r : (P,) float64 ndarray, px
    jacobian : (P, 5) float64 ndarray
        ``dr / d(cx, cy, A, B, C)`` (only if ``with_jacobian``).
    """
    f = fit[owner]
    ux, uy = points_xy[:, 0] - f[:, 0], points_xy[:, 1] - f[:, 1]
    a, b, c = f[:, 2], f[:, 3], f[:, 4]
    s = np.maximum(a * ux * ux + 2 * b * ux * uy + c * uy * uy, 1e-12)
    norm = np.maximum(np.hypot(ux, uy), 1e-12)
    inv_sqrt_s = 1 / np.sqrt(s)
    r = norm * (1 - inv_sqrt_s)
    if not with_jacobian:
        return r, None
    # dr = d|u| (1 - s^-1/2) + |u| s^-3/2 ds / 2
    half_ds_factor = 0.5 * norm * inv_sqrt_s / s
    qux, quy = a * ux + b * uy, b * ux + c * uy
    jac = np.column_stack(
        [
            -ux / norm * (1 - inv_sqrt_s) - 2 * qux * half_ds_factor,
            -uy / norm * (1 - inv_sqrt_s) - 2 * quy * half_ds_factor,
            ux * ux * half_ds_factor,
            2 * ux * uy * half_ds_factor,
            uy * uy * half_ds_factor,
        ]
    )
    return r, jac


def _fit_ellipses(points_xy, owner, centre0, radius0, params: CentroidParams):
    """Robust Gauss-Newton ellipse fits of all beads at once.

    Returns
    -------
    fit : (n, 5) float64 ndarray
        ``(cx, cy, A, B, C)``.
    rmse : (n,) float64 ndarray, px
    n_inliers : (n,) int64 ndarray
    covariance : (n, 2, 2) float64 ndarray, px^2
        Of each centre.
    """
    n = len(centre0)
    fit = _algebraic_fit(points_xy, owner, centre0, n)
    # a fit that failed starts from the candidate's circle
    circle = np.column_stack([centre0, 1 / radius0**2, np.zeros(n), 1 / radius0**2])
    fit = np.where(np.all(np.isfinite(fit), axis=1)[:, None], fit, circle)

    weights = np.ones(len(owner))
    for _round in range(params.n_rounds):
        r, jac = _radial_residuals(points_xy, owner, fit, True)
        # scale per bead: 1.2533 mean |r| is sigma for Gaussian residuals, taken over the previous round's
        # inliers (all points at first, which only makes the first trimming lenient); a floor keeps
        # noise-free synthetic beads from rejecting good points
        mean_abs = np.bincount(owner, weights * np.abs(r), n) / np.maximum(np.bincount(owner, weights, n), 1)
        weights = (np.abs(r) <= params.outlier_sigma * np.maximum(1.2533 * mean_abs, 0.02)[owner]).astype(np.float64)
        for iteration in range(params.n_iterations):
            if iteration:
                r, jac = _radial_residuals(points_xy, owner, fit, True)
            wj = jac * weights[:, None]
            step = _solve(_group_normal(owner, wj, jac, n), -_group_sum(owner, wj * r[:, None], n), damping=1e-6)
            fit = fit + np.nan_to_num(step)
    r, jac = _radial_residuals(points_xy, owner, fit, True)
    n_inliers = np.bincount(owner, weights, n).round().astype(np.int64)
    rmse = np.sqrt(np.bincount(owner, weights * r * r, n) / np.maximum(n_inliers, 1))
    return fit, rmse, n_inliers, _arc_jackknife_covariance(points_xy, owner, centre0, weights, r, jac, params.n_arcs)


def _arc_jackknife_covariance(points_xy, owner, centre0, weights, r, jac, n_arcs: int) -> np.ndarray:
    """Covariance of each centre by a delete-one-arc jackknife; (n, 2, 2) px^2.

    The outline is cut into ``n_arcs`` equal arcs (``points_xy`` must be sorted
    by bead and by angle around ``centre0``);
    dropping arc ``a`` moves the solution by ``(H - H_a)^-1 g_a`` (one
    Gauss-Newton step from the solution, where the total gradient vanishes).
    Unlike ``s^2 H^-1`` this keeps the correlation of neighbouring edge
    points (they share smoothed pixels, and real intensifier noise is itself
    correlated), as long as it is shorter than an arc.
    """
    n = len(centre0)
    # arcs by angle around the candidate centre, around which the points are already sorted
    angle = np.arctan2(points_xy[:, 1] - centre0[owner, 1], points_xy[:, 0] - centre0[owner, 0])
    arc = np.minimum(((angle + np.pi) / (2 * np.pi) * n_arcs).astype(np.int64), n_arcs - 1)
    group = owner * n_arcs + arc
    wj = jac * weights[:, None]
    # shape (n, n_arcs, 5, 5) and (n, n_arcs, 5)
    hessian_arc = _group_normal(group, wj, jac, n * n_arcs).reshape(n, n_arcs, 5, 5)
    gradient_arc = _group_sum(group, wj * r[:, None], n * n_arcs).reshape(n, n_arcs, 5)
    gradient_arc -= gradient_arc.mean(axis=1, keepdims=True)  # the total gradient is zero at the solution
    hessian = hessian_arc.sum(axis=1, keepdims=True)
    shift = _solve(hessian - hessian_arc, gradient_arc)[..., :2]
    shift -= shift.mean(axis=1, keepdims=True)
    return (n_arcs - 1) / n_arcs * np.einsum("nki,nkj->nij", shift, shift)


def _fit_reasons(fit, centre0, radius0, n_inliers, covariance, params: CentroidParams) -> np.ndarray:
    """Why each fit is unusable (``""`` when it is); (n,) str."""
    reason = np.full(len(centre0), "", dtype="<U16")
    major, minor, _ = _axes(fit[:, 2:])
    finite = np.all(np.isfinite(fit), axis=1) & np.isfinite(major) & np.isfinite(minor) & np.all(np.isfinite(covariance), axis=(1, 2))
    finite &= (covariance[:, 0, 0] > 0) & (covariance[:, 1, 1] > 0)
    expected_points = 2 * np.pi * np.where(finite, np.sqrt(np.abs(major * minor)), radius0)
    reason[~finite] = "no_fit"
    shape_bad = finite & ((major > params.max_axis_ratio * minor) | (major > 2 * radius0 + params.min_annulus_px) | (minor < 0.3 * radius0))
    reason[shape_bad] = "shape"
    moved = finite & (np.hypot(*(fit[:, :2] - centre0).T) > 0.5 * radius0 + 1)
    reason[moved & ~shape_bad] = "moved"
    reason[(n_inliers < np.maximum(params.min_edge_fraction * expected_points, 6))] = "few_edges"
    return reason
