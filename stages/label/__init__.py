"""Automatic labelling: the phantom bead id of every detection in one frame, or in a sequence of frames.

Two kinds of phantom are handled (docs/concepts.md, "Conventions" for pixels, poses
and the interior orientation); which one a frame or a sequence is labelled as is the phantom kind's
choice (:func:`fluorocal.stages.kinds.labelling.label_beads`,
:func:`fluorocal.stages.kinds.labelling.label_sequence`):

- **3D bead phantoms** (a cube, :mod:`.cube`): an approximate pose is found from the marker
  beads (role ``marker``, recognised by their larger apparent size), from a
  few seeds ``(id, x, y)`` or from a neighbouring frame's pose (:mod:`.markers`; with fewer
  than three marker detections, neighbouring beads complete the P3P: beads
  near a marker in the image are often its neighbours on the phantom). From there the
  labelling iterates (:mod:`.iterate`): project every bead through the pose and the assumed
  interior orientation plus a low-order 2D polynomial correction (:mod:`.correction`; the
  image-intensifier distortion leaves residuals of 10-20 px at the field edge
  that a pinhole cannot absorb), assign detections to projections optimally
  within a distance gate (:mod:`.assign`, :func:`scipy.optimize.linear_sum_assignment`),
  refine the pose (RANSAC first, then least squares together with the
  principal distance, since the configured geometry is rough) and the
  correction on the assigned pairs, until the assignment stops changing.
  Because the gate only admits pairs that the current model predicts well,
  the labelled set grows from where the model is good (near the markers and
  the centre) outward, and the correction's degree grows with it. Beads whose
  outlines lie within about one bead diameter of another bead's are ambiguous
  (front and back faces of the cube overlap in the X-ray) and are left out,
  together with the detections they absorb, unless their own detection tells them apart: it lies
  within three times the frame's RMS residual of the bead's prediction, and no other bead is closer
  than touching by more than the precision of the estimated outlines (twice the frame's spread of
  measured bead sizes) — a bead judged a few % short of touching on estimated centres and diameters
  is usually clear of its neighbour (:func:`.assign.told_apart`). A labelling is accepted only if
  it explains most detections with small residuals and puts marker-sized
  detections on markers. A bead phantom is periodic, so a labelling may have rivals
  that explain the frame almost as well: the phantom slipped by a bead row, turned a
  few degrees about a wall seen face-on (a hinge), or turned by one of its
  near-symmetries (:mod:`.symmetry`). Every labelling is weighed against them by its
  evidence (:mod:`.rivals`: detections explained, minus those left unexplained and the
  beads predicted where nothing was detected, the markers' sizes), and it stands only
  if it is clearly the best.
- **Sequences** (:func:`label_bead_sequence`): each frame is first labelled from its own
  seeds or markers; a frame that fails, whose pose lies far from its neighbours', or whose
  labelling from its markers leaves much of it unexplained (a marker pose a few degrees off
  converges with the correction bent to fit), is then labelled from its labelled neighbours
  on either side (:mod:`.motion`, :mod:`.prior`): the orientation is predicted between them (or from one side and the
  sequence's mean step), with uncertainties about and across the turntable axis
  measured on the sequence itself (a regular step predicts the turn well, a wobbling
  axis the tilt less so), and so is the phantom's depth; small rotations of the
  prediction in any direction (the wobble) are searched with the position free (the
  shift vote, :mod:`.votes`), using the neighbour's camera (principal distance,
  distortion), then turns about the axis over the full circle. When the frame's
  evidence cannot tell two labellings apart, the one much nearer the prediction wins;
  otherwise the frame fails ("ambiguous"). The prediction itself is tried first, and
  the search ends as soon as a winner stands alone: its evidence within a margin of the
  most any labelling could have (every detection explained), near the prediction, so
  that nothing found later could displace it (:func:`.rivals.stands_alone`).
- **Grid plates** (``phantom.lattice`` ``"hex"`` or ``"square"``, :mod:`.lattice`,
  :func:`label_plate_sequence`): the holes are indexed on their lattice by topology, growing outward from a hole near
  the centre with local lattice vectors re-estimated at every hole, so that
  the distortion, missing holes and the field edge do not cause slips. The
  object coordinates are the lattice coordinates times the pitch, z = 0, and
  the ids encode the lattice indices (:func:`lattice_id`).

A frame whose labelling fails is returned with ``ok = False`` and a
``reason``; nothing is labelled in it (never a silent mislabelling).

The pinhole helpers (camera matrix, poses to and from OpenCV, projection, P3P) are in :mod:`.camera`.
"""

from fluorocal.stages.label.frame import label_bead_frame, label_plate_frame
from fluorocal.stages.label.labels import Labels
from fluorocal.stages.label.lattice import LATTICE_ID_BASE, LATTICE_ID_OFFSET, lattice_id, lattice_index, lattice_xyz_mm
from fluorocal.stages.label.lattice_sequence import label_plate_sequence
from fluorocal.stages.label.params import (
    STATUS_AMBIGUOUS,
    STATUS_LABELLED,
    STATUS_REJECTED,
    STATUS_UNMATCHED,
    LabelParams,
)
from fluorocal.stages.label.sequence import label_bead_sequence

__all__ = [
    "LATTICE_ID_BASE",
    "LATTICE_ID_OFFSET",
    "STATUS_AMBIGUOUS",
    "STATUS_LABELLED",
    "STATUS_REJECTED",
    "STATUS_UNMATCHED",
    "LabelParams",
    "Labels",
    "label_bead_frame",
    "label_bead_sequence",
    "label_plate_frame",
    "label_plate_sequence",
    "lattice_id",
    "lattice_index",
    "lattice_xyz_mm",
]
