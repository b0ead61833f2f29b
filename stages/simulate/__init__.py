"""Radiograph simulator with ground truth: phantom, acquisition, distortion and image formation.

Everything here is a pure function of :class:`SimulateParams` (randomness only
from ``np.random.default_rng`` seeded by ``params.seed``, one stream per
purpose, so the geometry does not depend on whether frames are rendered);
file writing lives in ``pipeline/cmd_simulate.py``.

Model, in the order light travels (conventions: ``stages/geometry.py``):

1. **Phantom** (:func:`make_phantom`). ``"cube"``: 3.5 mm steel beads set in
   the mid-planes of the four vertical walls of an open acrylic box (no lid
   or floor), one grid per wall, neighbouring walls' rows offset by half a
   row pitch (in an oblique view the walls that overlap in projection are
   neighbours), plus larger ``marker`` beads. ``"grid"``: a steel plate with
   holes on a hexagonal lattice. Three coordinate sets: nominal (design),
   true (nominal + fabrication error; for the plate structured like a
   drilled plate's: rows, alternate rows, holes) and reference (true +
   survey noise).
2. **Acquisition** (:func:`make_acquisition`). The phantom stands on a
   turntable (rotation about the vertical lab axis, with translations and
   height changes); each system is a source and a detector fixed in the lab,
   looking horizontally at the isocentre; system B sits ``system_angle_deg``
   from A and exposes at the same instants. Camera poses ``(q, T)`` are
   expressed in the phantom (object) frame. A grid plate lies on system A's
   intensifier: moved by hand between exposures, or, with
   ``orientations_deg``, riding on it through a sequence of C-arm
   orientations (:class:`Orientation`), moving a little between them.
3. **Distortion** (:class:`ImageDistortion`, forward ideal -> distorted):
   pincushion radial, S-distortion (rotation growing with r²), decentring and
   a smooth random field (cubic B-spline of random coefficients); at a C-arm
   orientation, plus the earth field's change (:mod:`.orientation`).
4. **Image formation** (:func:`render_frame`). Each output pixel centre is
   mapped through the *inverse* distortion to its ideal ray (Newton, to
   1e-7 px; :func:`ideal_pixel_map`); an ideal image is never warped.
   Line integrals: exact chord lengths through every sphere (or hole
   cylinder) and through the acrylic walls (or plate), Beer–Lambert. Pixels
   within a pixel of a bead outline are integrated over 21 sub-samples (a
   Fibonacci lattice), mapped to ideal rays by the local first-order inverse
   map (error < 3e-4 px, tested; far below the sub-sample spacing). Then heel
   effect, focal-spot + intensifier blur (Gaussian), veiling glare,
   vignetting, round field of view, quantum (normal approximation of
   Poisson) + electronic noise and 12-bit quantisation.

"Outline centre": the silhouette of a sphere is the ellipse where the cone
from the source tangent to the sphere meets the image plane (for a hole: the
perspective image of its mid-plane circle). Its ideal centre is the exact
centre of that conic. Through the distortion the outline is no longer an
ellipse; its *distorted outline centre* is the area centroid of the region
it bounds (the centroid an opaque flat silhouette would have), computed from
``N_OUTLINE`` points spaced uniformly in the ideal ellipse's parameter, so
that with no distortion it equals the conic centre exactly.

Modules, one job each: :mod:`.params` (parameters, version, seed streams),
:mod:`.phantom` (bead layouts, plate errors), :mod:`.distortion` (the
intensifier's distortion and its inverse pixel map), :mod:`.orientation`
(C-arm orientations and the earth field's distortion), :mod:`.acquisition`
(systems, turntable and plate poses), :mod:`.projection` (per-frame bead truth), :mod:`.raster`
(per-system pixel geometry), :mod:`.absorption` (line integrals),
:mod:`.render` (detector chain), :mod:`.truth` (truth records and
``truth.json``) and :mod:`.simulation` (the entry :func:`simulate`).
"""

from fluorocal.stages.simulate.acquisition import Acquisition, SystemTruth, make_acquisition
from fluorocal.stages.simulate.distortion import ImageDistortion, ideal_pixel_map, make_distortion
from fluorocal.stages.simulate.orientation import Orientation, make_orientations, orientation_name
from fluorocal.stages.simulate.params import N_OUTLINE, SYSTEM_NAMES, VERSION, SimulateParams
from fluorocal.stages.simulate.phantom import make_phantom, plate_errors
from fluorocal.stages.simulate.projection import FrameTruth, project_beads
from fluorocal.stages.simulate.raster import SystemRaster, local_jacobian, system_raster
from fluorocal.stages.simulate.render import render_frame
from fluorocal.stages.simulate.simulation import simulate
from fluorocal.stages.simulate.truth import SimulatedData, Truth, truth_to_dict

__all__ = [
    "N_OUTLINE",
    "SYSTEM_NAMES",
    "VERSION",
    "Acquisition",
    "FrameTruth",
    "ImageDistortion",
    "Orientation",
    "SimulateParams",
    "SimulatedData",
    "SystemRaster",
    "SystemTruth",
    "Truth",
    "ideal_pixel_map",
    "local_jacobian",
    "make_acquisition",
    "make_distortion",
    "make_orientations",
    "make_phantom",
    "orientation_name",
    "plate_errors",
    "project_beads",
    "render_frame",
    "simulate",
    "system_raster",
    "truth_to_dict",
]
