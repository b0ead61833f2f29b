"""The label stage: a frame or one system's frames labelled as the phantom's kind labels them.

The stage's entry module, apart from :mod:`.learning`: it imports the kinds and the labelling, never a
solver, so an edit of the calibration's code leaves the labels' cache keys alone.
"""

from __future__ import annotations

from fluorocal.stages.kinds import kind_of
from fluorocal.stages.label import LabelParams, Labels

__all__ = ["LabelParams", "label_beads", "label_sequence"]


def label_beads(centroids, phantom, params: LabelParams, prior_pose: tuple | None = None) -> Labels:
    """Give every detection of one frame its phantom bead id (or grid-plate hole id), as the phantom's kind does.

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
        A 3D phantom's approximate pose, e.g. a neighbouring frame's; tried when the markers give no
        acceptable labelling (ignored when seeds are given). Its orientation is taken as right within a few
        degrees (small rotations of it about any axis are searched, :mod:`fluorocal.stages.label.prior`), its
        position not: the phantom's shift across the beam is searched over the whole image and its distance
        over a few %. The labelling found is kept only if no rival explains the frame about as well (a
        periodic bead layout one row off, a pose that a symmetry of the phantom allows), unless the beads'
        sizes or a much nearer prior orientation rule it out; :func:`label_sequence` gives the search the
        sequence's motion as well. A grid plate's holes are indexed on its lattice (no pose needed).

    Returns
    -------
    Labels
        ``ok = False`` with a ``reason`` when the frame could not be labelled reliably.

    Raises
    ------
    InputError
        A 3D phantom without ``source_image_distance_mm`` and ``pixel_pitch_mm``, a phantom of fewer than 4
        beads, a grid plate without a valid lattice or pitch, or seeds naming beads the phantom lacks.

    Examples
    --------
    An 11 x 11 square grid plate seen head-on (the centroids' columns the labelling reads):

    >>> from types import SimpleNamespace
    >>> import numpy as np
    >>> from fluorocal.stages.artifacts import Phantom
    >>> xy = 511.5 + 13.0 * np.array([(i, j) for i in range(-5, 6) for j in range(-5, 6)], float)
    >>> one = np.ones(len(xy))
    >>> frame = SimpleNamespace(xy_px=xy, sigma_x=0.05 * one, sigma_y=0.05 * one, rho=0 * one,
    ...                         major_px=3 * one, minor_px=3 * one, ok=one.astype(bool))
    >>> labels = label_beads(frame, Phantom([], [], [], [], "square", 1.0), LabelParams())
    >>> labels.ok, labels.n_labelled
    (True, 121)
    """
    return kind_of(phantom).label_frame(centroids, phantom, params, prior_pose)


def label_sequence(
    centroids_seq, phantom, params: LabelParams, seeds_by_frame: dict | None = None
) -> tuple[Labels, ...]:
    """The label stage: one system's frames labelled in exposure order, as the phantom's kind labels them.

    A 3D bead phantom's frames each from its own markers or seeds, else from its neighbours
    (:func:`fluorocal.stages.label.label_bead_sequence`); a grid plate's holes on its lattice, with one
    numbering across the frames (:func:`fluorocal.stages.label.label_plate_sequence`).

    Parameters
    ----------
    centroids_seq : sequence of Centroids
        The frames in acquisition order.
    phantom : Phantom
    params : LabelParams
        Its ``seeds`` are ignored here; give them per frame in ``seeds_by_frame``.
    seeds_by_frame : dict of int to tuple, optional
        Frame position -> ``(id, x_px, y_px)`` seeds of that frame.

    Returns
    -------
    tuple of Labels
        One per frame, in order.

    Examples
    --------
    A grid plate's holes get one numbering across the frames (the frame of :func:`label_beads`' example, twice):

    >>> from types import SimpleNamespace
    >>> import numpy as np
    >>> from fluorocal.stages.artifacts import Phantom
    >>> xy = 511.5 + 13.0 * np.array([(i, j) for i in range(-5, 6) for j in range(-5, 6)], float)
    >>> one = np.ones(len(xy))
    >>> frame = SimpleNamespace(xy_px=xy, sigma_x=0.05 * one, sigma_y=0.05 * one, rho=0 * one,
    ...                         major_px=3 * one, minor_px=3 * one, ok=one.astype(bool))
    >>> first, second = label_sequence([frame, frame], Phantom([], [], [], [], "square", 1.0), LabelParams())
    >>> first.n_labelled, bool(np.array_equal(first.bead_id, second.bead_id))
    (121, True)
    """
    return kind_of(phantom).label_sequence(centroids_seq, phantom, params, seeds_by_frame)
