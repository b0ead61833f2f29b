"""Bead detection: candidate blobs in a radiograph, each accepted or rejected with a reason.

The stage finds the image intensifier's field of view, flattens the
background and thresholds each blob at half its own contrast, so that it is
scale-aware and insensitive to vignetting, the heel effect and anatomy:

1. **Field of view.** The bright disc (round or octagonal) of the intensifier
   is thresholded at half its median level on a copy reduced to about 256 px;
   the convex hull of the largest region is the field of view.
2. **Log domain.** X-ray attenuation is multiplicative, so ``L = ln(I + 1)``
   turns vignetting, the heel effect and overlying anatomy into additive,
   slowly varying or step-like terms, and gives every steel bead the same
   contrast whatever lies over it.
3. **Polarity** (``"auto"``): the sign of the heavier tail of ``L`` minus its
   running median (dark steel beads on an open field, or bright holes of a
   grid plate).
4. **Flattening.** A grey-level black (dark beads) or white (bright holes)
   top-hat with a square larger than the largest bead keeps only the blobs
   smaller than the square; it leaves ramps and straight steps (bone edges,
   the plate of a grid phantom) at zero, because a flat symmetric closing or
   opening restores monotone edges.
5. **Blobs.** The top-hat, smoothed at a sixth of the smallest expected
   diameter, is thresholded where the intensity has changed by half of the
   change at its local maximum (half-maximum regions, one per bead whatever
   its contrast); each region's area and second moments give its diameter,
   roundness and an initial centre. A region too large or not round (a bead
   on a pedestal of anatomy about its own width) is measured again at 85 %.
6. **Rejection.** ``"fov_edge"`` (cut by the field-of-view edge),
   ``"size"``, ``"merged"`` (two touching beads: an elongated region as wide
   as one bead and up to two beads long), ``"not_round"`` and ``"faint"``
   (contrast below an absolute floor, a signal-to-noise floor, or a fraction
   of the median bead contrast in the frame).

With ``min_diameter_px = max_diameter_px = 0`` the expected diameter range is
estimated from the frame itself, on a 2x-reduced copy, from the round, strong
blobs found with a generous top-hat. When the smallest expected bead is at
least 6 px wide (its smoothing, a sixth of that, is then at least the 1 px
floor), steps 4-6 also run on a 2x-reduced copy, smoothed by the same
Gaussian in full-frame px (the candidates' centres need only be good to a few
tenths of a pixel: the centroid stage refines them); there a ``"merged"``
blob is also measured again at 85 % (two beads a pixel or two apart can merge
on the coarser grid).

Coordinates follow ``stages/geometry.py``: ``(x, y)`` with x = column, y = row,
the centre of the top-left pixel at ``(0, 0)``.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass, replace

import numpy as np
from fluorocal.stages._fov import bead_polarity, field_of_view, fov_clearance, pixel_noise
from fluorocal.stages._image import frame_name, log_image
from fluorocal.stages._regions import cores, flatten, regions
from fluorocal.stages.artifacts import SCHEMA_VERSION, Radiograph, as_arrays, check_shape, freeze
from fluorocal.stages.errors import InputError, ShapeError

log = logging.getLogger(__name__)

POLARITIES = ("auto", "dark", "bright")

#: rejection reasons, in the order they are tested (the first that applies is reported)
REASONS = ("fov_edge", "size", "merged", "not_round", "faint")

#: largest bead diameter the automatic estimate looks for, px
_MAX_ESTIMATE_DIAMETER_PX = 48.0


class EmptyFrameWarning(UserWarning):
    """A frame gave no accepted bead (blank, saturated or bead-free); the artifact is empty."""


@dataclass(frozen=True)
class DetectParams:
    """Parameters of :func:`detect_beads`.

    Attributes
    ----------
    polarity : {"auto", "dark", "bright"}
        ``"dark"``: beads darker than their surroundings (steel beads);
        ``"bright"``: brighter (holes of a grid plate); ``"auto"`` (default):
        decided from the heavier tail of the flattened log image (by
        ``fluorocal run`` once per system, see :func:`estimate_appearance`;
        here, on the frame itself).
    min_diameter_px, max_diameter_px : float
        Expected bead diameter range, px. Both 0 (default): estimated
        (``fluorocal run``: once per system; here: from the frame).
        Otherwise ``0 < min_diameter_px <= max_diameter_px``.
    min_contrast : float
        Absolute floor on a blob's log contrast ``ln(I_background / I_bead)``
        (about the fractional attenuation for small values). Default 0.05.
    min_snr : float
        Floor on the score: log contrast over the frame's pixel noise in the
        log image. Default 8.
    min_relative_contrast : float
        Floor on a blob's contrast as a fraction of the median contrast of the
        frame's otherwise acceptable blobs. Default 0.6.
    min_axis_ratio : float
        Minor over major axis of the blob's half-maximum region below which it
        is not round (a bead seen obliquely stays above 0.85). Default 0.7.
    min_fill : float
        Area of the half-maximum region over the area of its moment ellipse;
        a disc gives 1, a triangle 0.83, a ring or an L much less. Default 0.88.
    fov_margin_px : float
        A bead must lie this far, beyond its own radius, inside the field of
        view (the intensifier's edge is blurred over a few px). Default 2.
    """

    polarity: str = "auto"
    min_diameter_px: float = 0.0
    max_diameter_px: float = 0.0
    min_contrast: float = 0.05
    min_snr: float = 8.0
    min_relative_contrast: float = 0.6
    min_axis_ratio: float = 0.7
    min_fill: float = 0.88
    fov_margin_px: float = 2.0

    def __post_init__(self):
        if self.polarity not in POLARITIES:
            raise InputError(f"polarity must be one of {POLARITIES}; got {self.polarity!r}")
        lo, hi = self.min_diameter_px, self.max_diameter_px
        if not ((lo == 0 and hi == 0) or (0 < lo <= hi)):
            raise InputError(
                f"min_diameter_px, max_diameter_px must both be 0 (estimate) or 0 < min <= max; got {lo}, {hi}"
            )
        for name in ("min_contrast", "min_snr", "min_relative_contrast", "fov_margin_px"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0; got {getattr(self, name)}")
        for name in ("min_axis_ratio", "min_fill"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"{name} must be in [0, 1]; got {getattr(self, name)}")


@dataclass(frozen=True)
class BeadCandidates:
    """Candidate beads of one frame, accepted or rejected with a reason.

    Attributes
    ----------
    xy_px : (N, 2) float64 ndarray, px
        Centre of each candidate's half-maximum region, ``(x, y)``.
    radius_px : (N,) float64 ndarray, px
        Radius of the disc of the same area as the half-maximum region.
    contrast : (N,) float64 ndarray
        Peak log contrast ``ln(I_background / I_bead)`` (sign-corrected for
        bright beads), after smoothing.
    score : (N,) float64 ndarray
        ``contrast`` over the frame's pixel noise in the log image (an SNR).
    accepted : (N,) bool ndarray
    reason : (N,) str ndarray
        ``""`` where accepted, else one of :data:`REASONS`.
    polarity : str
        ``"dark"`` or ``"bright"`` (``"auto"`` resolved).
    fov_center_xy_px : tuple of float, px
        Centre ``(x, y)`` of the smallest circle around the field of view.
    fov_radius_px : float, px
        Its radius (an octagonal field lies inside it; candidates are tested
        against the field's own outline).
    diameter_px : float, px
        Median diameter of the accepted beads (0 when none).
    source : str
    frame_index : int
    """

    xy_px: np.ndarray
    radius_px: np.ndarray
    contrast: np.ndarray
    score: np.ndarray
    accepted: np.ndarray
    reason: np.ndarray
    polarity: str
    fov_center_xy_px: tuple = (0.0, 0.0)
    fov_radius_px: float = 0.0
    diameter_px: float = 0.0
    source: str = ""
    frame_index: int = 0
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        as_arrays(self, np.float64, "xy_px", shape=(-1, 2))
        as_arrays(self, np.float64, "radius_px", "contrast", "score")
        as_arrays(self, bool, "accepted")
        as_arrays(self, "<U16", "reason")
        object.__setattr__(self, "fov_center_xy_px", tuple(float(v) for v in self.fov_center_xy_px))
        n = len(self.xy_px)
        for name in ("radius_px", "contrast", "score", "accepted", "reason"):
            check_shape(name, getattr(self, name), (n,))
        if not np.all(np.isfinite(self.xy_px)):
            raise ShapeError("xy_px holds non-finite coordinates")
        if np.any(self.accepted != (self.reason == "")):
            raise ShapeError("reason must be '' exactly where accepted is True")
        if self.polarity not in ("dark", "bright"):
            raise InputError(f"polarity must be 'dark' or 'bright'; got {self.polarity!r}")
        freeze(self)

    def __len__(self) -> int:
        return len(self.xy_px)

    @property
    def n_accepted(self) -> int:
        return int(self.accepted.sum())

    def summary(self) -> str:
        """One line: accepted candidates, rejections by reason, polarity and bead size."""
        reasons, counts = np.unique(self.reason[~self.accepted], return_counts=True)
        rejected = ", ".join(f"{n} {r}" for r, n in zip(reasons, counts)) or "none"
        return f"{self.n_accepted} accepted, rejected: {rejected}; {self.polarity} beads ~{self.diameter_px:.1f} px"


def detect_beads(radiograph: Radiograph, params: DetectParams) -> BeadCandidates:
    """Find candidate beads in one frame.

    Parameters
    ----------
    radiograph : Radiograph
        The frame (float32, larger = brighter).
    params : DetectParams

    Returns
    -------
    BeadCandidates
        Every blob of a plausible size, accepted or rejected with a reason.
        A blank, saturated or bead-free frame gives no accepted candidate and
        an :class:`EmptyFrameWarning` naming the frame.

    Examples
    --------
    >>> yy, xx = np.mgrid[0:128, 0:128]
    >>> image = np.where((xx - 60.3) ** 2 + (yy - 70.6) ** 2 < 8.0**2, 150.0, 1400.0)
    >>> found = detect_beads(Radiograph(image, 12), DetectParams())
    >>> found.polarity, found.n_accepted, np.round(found.xy_px[found.accepted], 0).tolist()
    ('dark', 1, [[60.0, 71.0]])
    """
    import cv2

    image = radiograph.image
    name = frame_name(radiograph)
    prepared = _prepared(image)
    if prepared is None:
        return _empty(radiograph, params, name, "no field of view (blank frame)")
    hull_xy, fov_mask, noise, half_log, half_mask = prepared
    (cx, cy), fov_radius = cv2.minEnclosingCircle(hull_xy.astype(np.float32))
    polarity = params.polarity if params.polarity != "auto" else bead_polarity(image, fov_mask)
    if params.max_diameter_px > 0:
        d_min, d_max = params.min_diameter_px, params.max_diameter_px
    else:
        estimate = _estimate_diameter_range(half_log, half_mask, polarity, noise, params)
        if estimate is None:
            why = "no bead-like blob (bead-free or saturated frame)"
            return _empty(radiograph, params, name, why, polarity, (cx, cy), fov_radius)
        d_min, d_max = estimate
    blobs, reason = _frame_blobs(image, fov_mask, half_log, half_mask, polarity, d_min, d_max, noise, params)
    blobs, reason = _keep_reportable(blobs, reason, hull_xy, d_min, d_max, params)
    accepted = reason == ""
    if not accepted.any():
        warnings.warn(f"{name}: no bead accepted ({len(reason)} candidates rejected)", EmptyFrameWarning, stacklevel=2)
    diameter = float(np.median(2 * blobs["radius_px"][accepted])) if accepted.any() else 0.0
    log.debug(
        "%s: %d/%d candidates accepted, polarity %s, diameter %.1f px",
        name,
        accepted.sum(),
        len(reason),
        polarity,
        diameter,
    )
    return BeadCandidates(
        xy_px=blobs["xy_px"],
        radius_px=blobs["radius_px"],
        contrast=blobs["contrast"],
        score=blobs["contrast"] / noise,
        accepted=accepted,
        reason=reason,
        polarity=polarity,
        fov_center_xy_px=(cx, cy),
        fov_radius_px=float(fov_radius),
        diameter_px=diameter,
        source=radiograph.source,
        frame_index=radiograph.frame_index,
    )


def _prepared(image: np.ndarray):
    """``(hull_xy, fov_mask, noise, half_log, half_mask)`` of a frame (None without a field of view).

    ``half_*``: of a 2x-reduced copy, for the size estimate and for finding beads of 6 px and more.
    """
    import cv2

    height, width = image.shape
    if min(height, width) < 8:  # too small to hold a bead and its surround, or a half-size copy of one
        return None
    half = cv2.resize(image, (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    fov = field_of_view(image, half)
    if fov is None:
        return None
    hull_xy, fov_mask = fov
    half_log = log_image(half)
    half_mask = cv2.resize(fov_mask, (width // 2, height // 2), interpolation=cv2.INTER_NEAREST)
    return hull_xy, fov_mask, pixel_noise(image, fov_mask), half_log, half_mask


def estimate_appearance(radiographs, params: DetectParams) -> DetectParams:
    """``params`` with its automatic polarity and bead diameter range decided once, for a whole system.

    One system images one phantom at one magnification: the beads' polarity and size are the system's.
    Estimated once, on the first of ``radiographs`` that shows beads, they spare :func:`detect_beads`
    the estimate on every frame. Values already given in ``params`` are kept.

    Parameters
    ----------
    radiographs : iterable of Radiograph
        Frames of one system, tried in order (give a few: a blank first frame is passed over).
    params : DetectParams

    Returns
    -------
    DetectParams
        ``params`` with ``polarity`` resolved and the diameter range filled (rounded outwards to
        0.01 px); ``params`` unchanged when no frame shows a bead-like blob.

    Examples
    --------
    >>> yy, xx = np.mgrid[0:128, 0:128]
    >>> image = np.where((xx - 60.3) ** 2 + (yy - 70.6) ** 2 < 8.0**2, 150.0, 1400.0)
    >>> given = estimate_appearance([Radiograph(image, 12)], DetectParams())
    >>> given.polarity, 0 < given.min_diameter_px < 16 < given.max_diameter_px
    ('dark', True)
    """
    if params.polarity != "auto" and params.max_diameter_px > 0:
        return params
    for radiograph in radiographs:
        prepared = _prepared(radiograph.image)
        if prepared is None:
            continue
        _, fov_mask, noise, half_log, half_mask = prepared
        polarity = params.polarity if params.polarity != "auto" else bead_polarity(radiograph.image, fov_mask)
        if params.max_diameter_px > 0:
            return replace(params, polarity=polarity)
        estimate = _estimate_diameter_range(half_log, half_mask, polarity, noise, params)
        if estimate is not None:
            d_min, d_max = np.floor(100 * estimate[0]) / 100, np.ceil(100 * estimate[1]) / 100
            return replace(params, polarity=polarity, min_diameter_px=float(d_min), max_diameter_px=float(d_max))
    return params


def _frame_blobs(image, fov_mask, half_log, half_mask, polarity, d_min, d_max, noise, params: DetectParams):
    """:func:`_blobs` of the frame, on its 2x-reduced copy ``half_log`` when the beads are large enough.

    Returns the blobs (in full-frame px) and their rejection reasons, as :func:`_blobs`.
    """
    height, width = image.shape
    if d_min >= _REDUCE_FROM_DIAMETER_PX and min(height, width) >= 128:
        blobs, reason = _blobs(half_log, half_mask, polarity, d_min / 2, d_max / 2, noise, params, reduced=True)
        # a reduced pixel i covers full pixels 2i and 2i + 1: its centre is at 2i + 0.5
        blobs["xy_px"] = 2 * blobs["xy_px"] + 0.5
        for key in ("radius_px", "minor_diameter_px"):
            blobs[key] = 2 * blobs[key]
    else:
        blobs, reason = _blobs(log_image(image), fov_mask, polarity, d_min, d_max, noise, params, reduced=False)
    return blobs, reason


def _empty(radiograph, params, name, why, polarity=None, fov_center=(0.0, 0.0), fov_radius=0.0) -> BeadCandidates:
    warnings.warn(f"{name}: {why}; no bead candidates", EmptyFrameWarning, stacklevel=3)
    return BeadCandidates(
        xy_px=np.empty((0, 2)),
        radius_px=np.empty(0),
        contrast=np.empty(0),
        score=np.empty(0),
        accepted=np.empty(0, dtype=bool),
        reason=np.empty(0, dtype="<U16"),
        polarity=polarity or (params.polarity if params.polarity != "auto" else "dark"),
        fov_center_xy_px=fov_center,
        fov_radius_px=float(fov_radius),
        source=radiograph.source,
        frame_index=radiograph.frame_index,
    )


#: beads at least this wide (px) are found on a 2x-reduced copy (4x fewer pixels; the centroid stage refines): their
#: smoothing, a sixth of that, is then at least the full frame's 1 px floor, so both see the same smoothed beads
_REDUCE_FROM_DIAMETER_PX = 6.0


def _blobs(
    log_frame, fov_mask, polarity, d_min, d_max, noise, params: DetectParams, *, reduced: bool
) -> tuple[dict, np.ndarray]:
    """Candidate blobs and their rejection reasons.

    ``reduced``: ``log_frame`` is the frame reduced 2x; it is smoothed as the full frame would be (in full-frame
    px), and regions meeting only at a corner are two (a bead's region is 4-connected). Two beads a pixel or two
    apart, which the full frame keeps apart, can still merge on the coarser grid: a blob taken for two merged
    beads is measured again at 85 % too, and its cores replace it when their outlines keep a full-frame pixel
    apart.

    Each blob is first measured at half its local peak. A blob too large or
    not round there (a bead on a pedestal of anatomy of about its own width)
    is measured again at 85 % of its peak: the round regions of a plausible
    size inside it replace it, their radii widened by the median difference
    of the half-maximum and 85 % radii of the frame's clean beads.

    Returns
    -------
    blobs : dict of ndarray
        As :func:`~stages._regions.regions`.
    reason : (N,) str ndarray
    """
    flattened = flatten(log_frame, fov_mask, polarity, d_min, d_max, 0.5 if reduced else 1.0)
    connectivity = 4 if reduced else 8
    # only blobs whose peak clears the absolute floors become regions (a top-hat of pure noise is itself positive)
    floor = max(params.min_contrast, params.min_snr * noise)
    half, half_labels, boxes = regions(flattened, 0.5, floor, polarity, connectivity, core_fraction=0.85)
    core_area = half.pop("core_area")
    reason = _reasons(half, d_min, d_max, noise, params)
    retry = (reason == "size") | (reason == "not_round")
    if reduced:
        # two beads a pixel or two apart, which the full frame keeps apart, can merge on the coarser grid
        retry |= reason == "merged"
    if not retry.any():
        return half, reason
    clean = reason == ""
    # the 85 % contour lies inside the half-maximum one by about the edge's blur width, whatever the size
    with_core = clean & (core_area > 0)
    widen = (
        float(np.median(half["radius_px"][with_core] - np.sqrt(core_area[with_core] / np.pi)))
        if with_core.any()
        else 0.0
    )
    # the size test on the core itself (smaller than its outline), then its radius widened to the outline's;
    # a core lies inside its blob, so a blob narrower than the smallest core holds none
    core_d_min = max(d_min - 2 * widen, 0.0)
    retry &= 2 * half["radius_px"] >= core_d_min
    if not retry.any():
        return half, reason
    core, parent = cores(flattened, half_labels, boxes, np.flatnonzero(retry), 0.85, floor, polarity, connectivity)
    core_reason = _reasons(core, core_d_min, d_max, noise, params, typical_contrast=_typical_contrast(half, clean))
    core["radius_px"] = core["radius_px"] + widen
    rescued = core_reason == ""
    if reduced:
        # ... and are two beads again when their outlines (the widened cores) keep two full-frame pixels apart:
        # closer, each one's centroid is pulled by the other's edge by more than its stated uncertainty
        ok = np.flatnonzero(rescued)
        rescued[ok] = ~_overlapping(core["xy_px"][ok], core["radius_px"][ok], parent[ok], 1.0)
    if not rescued.any():
        return half, reason
    replaced = np.zeros(len(reason), bool)
    replaced[parent[rescued]] = True
    blobs = {k: np.concatenate([v[~replaced], core[k][rescued]]) for k, v in half.items()}
    return blobs, np.concatenate([reason[~replaced], core_reason[rescued]])


def _overlapping(xy, radius, group, margin: float) -> np.ndarray:
    """Circles (``xy``, ``radius``) within ``margin`` of another circle of the same ``group``; (M,) bool."""
    distance = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    near = (group[:, None] == group[None]) & (distance < radius[:, None] + radius[None] + margin)
    np.fill_diagonal(near, False)
    return near.any(axis=1)


def _typical_contrast(blobs: dict, plausible: np.ndarray) -> float:
    return float(np.median(blobs["contrast"][plausible])) if plausible.any() else 0.0


def _reasons(
    blobs: dict, d_min, d_max, noise, params: DetectParams, typical_contrast: float | None = None
) -> np.ndarray:
    """The first rejection reason (other than the field of view) that applies to each blob; (N,) str, ``""`` if none."""
    diameter = 2 * blobs["radius_px"]
    reason = np.full(len(diameter), "", dtype="<U16")
    elongated = (blobs["axis_ratio"] < params.min_axis_ratio) | (blobs["fill"] < params.min_fill)
    # two touching beads: as wide as one bead, 1.3 to 2.4 beads' area
    area_over_minor_disc = (diameter / np.maximum(blobs["minor_diameter_px"], 1e-6)) ** 2
    merged = (
        elongated
        & (area_over_minor_disc >= 1.3)
        & (area_over_minor_disc <= 2.4)
        & (blobs["minor_diameter_px"] >= d_min)
        & (blobs["minor_diameter_px"] <= d_max)
    )
    absolute_faint = (blobs["contrast"] < params.min_contrast) | (blobs["contrast"] < params.min_snr * noise)
    in_size = (diameter >= d_min) & (diameter <= d_max)
    if typical_contrast is None:
        typical_contrast = _typical_contrast(blobs, in_size & ~elongated & ~absolute_faint)
    faint = absolute_faint | (blobs["contrast"] < params.min_relative_contrast * typical_contrast)
    # the first condition listed wins: fill the array from the last to the first
    reason[faint] = "faint"
    reason[elongated & ~merged] = "not_round"
    reason[merged] = "merged"
    reason[~in_size & ~merged] = "size"
    return reason


def _keep_reportable(
    blobs: dict, reason: np.ndarray, hull_xy, d_min, d_max, params: DetectParams
) -> tuple[dict, np.ndarray]:
    """Mark blobs cut by the field's edge, and drop those that are plainly background."""
    reason = reason.copy()
    clearance = fov_clearance(blobs["xy_px"], hull_xy)
    reason[clearance < blobs["radius_px"] + params.fov_margin_px] = "fov_edge"
    diameter = 2 * blobs["radius_px"]
    # blobs far from the bead size, or faint and of the wrong size, are background, not candidates worth reporting
    keep = (
        (diameter >= 0.5 * d_min)
        & (diameter <= 2 * d_max)
        & ~((reason == "faint") & ((diameter < d_min) | (diameter > d_max)))
    )
    return {k: v[keep] for k, v in blobs.items()}, reason[keep]


def _estimate_diameter_range(half_log, half_mask, polarity, noise, params: DetectParams):
    """Expected bead diameter range ``(min, max)``, full-frame px, from the round strong blobs of a 2x-reduced image.

    Returns ``None`` when there is no such blob.
    """
    # averaging 2x2 pixels halves white noise
    flattened = flatten(half_log, half_mask, polarity, 2.0, _MAX_ESTIMATE_DIAMETER_PX / 2, 1.0)
    blobs, _, _ = regions(flattened, 0.5, max(params.min_contrast, params.min_snr * noise / 2), polarity)
    diameter = 2 * 2 * blobs["radius_px"]
    strong = (blobs["contrast"] >= max(params.min_contrast, params.min_snr * noise / 2)) & (diameter >= 4)
    round_ = (blobs["axis_ratio"] >= params.min_axis_ratio) & (blobs["fill"] >= params.min_fill)
    good = strong & round_
    if not good.any():
        return None
    # the typical bead: the median diameter of the round blobs whose contrast is near the strongest ones'
    contrast = blobs["contrast"][good]
    d = diameter[good]
    beadlike = contrast >= 0.5 * np.percentile(contrast, 90)
    typical = float(np.median(d[beadlike]))
    near = d[beadlike][(d[beadlike] >= 0.5 * typical) & (d[beadlike] <= 2.5 * typical)]
    # the reduced copy measures diameters a little small (its pixels average the blurred edges)
    return max(3.0, 0.6 * min(typical, near.min())), 1.5 * max(typical, near.max())
