"""Automatic labelling: the phantom bead id of every detection in one frame.

Two kinds of phantom are handled (README.md "Conventions" for pixels, poses
and the interior orientation):

- **3D bead phantoms** (a cube): an approximate pose is found from the marker
  beads (role ``marker``, recognised by their larger apparent size), from a
  few seeds ``(id, x, y)`` or from the previous frame's pose (with fewer
  than three marker detections, neighbouring beads complete the P3P: beads
  near a marker in the image are often its neighbours on the phantom). From there the
  labelling iterates: project every bead through the pose and the assumed
  interior orientation plus a low-order 2D polynomial correction (the
  image-intensifier distortion leaves residuals of 10-20 px at the field edge
  that a pinhole cannot absorb), assign detections to projections optimally
  within a distance gate (:func:`scipy.optimize.linear_sum_assignment`),
  refine the pose (RANSAC first, then least squares together with the
  principal distance, since the configured geometry is rough) and the
  correction on the assigned pairs, until the assignment stops changing.
  Because the gate only admits pairs that the current model predicts well,
  the labelled set grows from where the model is good (near the markers and
  the centre) outward, and the correction's degree grows with it. Beads whose
  outlines lie within about one bead diameter of another bead's are ambiguous
  (front and back faces of the cube overlap in the X-ray) and are left out,
  together with the detections they absorb. A labelling is accepted only if
  it explains most detections with small residuals and puts marker-sized
  detections on markers. From another frame's pose (a sequence), the
  orientation is taken as roughly right but the position is searched: every
  detection-bead pair votes for the shift of the phantom across the beam that
  would put the bead on the detection, over the whole image and a few depths;
  the peaks of the vote are labelled, and the best labelling is kept only if
  no distinct one (a periodic layout one row off) explains the frame about as
  well. In a sequence (:func:`label_sequence`), a frame that still fails is
  searched over turns about the turntable axis estimated from the frames
  already labelled.
- **Grid plates** (``phantom.lattice`` ``"hex"`` or ``"square"``): the holes
  are indexed on their lattice by topology, growing outward from a hole near
  the centre with local lattice vectors re-estimated at every hole, so that
  the distortion, missing holes and the field edge do not cause slips. The
  object coordinates are the lattice coordinates times the pitch, z = 0, and
  the ids encode the lattice indices (:func:`lattice_id`).

A frame whose labelling fails is returned with ``ok = False`` and a
``reason``; nothing is labelled in it (never a silent mislabelling).
"""

from __future__ import annotations

import heapq
import itertools
import logging
from dataclasses import dataclass, field, replace

import numpy as np
from fluorocal.stages._geometry import matrix_to_quat, quat_to_matrix, rotvec_to_quat, to_camera
from fluorocal.stages.artifacts import SCHEMA_VERSION, Phantom, check_shape, freeze
from fluorocal.stages.errors import InputError

VERSION = 2

log = logging.getLogger(__name__)

#: per-detection status codes in :attr:`Labels.detection_status`
STATUS_LABELLED, STATUS_AMBIGUOUS, STATUS_UNMATCHED, STATUS_REJECTED = 0, 1, 2, 3

#: grid-plate ids: ``id = (i + LATTICE_ID_OFFSET) * LATTICE_ID_BASE + (j + LATTICE_ID_OFFSET)``
LATTICE_ID_OFFSET = 5000
LATTICE_ID_BASE = 10000

# hexagonal lattice: hole (i, j) at i*a1 + j*a2 with a2 = a1 rotated by +60 degrees
_HEX_STEPS = np.array([[1, 0], [0, 1], [-1, 1], [-1, 0], [0, -1], [1, -1]])
_SQUARE_STEPS = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
# P3P problems solved per frame from marker triples, and marker hypotheses verified on all beads
_P3P_BUDGET = 1500
_N_VERIFY = 6
# beads sampled to pre-rank many marker hypotheses
_N_SAMPLE = 64
# with only two marker detections: their nearest detections and the markers' nearest beads tried as a third pair
_PAIR_NEAR_DETECTIONS = 3
_PAIR_NEAR_BEADS = 8
# a second pose hypothesis whose coarse score reaches this fraction of the best's is labelled too
_RIVAL_SCORE = 0.8
# ... and if its labelling explains this fraction of the best's, with other labels, the frame is ambiguous
_RIVAL_LABELS = 0.95
# a marker pose whose pinhole projection has a detection near this fraction of all detections ends the search
_GOOD_COARSE = 0.6
# detections considered per prediction in the assignment (within the gate, nearest first)
_MAX_CANDIDATES = 4
# correction degree at each labelling iteration (then the configured degree)
_DEGREE_SCHEDULE = (0, 1, 3, 5)
# c is refined only when the labelled beads' depths spread by this fraction of their mean depth (std)
_MIN_DEPTH_SPREAD = 0.02
# ... in the first iterations after the coarse pose only (it settles in two)
_C_ITERATIONS = 2
# cost of a forbidden pair in the assignment: larger than any sum of gated distances
_FORBIDDEN = 1e9
# from another frame's pose: peaks of the shift vote kept as starts, sought among this many of the strongest bins
_N_PEAKS = 8
_N_PEAK_BINS = 300
# ... starts labelled (best coarse score first) until one is acceptable
_MAX_STARTS = 6
# ... and another start is labelled in full when its screen count reaches this fraction of the labelling's
_SCREEN_RIVAL = 0.85
# the phantom's distance from the source may change by this fraction between neighbouring frames
_MAX_DEPTH_CHANGE = 0.05
# detections voting (evenly thinned) when depths or turns are compared, and turns searched in full
_N_DEPTH_DETECTIONS = 80
_N_TURN_DETECTIONS = 120
_N_TURNS = 4
_N_TURN_CANDIDATES = 12
# the turntable axis is estimated from the sequence once its labelled frames span this turn
_MIN_AXIS_TURN_DEG = 3.0


@dataclass(frozen=True)
class LabelParams:
    """Parameters of :func:`label_beads`.

    Distances given in bead diameters scale with each bead's apparent
    diameter in the frame (its projected diameter once a pose is known, the
    median detected diameter before), so the defaults hold for any bead size.

    Attributes
    ----------
    source_image_distance_mm : float
        Source-image distance of the system (mm, approximate); filled by the pipeline from the system config.
    pixel_pitch_mm : float
        Detector pixel pitch (mm, approximate); filled from the system config. The assumed principal
        distance is ``c = source_image_distance_mm / pixel_pitch_mm`` px.
    image_size_px : tuple of int
        ``(width, height)`` of the frame; the assumed principal point is its centre. ``()`` (default): from the
        centroids artifact when it carries the image shape, otherwise the centre of the detections' bounding box.
    seeds : tuple of (id, x_px, y_px)
        Manually identified beads in this frame (at least 3, ideally 4 or more spread out); when given they
        replace the markers and any prior pose. Default ``()``.
    gate_bead_diameters : float
        Assignment gate: a detection may be assigned to a bead only within this distance of its predicted
        position (default 0.5, half the ambiguity distance, so that an unambiguous bead's nearest rival is
        at least as far again).
    final_gate_bead_diameters : float
        A label is kept only if the detection lies within this distance of the final prediction
        (pose + correction; default 0.25).
    ambiguity_bead_diameters : float
        A bead is ambiguous when another bead's outline centre lies closer than this times the mean of their
        apparent diameters (default 1.0: the outlines touch). Centres are the measured ones where a bead was
        detected, the predicted ones elsewhere; diameters are projected from the pose, scaled by the local
        magnification of the correction.
    ransac_threshold_bead_diameters : float
        Inlier threshold of the RANSAC pose on the first, coarse assignment (default 0.3).
    ransac_iterations : int
        Iterations of the RANSAC pose (default 200).
    correction_degree : int
        Total degree (0-5) of the 2D polynomial correction fitted during labelling (default 3; 0 = pinhole
        only); it is reached over the first iterations, as the labelled set grows.
    max_iterations : int
        Cap on assignment/refinement iterations (default 15).
    marker_size_ratio : float
        Apparent size ratio of markers to ordinary beads; 0 (default) = from the phantom's diameters.
    max_marker_candidates : int
        At most this many of the largest detections are tried as markers (default 10).
    min_labelled : int
        A 3D-phantom frame with fewer labelled beads fails (default 12).
    min_labelled_fraction : float
        A frame fails when fewer than this fraction of its valid detections are labelled or ambiguous
        (default 0.7): most detections of a sound frame are beads of the phantom.
    max_axis_ratio : float
        3D phantoms: detections more elongated than this (major / minor axis) are merged blobs of overlapping
        beads, not labelled (default 1.3; a sphere's outline stays within a few % of round).
    max_rms_bead_diameters, max_rms_floor_px : float
        A frame fails when the labelled detections' RMS distance from the final prediction (pose + correction)
        exceeds ``max(max_rms_floor_px, max_rms_bead_diameters x diameter)`` (defaults 0.1 and 1.5 px): right
        labels leave centroid noise and unmodelled distortion (< 1 px), chance matches spread over the gate.
    lattice_tolerance_pitch : float
        Grid plates: a hole is accepted within this fraction of the local spacing of its predicted
        lattice position (default 0.3).
    lattice_max_gap : int
        Grid plates: the growth bridges up to this many consecutive missing holes (default 2).
    """

    source_image_distance_mm: float = 0.0
    pixel_pitch_mm: float = 0.0
    image_size_px: tuple[int, ...] = ()
    seeds: tuple[tuple[float, ...], ...] = ()
    gate_bead_diameters: float = 0.5
    final_gate_bead_diameters: float = 0.25
    ambiguity_bead_diameters: float = 1.0
    ransac_threshold_bead_diameters: float = 0.3
    ransac_iterations: int = 200
    correction_degree: int = 3
    max_iterations: int = 15
    marker_size_ratio: float = 0.0
    max_marker_candidates: int = 10
    min_labelled: int = 12
    min_labelled_fraction: float = 0.7
    max_axis_ratio: float = 1.3
    max_rms_bead_diameters: float = 0.1
    max_rms_floor_px: float = 1.5
    lattice_tolerance_pitch: float = 0.3
    lattice_max_gap: int = 2

    def __post_init__(self):
        positive = (
            "gate_bead_diameters",
            "final_gate_bead_diameters",
            "ambiguity_bead_diameters",
            "ransac_threshold_bead_diameters",
            "lattice_tolerance_pitch",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0; got {getattr(self, name)}")
        if self.source_image_distance_mm < 0 or self.pixel_pitch_mm < 0:
            raise InputError(
                "source_image_distance_mm and pixel_pitch_mm must be >= 0; "
                f"got {self.source_image_distance_mm}, {self.pixel_pitch_mm}"
            )
        if len(self.image_size_px) not in (0, 2):
            raise InputError(f"image_size_px must be () or (width, height); got {self.image_size_px}")
        if any(len(s) != 3 for s in self.seeds):
            raise InputError(f"seeds must be (id, x_px, y_px) triples; got {self.seeds}")
        if not 0 <= self.correction_degree <= 5:
            raise InputError(f"correction_degree must be in 0..5; got {self.correction_degree}")


@dataclass(frozen=True)
class Labels:
    """The labelled detections of one frame.

    Attributes
    ----------
    det_index : (N,) int64 ndarray
        Index of each labelled detection into the centroids artifact.
    bead_id : (N,) int64 ndarray
        Phantom bead id (grid plates: :func:`lattice_id` of the hole's lattice indices).
    xy_px : (N, 2) float64 ndarray, px
        Measured (distorted) centre of each labelled detection.
    sigma_px : (N, 3) float64 ndarray
        ``(sigma_x px, sigma_y px, rho)`` of each centre, from the centroid stage.
    object_xyz_mm : (N, 3) float64 ndarray, mm
        Nominal object coordinates of each labelled bead (grid plates: lattice coordinates x pitch, z = 0).
    detection_status : (M,) int8 ndarray
        For every detection of the centroids artifact: ``STATUS_LABELLED`` (0), ``STATUS_AMBIGUOUS`` (1, assigned
        to a bead whose projection overlaps another's), ``STATUS_UNMATCHED`` (2) or ``STATUS_REJECTED`` (3, not a
        usable centroid: failed fit, or too elongated for one bead).
    q : (4,) float64 ndarray
        Approximate pose rotation ``(w, x, y, z)``, object to camera (NaN when the frame failed).
    source_mm : (3,) float64 ndarray, mm
        Approximate X-ray source position in object space (NaN when the frame failed).
    iop : (3,) float64 ndarray, px
        The interior orientation ``(xp, yp, c)`` of the labelling: the principal point assumed at the image
        centre, ``c`` from the configured source-image distance and pixel pitch, refined during the labelling of
        a 3D phantom when its beads span enough depth (approximate: the adjustment estimates the IOP).
    n_labelled, n_ambiguous, n_unmatched : int
        Valid detections labelled / left out as ambiguous / matching no bead.
    rms_px : float
        Reprojection RMS of the labelled detections under the pinhole pose and the assumed IOP (px, in-sample;
        includes the uncorrected distortion). NaN for a grid plate labelled without the geometry.
    rms_corrected_px : float
        The same after the low-order polynomial correction fitted during labelling (px, in-sample; for a grid
        plate, of a homography plus that correction, so it is available without the geometry).
    ok : bool
        False when the frame's labelling failed; then nothing is labelled.
    reason : str
        Why it failed ("" when ok).
    pose_source : str
        ``"markers"``, ``"seeds"``, ``"prior"``, ``"lattice"`` or ``""``.
    """

    det_index: np.ndarray
    bead_id: np.ndarray
    xy_px: np.ndarray
    sigma_px: np.ndarray
    object_xyz_mm: np.ndarray
    detection_status: np.ndarray
    q: np.ndarray
    source_mm: np.ndarray
    iop: np.ndarray
    n_labelled: int = 0
    n_ambiguous: int = 0
    n_unmatched: int = 0
    rms_px: float = float("nan")
    rms_corrected_px: float = float("nan")
    ok: bool = True
    reason: str = ""
    pose_source: str = ""
    schema_version: int = SCHEMA_VERSION

    def __post_init__(self):
        for name in ("det_index", "bead_id"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.int64).reshape(-1))
        for name, width in (("xy_px", 2), ("sigma_px", 3), ("object_xyz_mm", 3)):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1, width))
        object.__setattr__(self, "detection_status", np.asarray(self.detection_status, dtype=np.int8).reshape(-1))
        for name, n in (("q", 4), ("source_mm", 3), ("iop", 3)):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(n))
        n = len(self.det_index)
        check_shape("bead_id", self.bead_id, (n,))
        check_shape("xy_px", self.xy_px, (n, 2))
        check_shape("sigma_px", self.sigma_px, (n, 3))
        check_shape("object_xyz_mm", self.object_xyz_mm, (n, 3))
        for name in ("n_labelled", "n_ambiguous", "n_unmatched"):
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "ok", bool(self.ok))
        freeze(self)

    def __len__(self) -> int:
        return len(self.det_index)

    def to_table(self) -> tuple[list[str], list[list]]:
        """The labelled detections as ``(header, rows)`` with columns ``id,x,y,sigma_x,sigma_y,rho``."""
        header = ["id", "x", "y", "sigma_x", "sigma_y", "rho"]
        rows = [
            [int(i), float(x), float(y), float(sx), float(sy), float(r)]
            for i, (x, y), (sx, sy, r) in zip(self.bead_id, self.xy_px, self.sigma_px)
        ]
        return header, rows

    def summary(self) -> str:
        """One line: counts, pose source and RMS, or the failure reason."""
        if not self.ok:
            return f"labelling failed: {self.reason}"
        return (
            f"{self.n_labelled} labelled, {self.n_ambiguous} ambiguous, {self.n_unmatched} unmatched; pose from {self.pose_source}, "
            f"RMS {self.rms_px:.2f} px pinhole, {self.rms_corrected_px:.2f} px corrected"
        )


def lattice_id(ij: np.ndarray) -> np.ndarray:
    """Bead ids of grid-plate holes from their lattice indices ``(i, j)``; inverse of :func:`lattice_index`.

    Examples
    --------
    >>> lattice_id(np.array([[0, 0], [-3, 2]]))
    array([50005000, 49975002])
    """
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    return (ij[:, 0] + LATTICE_ID_OFFSET) * LATTICE_ID_BASE + (ij[:, 1] + LATTICE_ID_OFFSET)


def lattice_index(ids: np.ndarray) -> np.ndarray:
    """Lattice indices ``(N, 2)`` of grid-plate hole ids made by :func:`lattice_id`."""
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    return np.column_stack([ids // LATTICE_ID_BASE - LATTICE_ID_OFFSET, ids % LATTICE_ID_BASE - LATTICE_ID_OFFSET])


def lattice_xyz_mm(ij: np.ndarray, lattice: str, pitch_mm: float) -> np.ndarray:
    """Object coordinates ``(N, 3)`` (mm, z = 0) of lattice indices ``(i, j)``.

    A hexagonal lattice has hole ``(i, j)`` at ``pitch * (i + j/2, j * sqrt(3)/2)``; a square one at
    ``pitch * (i, j)``.
    """
    ij = np.asarray(ij, dtype=np.float64).reshape(-1, 2)
    basis = _lattice_basis(lattice)
    return np.column_stack([pitch_mm * ij @ basis.T, np.zeros(len(ij))])


def label_beads(centroids, phantom: Phantom, params: LabelParams, prior_pose: tuple | None = None) -> Labels:
    """Give every detection of one frame its phantom bead id.

    Parameters
    ----------
    centroids : Centroids
        The centroid stage's output for the frame: ``xy_px (M, 2)``, ``sigma_x``, ``sigma_y``, ``rho``,
        ``major_px``, ``minor_px`` (semi-axes) and ``ok`` per detection.
    phantom : Phantom
        Nominal bead coordinates and roles, or a grid plate (``lattice``, ``pitch_mm``).
    params : LabelParams
        ``source_image_distance_mm`` and ``pixel_pitch_mm`` must be set for a 3D phantom.
    prior_pose : (q, source_mm), optional
        An approximate pose, e.g. the previous frame's of a sequence; tried when the markers give no acceptable
        labelling (ignored when seeds are given). Its orientation is taken as roughly right, its position not:
        the phantom's shift across the beam is searched over the whole image and its distance over a few %,
        every clear peak is labelled, and the best labelling is kept only if no distinct one explains the
        frame about as well (a periodic bead layout could otherwise slip by a row).

    Returns
    -------
    Labels
        ``ok = False`` with a ``reason`` when the frame could not be labelled reliably.

    Raises
    ------
    InputError
        A 3D phantom without ``source_image_distance_mm`` and ``pixel_pitch_mm``, a phantom of fewer than 4
        beads, a grid plate without a valid lattice or pitch, or seeds naming beads the phantom lacks.
    """
    return _label_frame(centroids, phantom, params, prior_pose)


def _label_frame(centroids, phantom: Phantom, params: LabelParams, prior_pose=None, turntable_axis=None) -> Labels:
    """:func:`label_beads`, with the turntable axis (camera frame) of a sequence when it is known."""
    det = _Detections.from_centroids(centroids)
    iop = _assumed_iop(det, centroids, params, need_c=not phantom.lattice)
    if phantom.lattice:
        if phantom.lattice not in ("hex", "square"):
            raise InputError(f"phantom.lattice must be 'hex' or 'square'; got {phantom.lattice!r}")
        if not phantom.pitch_mm > 0:
            raise InputError(f"phantom.pitch_mm must be > 0 for a grid plate; got {phantom.pitch_mm}")
        return _label_grid(det, phantom, params, iop)
    if phantom.n_beads < 4:
        raise InputError(f"phantom must have at least 4 beads; got {phantom.n_beads}")
    return _label_cube(det, phantom, params, iop, prior_pose, turntable_axis)


def label_sequence(
    centroids_seq, phantom: Phantom, params: LabelParams, seeds_by_frame: dict | None = None
) -> tuple[Labels, ...]:
    """Label the frames of one system's sequence, passing each frame's pose on to its neighbours.

    Frames with seeds (``seeds_by_frame[i]``, ``(id, x_px, y_px)`` triples) are labelled from them; the
    others from the markers and from the pose of the nearest labelled frame before them (a forward
    pass), then, for frames still unlabelled, of the nearest one after them (a backward pass). The
    neighbour's position is searched over the whole image (see :func:`label_beads`); a frame that
    still fails is searched over turns about the turntable axis, estimated from the labelled frames'
    orientations (before they span a few degrees: the image's vertical axis). Each frame is still
    accepted or rejected on its own evidence.

    Parameters
    ----------
    centroids_seq : sequence of Centroids
        The frames in acquisition order.
    phantom : Phantom
    params : LabelParams
        Its ``seeds`` are ignored here; give them per frame in ``seeds_by_frame``.
    seeds_by_frame : dict of int to tuple, optional

    Returns
    -------
    tuple of Labels
        One per frame, in order.
    """
    seeds_by_frame = dict(seeds_by_frame or {})
    n = len(centroids_seq)
    bad = [i for i in seeds_by_frame if not 0 <= i < n]
    if bad:
        raise InputError(f"seeds_by_frame names frames {bad} outside 0..{n - 1}")
    base = replace(params, seeds=())
    out: list[Labels | None] = [None] * n
    rotations: dict[int, np.ndarray] = {}  # frame -> R (object to camera) of the labelled frames

    def run(i, prior):
        seeds = tuple(tuple(s) for s in seeds_by_frame.get(i, ()))
        if seeds:
            return label_beads(centroids_seq[i], phantom, replace(base, seeds=seeds))
        axis = _turntable_axis(list(rotations.values())) if prior is not None else None
        return _label_frame(centroids_seq[i], phantom, base, prior, axis)

    def keep(i):
        if out[i].ok and not phantom.lattice:
            rotations[i] = quat_to_matrix(out[i].q)
            return (out[i].q, out[i].source_mm)
        return None

    prior = None
    for i in range(n):
        out[i] = run(i, prior)
        prior = keep(i) or prior
    prior = None
    for i in reversed(range(n)):
        if not out[i].ok and prior is not None:
            out[i] = run(i, prior)
        prior = keep(i) or prior
    return tuple(out)


def _turntable_axis(rotations: list) -> np.ndarray | None:
    """The axis (camera frame) about which the phantom turns between the labelled frames of a sequence.

    A turntable turns the phantom about an axis fixed in the lab, hence in the camera frame of a
    system: ``R_j R_i^T`` is a turn about it. The axis is the principal direction of the rotation
    vectors of every labelled frame relative to the first, once they span at least
    ``_MIN_AXIS_TURN_DEG``; before that, the image's vertical axis (a turntable seen by a horizontal
    beam, the usual setup). None without a labelled frame.
    """
    from scipy.spatial.transform import Rotation

    if not rotations:
        return None
    Rs = np.asarray(rotations)
    rotvecs = Rotation.from_matrix(Rs @ Rs[0].T).as_rotvec()
    if np.degrees(np.linalg.norm(rotvecs, axis=1).max()) < _MIN_AXIS_TURN_DEG:
        return np.array([0.0, 1.0, 0.0])
    return np.linalg.eigh(rotvecs.T @ rotvecs)[1][:, -1]


# --- inputs ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Detections:
    """The detections of a frame, with the usable ones flagged."""

    xy_px: np.ndarray  # (M, 2)
    sigma_px: np.ndarray  # (M, 3)
    size_px: np.ndarray  # (M,) apparent diameter (twice the minor semi-axis), NaN when unknown
    axis_ratio: np.ndarray  # (M,) major / minor semi-axis, NaN when unknown
    valid: np.ndarray  # (M,) bool

    @classmethod
    def from_centroids(cls, centroids) -> "_Detections":
        xy = np.asarray(centroids.xy_px, dtype=np.float64).reshape(-1, 2)
        m = len(xy)

        def column(name, default):
            value = getattr(centroids, name, None)
            return (
                np.full(m, default, dtype=np.float64)
                if value is None
                else np.asarray(value, dtype=np.float64).reshape(m)
            )

        sigma = np.column_stack([column("sigma_x", np.nan), column("sigma_y", np.nan), column("rho", 0.0)])
        ok = getattr(centroids, "ok", None)
        valid = np.ones(m, dtype=bool) if ok is None else np.asarray(ok, dtype=bool).reshape(m).copy()
        valid &= np.isfinite(xy).all(1) & np.isfinite(sigma).all(1)
        minor = column("minor_px", np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = column("major_px", np.nan) / minor
        # the minor axis, not the area: two touching beads merged into one blob keep a small minor axis
        return cls(xy, sigma, 2.0 * minor, ratio, valid)


def _image_size(centroids, params: LabelParams) -> tuple[float, float] | None:
    if params.image_size_px:
        return float(params.image_size_px[0]), float(params.image_size_px[1])
    shape = getattr(centroids, "image_shape", None)  # (H, W), if the centroid stage records it
    if shape is not None and len(shape) == 2 and all(s > 0 for s in shape):
        return float(shape[1]), float(shape[0])
    return None


def _assumed_iop(det: _Detections, centroids, params: LabelParams, *, need_c: bool) -> np.ndarray:
    """``(xp, yp, c)``: principal point at the image centre, ``c = SID / pitch``.

    Without the image size, the centre of the detections' bounding box stands in for the image centre
    (the field of view of an image intensifier is centred on the detector); the pose absorbs the difference.
    """
    if need_c and not (params.source_image_distance_mm > 0 and params.pixel_pitch_mm > 0):
        raise InputError(
            "params.source_image_distance_mm and params.pixel_pitch_mm must be > 0 to label a 3D phantom; "
            f"got {params.source_image_distance_mm}, {params.pixel_pitch_mm}"
        )
    c = params.source_image_distance_mm / params.pixel_pitch_mm if params.pixel_pitch_mm > 0 else np.nan
    size = _image_size(centroids, params)
    if size is not None:
        return np.array([(size[0] - 1) / 2, (size[1] - 1) / 2, c])
    pts = det.xy_px[det.valid]
    if not len(pts):
        return np.array([0.0, 0.0, c])
    return np.array([*(0.5 * (pts.min(0) + pts.max(0))), c])


def _camera_matrix(iop: np.ndarray) -> np.ndarray:
    xp, yp, c = iop
    return np.array([[c, 0.0, xp], [0.0, c, yp], [0.0, 0.0, 1.0]])


def _failed(det: _Detections, iop: np.ndarray, reason: str, pose_source: str = "") -> Labels:
    log.info("labelling failed: %s", reason)
    status = np.where(det.valid, STATUS_UNMATCHED, STATUS_REJECTED)
    empty = np.empty((0,))
    return Labels(
        empty,
        empty,
        np.empty((0, 2)),
        np.empty((0, 3)),
        np.empty((0, 3)),
        status,
        np.full(4, np.nan),
        np.full(3, np.nan),
        iop,
        0,
        0,
        int(det.valid.sum()),
        ok=False,
        reason=reason,
        pose_source=pose_source,
    )


# --- poses: ours (q, T) <-> OpenCV (rvec, tvec) -------------------------------------------------
# OpenCV's camera frame (x right, y down, z forward) is ours; it maps object to camera as
# p = R P + t, ours as p = R (P - T), so t = -R T and T = -R^T t.


def _pose_to_cv(R: np.ndarray, source_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(rvec, tvec)`` of our pose ``(R, T)``."""
    import cv2

    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rvec.reshape(3), -R @ np.asarray(source_mm, dtype=np.float64)


def _pose_from_cv(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Our pose ``(q, T)`` of OpenCV's ``(rvec, tvec)``."""
    q = rotvec_to_quat(np.asarray(rvec, dtype=np.float64).reshape(3))
    return q, -quat_to_matrix(q).T @ np.asarray(tvec, dtype=np.float64).reshape(3)


def _project_cam(p_cam: np.ndarray, iop: np.ndarray) -> np.ndarray:
    """The pinhole of :func:`stages._geometry.project` on camera-frame points (the labelling keeps poses as
    rotation matrices, so the quaternion round trip is skipped); NaN behind the source.
    """
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.column_stack([iop[0] + iop[2] * p_cam[:, 0] / z, iop[1] + iop[2] * p_cam[:, 1] / z])


# --- the low-order image correction used while labelling ----------------------------------------


@dataclass(frozen=True)
class _Correction:
    """``measured ≈ ideal + Σ coef_k · u^a v^b`` with ``(u, v) = (ideal - centre) / scale``."""

    centre: np.ndarray
    scale: float
    degree: int = 0
    coef: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def basis(self, xy: np.ndarray) -> np.ndarray:
        uv = (xy - self.centre) / self.scale
        u, v = uv[:, 0], uv[:, 1]
        # shape (N, n_terms)
        return np.column_stack([u ** (d - k) * v**k for d in range(self.degree + 1) for k in range(d + 1)])

    def apply(self, xy: np.ndarray) -> np.ndarray:
        """Predicted measured positions of ideal points ``xy``."""
        if not len(self.coef) or not len(xy):
            return xy
        return xy + self.basis(xy) @ self.coef

    def undo(self, measured: np.ndarray, ideal_guess: np.ndarray) -> np.ndarray:
        """Approximately ideal positions of ``measured`` points, given nearby ideal predictions."""
        if not len(self.coef) or not len(measured):
            return measured
        return measured - self.basis(ideal_guess) @ self.coef


def _n_terms(degree: int) -> int:
    return (degree + 1) * (degree + 2) // 2


def _max_degree(n_points: int) -> int:
    """Highest polynomial degree fitted to ``n_points`` pairs: at least 3 pairs per coefficient."""
    degree = 0
    while degree < 5 and n_points >= 3 * _n_terms(degree + 1):
        degree += 1
    return degree


def _fit_correction(
    ideal: np.ndarray, measured: np.ndarray, degree: int, centre: np.ndarray, scale: float
) -> _Correction:
    """Least-squares polynomial correction, refitted once without gross outliers."""
    corr = _Correction(centre, scale, degree)
    A = corr.basis(ideal)
    d = measured - ideal
    keep = np.ones(len(d), dtype=bool)
    coef = np.zeros((A.shape[1], 2))
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], d[keep], rcond=None)[0]
        r = np.linalg.norm(d - A @ coef, axis=1)
        keep = r <= max(3.0 * 1.4826 * np.median(r), 0.5)
        if keep.sum() < A.shape[1] + 2:
            break
    return _Correction(centre, scale, degree, coef)


# --- assignment ---------------------------------------------------------------------------------


def _assign(pred_xy: np.ndarray, gate_px: np.ndarray, det_xy: np.ndarray, det_tree) -> tuple[np.ndarray, np.ndarray]:
    """Optimal one-to-one assignment of predictions to detections within per-prediction gates.

    Parameters
    ----------
    pred_xy : (P, 2) float64 ndarray, px
    gate_px : (P,) float64 ndarray, px
    det_xy : (D, 2) float64 ndarray, px
    det_tree : scipy.spatial.cKDTree of ``det_xy``

    Returns
    -------
    i_pred, i_det : (K,) int64 ndarrays
        Matched pairs; the total distance is minimal among assignments with the most pairs.
    """
    from scipy.optimize import linear_sum_assignment

    if not len(pred_xy) or not len(det_xy):
        return np.empty(0, np.int64), np.empty(0, np.int64)
    k = min(_MAX_CANDIDATES, len(det_xy))
    d, j = det_tree.query(pred_xy, k=k, distance_upper_bound=float(np.max(gate_px)))
    d, j = d.reshape(len(pred_xy), k), j.reshape(len(pred_xy), k)
    inside = d <= gate_px[:, None]
    rows = np.nonzero(inside)[0]
    cols = j[inside]
    counts = inside.sum(1)
    if not len(rows):
        return rows, cols
    dist = d[inside]
    col_counts = np.bincount(cols, minlength=len(det_xy))
    # pairs whose prediction and detection have no other candidate need no optimisation
    simple = (counts[rows] == 1) & (col_counts[cols] == 1)
    out_r, out_c = [rows[simple]], [cols[simple]]
    hard_r, hard_c, hard_d = rows[~simple], cols[~simple], dist[~simple]
    if len(hard_r):
        ur, ir = np.unique(hard_r, return_inverse=True)
        uc, ic = np.unique(hard_c, return_inverse=True)
        cost = np.full((len(ur), len(uc)), _FORBIDDEN)
        cost[ir, ic] = hard_d
        a, b = linear_sum_assignment(cost)
        good = cost[a, b] < _FORBIDDEN
        out_r.append(ur[a[good]])
        out_c.append(uc[b[good]])
    return np.concatenate(out_r), np.concatenate(out_c)


def _ambiguous(pred_xy: np.ndarray, diam_px: np.ndarray, factor: float) -> np.ndarray:
    """Beads whose projection lies within ``factor`` x the mean of both diameters of another's."""
    from scipy.spatial import cKDTree

    amb = np.zeros(len(pred_xy), dtype=bool)
    if len(pred_xy) < 2:
        return amb
    pairs = cKDTree(pred_xy).query_pairs(r=factor * float(np.max(diam_px)), output_type="ndarray")
    if len(pairs):
        d = np.linalg.norm(pred_xy[pairs[:, 0]] - pred_xy[pairs[:, 1]], axis=1)
        close = pairs[d < factor * 0.5 * (diam_px[pairs[:, 0]] + diam_px[pairs[:, 1]])]
        amb[close.ravel()] = True
    return amb


# --- 3D phantoms ---------------------------------------------------------------------------------


@dataclass
class _Frame:
    """What the cube labelling needs about one frame, computed once."""

    det: _Detections
    phantom: Phantom
    params: LabelParams
    iop: np.ndarray
    K: np.ndarray
    det_idx: np.ndarray  # (D,) indices of the valid detections
    det_xy: np.ndarray  # (D, 2)
    det_tree: object
    diam_ref_px: float  # median apparent diameter of ordinary beads, px
    bead_diam_mm: np.ndarray  # (B,) NaN filled with the median
    width: float
    height: float


def _label_cube(
    det: _Detections, phantom: Phantom, params: LabelParams, iop: np.ndarray, prior_pose, turntable_axis=None
) -> Labels:
    from scipy.spatial import cKDTree

    # a sphere projects to a nearly round outline: an elongated blob is overlapping beads, not one of them
    det = replace(det, valid=det.valid & ~(det.axis_ratio > params.max_axis_ratio))
    det_idx = np.flatnonzero(det.valid)
    if len(det_idx) < 4:
        return _failed(det, iop, f"only {len(det_idx)} usable detections")
    sizes = det.size_px[det_idx]
    diam_ref = float(np.nanmedian(sizes)) if np.isfinite(sizes).any() else np.nan
    bead_diam = phantom.diameter_mm.copy()
    if np.isfinite(bead_diam).any():
        bead_diam[~np.isfinite(bead_diam)] = np.nanmedian(bead_diam)
    if not np.isfinite(diam_ref):
        diam_ref = _typical_spacing(det.xy_px[det_idx]) / 3.0
    # the image extent, or (unknown) one symmetric about the assumed centre that holds every detection
    pts = det.xy_px[det_idx]
    width = max(2 * iop[0] + 1, 2 * float(pts[:, 0].max()) - 2 * iop[0] + diam_ref)
    height = max(2 * iop[1] + 1, 2 * float(pts[:, 1].max()) - 2 * iop[1] + diam_ref)
    frame = _Frame(
        det, phantom, params, iop, _camera_matrix(iop), det_idx, pts, cKDTree(pts), diam_ref, bead_diam, width, height
    )

    groups = []  # (pose source, [(R, T), ...] best first, their coarse scores or None)
    if params.seeds:
        pose, why = _pose_from_seeds(frame)
        if pose is None:
            return _failed(det, iop, why, "seeds")
        groups.append(("seeds", [pose], None))
    else:
        poses, scores, why = _marker_poses(frame)
        if poses:
            groups.append(("markers", poses, scores))
        if prior_pose is not None:
            q, T = prior_pose
            groups.append(("prior", [(quat_to_matrix(np.asarray(q, float)), np.asarray(T, float))], None))
        if not groups:
            return _failed(det, iop, why, "markers")

    reason = "no pose hypothesis converged"
    for source, poses, scores in groups:
        if source == "prior":
            best, why = _label_from_prior(frame, *poses[0], turntable_axis)
            if best is None:
                reason = why
                continue
            best["source"] = source
            return _labels_from_result(frame, best)
        best = None
        for i, (R, T) in enumerate(poses):
            result = _iterate(frame, R, T)
            ok, why = (False, "the labelling diverged") if result is None else _acceptable(frame, result)
            if ok:
                result["source"] = source
                best = result
                break
            reason = why
        if best is None:
            continue
        # a distinct pose that explains the detections about as well means the markers do not fix the pose
        rival_start = scores is not None and i + 1 < len(poses) and scores[i + 1] >= _RIVAL_SCORE * scores[i]
        rival = _iterate(frame, *poses[i + 1]) if rival_start else None
        if rival is not None and _acceptable(frame, rival)[0] and _rivals(best, rival):
            if rival["n_labelled"] > best["n_labelled"]:
                best, rival = rival, best
            why = (
                f"two poses explain the frame about equally well ({best['n_labelled']} vs {rival['n_labelled']} labels)"
            )
            return _failed(det, iop, why, source)
        return _labels_from_result(frame, best)
    return _failed(det, iop, reason, groups[-1][0] if groups else "")


def _rivals(best: dict, other: dict) -> bool:
    """True if ``other`` labels about as many detections as ``best``, mostly with other ids."""
    if other["n_labelled"] < _RIVAL_LABELS * best["n_labelled"]:
        return False
    return _agreement(best, other) < 0.9


def _agreement(a: dict, b: dict) -> float:
    """Fraction of ``a``'s labelled detections that ``b`` gives the same bead."""
    if not len(a["det"]):
        return 0.0
    same = dict(zip(b["det"].tolist(), b["bead"].tolist()))
    return float(np.mean([same.get(d) == k for d, k in zip(a["det"].tolist(), a["bead"].tolist())]))


def _typical_spacing(xy: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    if len(xy) < 2:
        return 10.0
    d, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(d[:, 1]))


def _acceptable(frame: _Frame, result: dict) -> tuple[bool, str]:
    p = frame.params
    n_valid = len(frame.det_idx)
    n_lab = result["n_labelled"]
    if n_lab < p.min_labelled:
        return False, f"only {n_lab} beads labelled (min_labelled = {p.min_labelled})"
    explained = (n_lab + result["n_ambiguous"]) / max(n_valid, 1)
    if explained < p.min_labelled_fraction:
        return False, (
            f"only {explained:.0%} of {n_valid} detections explained by the phantom "
            f"(min_labelled_fraction = {p.min_labelled_fraction})"
        )
    limit = max(p.max_rms_floor_px, p.max_rms_bead_diameters * frame.diam_ref_px)
    if not result["rms_corrected_px"] <= limit:
        # right labels leave centroid noise and unmodelled distortion; chance matches spread over the gate
        rms = result["rms_corrected_px"]
        return False, f"labelling residuals of {rms:.2f} px RMS exceed {limit:.2f} px: chance matches, not a fit"
    if not result["sizes_consistent"]:
        return (
            False,
            "the labelling puts beads of one diameter on detections of another (markers misplaced): wrong pose",
        )
    return True, ""


# --- from another frame's pose: a global search over the phantom's shift (and turn) -------------


def _label_from_prior(
    frame: _Frame, R0: np.ndarray, T0: np.ndarray, axis: np.ndarray | None
) -> tuple[dict | None, str]:
    """Label a frame from a neighbouring frame's pose ``(R0, T0)``; ``(result, "")`` or ``(None, reason)``.

    The neighbouring pose fixes the orientation roughly (a turntable step) but not the position: the
    phantom may have moved by several bead rows across the beam and by a few % of its distance along
    it, and a start one row off converges to a labelling one row off that fits about as well. So the
    position is searched over the whole image (:func:`_shift_starts`), the best peaks are labelled, and
    the best labelling is kept only if no distinct one explains the frame about as well
    (:func:`_best_start`). When that fails and the sequence's turntable ``axis`` (camera frame) is
    known, the search is repeated over turns of the phantom about that axis (:func:`_turn_starts`).
    """
    rays = _rays(frame, frame.det_xy)
    best, why = _best_start(frame, _shift_starts(frame, R0, T0, rays))
    if best is not None or axis is None:
        return best, why
    return _best_start(frame, _turn_starts(frame, R0, T0, axis))


def _rays(frame: _Frame, xy: np.ndarray) -> np.ndarray:
    """``(x, y) / z`` in camera coordinates of the rays through image points ``xy`` (pinhole)."""
    return (xy - frame.iop[:2]) / frame.iop[2]


def _depth_steps(frame: _Frame, depth_mm: float) -> np.ndarray:
    """Changes of the phantom's distance from the source (mm) to try: up to ``_MAX_DEPTH_CHANGE`` of it,
    in steps that move the detection farthest from the principal point by one assignment gate.
    """
    r_max = float(np.max(np.linalg.norm(frame.det_xy - frame.iop[:2], axis=1), initial=1.0))
    step = frame.params.gate_bead_diameters * frame.diam_ref_px * depth_mm / max(r_max, 1.0)
    n = int(np.ceil(_MAX_DEPTH_CHANGE * depth_mm / step))
    return np.arange(-n, n + 1) * step


def _shift_starts(frame: _Frame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, n_keep: int = 0) -> list:
    """Start poses ``[(R, T, votes)]``: the pose moved to where many beads meet detections, best first.

    Each of :func:`_depth_steps` is tried; at each, every pair of a detection and a bead votes for the
    shift across the beam that puts the bead on the detection's ray (:func:`_shift_votes`). The depth
    whose strongest peak gathers the most votes of a thinned set of detections (``_N_DEPTH_DETECTIONS``)
    is kept, and the vote of all detections there gives its peaks (``n_keep``, default
    ``_N_PEAKS``): the peaks of a periodic layout, one period apart, must all be labelled to be told
    apart.
    """
    depth = float(np.median((frame.phantom.xyz_mm - T) @ R[2]))
    thin = (
        rays[np.linspace(0, len(rays) - 1, _N_DEPTH_DETECTIONS).astype(int)]
        if len(rays) > _N_DEPTH_DETECTIONS
        else rays
    )
    steps = _depth_steps(frame, depth)
    best_dz = steps[int(np.argmax([_shift_strength(frame, R, T - dz * R[2], thin) for dz in steps]))]
    return _shift_peaks(frame, R, T - best_dz * R[2], rays, n_keep or _N_PEAKS)


def _shift_votes(
    frame: _Frame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, *, bin_gates: float = 0.5, box: int = 3
):
    """The vote for shifts of pose ``(R, T)`` across the beam; None without beads in front of the source.

    Every pair of a detection (``rays``) and a bead votes for the shift (camera x, y at the bead's depth,
    mm) that puts the bead on the detection's ray. Votes are binned at ``bin_gates`` assignment gates.

    Returns
    -------
    hist : (H, W) int64 ndarray
        Votes per bin.
    votes : (H, W) int64 ndarray
        Votes summed over ``box`` x ``box`` bins (starting at the bin, or for an odd box, centred on it).
    lo : (2,) float64 ndarray
        Index of bin ``[0, 0]`` (shift / bin size, floored).
    bin_mm : float
    """
    p_cam = (frame.phantom.xyz_mm - T) @ R.T
    p_cam = p_cam[p_cam[:, 2] > 0]
    if len(p_cam) < 4 or not len(rays):
        return None
    bin_mm = (
        bin_gates * frame.params.gate_bead_diameters * frame.diam_ref_px * float(np.median(p_cam[:, 2])) / frame.iop[2]
    )
    # shape (D, B) each: the shift (in bins) that moves bead b onto detection d's ray, at b's depth
    z = p_cam[:, 2] / bin_mm
    fx = rays[:, 0:1] * z - p_cam[:, 0] / bin_mm
    fy = rays[:, 1:2] * z - p_cam[:, 1] / bin_mm
    lo = np.floor([fx.min(), fy.min()])
    ix, iy = (fx - lo[0]).astype(np.int64), (fy - lo[1]).astype(np.int64)
    shape = (int(ix.max()) + 1, int(iy.max()) + 1)
    ix *= shape[1]
    ix += iy
    hist = np.bincount(ix.ravel(), minlength=shape[0] * shape[1]).reshape(shape)
    padded = np.pad(hist, ((box // 2, box - 1 - box // 2),) * 2)
    # separable box sum
    rows = sum(padded[a : a + shape[0]] for a in range(box))
    votes = sum(rows[:, b : b + shape[1]] for b in range(box))
    return hist, votes, lo, bin_mm


def _shift_strength(frame: _Frame, R: np.ndarray, T: np.ndarray, rays: np.ndarray) -> float:
    """Votes of the strongest peak of :func:`_shift_votes`, on a coarser grid (bins of a gate, 2 x 2 sums;
    for comparing depths and turns, 4x faster), 0 without one.
    """
    vote = _shift_votes(frame, R, T, rays, bin_gates=1.0, box=2)
    return 0.0 if vote is None else float(vote[1].max())


def _shift_peaks(frame: _Frame, R: np.ndarray, T: np.ndarray, rays: np.ndarray, n_keep: int) -> list:
    """The ``n_keep`` strongest peaks ``[(R, T, votes)]`` of :func:`_shift_votes`, at least 3 bins apart,
    each located at the vote-weighted mean of its 3 x 3 bins.
    """
    vote = _shift_votes(frame, R, T, rays)
    if vote is None:
        return []
    hist, votes, lo, bin_mm = vote
    shape = votes.shape
    votes = votes.ravel()
    # greedy non-maximum suppression among the strongest bins
    top = np.argpartition(-votes, min(_N_PEAK_BINS, len(votes) - 1))[:_N_PEAK_BINS]
    top = top[np.argsort(-votes[top], kind="stable")]
    kept: list[tuple[int, int]] = []
    out = []
    for k in top:
        if votes[k] <= 0 or len(kept) == n_keep:
            break
        i, j = divmod(int(k), shape[1])
        if any(abs(i - a) <= 2 and abs(j - b) <= 2 for a, b in kept):
            continue
        kept.append((i, j))
        i0, j0 = max(i - 1, 0), max(j - 1, 0)
        win = hist[i0 : i + 2, j0 : j + 2].astype(np.float64)
        ii, jj = np.meshgrid(np.arange(i0, i0 + win.shape[0]), np.arange(j0, j0 + win.shape[1]), indexing="ij")
        centre = (np.array([(ii * win).sum(), (jj * win).sum()]) / win.sum() + lo + 0.5) * bin_mm
        out.append((R, T - R.T @ np.array([centre[0], centre[1], 0.0]), float(votes[k])))
    return out


def _turn_starts(frame: _Frame, R0: np.ndarray, T0: np.ndarray, axis: np.ndarray) -> list:
    """Start poses ``[(R, T, votes)]`` turned about ``axis`` (camera frame) over the full circle.

    The phantom is turned about the axis through its centre, in steps that move the beads farthest
    from the axis by two assignment gates. Each turn is scored by the strongest peak of its shift vote
    on a coarse grid and a thinned set of detections (:func:`_shift_strength`, the prior's depth); the
    ``_N_TURN_CANDIDATES`` best local maxima over the angle are re-scored on the fine grid with all
    detections (:func:`_shift_votes`) at half-step offsets, and the ``_N_TURNS`` best get the full search of
    :func:`_shift_starts`. All their peaks are returned, best first: a phantom that looks alike after
    a turn (a cube after a quarter turn) must show both.
    """
    import cv2

    xyz = frame.phantom.xyz_mm
    centre = xyz.mean(0)
    p_centre = R0 @ (centre - T0)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    rel = (xyz - centre) @ R0.T
    radius = float(np.max(np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)))
    gate_mm = frame.params.gate_bead_diameters * frame.diam_ref_px * p_centre[2] / frame.iop[2]
    n_steps = int(np.clip(np.ceil(np.pi * radius / gate_mm), 8, 360))
    step = 2 * np.pi / n_steps
    rays = _rays(frame, frame.det_xy)

    def turned(angle):
        turn, _ = cv2.Rodrigues(axis * angle)
        R = turn @ R0
        return R, centre - R.T @ p_centre

    def strength(angle):
        vote = _shift_votes(frame, *turned(angle), rays)
        return 0.0 if vote is None else float(vote[1].max())

    thin = (
        rays[np.linspace(0, len(rays) - 1, _N_TURN_DETECTIONS).astype(int)] if len(rays) > _N_TURN_DETECTIONS else rays
    )
    scan = np.array([_shift_strength(frame, *turned(a), thin) for a in np.arange(n_steps) * step])
    local = np.flatnonzero((scan >= np.roll(scan, 1)) & (scan >= np.roll(scan, -1)))
    refined = []
    for k in local[np.argsort(-scan[local], kind="stable")][:_N_TURN_CANDIDATES]:
        angles = (k + np.array([-0.5, 0.0, 0.5])) * step
        scores = [strength(a) for a in angles]
        refined.append((max(scores), angles[int(np.argmax(scores))]))
    refined.sort(key=lambda s: -s[0])
    starts = [s for _, a in refined[:_N_TURNS] for s in _shift_starts(frame, *turned(a), rays)]
    return sorted(starts, key=lambda s: -s[2])


def _best_start(frame: _Frame, starts: list) -> tuple[dict | None, str]:
    """Label from the starts, best coarse score first; the best labelling, unless a rival matches it.

    Starts are labelled until one is acceptable. A periodic layout gives a start one period off almost
    the same coarse score, so every other start is then checked: moved as that labelling moved from its
    start, and re-aligned by the median offset of its matches, it is counted with the labelling's model
    (pose, ``c``, correction) and the final gate (:func:`_screen`); those that reach
    ``_SCREEN_RIVAL`` of the labelling's own count, with detection sizes that fit the beads (a slip
    that puts markers on ordinary beads is no rival), are labelled in full, and the best labelling is kept
    only if no distinct acceptable one comes within ``_RIVAL_LABELS`` of it.
    """
    if not starts:
        return None, "no shift of the previous frame's pose brings beads onto the detections"
    scores = np.array([_coarse_score(frame, R, T) for R, T, _ in starts])
    order = np.argsort(-scores, kind="stable")
    reason = "no shift of the previous frame's pose gives an acceptable labelling"
    best, k_best = None, -1
    for k in order[:_MAX_STARTS]:
        result = _iterate(frame, starts[k][0], starts[k][1])
        ok, why = (False, "the labelling diverged") if result is None else _acceptable(frame, result)
        if ok:
            best, k_best = result, k
            break
        reason = f"from the previous frame's pose, shifted: {why}"
    if best is None:
        return None, reason
    # the rigid motion that took the start to the labelling's pose, in camera coordinates: p -> A p + b
    R0, T0, _ = starts[k_best]
    A = best["R"] @ R0.T
    b = best["R"] @ (T0 - best["T"])
    own, _ = _screen(frame, best, best["R"], best["T"])
    accepted = [best]
    for k in order:
        if k == k_best:
            continue
        R = A @ starts[k][0]
        T = starts[k][1] - R.T @ b
        n, sizes_ok = _screen(frame, best, R, T, _SCREEN_RIVAL * own)
        if n < _SCREEN_RIVAL * own or not sizes_ok:
            continue
        result = _iterate(frame, *starts[k][:2])
        if result is None or not _acceptable(frame, result)[0]:
            continue
        if all(_agreement(result, other) < 0.9 for other in accepted):
            accepted.append(result)
    accepted.sort(key=lambda r: -r["n_labelled"])
    best = accepted[0]
    for other in accepted[1:]:
        if _rivals(best, other):
            return None, (
                f"two shifts of the previous frame's pose explain the frame about equally well "
                f"({best['n_labelled']} vs {other['n_labelled']} labels)"
            )
    return best, ""


def _screen(frame: _Frame, result: dict, R: np.ndarray, T: np.ndarray, min_count: float = 0.0) -> tuple[int, bool]:
    """Beads that pose ``(R, T)`` puts within the final gate of a detection, under ``result``'s model, and
    whether their detections' sizes fit them (:func:`_sizes_consistent`; checked only for ``min_count``
    beads or more, True below).

    The pose is first moved across the image by the median offset of the detections within the
    assignment gate of its predictions (twice), so that a start a little off its peak counts in full.
    """
    p = frame.params
    sub = replace(frame, iop=result["iop"])
    vis, ideal, diam = _visible(sub, R, T)
    if not len(vis):
        return 0, True
    pred = result["corr"].apply(ideal[vis])
    for _ in range(2):
        d, j = frame.det_tree.query(pred, distance_upper_bound=p.gate_bead_diameters * frame.diam_ref_px)
        hit = np.isfinite(d)
        if hit.sum() < 3:
            return int(hit.sum()), True
        pred = pred + np.median(frame.det_xy[j[hit]] - pred[hit], axis=0)
    d, j = frame.det_tree.query(pred)
    close = d <= p.final_gate_bead_diameters * diam[vis]
    n = int(close.sum())
    return n, n < min_count or _sizes_consistent(sub, R, T, vis[close], j[close])


def _visible(frame: _Frame, R: np.ndarray, T: np.ndarray):
    """Projections of the beads in front of the source and inside the image, and their apparent diameters."""
    p_cam = (frame.phantom.xyz_mm - T) @ R.T
    xy = _project_cam(p_cam, frame.iop)
    z = p_cam[:, 2]
    diam = frame.iop[2] * frame.bead_diam_mm / np.where(z > 0, z, np.nan)
    diam = np.where(np.isfinite(diam), diam, frame.diam_ref_px)
    margin = 0.5 * diam
    vis = (z > 0) & np.all(np.isfinite(xy), axis=1)
    vis &= (xy[:, 0] > -0.5 + margin) & (xy[:, 0] < frame.width - 0.5 - margin)
    vis &= (xy[:, 1] > -0.5 + margin) & (xy[:, 1] < frame.height - 0.5 - margin)
    return np.flatnonzero(vis), xy, diam


def _solve_pose(frame: _Frame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray):
    """Refine a pose on correspondences (Levenberg-Marquardt from the current pose)."""
    import cv2

    if len(obj) < 6:
        return R, T
    rvec, tvec = _pose_to_cv(R, T)
    ok, rvec, tvec = cv2.solvePnP(
        obj,
        img,
        frame.K,
        None,
        rvec.reshape(3, 1).copy(),
        tvec.reshape(3, 1).copy(),
        useExtrinsicGuess=True,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok or not np.all(np.isfinite(tvec)):
        return R, T
    R_new, _ = cv2.Rodrigues(rvec)
    return R_new, -R_new.T @ tvec.reshape(3)


def _solve_pose_and_c(frame: _Frame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray):
    """Refine the pose and the principal distance ``c`` together (least squares from the current values).

    The configured source-image distance and pixel pitch are rough; a wrong ``c`` leaves a perspective
    error across the depth of a 3D phantom that the 2D correction cannot absorb. ``c`` is observable
    only through that depth, so it is refined only when the labelled beads span enough of it.

    Returns
    -------
    R : (3, 3) float64 ndarray
    T : (3,) float64 ndarray, mm
    c : float, px
    """
    import cv2
    from scipy.optimize import least_squares

    c0 = float(frame.iop[2])
    R, T = _solve_pose(frame, obj, img, R, T)
    z = (obj - T) @ R[2]
    if len(obj) < 30 or np.std(z) < _MIN_DEPTH_SPREAD * np.mean(z):
        return R, T, c0
    rvec, tvec = _pose_to_cv(R, T)

    def residuals(x):
        Rx, _ = cv2.Rodrigues(x[:3])
        p_cam = obj @ Rx.T + x[3:6]
        return (frame.iop[:2] + c0 * np.exp(x[6]) * p_cam[:, :2] / p_cam[:, 2:] - img).ravel()

    fit = least_squares(residuals, np.concatenate([rvec, tvec, [0.0]]), method="lm", x_scale="jac")
    c = c0 * float(np.exp(fit.x[6]))
    if not (fit.success and 0.5 * c0 < c < 2.0 * c0):
        return R, T, c0
    R_new, _ = cv2.Rodrigues(fit.x[:3])
    return R_new, -R_new.T @ fit.x[3:6], c


def _ransac_pose(frame: _Frame, obj: np.ndarray, img: np.ndarray, R: np.ndarray, T: np.ndarray):
    """Robust pose on a coarse assignment; returns the pose and the inlier mask."""
    import cv2

    if len(obj) < 6:
        return R, T, np.ones(len(obj), dtype=bool)
    rvec, tvec = _pose_to_cv(R, T)
    thr = frame.params.ransac_threshold_bead_diameters * frame.diam_ref_px
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        obj,
        img,
        frame.K,
        None,
        rvec.reshape(3, 1).copy(),
        tvec.reshape(3, 1).copy(),
        useExtrinsicGuess=True,
        iterationsCount=frame.params.ransac_iterations,
        reprojectionError=thr,
        confidence=0.999,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    mask = np.zeros(len(obj), dtype=bool)
    if not ok or inliers is None or len(inliers) < 6:
        return R, T, np.ones(len(obj), dtype=bool)
    mask[inliers.ravel()] = True
    R_new, _ = cv2.Rodrigues(rvec)
    return R_new, -R_new.T @ tvec.reshape(3), mask


def _iterate(frame: _Frame, R: np.ndarray, T: np.ndarray) -> dict | None:
    """Assign, refine pose and correction, repeat until the assignment is stable."""
    p = frame.params
    xyz = frame.phantom.xyz_mm
    scale = 0.5 * float(np.hypot(frame.width, frame.height))
    corr = _Correction(frame.iop[:2].copy(), scale)
    previous, target_degree = None, 0
    for it in range(p.max_iterations):
        vis, ideal, diam = _visible(frame, R, T)
        if len(vis) < 4:
            return None
        pred = corr.apply(ideal[vis])
        amb = _ambiguous(pred, diam[vis], p.ambiguity_bead_diameters)
        i_pred, i_det = _assign(pred, p.gate_bead_diameters * diam[vis], frame.det_xy, frame.det_tree)
        key = (vis[i_pred].tobytes(), i_det.tobytes())
        if key == previous and corr.degree >= target_degree:
            break
        previous = key
        use = ~amb[i_pred]
        beads, dets = vis[i_pred[use]], i_det[use]
        if len(beads) < 6:
            return None
        obj = xyz[beads]
        measured = frame.det_xy[dets]
        if it == 0:
            R, T, inl = _ransac_pose(frame, obj, measured, R, T)
            beads, dets, measured, obj = beads[inl], dets[inl], measured[inl], obj[inl]
        else:
            img = corr.undo(measured, ideal[beads])
            if it <= _C_ITERATIONS:
                R, T, c = _solve_pose_and_c(frame, obj, img, R, T)
            else:
                (R, T), c = _solve_pose(frame, obj, img, R, T), frame.iop[2]
            if c != frame.iop[2]:
                iop = np.array([frame.iop[0], frame.iop[1], c])
                frame = replace(frame, iop=iop, K=_camera_matrix(iop))
        ideal_now = _project_cam((obj - T) @ R.T, frame.iop)
        target_degree = min(p.correction_degree, _max_degree(len(beads)))
        degree = min(target_degree, _DEGREE_SCHEDULE[min(it, len(_DEGREE_SCHEDULE) - 1)])
        if degree > 0:
            corr = _fit_correction(ideal_now, measured, degree, frame.iop[:2], scale)
        else:
            corr = _Correction(frame.iop[:2], scale)

    # final labels: pairs within the final gate of the final prediction
    vis, ideal, diam = _visible(frame, R, T)
    pred = corr.apply(ideal[vis])
    i_pred, i_det = _assign(pred, p.gate_bead_diameters * diam[vis], frame.det_xy, frame.det_tree)
    resid = np.linalg.norm(pred[i_pred] - frame.det_xy[i_det], axis=1)
    # overlap is judged on the measured outlines where a bead was detected, on the prediction elsewhere
    where = pred.copy()
    where[i_pred] = frame.det_xy[i_det]
    # apparent diameters: the pinhole's, scaled by the local magnification of the distortion correction
    h = 1.0
    jac = np.stack([corr.apply(ideal[vis] + [h, 0.0]) - pred, corr.apply(ideal[vis] + [0.0, h]) - pred], axis=-1) / h
    size = diam[vis] * np.sqrt(np.abs(np.linalg.det(jac)))
    amb = _ambiguous(where, size, p.ambiguity_bead_diameters)
    close = resid <= p.final_gate_bead_diameters * diam[vis][i_pred]
    lab = close & ~amb[i_pred]
    ambig = amb[i_pred]
    beads, dets = vis[i_pred[lab]], i_det[lab]
    ideal_lab = ideal[beads]
    pin = np.linalg.norm(ideal_lab - frame.det_xy[dets], axis=1)
    return {
        "R": R,
        "T": T,
        "iop": frame.iop,
        "bead": beads,
        "det": dets,
        "ambiguous_det": i_det[ambig],
        "n_labelled": len(beads),
        "n_ambiguous": int(ambig.sum()),
        "rms_px": float(np.sqrt(np.mean(pin**2))) if len(pin) else np.nan,
        "rms_corrected_px": float(np.sqrt(np.mean(resid[lab] ** 2))) if lab.any() else np.nan,
        "sizes_consistent": _sizes_consistent(frame, R, T, beads, dets),
        "corr": corr,
    }


def _marker_mask(frame: _Frame) -> np.ndarray:
    return frame.phantom.role == "marker"


def _marker_threshold(frame: _Frame) -> float | None:
    """Apparent diameter (px) above which a detection is taken as a marker, or None if markers are not distinct."""
    markers = _marker_mask(frame)
    ratio = frame.params.marker_size_ratio
    if not ratio > 0:
        d = frame.phantom.diameter_mm
        if not (np.isfinite(d[markers]).any() and np.isfinite(d[~markers]).any()):
            return None
        ratio = float(np.nanmedian(d[markers]) / np.nanmedian(d[~markers]))
    if ratio < 1.15 or not np.isfinite(frame.diam_ref_px):
        return None
    # the geometric midpoint between the two sizes is robust to the depth spread of magnification
    return frame.diam_ref_px * np.sqrt(ratio)


def _sizes_consistent(frame: _Frame, R: np.ndarray, T: np.ndarray, beads: np.ndarray, dets: np.ndarray) -> bool:
    """False if beads of distinct diameters (markers) were given detections of the wrong size — a wrong pose.

    The predicted apparent diameter ``c D / z`` of each labelled bead is compared with its detection's,
    after removing their median ratio (edge definition, blur and the guessed magnification scale both).
    Phantoms whose beads all have about one diameter pass unchecked.
    """
    d_mm = frame.bead_diam_mm[beads]
    measured = frame.det.size_px[frame.det_idx[dets]]
    known = np.isfinite(d_mm) & np.isfinite(measured) & (measured > 0)
    if known.sum() < 3:
        return True
    spread = float(np.nanmax(frame.bead_diam_mm) / np.nanmedian(frame.bead_diam_mm))
    if spread < 1.15:
        return True
    z = (frame.phantom.xyz_mm[beads[known]] - T) @ R[2]
    log_ratio = np.log(measured[known] / (frame.iop[2] * d_mm[known] / z))
    off = np.abs(log_ratio - np.median(log_ratio)) > 0.5 * np.log(spread)
    distinct = np.abs(np.log(d_mm[known] / np.nanmedian(frame.bead_diam_mm))) > 0.5 * np.log(spread)
    # one or two borderline sizes are tolerated; a wrong pose swaps many
    return int(off.sum()) <= max(2, int(0.5 * distinct.sum()))


def _pose_from_seeds(frame: _Frame):
    """A pose from manually identified beads ``(id, x, y)``: SQPnP on 4 or more, P3P + verification on 3."""
    import cv2

    seeds = np.asarray(frame.params.seeds, dtype=np.float64).reshape(-1, 3)
    lookup = {int(i): k for k, i in enumerate(frame.phantom.ids)}
    unknown = [int(i) for i in seeds[:, 0] if int(i) not in lookup]
    if unknown:
        raise InputError(f"params.seeds name beads not in the phantom: {unknown}")
    if len(seeds) < 3:
        return None, f"params.seeds needs at least 3 beads; got {len(seeds)}"
    obj = frame.phantom.xyz_mm[[lookup[int(i)] for i in seeds[:, 0]]]
    img = seeds[:, 1:3].copy()
    if len(seeds) >= 4:
        ok, rvec, tvec = cv2.solvePnP(obj, img, frame.K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None, "no pose fits the seeds"
        R, _ = cv2.Rodrigues(rvec)
        if len(seeds) >= 6:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, frame.K, None, rvec, tvec)
            R, _ = cv2.Rodrigues(rvec)
        return (R, -R.T @ tvec.reshape(3)), ""
    poses = _p3p(frame, obj, img)
    if not poses:
        return None, "no pose fits the seeds"
    scores = [_coarse_score(frame, R, T) for R, T in poses]
    return poses[int(np.argmax(scores))], ""


def _p3p(frame: _Frame, obj: np.ndarray, img: np.ndarray) -> list:
    import cv2

    n, rvecs, tvecs = cv2.solveP3P(obj, img, frame.K, None, flags=cv2.SOLVEPNP_AP3P)
    out = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        R, _ = cv2.Rodrigues(rvec)
        T = -R.T @ tvec.reshape(3)
        # the phantom must lie in front of the source, between it and the detector
        z = (frame.phantom.xyz_mm.mean(0) - T) @ R[2]
        if 0 < z < frame.iop[2] * frame.params.pixel_pitch_mm:
            out.append((R, T))
    return out


def _coarse_score(frame: _Frame, R: np.ndarray, T: np.ndarray) -> int:
    """Number of visible beads with a detection within the gate of their pinhole projection."""
    vis, xy, diam = _visible(frame, R, T)
    if not len(vis):
        return 0
    d, _ = frame.det_tree.query(xy[vis], distance_upper_bound=frame.params.gate_bead_diameters * frame.diam_ref_px)
    return int(np.isfinite(d).sum())


def _prerank(frame: _Frame, Rs: np.ndarray, Ts: np.ndarray) -> np.ndarray:
    """Order of many pose hypotheses, best first, by coarse scores on samples of the beads.

    A small sample sorts out the bulk; the best tenth is re-scored on a larger one.
    """
    coarse = _coarse_scores(frame, Rs, Ts, n_sample=_N_SAMPLE // 4)
    order = np.argsort(-coarse, kind="stable")
    head = order[: max(4 * _N_VERIFY, len(order) // 10)]
    fine = _coarse_scores(frame, Rs[head], Ts[head], n_sample=_N_SAMPLE)
    return head[np.argsort(-fine, kind="stable")]


def _coarse_scores(frame: _Frame, Rs: np.ndarray, Ts: np.ndarray, *, n_sample: int) -> np.ndarray:
    """:func:`_coarse_score` of many poses at once, on an evenly spaced sample of the beads."""
    step = max(1, frame.phantom.n_beads // n_sample)
    xyz = frame.phantom.xyz_mm[::step]
    # shape (H, S, 3)
    p_cam = np.einsum("hij,hsj->hsi", Rs, xyz[None, :, :] - Ts[:, None, :])
    z = p_cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = frame.iop[:2] + frame.iop[2] * p_cam[..., :2] / z[..., None]
    inside = (z > 0) & np.all(np.isfinite(xy), axis=-1)
    inside &= (xy[..., 0] > -0.5) & (xy[..., 0] < frame.width - 0.5)
    inside &= (xy[..., 1] > -0.5) & (xy[..., 1] < frame.height - 0.5)
    d = np.full(z.shape, np.inf)
    gate = frame.params.gate_bead_diameters * frame.diam_ref_px
    d[inside], _ = frame.det_tree.query(xy[inside], distance_upper_bound=gate)
    return np.isfinite(d).sum(axis=1)


def _marker_poses(frame: _Frame, n_keep: int = 4):
    """Pose hypotheses from marker correspondences: P3P on triples, scored by all markers, then by all beads."""
    import cv2

    markers = np.flatnonzero(_marker_mask(frame))
    if not len(markers):
        return [], [], "the phantom has no marker beads (role 'marker'); give seeds"
    thr = _marker_threshold(frame)
    if thr is None:
        return [], [], "marker beads are not distinguishable by size (diameters missing or too similar); give seeds"
    sizes = frame.det.size_px[frame.det_idx]
    cand = np.flatnonzero(sizes > thr)
    cand = cand[np.argsort(-sizes[cand])][: frame.params.max_marker_candidates]
    if not len(cand):
        return [], [], "no marker-sized detection found; need 1 or more, or seeds"
    if len(cand) == 1:
        poses, scores = _rank_hypotheses(frame, *_single_hypotheses(frame, cand[0], markers), n_keep)
        return poses, scores, "" if poses else "no pose fits the one marker-sized detection"
    if len(cand) == 2 or len(markers) == 2:
        poses, scores = _rank_hypotheses(frame, *_pair_hypotheses(frame, cand[:2], markers), n_keep)
        return poses, scores, "" if poses else "no pose fits the two marker-sized detections"
    cand_xy = frame.det_xy[cand]
    m_xyz = frame.phantom.xyz_mm[markers]
    # a marker's detection lies within half its apparent diameter of its projection, up to distortion
    gate = 0.5 * thr
    # candidate triples, largest detections first (the surest markers), each against every ordered triple of
    # phantom markers; a triple of true markers soon yields a pose that predicts a fourth
    marker_triples = list(itertools.permutations(range(len(markers)), 3))
    batches = []
    for i_triple, t in enumerate(itertools.combinations(range(len(cand)), 3)):
        if i_triple and i_triple * len(marker_triples) >= _P3P_BUDGET:
            break
        img = cand_xy[list(t)]
        rvecs, tvecs = [], []
        for mt in marker_triples:
            n, rv, tv = cv2.solveP3P(m_xyz[list(mt)], img, frame.K, None, flags=cv2.SOLVEPNP_AP3P)
            rvecs.extend(r.reshape(3) for r in rv[:n])
            tvecs.extend(v.reshape(3) for v in tv[:n])
        if rvecs:
            batches.append(_score_marker_hyps(frame, np.array(rvecs), np.array(tvecs), m_xyz, cand_xy, gate))
            n_m, mean_d, Rs, Ts = batches[-1]
            # a pose from three markers that predicts a fourth and explains most detections: look no further
            best = np.lexsort((mean_d, -n_m))[:2]
            good = _GOOD_COARSE * len(frame.det_idx)
            if any(n_m[h] >= 4 and _coarse_score(frame, Rs[h], Ts[h]) >= good for h in best):
                break
    if batches:
        n_matched, mean_d, Rs, Ts = (np.concatenate(x) for x in zip(*batches))
    else:
        n_matched, mean_d, Rs, Ts = np.zeros(0, int), np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3))
    # a pose that predicts a fourth marker is evidence; three are fitted by every P3P solution
    best_n = int(n_matched.max(initial=0))
    plausible = np.flatnonzero(n_matched >= (best_n if best_n >= 4 else 3))
    if len(plausible) > _N_VERIFY:
        # marker counts tie (three candidates fit every P3P solution): pre-rank on a sample of all beads
        order = plausible[_prerank(frame, Rs[plausible], Ts[plausible])]
    else:
        order = plausible[np.lexsort((mean_d[plausible], -n_matched[plausible]))]
    top = []
    for h in order:
        if len(top) == _N_VERIFY:
            break
        if not any(_same_pose(Rs[h], Ts[h], R, T) for R, T in top):
            top.append((Rs[h], Ts[h]))
    # verify the best marker hypotheses on all beads
    scores = np.array([_coarse_score(frame, R, T) for R, T in top])
    if scores.max(initial=0) < _GOOD_COARSE * len(frame.det_idx):
        # maybe one of the marker-sized detections is not a marker: try the pairs of the largest three
        for pair in itertools.combinations(cand[:3], 2):
            Rp, Tp = _pair_hypotheses(frame, np.array(pair), markers)
            poses, more = _rank_hypotheses(frame, Rp, Tp, n_keep)
            top, scores = top + poses, np.concatenate([scores, more])
    keep = np.argsort(-scores, kind="stable")[:n_keep]
    return [top[i] for i in keep], scores[keep].tolist(), "" if top else "no pose fits the marker-sized detections"


def _pair_hypotheses(frame: _Frame, pair: np.ndarray, markers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose hypotheses ``(Rs (H, 3, 3), Ts (H, 3))`` from two marker detections, each completed by a neighbour.

    Beads near a marker in the image are often its neighbours on the phantom: for each assignment of two
    markers to the two detections, P3P is solved with a third correspondence between one of the detections
    nearest to a marker detection in the image and one of the ordinary beads nearest to that marker.
    """
    import cv2
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    xyz = frame.phantom.xyz_mm
    ordinary = np.flatnonzero(~_marker_mask(frame))
    k_img = min(_PAIR_NEAR_DETECTIONS, len(frame.det_idx) - 2)
    k_obj = min(_PAIR_NEAR_BEADS, len(ordinary))
    if k_img < 1 or k_obj < 1:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    # for each marker detection its nearest other detections; for each marker its nearest ordinary beads
    _, near_det = frame.det_tree.query(frame.det_xy[pair], k=k_img + 3)
    near_det = [[d for d in row if d not in pair][:k_img] for row in near_det]
    _, near = cKDTree(xyz[ordinary]).query(xyz[markers], k=k_obj)
    near_bead = dict(zip(markers.tolist(), ordinary[np.asarray(near).reshape(len(markers), -1)]))
    rvecs, tvecs = [], []
    for i, j in itertools.permutations(markers.tolist(), 2):
        for m_bead, neighbours in ((i, near_det[0]), (j, near_det[1])):
            for d in neighbours:
                img = frame.det_xy[[pair[0], pair[1], d]]
                for k in near_bead[m_bead]:
                    n, rv, tv = cv2.solveP3P(xyz[[i, j, k]], img, frame.K, None, flags=cv2.SOLVEPNP_AP3P)
                    rvecs.extend(r.reshape(3) for r in rv[:n])
                    tvecs.extend(t.reshape(3) for t in tv[:n])
    if not rvecs:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    Rs = Rotation.from_rotvec(np.array(rvecs)).as_matrix()
    return Rs, -np.einsum("hji,hj->hi", Rs, np.array(tvecs))


def _single_hypotheses(frame: _Frame, a: int, markers: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pose hypotheses ``(Rs, Ts)`` from one marker detection and two of its neighbours (see :func:`_pair_hypotheses`)."""
    import cv2
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    xyz = frame.phantom.xyz_mm
    ordinary = np.flatnonzero(~_marker_mask(frame))
    k_img = min(_PAIR_NEAR_DETECTIONS + 1, len(frame.det_idx) - 1)
    k_obj = min(_PAIR_NEAR_BEADS, len(ordinary))
    if k_img < 2 or k_obj < 2:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    _, near_det = frame.det_tree.query(frame.det_xy[a], k=k_img + 1)
    near_det = [d for d in near_det if d != a][:k_img]
    _, near = cKDTree(xyz[ordinary]).query(xyz[markers], k=k_obj)
    near = ordinary[np.asarray(near).reshape(len(markers), -1)]
    rvecs, tvecs = [], []
    for i, beads in zip(markers.tolist(), near):
        for d1, d2 in itertools.combinations(near_det, 2):
            img = frame.det_xy[[a, d1, d2]]
            for k1, k2 in itertools.permutations(beads.tolist(), 2):
                n, rv, tv = cv2.solveP3P(xyz[[i, k1, k2]], img, frame.K, None, flags=cv2.SOLVEPNP_AP3P)
                rvecs.extend(r.reshape(3) for r in rv[:n])
                tvecs.extend(t.reshape(3) for t in tv[:n])
    if not rvecs:
        return np.empty((0, 3, 3)), np.empty((0, 3))
    Rs = Rotation.from_rotvec(np.array(rvecs)).as_matrix()
    return Rs, -np.einsum("hji,hj->hi", Rs, np.array(tvecs))


def _rank_hypotheses(frame: _Frame, Rs: np.ndarray, Ts: np.ndarray, n_keep: int) -> tuple[list, list]:
    """The ``n_keep`` best distinct poses: pre-ranked on a sample of the beads, then scored on all of them."""
    if not len(Rs):
        return [], []
    order = _prerank(frame, Rs, Ts)
    top = []
    for h in order:
        if len(top) == _N_VERIFY:
            break
        if not any(_same_pose(Rs[h], Ts[h], R, T) for R, T in top):
            top.append((Rs[h], Ts[h]))
    scores = np.array([_coarse_score(frame, R, T) for R, T in top])
    keep = np.argsort(-scores, kind="stable")[:n_keep]
    return [top[k] for k in keep], scores[keep].tolist()


def _same_pose(R1, T1, R2, T2) -> bool:
    """Poses closer than about 2 degrees and 20 mm lead to the same labelling start."""
    cos = 0.5 * (np.trace(R1.T @ R2) - 1.0)
    return cos > np.cos(np.radians(2.0)) and np.linalg.norm(T1 - T2) < 20.0


def _score_marker_hyps(
    frame: _Frame, rvecs: np.ndarray, tvecs: np.ndarray, m_xyz: np.ndarray, cand_xy: np.ndarray, gate: float
):
    """Markers matched and their mean distance for each OpenCV pose hypothesis of plausible depth.

    Returns
    -------
    n_matched : (H,) int ndarray
    mean_d : (H,) float64 ndarray, px
    Rs : (H, 3, 3) float64 ndarray
    Ts : (H, 3) float64 ndarray, mm
    """
    from scipy.spatial.transform import Rotation

    Rs = Rotation.from_rotvec(rvecs).as_matrix()
    # shape (H, M, 3)
    p_cam = np.einsum("hij,mj->hmi", Rs, m_xyz) + tvecs[:, None, :]
    z = p_cam[..., 2]
    front = np.all(z > 0, axis=1) & (np.median(z, axis=1) < frame.iop[2] * frame.params.pixel_pitch_mm)
    Rs, tvecs, p_cam, z = Rs[front], tvecs[front], p_cam[front], z[front]
    xy = frame.iop[:2] + frame.iop[2] * p_cam[..., :2] / z[..., None]
    # shape (H, M, C)
    d = np.linalg.norm(xy[:, :, None, :] - cand_xy[None, None, :, :], axis=-1)
    nearest = d.min(axis=1)  # each candidate's nearest projected marker
    matched = nearest < gate
    n = matched.sum(1)
    mean_d = np.where(matched, nearest, 0).sum(1) / np.maximum(n, 1)
    return n, mean_d, Rs, -np.einsum("hji,hj->hi", Rs, tvecs)


def _labels_from_result(frame: _Frame, res: dict) -> Labels:
    det = frame.det
    status = np.where(det.valid, STATUS_UNMATCHED, STATUS_REJECTED).astype(np.int8)
    status[frame.det_idx[res["ambiguous_det"]]] = STATUS_AMBIGUOUS
    idx = frame.det_idx[res["det"]]
    status[idx] = STATUS_LABELLED
    order = np.argsort(idx)
    idx, beads = idx[order], res["bead"][order]
    q = matrix_to_quat(res["R"])
    return Labels(
        idx,
        frame.phantom.ids[beads],
        det.xy_px[idx],
        det.sigma_px[idx],
        frame.phantom.xyz_mm[beads],
        status,
        q,
        res["T"],
        res["iop"],
        n_labelled=len(idx),
        n_ambiguous=int((status == STATUS_AMBIGUOUS).sum()),
        n_unmatched=int((status == STATUS_UNMATCHED).sum()),
        rms_px=res["rms_px"],
        rms_corrected_px=res["rms_corrected_px"],
        ok=True,
        reason="",
        pose_source=res["source"],
    )


# --- grid plates --------------------------------------------------------------------------------


def _lattice_basis(lattice: str) -> np.ndarray:
    """Columns: the two lattice vectors in units of the pitch."""
    if lattice == "hex":
        return np.array([[1.0, 0.5], [0.0, np.sqrt(3.0) / 2]])
    return np.eye(2)


def _label_grid(det: _Detections, phantom: Phantom, params: LabelParams, iop: np.ndarray) -> Labels:
    det_idx = np.flatnonzero(det.valid)
    if len(det_idx) < 7:
        return _failed(det, iop, f"only {len(det_idx)} usable detections on the grid plate")
    xy = det.xy_px[det_idx]
    ij, indexed, spacing, n_conflicts = _grow_lattice(xy, phantom.lattice, params, iop[:2])
    if indexed.sum() < 7:
        why = f"the lattice could not be grown from the centre ({int(indexed.sum())} holes indexed)"
        return _failed(det, iop, why, "lattice")
    if n_conflicts:
        log.info("lattice growth met %d conflicting predictions (resolved by distance)", n_conflicts)
    sel = np.flatnonzero(indexed)
    obj = lattice_xyz_mm(ij[sel], phantom.lattice, phantom.pitch_mm)
    # a slip would put holes a whole spacing off the smooth image of the plate: drop such holes, or the frame
    resid = _plate_residuals(obj, xy[sel], iop, params)
    off = resid > params.lattice_tolerance_pitch * spacing
    if off.sum() > max(3, 0.02 * len(sel)):
        why = f"{int(off.sum())} of {len(sel)} indexed holes are off the plate's smooth image: lattice slips"
        return _failed(det, iop, why, "lattice")
    sel, obj, resid = sel[~off], obj[~off], resid[~off]
    idx = det_idx[sel]
    status = np.where(det.valid, STATUS_UNMATCHED, STATUS_REJECTED).astype(np.int8)
    status[idx] = STATUS_LABELLED
    q, T, rms = _planar_pose(obj, det.xy_px[idx], iop)
    return Labels(
        idx,
        lattice_id(ij[sel]),
        det.xy_px[idx],
        det.sigma_px[idx],
        obj,
        status,
        q,
        T,
        iop,
        n_labelled=len(idx),
        n_ambiguous=0,
        n_unmatched=int((status == STATUS_UNMATCHED).sum()),
        rms_px=rms,
        rms_corrected_px=float(np.sqrt(np.mean(resid**2))),
        ok=True,
        pose_source="lattice",
    )


def _dominant_angle(vectors: np.ndarray, fold: int) -> float:
    """The lattice orientation (rad) from neighbour vectors, modulo ``2 pi / fold``, closest to +x."""
    theta = np.arctan2(vectors[:, 1], vectors[:, 0])
    phi = np.angle(np.exp(1j * fold * theta).sum()) / fold
    period = 2 * np.pi / fold
    return float((phi + period / 2) % period - period / 2)


def _grow_lattice(xy: np.ndarray, lattice: str, params: LabelParams, centre: np.ndarray):
    """Index holes on their lattice by growing from the hole nearest ``centre``.

    Returns
    -------
    ij : (N, 2) int64 ndarray
        Lattice indices (valid where ``indexed``).
    indexed : (N,) bool ndarray
    spacing_px : float
        Median nearest-neighbour distance of the holes.
    n_conflicts : int
    """
    from scipy.spatial import cKDTree

    steps = _HEX_STEPS if lattice == "hex" else _SQUARE_STEPS
    fold = 6 if lattice == "hex" else 4
    tree = cKDTree(xy)
    k = len(steps)
    dists, nbrs = tree.query(xy, k=min(k + 1, len(xy)))
    spacing = float(np.median(dists[:, 1]))
    start = int(tree.query(centre)[1])
    # local orientation around the start hole (its 30 nearest holes' neighbour vectors)
    _, near = tree.query(xy[start], k=min(30, len(xy)))
    vec = (xy[nbrs[near, 1:]] - xy[near, None, :]).reshape(-1, 2)
    length = np.linalg.norm(vec, axis=1)
    vec = vec[(length > 0.7 * spacing) & (length < 1.3 * spacing)]
    if not len(vec):
        return np.zeros((len(xy), 2), np.int64), np.zeros(len(xy), bool), spacing, 0
    angle = _dominant_angle(vec, fold)
    rot = 2 * np.pi / fold if lattice == "square" else np.pi / 3
    # columns a1, a2 in px; a2 is a1 turned by +60 (hex) or +90 (square) degrees, toward +y
    B0 = spacing * np.array([[np.cos(angle), np.cos(angle + rot)], [np.sin(angle), np.sin(angle + rot)]])
    tol = params.lattice_tolerance_pitch

    ij = np.zeros((len(xy), 2), np.int64)
    indexed = np.zeros(len(xy), bool)
    at: dict[tuple[int, int], int] = {}  # lattice index -> detection (real holes only)
    virtual: dict[tuple[int, int], int] = {}  # lattice index -> gap depth of a bridged, missing hole
    pos: dict[tuple[int, int], np.ndarray] = {}
    basis: dict[tuple[int, int], np.ndarray] = {}
    n_conflicts = 0

    def local_basis(key, fallback):
        """Lattice vectors from indexed neighbours of ``key`` (least squares), else ``fallback``."""
        d_list, v_list = [], []
        for s in steps:
            nb = (key[0] + s[0], key[1] + s[1])
            if nb in at:
                d_list.append(s)
                v_list.append(xy[at[nb]] - pos[key])
        if len(d_list) >= 2:
            D, V = np.array(d_list, float), np.array(v_list)
            if abs(np.linalg.det(D.T @ D)) > 0.5:
                return np.linalg.lstsq(D, V, rcond=None)[0].T
        return fallback

    key0 = (0, 0)
    at[key0], pos[key0], basis[key0] = start, xy[start], B0
    ij[start], indexed[start] = key0, True
    heap = [(0.0, key0)]
    while heap:
        _, key = heapq.heappop(heap)
        B = local_basis(key, basis[key])
        basis[key] = B
        depth = virtual.get(key, 0)
        pred = pos[key] + steps @ B.T
        d, hit = tree.query(pred, distance_upper_bound=tol * spacing)
        for s, p_xy, dist, h in zip(steps, pred, d, hit):
            nb = (key[0] + int(s[0]), key[1] + int(s[1]))
            if np.isfinite(dist):
                if indexed[h]:
                    if tuple(ij[h]) != nb:
                        n_conflicts += 1
                    continue
                if nb in at:
                    n_conflicts += 1
                    continue
                at[nb], pos[nb], basis[nb] = int(h), xy[h], B
                virtual.pop(nb, None)
                ij[h], indexed[h] = nb, True
                heapq.heappush(heap, (float(np.linalg.norm(xy[h] - xy[start])), nb))
            elif nb not in at and nb not in pos and depth < params.lattice_max_gap:
                virtual[nb] = depth + 1
                pos[nb], basis[nb] = p_xy, B
                heapq.heappush(heap, (float(np.linalg.norm(p_xy - xy[start])), nb))
    return ij, indexed, spacing, n_conflicts


def _plate_residuals(obj: np.ndarray, img: np.ndarray, iop: np.ndarray, params: LabelParams) -> np.ndarray:
    """Distances (px) of the holes from a homography of the plate plus the low-order correction."""
    import cv2

    H, _ = cv2.findHomography(obj[:, :2], img, 0)
    if H is None:
        return np.zeros(len(obj))
    from_h = cv2.perspectiveTransform(obj[None, :, :2].astype(np.float64), H)[0]
    degree = params.correction_degree
    while degree > 0 and len(obj) < 3 * _n_terms(degree):
        degree -= 1
    scale = 0.5 * float(np.hypot(*np.ptp(img, axis=0))) or 1.0
    pred = _fit_correction(from_h, img, degree, iop[:2], scale).apply(from_h) if degree > 0 else from_h
    return np.linalg.norm(pred - img, axis=1)


def _planar_pose(obj: np.ndarray, img: np.ndarray, iop: np.ndarray):
    """Pose (IPPE) of a grid plate and its pinhole RMS (px), when the geometry (``c``) is known; else NaN."""
    import cv2

    if not (np.isfinite(iop[2]) and len(obj) >= 4):
        return np.full(4, np.nan), np.full(3, np.nan), np.nan
    ok, rvec, tvec = cv2.solvePnP(obj, img, _camera_matrix(iop), None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return np.full(4, np.nan), np.full(3, np.nan), np.nan
    q, T = _pose_from_cv(rvec, tvec)
    pin = _project_cam(to_camera(obj, q, T), iop)
    return q, T, float(np.sqrt(np.mean(np.sum((pin - img) ** 2, axis=1))))
