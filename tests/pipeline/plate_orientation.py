"""Held-out C-arm orientations of a grid-plate sequence: issue 12's orientation target.

Shared by tests/pipeline/test_plate_orientation.py and benchmarks/orientation.py.

Protocol:

1. every frame of the project is detected, centroided and labelled by the pipeline (as ``fluorocal run
   --until label``): the lattice numbering is one across the sequence
   (:mod:`fluorocal.stages.label.lattice_sequence`), so a hole has the same id in every frame;
2. the plate is calibrated (:func:`fluorocal.stages.plate.calibrate_plate`, default ``PlateParams``
   unless given) from the calibration orientations' frames only;
3. each held-out frame's holes are corrected by a field: (a) the field interpolated at the frame's
   angles (:func:`fluorocal.stages.orientation.interpolate_field`), (b) the field of one of the two
   nearest calibrated orientations (transfer), (c) none; the corrected centres are compared with the
   plate's self-calibrated layout ``nominal_mm + plate_error_mm`` by the least-squares homography, and
   the figure is the RMS of the residual's length per hole, px (per component: that / sqrt 2). Scored
   are the frame's holes whose plate error was estimated (seen in two calibration frames or more) where
   every calibrated field is supported: the same holes for every field;
4. for reference, the field's own held-out figure at a calibrated orientation (:func:`own_holdout_px`).

On a simulated sequence the truth is known: :func:`true_fields` gives the true correction at each
orientation, to compare with by :func:`tests.stages.plate_truth.field_error_px` (modulo a homography).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tests.helpers import rms_length, rms_modulo_homography

#: the orientations of the sequences: name -> (orbit, tilt), degrees
ANGLES_DEG = {"centred": (0, 0), "tilt15": (0, 15), "tilt30": (0, 30), "tilt45": (0, 45), "tilt60": (0, 60)}
#: calibrated at three orientations 30° apart; held out: the two in between
CALIBRATED = ("centred", "tilt30", "tilt60")
HELD_OUT = ("tilt15", "tilt45")
#: the real ARCADIS grid frames, one per orientation: name -> (file, orbit, tilt)
REAL_ORIENTATIONS = {
    "centred": ("grid_centered_0.dcm", 0, 0),
    "orbit30": ("grid_orbit_30.dcm", 30, 0),
    "tilt15": ("grid_tilt_15.dcm", 0, 15),
    "tilt30": ("grid_tilt_30.dcm", 0, 30),
    "tilt45": ("grid_tilt_45.dcm", 0, 45),
    "tilt60": ("grid_tilt_60.dcm", 0, 60),
}


def real_grid_config(folder: Path, arcadis: Path, names) -> Path:
    """A project on the real grid frames of the named orientations (the DICOMs record no angles: given here)."""
    groups = ",\n".join(
        f'  {{name = "{n}", frames = ["{arcadis / REAL_ORIENTATIONS[n][0]}"], orbit = {REAL_ORIENTATIONS[n][1]}, '
        f"tilt = {REAL_ORIENTATIONS[n][2]}}}"
        for n in names
    )
    frames = ", ".join(f'"{arcadis / REAL_ORIENTATIONS[n][0]}"' for n in names)
    text = (
        '[phantom]\nlattice = "hex"\npitch = 3.3\n\n[[systems]]\nname = "arcadis"\n'
        f"frames = [{frames}]\nsource_image_distance = 1000\npixel_pitch = 0.21\norientations = [\n{groups}\n]\n"
    )
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "fluorocal.toml").write_text(text)
    return folder / "fluorocal.toml"


#: the real ARCADIS frame of each orientation (in ../shared/data/arcadis)
REAL_FRAMES = {
    "centred": "grid_centered_0.dcm",
    "tilt15": "grid_tilt_15.dcm",
    "tilt30": "grid_tilt_30.dcm",
    "tilt45": "grid_tilt_45.dcm",
    "tilt60": "grid_tilt_60.dcm",
}


def write_project(path: Path, frames: dict, *, phantom: str, geometry: str, output_dir: str = "out") -> Path:
    """A one-system project config at ``path``: one orientation per frame (name -> file), at :data:`ANGLES_DEG`.

    ``phantom`` and ``geometry`` are the TOML lines of ``[phantom]`` and of the system's geometry.
    """
    groups = ",\n".join(
        f"  {{name = {json.dumps(n)}, frames = [{json.dumps(str(f))}], orbit = {ANGLES_DEG[n][0]}, "
        f"tilt = {ANGLES_DEG[n][1]}}}"
        for n, f in frames.items()
    )
    files = ", ".join(json.dumps(str(f)) for f in frames.values())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        f'[phantom]\n{phantom}\n\n[[systems]]\nname = "A"\nframes = [{files}]\n{geometry}\n'
        f"orientations = [\n{groups},\n]\n\n[output]\ndir = {json.dumps(output_dir)}\n"
    )
    return path


def write_real_project(root: Path, data_dir: Path) -> Path:
    """A project config in ``root`` on the real grid frames of :data:`REAL_FRAMES`, with their angles.

    The geometry is approximate (the DICOMs record none): a plate calibration needs only the pitch's
    scale. Returns the config's path.
    """
    return write_project(
        root / "fluorocal.toml",
        {name: (Path(data_dir) / file).resolve() for name, file in REAL_FRAMES.items()},
        phantom='lattice = "hex"\npitch = 3.3',
        geometry="source_image_distance = 1000\npixel_pitch = 0.21",
    )


@dataclass(frozen=True)
class Sequence:
    """A grid-plate project's labelled frames, with each frame's orientation."""

    observations: object  # fluorocal.stages.artifacts.Observations, every labelled frame
    phantom: object  # fluorocal.stages.artifacts.Phantom
    image_size_px: tuple  # (width, height)
    orientations: tuple  # per frame: (system, exposure, name, orbit_deg, tilt_deg)
    failed: tuple  # "frame (reason)" of the frames whose labelling failed

    def exposure_of(self, name: str) -> int:
        """The exposure of orientation ``name``'s (single) frame."""
        (exposure,) = [e for _, e, n, _, _ in self.orientations if n == name]
        return exposure

    def angles_of(self, name: str) -> tuple[float, float]:
        (angles,) = {(o, t) for _, _, n, o, t in self.orientations if n == name}
        return angles

    def subset(self, names) -> tuple:
        """The observations and frame orientations of the orientations ``names`` only."""
        from fluorocal.stages.artifacts import Observations

        frames = [e for _, e, n, _, _ in self.orientations if n in names]
        obs = self.observations
        rows = np.isin(obs.exposure, frames)
        subset = Observations(
            obs.system[rows],
            obs.exposure[rows],
            obs.bead_id[rows],
            obs.xy_px[rows],
            obs.sigma_px[rows],
            obs.system_names,
        )
        return subset, tuple(o for o in self.orientations if o[2] in names)

    def frame(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Hole ids ``(N,)`` and measured centres ``(N, 2)`` px of orientation ``name``'s frame."""
        obs = self.observations
        rows = obs.exposure == self.exposure_of(name)
        return obs.bead_id[rows], obs.xy_px[rows]


def labelled_sequence(config_path: Path) -> Sequence:
    """Detect, centroid and label every frame of the (one-system) project at ``config_path``, with its cache."""
    from fluorocal.cache import ArtifactCache
    from fluorocal.config import load_config
    from fluorocal.gather import failed_frames, observations_from_labels
    from fluorocal.graph import default_stages, stage_params_classes
    from fluorocal.orientations import frame_orientations
    from fluorocal.run import Runner

    config = load_config(config_path, stage_params_allowed=stage_params_classes())
    runner = Runner(config, default_stages(), ArtifactCache(config.cache_dir), until="label", progress=False)
    runner.run()
    units = runner.units
    labels = [runner.get("label", u) for u in range(len(units))]
    found = frame_orientations(config, units)
    return Sequence(
        observations_from_labels(units, labels, config),
        runner.get("phantom", None),
        tuple(units[0].size_px),
        tuple((u.system, u.exposure, o.name, o.orbit_deg, o.tilt_deg) for u, o in zip(units, found)),
        tuple(failed_frames(units, labels, config)),
    )


def calibrate(seq: Sequence, names, params=None):
    """The plate calibration from the orientations ``names`` only: ``(PlateCalibration, [OrientationField])``."""
    from fluorocal.stages.orientation import OrientationField
    from fluorocal.stages.plate import PlateParams, calibrate_plate

    obs, orientations = seq.subset(names)
    cal = calibrate_plate(
        obs,
        seq.phantom,
        PlateParams() if params is None else params,
        image_size_px=(seq.image_size_px,),
        orientations=orientations,
    )
    fields = [
        OrientationField(name, float(a[0]), float(a[1]), f)
        for name, a, f in zip(cal.orientation_names, cal.orientation_angles_deg, cal.fields)
    ]
    return cal, fields


@dataclass(frozen=True)
class HeldOutFrame:
    """A held-out frame's scored holes: their measured centres and their self-calibrated plate positions."""

    name: str
    angles_deg: tuple  # (orbit, tilt)
    hole_id: np.ndarray  # (M,) lattice ids
    xy_px: np.ndarray  # (M, 2) measured centres
    layout_mm: np.ndarray  # (M, 2) nominal + estimated plate error

    @property
    def n_holes(self) -> int:
        return len(self.xy_px)

    def rms_px(self, field=None) -> float:
        """RMS residual length per hole after correcting by ``field`` (None: no correction), px."""
        corrected = self.xy_px if field is None else field.undistort_points(self.xy_px)
        return rms_modulo_homography(self.layout_mm, corrected)


def held_out_frame(seq: Sequence, cal, fields, name: str) -> HeldOutFrame:
    """Orientation ``name``'s frame, its holes restricted as in the module docstring (step 3)."""
    ids, xy = seq.frame(name)
    where = {int(h): k for k, h in enumerate(cal.hole_id)}
    k = np.array([where.get(int(h), -1) for h in ids], np.int64)
    keep = k >= 0
    keep[keep] = cal.plate_estimated[k[keep]]
    for f in fields:
        keep &= f.field.support_at(xy)
    k = k[keep]
    return HeldOutFrame(name, seq.angles_of(name), ids[keep], xy[keep], cal.nominal_mm[k] + cal.plate_error_mm[k])


def nearest(fields, angles_deg, count: int = 2) -> list:
    """The ``count`` calibrated orientations nearest ``angles_deg`` (orbit, tilt), nearest first."""
    distance = [math.hypot(f.orbit_deg - angles_deg[0], f.tilt_deg - angles_deg[1]) for f in fields]
    return [fields[i] for i in np.argsort(distance, kind="stable")[:count]]


def own_holdout_px(seq: Sequence, names, calibrated_name: str, params=None) -> float:
    """The field's own held-out figure at the calibrated orientation ``calibrated_name``, px.

    The calibration from the orientations ``names`` is solved twice, with that orientation's frame's
    even, then odd, lattice rows left out, and the left-out holes scored as in step 3
    (:func:`fluorocal.stages.plate.holdout.holdout_score`); RMS residual length per hole.
    """
    from fluorocal.stages.label.lattice import lattice_index
    from fluorocal.stages.plate import PlateParams
    from fluorocal.stages.plate.holdout import holdout_score
    from fluorocal.stages.plate.problem import frame_orientations, plate_problem

    obs, orientations = seq.subset(names)
    params = PlateParams() if params is None else params
    problem, index = plate_problem(obs, seq.phantom, 0, frame_orientations(obs, orientations), seq.image_size_px)
    settings = params.settings(seq.phantom.pitch_mm, estimate_plate=True)
    frame = int(np.flatnonzero(index["exposures"] == seq.exposure_of(calibrated_name))[0])
    row = lattice_index(index["hole_ids"])[:, 1]
    return rms_length(holdout_score(problem, settings, row, frames=[frame]).residual_px)


def true_fields(truth: dict) -> dict:
    """The simulator's true correction at each orientation: name -> CorrectionField."""
    from tests.stages.plate_truth import truth_field

    size = truth["image_size_px"]
    return {o["name"]: truth_field(o["correction_grid"], size, size) for o in truth["systems"][0]["orientations"]}
