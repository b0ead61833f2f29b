"""Projection truth: every bead's ideal, distorted and outline centre in one frame, with visibility flags."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import camera_matrix, check_points, project, quat_to_matrix, to_camera
from fluorocal.stages.simulate.distortion import ImageDistortion
from fluorocal.stages.simulate.params import N_OUTLINE


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
        ``distortion.distort_points(ideal_xy_px)``.
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

    @property
    def visible(self) -> np.ndarray:
        """``(N,) bool``: the beads that overlap no other and keep clear of the field's rim."""
        return ~self.overlap & ~self.field_edge

    def match(self, xy_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Match measured centres to the beads: a centre within a quarter of a bead's diameter finds it.

        Parameters
        ----------
        xy_px : (M, 2) float64 ndarray, px
            Measured centres (for example the fitted centroids of a frame).

        Returns
        -------
        found : (N,) bool ndarray
            The :attr:`visible` beads whose nearest measured centre is within a quarter of their diameter.
        nearest : (N,) int64 ndarray
            Row of ``xy_px`` nearest to each bead.
        false : (M,) bool ndarray
            The measured centres farther than a quarter of its diameter from the nearest bead's outline centre.
        """
        from scipy.spatial import cKDTree

        d, nearest = cKDTree(xy_px).query(self.outline_xy_px)
        found = self.visible & (d < self.diameter_px / 4)
        d_back, k = cKDTree(self.outline_xy_px).query(xy_px)
        return found, nearest, d_back > self.diameter_px[k] / 4

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
    K = camera_matrix((xp, yp, c))
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
    """Area centroids ``(N, 2)`` and areas ``(N,)`` of closed polygons ``(N, M, 2)`` (shoelace).

    Taken about each polygon's first vertex: in image coordinates (hundreds of px) the shoelace's products of a
    few-px polygon cancel to ~1e-8 px.
    """
    origin = points[:, 0, :]
    x, y = points[..., 0] - origin[:, 0, None], points[..., 1] - origin[:, 1, None]
    x1, y1 = np.roll(x, -1, axis=-1), np.roll(y, -1, axis=-1)
    cross = x * y1 - x1 * y
    area = cross.sum(-1) / 2
    cx = ((x + x1) * cross).sum(-1) / (6 * area)
    cy = ((y + y1) * cross).sum(-1) / (6 * area)
    return origin + np.column_stack([cx, cy]), np.abs(area)


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
    # shape (N, N_OUTLINE, 2): centre + L (cos t, sin t), by broadcasting (einsum's loop over so short a sum is slow)
    ring = centre[:, None, :] + axes[:, None, :, 0] * np.cos(t)[:, None] + axes[:, None, :, 1] * np.sin(t)[:, None]
    ring_d = distortion.distort_points(ring)
    outline_xy, area = _polygon_centroid_area(ring_d)
    radius_max = np.max(np.linalg.norm(ring_d - outline_xy[:, None, :], axis=-1), axis=1)
    return _Outlines(ideal, distortion.distort_points(ideal), centre, outline_xy, 2 * np.sqrt(area / np.pi), radius_max)


def _field_flags(o: _Outlines, image_size_px: int, fov_radius_px: float, margin: float):
    """Per bead: the outline meets the field of view and the image; it reaches within ``margin`` px of their edges.

    Returns
    -------
    visible, field_edge : (N,) bool ndarray
    """
    centre = np.full(2, (image_size_px - 1) / 2.0)
    r_fov = np.linalg.norm(o.outline_xy_px - centre, axis=1)
    rad = o.radius_max_px
    lo, hi = o.outline_xy_px - rad[:, None], o.outline_xy_px + rad[:, None]
    in_image = np.all((hi >= -0.5) & (lo <= image_size_px - 0.5), axis=1)
    visible = (r_fov < fov_radius_px + rad) & in_image
    field_edge = (r_fov > fov_radius_px - rad - margin) | np.any(
        (lo < -0.5 + margin) | (hi > image_size_px - 0.5 - margin), axis=1
    )
    return visible, field_edge


def _overlap_flags(o: _Outlines, margin: float) -> np.ndarray:
    """Per bead: its outline comes within ``margin`` px of another bead's outline; (N,) bool."""
    rad = o.radius_max_px
    overlap = np.zeros(len(rad), dtype=bool)
    if len(rad) > 1:
        from scipy.spatial import cKDTree

        tree = cKDTree(o.outline_xy_px)
        pairs = tree.query_pairs(2 * rad.max() + margin, output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
        close = np.linalg.norm(o.outline_xy_px[i] - o.outline_xy_px[j], axis=1) < rad[i] + rad[j] + margin
        overlap[i[close]] = True
        overlap[j[close]] = True
    return overlap


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
    visible, field_edge = _field_flags(o, image_size_px, fov_radius_px, overlap_margin_px)
    overlap = _overlap_flags(o, overlap_margin_px)
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
