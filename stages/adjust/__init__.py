"""Robust bundle adjustment: Student-t maximum likelihood, free network, interior orientation, biplanar constraint.

The model is the collinearity equation (paper section IV, eq. 1; conventions
in :mod:`stages.geometry`)::

    ideal_o = xy_o - Δ_o = (xp_s, yp_s) + c_s * (p_x, p_y) / p_z,
    p = R_s (R_j (P_i - T_j) - b_s)

for observation ``o`` of bead ``i`` in epoch ``j`` by system ``s``. The
unknowns are every observed bead's coordinates ``P_i`` (the nominal
coordinates only start them), the reference system's pose ``(q_j, T_j)`` per
epoch, per system the IOP ``(xp, yp, c)`` (estimated or held fixed: the paper's
"kNN + IOP" versus "kNN" schemes) and, for systems ``s >= 1``, one relative
orientation (ROP) ``(R_s, b_s)`` for the whole acquisition: frames of
different systems with the same ``exposure`` index share the phantom's pose
(biplanar). System 0 has ``R_0 = I``, ``b_0 = 0``. The corrections ``Δ`` are
constants of a solve (the learning stage updates them between solves).
Optionally (``additional_parameters="polynomial"``) each system's global
polynomial distortion model (:mod:`stages.adjust.polynomial`: radial ``k1..k3``,
decentring ``p1, p2``, affinity ``b1, b2``) is estimated with everything else:
``ideal_o = xy_o - Δ_o - Δ_AP(xy_o; xp_s, yp_s)``.

Estimation maximises the likelihood of a 2-D Student-t of every observation
with covariance ``σ² C_o`` (eq. 2), ``C_o`` from the centroid stage's
``(σx, σy, ρ)`` and ``σ²`` a variance factor estimated with the parameters
(``estimate_scale``), by Levenberg–Marquardt with analytic Jacobians: the
exact gradient, and the IRLS Hessian with weights
``w = (ν + 2) / (ν + r^T C^-1 r / σ²)`` (with Triggs' curvature correction
once σ² has settled, which shortens the IRLS tail). The datum is the inner
constraints of the object points relative to their nominal coordinates
(translation, rotation, scale: the results are in mm in the nominal frame),
solved as a bordered system. Each step eliminates either the points or the
poses by a Schur complement, whichever leaves the smaller dense system (with
a fixed phantom and many exposures: the poses, so the cost grows linearly in
the number of exposures).

What cannot be estimated is dropped with a debug message (beads seen in
fewer than two epochs or along nearly one direction, epochs with too few
beads; duplicate labels with a warning), and so is a bead whose inliers after the solve
are seen in fewer than two epochs (two rays, one a gross error: the point slides along the
good ray), after which the solve runs again (logged); too few frames raise :class:`InputError`, all frames
from one pose or a singular network :class:`EstimationError`. A pure
turntable (every rotation about one axis) is a critical motion for the
principal point: tilt the phantom between exposures or fix the IOP.

Also here: :func:`initial_orientation` (start values by per-frame resection)
and :func:`adjust_plate` (a robust homography per frame for grid plates, with
the same per-observation outputs).

Parameters have one owner each (:mod:`stages.adjust.options`):
:class:`SolverOptions` and :class:`DataSelection` are the user's (config
section ``[adjust]``); :class:`FreeParameters` (which parameters are
estimated) belongs to the caller that owns that choice (the learning loop's
scheme, ``fluorocal adjust``'s flags); ``compute_covariance`` is a keyword of
:func:`adjust_bundle`. Per-solve lines are logged at debug level only; the
result says whether it is ``usable``.

Modules (after COLMAP's split of its bundle adjuster):

- :mod:`~stages.adjust.collinearity`: residual functions and analytic Jacobians;
- :mod:`~stages.adjust.problem`: the problem builder (free/fixed parameters,
  gauge, packing, sparsity) and :mod:`~stages.adjust.selection` (what can be estimated);
- :mod:`~stages.adjust.robust`, :mod:`~stages.adjust.normal`,
  :mod:`~stages.adjust.solver`: the Student-t likelihood, the bordered Schur
  normal equations and Levenberg–Marquardt;
- :mod:`~stages.adjust.covariance` and :mod:`~stages.adjust.result` (:class:`Adjustment`, ``usable``);
- :mod:`~stages.adjust.orientation` (:class:`Orientation`, :func:`initial_orientation`),
  :mod:`~stages.adjust.bundle` (:func:`adjust_bundle`),
  :mod:`~stages.adjust.plate` and :mod:`~stages.adjust.homography` (grid plates),
  :mod:`~stages.adjust.polynomial` (the additional parameters).

Examples
--------
>>> import numpy as np
>>> from fluorocal.stages.geometry import project, quat_to_matrix, rotvec_to_quat
>>> from fluorocal.stages.artifacts import Observations
>>> rng = np.random.default_rng(0)
>>> xyz = rng.uniform(-50, 50, (40, 3))
>>> angles = np.deg2rad(np.arange(0, 360, 40))
>>> # tilted: not all rotations about one axis
>>> q = np.array([rotvec_to_quat([0.3 * (-1) ** k, a, 0.0]) for k, a in enumerate(angles)])
>>> src = -np.einsum("mji,j->mi", quat_to_matrix(q), [0.0, 0.0, 700.0])
>>> iop = np.array([512.0, 512.0, 4400.0])
>>> xy = np.concatenate([project(xyz, q[j], src[j], iop) for j in range(len(q))])
>>> obs = Observations(system=np.zeros(len(xy)), exposure=np.repeat(np.arange(len(q)), 40),
...                    bead_id=np.tile(np.arange(40), len(q)), xy_px=xy,
...                    sigma_px=np.tile([0.05, 0.05, 0.0], (len(xy), 1)))
>>> start = Orientation(iop_px=[[510.0, 515.0, 4300.0]], exposure=np.arange(len(q)), q_cam_from_obj=q,
...                     source_mm=src + 1.0)
>>> result = adjust_bundle(obs, (np.arange(40), xyz), start)
>>> bool(result.usable), bool(np.allclose(result.iop_px, iop, atol=1e-6))
(True, True)
"""

from fluorocal.stages.adjust.bundle import adjust_bundle
from fluorocal.stages.adjust.options import DataSelection, FreeParameters, SolverOptions
from fluorocal.stages.adjust.orientation import Orientation, initial_orientation
from fluorocal.stages.adjust.plate import PlateAdjustment, adjust_plate
from fluorocal.stages.adjust.result import Adjustment
from fluorocal.stages.adjust.selection import index_of, nominal_coordinates

__all__ = [
    "SolverOptions",
    "FreeParameters",
    "DataSelection",
    "Orientation",
    "Adjustment",
    "adjust_bundle",
    "initial_orientation",
    "PlateAdjustment",
    "adjust_plate",
    "nominal_coordinates",
    "index_of",
]
