"""The simulator's entry :func:`simulate`: phantom, acquisition, per-frame truth and rendered radiographs."""

from __future__ import annotations

import logging

import numpy as np
from fluorocal.stages.artifacts import Phantom, Radiograph
from fluorocal.stages.simulate.acquisition import Acquisition, make_acquisition
from fluorocal.stages.simulate.orientation import angle_codes
from fluorocal.stages.simulate.params import RNG_HIDDEN, RNG_NOISE, SimulateParams
from fluorocal.stages.simulate.phantom import make_phantom
from fluorocal.stages.simulate.projection import project_beads
from fluorocal.stages.simulate.raster import system_raster
from fluorocal.stages.simulate.render import render_frame
from fluorocal.stages.simulate.truth import SimulatedData, Truth

log = logging.getLogger(__name__)


def simulate(
    params: SimulateParams, *, render: bool = True, phantom: Phantom | None = None, on_frame=None
) -> SimulatedData:
    """Simulate an acquisition with its ground truth.

    Parameters
    ----------
    params : SimulateParams
    render : bool
        False skips image formation (geometry and truth only: fast).
    phantom : Phantom, optional
        Use these beads instead of ``make_phantom(params)``; its coordinates are
        then taken as exact (true = reference = nominal). Spheres for
        ``params.phantom == "cube"`` (the acrylic box is still present unless
        ``mu_acrylic_per_mm`` is 0), plate holes for ``"grid"``.
    on_frame : callable, optional
        Called as ``on_frame(system, exposure)`` after each rendered frame (progress reporting).

    Returns
    -------
    SimulatedData

    Examples
    --------
    >>> data = simulate(SimulateParams(n_frames=2, image_size_px=128), render=False)
    >>> data.system_names, len(data.truth.frames[0]), data.frames
    (('A',), 2, ((),))
    """
    if phantom is None:
        nominal, true_xyz, reference_xyz = make_phantom(params)
    else:
        nominal = phantom
        true_xyz = reference_xyz = phantom.xyz_mm.copy()
    default_mm = params.grid_hole_diameter_mm if params.phantom == "grid" else params.bead_diameter_mm
    diameter = np.where(np.isfinite(nominal.diameter_mm), nominal.diameter_mm, default_mm)
    acq = make_acquisition(params)
    shown = _shown_beads(params, nominal.role == "marker")
    truth_frames, frames = [], []
    for s, system in enumerate(acq.systems):
        per_system = _project_system(params, acq, s, nominal.ids, true_xyz, diameter, shown[s])
        truth_frames.append(per_system)
        log.debug(
            "system %s: %d exposures, %.0f visible beads per frame",
            system.name,
            params.n_exposures,
            np.mean([len(f) for f in per_system]),
        )
        frames.append(_render_system(params, acq, s, true_xyz, diameter, shown[s], on_frame) if render else ())
    truth = Truth(
        np.asarray(true_xyz, dtype=np.float64), np.asarray(reference_xyz, dtype=np.float64), acq, tuple(truth_frames)
    )
    return SimulatedData(params, nominal, truth, tuple(frames))


def _shown_beads(params: SimulateParams, marker: np.ndarray) -> np.ndarray:
    """``(S, K, N) bool``: the beads present in each frame; all but the markers hidden per ``hidden_marker_fraction``.

    In a frame drawn (with that probability) to hide markers, 1 to all of them are hidden, each count equally
    likely; which ones is drawn at random.
    """
    shown = np.ones((params.n_systems, params.n_exposures, len(marker)), dtype=bool)
    markers = np.flatnonzero(marker)
    if not (params.hidden_marker_fraction > 0 and len(markers)):
        return shown
    rng = np.random.default_rng([params.seed, RNG_HIDDEN])
    for s in range(params.n_systems):
        for k in range(params.n_exposures):
            if rng.random() < params.hidden_marker_fraction:
                n_hidden = rng.integers(1, len(markers) + 1)
                shown[s, k, rng.choice(markers, size=n_hidden, replace=False)] = False
    return shown


def _project_system(params: SimulateParams, acq: Acquisition, s: int, ids, true_xyz, diameter, shown) -> tuple:
    """Truth of every exposure k of system ``s`` (beads ``shown[k]``): a tuple of :class:`FrameTruth`."""
    per_system = []
    for k in range(params.n_exposures):
        system = acq.system_at(s, k)
        per_system.append(
            project_beads(
                ids[shown[k]],
                true_xyz[shown[k]],
                diameter[shown[k]],
                acq.q[s, k],
                acq.source_mm[s, k],
                system.iop_px,
                system.distortion,
                image_size_px=params.image_size_px,
                fov_radius_px=params.fov_radius_px,
                overlap_margin_px=params.overlap_margin_px,
                holes=params.phantom == "grid",
                system=s,
                exposure=k,
            )
        )
    return tuple(per_system)


def _noise_rng(params: SimulateParams, acq: Acquisition, s: int, k: int) -> np.random.Generator:
    """Exposure ``k``'s noise stream; in a grid sequence keyed by its orientation and its index there.

    So an orientation's frames are the same whichever other orientations are simulated with it.
    """
    o = int(acq.exposure_orientation[k])
    if o < 0:
        return np.random.default_rng([params.seed, RNG_NOISE, s, k])
    orbit, tilt = params.orientations_deg[o]
    return np.random.default_rng([params.seed, RNG_NOISE, s, *angle_codes(orbit, tilt), k % params.n_frames])


def _render_system(params: SimulateParams, acq: Acquisition, s: int, true_xyz, diameter, shown, on_frame) -> tuple:
    """Radiographs of every exposure of system ``s``, each with its own noise stream: a tuple of :class:`Radiograph`."""
    rasters = {}  # per orientation: the pixel geometry through its distortion
    rendered = []
    for k in range(params.n_exposures):
        system = acq.system_at(s, k)
        o = int(acq.exposure_orientation[k])
        if o not in rasters:
            rasters = {o: system_raster(params, system)}  # exposures come grouped by orientation
        image = render_frame(
            params,
            system,
            acq.q[s, k],
            acq.source_mm[s, k],
            true_xyz[shown[k]],
            diameter[shown[k]],
            rng=_noise_rng(params, acq, s, k),
            raster=rasters[o],
        )
        meta = {
            "format": "simulated",
            "system": system.name,
            "exposure": k,
            "ImagerPixelSpacing": [params.pixel_pitch_mm, params.pixel_pitch_mm],
            "DistanceSourceToDetector": system.source_image_distance_mm,
        }
        if o >= 0:
            orientation = acq.orientations[o]
            meta.update(orientation=orientation.name, orbit_deg=orientation.orbit_deg, tilt_deg=orientation.tilt_deg)
        rendered.append(
            Radiograph(image.astype(np.float32), params.bit_depth, f"simulated/{system.name}/frame_{k:03d}", 0, meta)
        )
        if on_frame is not None:
            on_frame(s, k)
    return tuple(rendered)
