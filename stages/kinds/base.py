"""What a kind of calibration object is to the stages: :class:`PhantomKind`.

Each kind (:mod:`.beads`, :mod:`.plate`) is one frozen object that owns what differs between kinds: how
a frame and a sequence are labelled, which schemes and config sections it accepts, and how its frames and
its outputs are treated. :mod:`fluorocal.stages.kinds` looks it up by the spelling of the project's
``[phantom]`` table. What calibrates it is :data:`fluorocal.stages.kinds.learning.CALIBRATIONS`, by its
:attr:`~PhantomKind.name` (kept apart so that the labelling does not import the solvers).
"""

from __future__ import annotations

from typing import Protocol


class PhantomKind(Protocol):
    """One kind of calibration object: what the stages and the pipeline ask of it instead of testing its data.

    Attributes
    ----------
    name : str
        The kind's name in outputs and messages (``"beads"``, ``"plate"``).
    noun : str
        How a message names it (``"a 3D bead phantom"``).
    calibrated_by : str
        How it is calibrated, as a message says it after "is calibrated" (``"by the learning loop ..."``).
    section : str
        The config section of its calibration's settings (``"learn"``, ``"plate"``); the other kinds'
        sections are refused in its project.
    schemes : tuple of Scheme
        The ``[calibration] scheme`` values it can be calibrated with.
    needs_geometry : bool
        Its labelling needs the system's rough geometry (source-image distance, pixel pitch) and the
        phantom's own file; otherwise its spelling and pitch are the whole phantom.
    pairs_frames : bool
        Two systems' frames are paired by position (biplanar epochs); otherwise each system is calibrated
        on its own, with any number of frames.
    several_orientations : bool
        A system's frames may be taken at several C-arm orientations (a field each).
    estimates_geometry : bool
        The calibration estimates the object's 3D geometry (object points to check frames against, an
        export with intrinsics); ``calibration.json`` says so as ``geometry_estimated``.
    check_points : bool
        Surveyed check points (``evaluate --reference``) can score it.
    """

    name: str
    noun: str
    calibrated_by: str
    section: str
    schemes: tuple
    needs_geometry: bool
    pairs_frames: bool
    several_orientations: bool
    estimates_geometry: bool
    check_points: bool

    def label_frame(self, centroids, phantom, params, prior_pose=None):
        """One frame's :class:`~fluorocal.stages.label.Labels` (``prior_pose``: a neighbour's, if the kind uses it)."""

    def label_sequence(self, centroids_seq, phantom, params, seeds_by_frame=None) -> tuple:
        """One system's frames labelled, in exposure order: one :class:`~fluorocal.stages.label.Labels` each."""
