"""Sub-pixel bead centres: robust ellipse fits to sub-pixel edge points, with the centre's covariance.

For each accepted candidate of :mod:`stages.detect`:

1. **Edge points.** The frame, flattened (step 4), is differentiated with
   derivative-of-Gaussian filters of scale ``edge_sigma_px`` (narrower for
   small beads). Around each
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
bead, summed per bead by sparse products), so a frame of hundreds of beads
costs a handful of array operations.

A frame whose accepted candidates all fail (anatomy taken for beads in a
bead-free frame) gives an :class:`~stages.detect.EmptyFrameWarning`.

Coordinates follow ``stages/geometry.py``: ``(x, y)`` with x = column, y = row,
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
import warnings
from dataclasses import dataclass

import numpy as np
from fluorocal.stages._edges import edge_points
from fluorocal.stages._ellipse import ellipse_axes, fit_ellipses
from fluorocal.stages._image import frame_name
from fluorocal.stages.artifacts import SCHEMA_VERSION, Radiograph, as_arrays, check_shape, freeze
from fluorocal.stages.detect import BeadCandidates, EmptyFrameWarning
from fluorocal.stages.errors import InputError

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
        averages more noise, smaller lets a neighbour's edge pull less). In a
        crowded frame, where the median gap from a bead's outline to its
        nearest neighbour's is under ``4 edge_sigma_px``, a quarter of that gap
        is used (at least ``min_edge_sigma_px``): there the pull of a
        neighbour's edge outweighs the noise (simulated 6 px beads 2-4 px
        apart: 0.072 px RMS at 1.5 px, 0.036 px at 1 px).
    min_edge_sigma_px : float
        Smallest filter scale, px. Default 1.0.
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
        Major over minor semi-axis beyond which a fit is not a bead. Default
        1.25: a sphere's silhouette within a 15 degree cone stays below 1.04,
        a grid plate's holes tilted by 30 degrees near 1.15; two overlapping
        beads fitted as one, or a patch of anatomy, are more elongated.
    max_rmse_px : float
        Inlier RMS distance from the ellipse beyond which the outline is not an
        ellipse (something else's edge was fitted: anatomy, or overlapping
        beads). Default 0.3 (measured: at most 0.05 px on beads in an open
        field, 0.21 px over bone edges; 0.48 px and more on patches of bone).
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
    max_axis_ratio: float = 1.25
    max_rmse_px: float = 0.3
    n_arcs: int = 6
    neighbour_margin_px: float = 6.0
    min_edge_sigma_px: float = 1.0

    def __post_init__(self):
        for name in (
            "edge_sigma_px",
            "min_edge_sigma_px",
            "annulus_fraction",
            "min_annulus_px",
            "outlier_sigma",
            "max_axis_ratio",
            "max_rmse_px",
            "neighbour_margin_px",
        ):
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
        as_arrays(self, np.float64, "xy_px", shape=(-1, 2))
        as_arrays(self, np.float64, *self._FLOATS)
        as_arrays(self, np.int64, "n_edges", "candidate_index")
        as_arrays(self, bool, "ok")
        as_arrays(self, "<U16", "reason")
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

    def summary(self) -> str:
        """One line: fitted beads, failures, median fit RMSE and centre sigma."""
        ok = self.ok
        rmse = float(np.median(self.fit_rmse_px[ok])) if ok.any() else float("nan")
        sigma = float(np.median(np.hypot(self.sigma_x[ok], self.sigma_y[ok]))) if ok.any() else float("nan")
        return (
            f"{int(ok.sum())} fitted, {int((~ok).sum())} failed;"
            f" median fit RMSE {rmse:.3f} px, centre sigma {sigma:.3f} px"
        )

    @property
    def sigma_px(self) -> np.ndarray:
        """``(sigma_x, sigma_y, rho)`` per bead, (N, 3) float64, as :class:`~stages.artifacts.Observations` holds it."""
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
        One row per accepted candidate, in candidate order. When candidates
        were accepted but no fit succeeds (a bead-free frame whose anatomy the
        detector took for beads), an :class:`~stages.detect.EmptyFrameWarning`
        names the frame.

    Raises
    ------
    InputError
        ``candidates`` came from a frame of another size (a candidate lies outside ``radiograph``).

    Examples
    --------
    >>> from fluorocal.stages.detect import DetectParams, detect_beads
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
        raise InputError(
            f"candidates lie outside the {width}x{height} radiograph {radiograph.source or ''}:"
            " detected in another frame?"
        )
    n = len(index)
    if n == 0:
        return _no_beads(candidates, index)

    points_xy, owner = _outline_points(radiograph, candidates, index, params)
    params_fit, rmse, n_inliers, covariance = fit_ellipses(
        points_xy,
        owner,
        centre0,
        radius0,
        n_arcs=params.n_arcs,
        n_rounds=params.n_rounds,
        n_iterations=params.n_iterations,
        outlier_sigma=params.outlier_sigma,
    )
    reason = _fit_reasons(params_fit, centre0, radius0, n_inliers, covariance, params)
    reason[(reason == "") & ~(rmse <= params.max_rmse_px)] = "rmse"
    if not np.any(reason == ""):
        # the detector accepted blobs, but none has a bead's outline (anatomy, a bead-free frame)
        why = ", ".join(f"{k} {v}" for k, v in zip(*np.unique(reason, return_counts=True)))
        warnings.warn(
            f"{frame_name(radiograph)}: no bead fitted ({n} candidates failed: {why})", EmptyFrameWarning, stacklevel=2
        )
    log.debug(
        "%s[%d]: %d of %d beads fitted, %d edge points",
        candidates.source,
        candidates.frame_index,
        int(np.sum(reason == "")),
        n,
        len(owner),
    )
    return _result(candidates, index, centre0, params_fit, covariance, rmse, n_inliers, reason)


def _outline_points(radiograph: Radiograph, candidates: BeadCandidates, index, params: CentroidParams):
    """Sub-pixel edge points of the candidates ``index``, those a neighbouring blob would pull dropped.

    Returns
    -------
    points_xy : (P, 2) float64 ndarray, px
    owner : (P,) int64 ndarray
        Position in ``index`` of the bead each point belongs to.
    """
    # every blob the detector saw, accepted or not, can bend the edges of a bead next to it
    near = _neighbours(index, candidates.xy_px, candidates.radius_px, params)
    sigma_px = _edge_sigma(index, near, candidates.xy_px, candidates.radius_px, params)
    points_xy, owner = edge_points(
        radiograph.image,
        candidates.xy_px[index],
        candidates.radius_px[index],
        candidates.polarity,
        sigma_px,
        annulus_fraction=params.annulus_fraction,
        min_annulus_px=params.min_annulus_px,
        min_cos_radial=params.min_cos_radial,
        min_gradient_fraction=params.min_gradient_fraction,
    )
    points_xy, owner = _drop_near_neighbours(
        points_xy, owner, index, near, candidates.xy_px, candidates.radius_px, params
    )
    return points_xy, owner


def _no_beads(candidates: BeadCandidates, index: np.ndarray) -> Centroids:
    """The artifact of a frame without accepted candidates (``index`` empty): every array of length 0."""
    return _result(
        candidates,
        index,
        np.empty((0, 2)),
        np.empty((0, 5)),
        np.empty((0, 2, 2)),
        np.empty(0),
        np.empty(0, np.int64),
        np.empty(0, "<U16"),
    )


def _result(candidates, index, centre0, fit, covariance, rmse, n_inliers, reason) -> Centroids:
    """Assemble the artifact from the fitted ``(cx, cy, A, B, C)`` and the centres' (n, 2, 2) covariance."""
    n = len(index)
    ok = reason == ""
    xy = np.where(ok[:, None], fit[:, :2], centre0) if n else np.empty((0, 2))
    major, minor, angle = ellipse_axes(fit[:, 2:]) if n else (np.empty(0),) * 3
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


def _neighbours(index, all_xy, all_radius, params: CentroidParams) -> np.ndarray:
    """Up to 7 other blobs near each fitted bead, nearest first, padded with ``M`` (no blob); (n, K) int64, K >= 1.

    Near: close enough for its outline to reach a point of the bead's search annulus.
    """
    from scipy.spatial import cKDTree

    n_blobs = len(all_xy)
    if n_blobs < 2:
        return np.full((len(index), 1), n_blobs)
    # a point of bead i lies within R_i (1 + annulus_fraction) + min_annulus_px of its centre
    point_reach = all_radius.max() * (1 + params.annulus_fraction) + params.min_annulus_px
    distance, near = cKDTree(all_xy).query(
        all_xy[index],
        k=min(n_blobs, 8),
        distance_upper_bound=point_reach + all_radius.max() + params.neighbour_margin_px,
    )
    near = np.where(np.isfinite(distance) & (near != index[:, None]), near, n_blobs)
    # each row's blobs nearest first (the bead itself, at distance 0, is now padding)
    order = np.argsort(np.where(near < n_blobs, distance, np.inf), axis=1, kind="stable")
    near = np.take_along_axis(near, order, axis=1)
    # columns of padding only (past every bead's last neighbour) are dropped
    return near[:, : max(int(np.max(np.sum(near < n_blobs, axis=1))), 1)]


def _edge_sigma(index, near, all_xy, all_radius, params: CentroidParams) -> float:
    """Scale (px) of the edge filter for a frame: ``edge_sigma_px``, narrowed where beads are crowded.

    Narrowed to a quarter of the typical gap between neighbouring outlines:
    a neighbour's edge pulls the gradient maxima of a bead over about twice
    the filter's scale; where beads are crowded (the median gap from a fitted
    bead's outline to its nearest neighbour's is small), a narrower filter
    lets it pull less, at the cost of more noise. Never below
    ``min_edge_sigma_px``.

    Parameters
    ----------
    index : (n,) int64 ndarray
        Rows of ``all_xy`` that are fitted.
    near : (n, K) int64 ndarray
        :func:`_neighbours` of each (``len(all_xy)``: none within reach).
    all_xy : (M, 2) float64 ndarray, px
    all_radius : (M,) float64 ndarray, px
    """
    nearest = near[:, 0]
    has = nearest < len(all_xy)
    gap = np.full(len(index), np.inf)
    gap[has] = (
        np.hypot(*(all_xy[nearest[has]] - all_xy[index[has]]).T) - all_radius[index[has]] - all_radius[nearest[has]]
    )
    return (
        float(np.clip(np.median(gap) / 4, params.min_edge_sigma_px, params.edge_sigma_px))
        if len(gap)
        else params.edge_sigma_px
    )


def _drop_near_neighbours(points_xy, owner, index, near, all_xy, all_radius, params: CentroidParams):
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
    near : (n, K) int64 ndarray
        :func:`_neighbours` of each fitted bead.
    all_xy : (M, 2) float64 ndarray, px
        Centres of every candidate blob.
    all_radius : (M,) float64 ndarray, px
    """
    if len(all_xy) < 2 or len(points_xy) == 0:
        return points_xy, owner
    padded_xy = np.vstack([all_xy, np.full((1, 2), np.inf)])
    # the margin shrinks for small blobs (whose outline is otherwise left with too few points), but not below
    # 3 px: a neighbour's edge pulls over the blur and filter widths, whatever the blob's size
    padded_reach = np.append(
        all_radius + np.minimum(params.neighbour_margin_px, np.maximum(0.6 * all_radius, 3.0)), 0.0
    )
    # only a neighbour whose reach meets the bead's search annulus can drop a point: the others become padding
    radius = all_radius[index]
    r_out = radius + np.maximum(params.annulus_fraction * radius, params.min_annulus_px)
    distance = np.hypot(*(padded_xy[near] - all_xy[index][:, None]).transpose(2, 0, 1))
    near = np.where(distance < r_out[:, None] + padded_reach[near], near, len(all_xy))
    near = np.take_along_axis(near, np.argsort(near == len(all_xy), axis=1, kind="stable"), axis=1)
    near = near[:, : int(np.max(np.sum(near < len(all_xy), axis=1)))]
    crowded_bead = np.any(near < len(all_xy), axis=1)
    keep = np.ones(len(owner), bool)
    check = crowded_bead[owner]
    if not check.any():
        return points_xy, owner
    x, y = points_xy[check, 0], points_xy[check, 1]
    clear = np.ones(len(x), bool)
    for column in near[owner[check]].T:  # each point's k-th nearest blob (padding: at infinity)
        clear &= (x - padded_xy[column, 0]) ** 2 + (y - padded_xy[column, 1]) ** 2 >= padded_reach[column] ** 2
    keep[check] = clear
    # a bead surrounded on all sides (a grid plate) keeps all its points: its neighbours pull symmetrically
    n = len(index)
    needed = np.maximum(params.min_edge_fraction * 2 * np.pi * all_radius[index], 6)
    crowded = np.bincount(owner, keep, n) < needed
    keep |= crowded[owner]
    return points_xy[keep], owner[keep]


def _fit_reasons(fit, centre0, radius0, n_inliers, covariance, params: CentroidParams) -> np.ndarray:
    """Why each fit is unusable (``""`` when it is); (n,) str."""
    reason = np.full(len(centre0), "", dtype="<U16")
    major, minor, _ = ellipse_axes(fit[:, 2:])
    finite = (
        np.all(np.isfinite(fit), axis=1)
        & np.isfinite(major)
        & np.isfinite(minor)
        & np.all(np.isfinite(covariance), axis=(1, 2))
    )
    finite &= (covariance[:, 0, 0] > 0) & (covariance[:, 1, 1] > 0)
    expected_points = 2 * np.pi * np.where(finite, np.sqrt(np.abs(major * minor)), radius0)
    reason[~finite] = "no_fit"
    shape_bad = finite & (
        (major > params.max_axis_ratio * minor)
        | (major > 2 * radius0 + params.min_annulus_px)
        | (minor < 0.3 * radius0)
    )
    reason[shape_bad] = "shape"
    moved = finite & (np.hypot(*(fit[:, :2] - centre0).T) > 0.5 * radius0 + 1)
    reason[moved & ~shape_bad] = "moved"
    reason[(n_inliers < np.maximum(params.min_edge_fraction * expected_points, 6))] = "few_edges"
    return reason
