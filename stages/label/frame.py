"""One frame labelled: its detections and assumed interior orientation, then a cube phantom or a grid plate."""

from __future__ import annotations

from fluorocal.stages.artifacts import MIN_PHANTOM_BEADS, Phantom
from fluorocal.stages.errors import InputError
from fluorocal.stages.label.cube import label_cube
from fluorocal.stages.label.detections import Detections, assumed_iop
from fluorocal.stages.label.labels import Labels
from fluorocal.stages.label.lattice import label_grid
from fluorocal.stages.label.params import LabelParams


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
        An approximate pose, e.g. a neighbouring frame's; tried when the markers give no acceptable
        labelling (ignored when seeds are given). Its orientation is taken as right within a few degrees
        (small rotations of it about any axis are searched, :mod:`.prior`), its position not: the phantom's
        shift across the beam is searched over the whole image and its distance over a few %. The
        labelling found is kept only if no rival explains the frame about as well (a periodic bead layout
        one row off, a pose that a symmetry of the phantom allows), unless the beads' sizes or a much
        nearer prior orientation rule it out; :func:`label_sequence` gives the search the sequence's
        motion as well.

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
    return label_frame(centroids, phantom, params, prior_pose)


def label_frame(centroids, phantom: Phantom, params: LabelParams, prior_pose=None, **search) -> Labels:
    """:func:`label_beads`, with the search options a sequence gives (:func:`~.cube.label_cube`)."""
    det = Detections.from_centroids(centroids)
    iop = assumed_iop(det, centroids, params, need_c=not phantom.lattice)
    if phantom.lattice:
        if phantom.lattice not in ("hex", "square"):
            raise InputError(f"phantom.lattice must be 'hex' or 'square'; got {phantom.lattice!r}")
        if not phantom.pitch_mm > 0:
            raise InputError(f"phantom.pitch_mm must be > 0 for a grid plate; got {phantom.pitch_mm}")
        return label_grid(det, phantom, params, iop)
    if phantom.n_beads < MIN_PHANTOM_BEADS:
        raise InputError(f"phantom must have at least {MIN_PHANTOM_BEADS} beads; got {phantom.n_beads}")
    return label_cube(det, phantom, params, iop, prior_pose, **search)
