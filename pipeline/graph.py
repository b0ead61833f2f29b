"""The stage registry and graph.

A :class:`Stage` declares its name, its inputs (upstream stages or the
sources ``frame`` and ``phantom``), its frozen ``Params`` class and its pure
function; the digest of the code it runs (:mod:`fluorocal.codehash`) goes
into every key: its function's module and its ``gather`` function's, and all
they import. The ``context`` and ``extras`` hooks are not in it: what they
compute is (they fill the parameters, which are hashed). Per-frame stages run once
per frame; a per-system stage runs once per imaging system on its frames'
artifacts in exposure order (a sequence) and gives one artifact per frame; a
gathering stage runs once per project on all frames' outputs of its first
input, which its ``gather`` function (pipeline side) turns into one input
artifact.

Stage modules are imported only when the graph is built, so ``--help`` stays
instant.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

SOURCES = ("frame", "phantom")


@dataclass(frozen=True)
class Stage:
    """One node of the graph.

    Attributes
    ----------
    name : str
    func : callable
        ``func(*inputs, params)``, pure.
    params_cls : type
        Frozen dataclass of the stage's parameters (config section ``[name]``).
    inputs : tuple of str
        Upstream stage names or sources (``"frame"``, ``"phantom"``).
    per_frame : bool
        One artifact per frame (True) or one per project (False).
    per_system : bool
        With ``per_frame``: computed once per imaging system, ``func(*inputs, params)``
        taking each per-frame input as the list of the system's frames' artifacts in
        exposure order and returning one artifact per frame, in that order. Each
        frame's key covers every input of its system, so a changed frame recomputes
        its system's sequence. Downstream it is a per-frame stage.
    gather : callable, optional
        For a per-project stage: ``gather(units, artifacts, context)`` turns the
        per-frame artifacts of the first input into one artifact.
    context : callable, optional
        ``context(config, unit, units) -> dict`` of Params fields the pipeline
        fills from the project (the system's geometry, the frame's size);
        ``unit`` is the frame of a per-frame stage, else None; ``units`` are
        the frames the call covers (a per-system stage: its system's, in
        exposure order; otherwise all).
    extras : callable, optional
        ``extras(config, units) -> dict`` of further frozen parameter objects
        passed to ``func`` as keyword arguments (and hashed into the key);
        ``units`` as for ``context``.
    takes_workers : bool
        ``func`` takes ``workers=``, the run's worker count (``--jobs``, ``[compute] jobs``), to run
        independent parts side by side in threads. How it runs, not what it computes: not in the key.
    """

    name: str
    func: Callable
    params_cls: type
    inputs: tuple[str, ...]
    per_frame: bool = True
    per_system: bool = False
    gather: Callable | None = None
    context: Callable | None = None
    extras: Callable | None = None
    takes_workers: bool = False

    def code_modules(self) -> tuple[str, ...]:
        """The modules whose code, with all they import, makes the stage's artifact.

        Its function's and its gather's, and the readers that turn its sources (:data:`SOURCE_CODE`: a frame
        file, the phantom CSV) into its inputs, whose keys hash only the files' bytes. ``context`` and
        ``extras`` are left out: their values, not their code, enter the key.
        """
        own = tuple(f.__module__ for f in (self.func, self.gather) if f is not None)
        return own + tuple(m for i in self.inputs for m in SOURCE_CODE.get(i, ()))

    def code_digest(self, memo=None) -> str:
        """Digest of the code of :meth:`code_modules` and all they import (:func:`fluorocal.codehash.code_digest`).

        ``memo``: a :class:`fluorocal.codehash.AnalysisMemo` of earlier runs' analyses.
        """
        from fluorocal.codehash import code_digest

        return code_digest(self.code_modules(), memo)


def _label_context(config, unit, units) -> dict:
    """The labelling's fields owned by ``[[systems]]``: its geometry, and its frames' size (one detector).

    ``units`` are one system's frames (label is a per-system stage); their seeds go through
    :func:`_label_extras`, so ``LabelParams.seeds`` stays empty.
    """
    from fluorocal.stages.errors import InputError

    system = config.systems[units[0].system]
    sizes = sorted({tuple(u.size_px) for u in units})
    if len(sizes) > 1:
        shown = ", ".join(f"{w}x{h}" for w, h in sizes)
        raise InputError(f"[[systems]] {system.name}: frames differ in size ({shown} px); one system has one detector")
    return {
        "source_image_distance_mm": system.source_image_distance_mm,
        "pixel_pitch_mm": system.pixel_pitch_mm,
        "image_size_px": sizes[0],
    }


def _label_extras(config, units) -> dict:
    """``seeds_by_frame`` of one system's sequence: position in ``units`` -> ``(id, x, y)`` seeds of that frame.

    Seeds without a file and frame apply to the system's first frame.
    """
    system = config.systems[units[0].system]
    if system.seeds is None:
        return {"seeds_by_frame": {}}
    seeds = _seeds(system.seeds)
    by_frame = {}
    for i, unit in enumerate(units):
        found = seeds.get((unit.path.name, unit.index), ()) + (seeds.get(("", 0), ()) if unit.exposure == 0 else ())
        if found:
            by_frame[i] = found
    return {"seeds_by_frame": by_frame}


@lru_cache(maxsize=8)
def _seeds(path):
    from fluorocal.stages.io import read_seeds

    return read_seeds(path)


#: frames of a system, from its first in exposure order, that the bead appearance estimate may try
APPEARANCE_FRAMES = 3


def _detect_context(config, unit, units) -> dict:
    """The automatic polarity and bead diameter range of the frame's system, estimated once per system.

    Estimated on the system's first frame (in exposure order) that shows beads, among its first
    :data:`APPEARANCE_FRAMES`; the values go into every frame's parameters, and so into its key:
    each frame's entry stays its own, and a serial run, a pool or a cluster compute the same ones.
    """
    from fluorocal.config import params_from_dict
    from fluorocal.stages.detect import DetectParams

    params = params_from_dict(
        DetectParams, config.stage_params.get("detect", {}), where=f"{config.path.name}: [detect] "
    )
    system = sorted((u for u in units if u.system == unit.system), key=lambda u: u.exposure)
    found = _system_appearance(tuple((u.path, u.file_sha256, u.index) for u in system[:APPEARANCE_FRAMES]), params)
    return {name: getattr(found, name) for name in ("polarity", "min_diameter_px", "max_diameter_px")}


@lru_cache(maxsize=8)
def _system_appearance(frames: tuple, params):
    """The estimate on ``(path, content sha256, index)`` frames, each read only while its content is that sha.

    The sha keys the memo to the content, and :func:`~fluorocal.steady.read_steady` refuses a file that
    changed since the run was planned or while it is read, as every frame read of a run does. A file's
    frames in a row are read (and hashed) together.
    """
    from itertools import groupby

    from fluorocal.stages.detect import estimate_appearance
    from fluorocal.steady import read_steady

    runs = groupby(frames, key=lambda f: f[:2])
    read = (read_steady(path, sha, [f[2] for f in run]) for (path, sha), run in runs)
    return estimate_appearance((frame for file_frames in read for frame in file_frames), params)


def _learn_extras(config, units) -> dict:
    from fluorocal.config import params_from_dict
    from fluorocal.stages.geometry import iop_guess
    from fluorocal.stages.kinds.learning import CalibrationSetup

    sizes, guesses = [], []
    for s, system in enumerate(config.systems):
        w, h = next(u.size_px for u in units if u.system == s)
        sizes.append((w, h))
        guesses.append(tuple(iop_guess((w, h), system.source_image_distance_mm, system.pixel_pitch_mm)))
    _check_phantom_sections(config)
    solver, selection = params_from_dict(
        _section_classes("adjust"), config.stage_params.get("adjust", {}), where=f"{config.path.name}: [adjust] "
    )
    (plate,) = params_from_dict(
        _section_classes("plate"), config.stage_params.get("plate", {}), where=f"{config.path.name}: [plate] "
    )
    setup = CalibrationSetup(
        scheme=config.scheme,
        image_size_px=tuple(sizes),
        iop_guess_px=tuple(guesses),
        orientations=plate_orientations(config, units),
    )
    return {"setup": setup, "solver": solver, "selection": selection, "plate": plate}


def _check_phantom_sections(config) -> None:
    """Refuse the other kinds' sections: ``[learn]`` for a grid plate, ``[plate]`` for a bead phantom."""
    from fluorocal.stages.errors import InputError
    from fluorocal.stages.kinds import KINDS

    kind = config.phantom.kind
    unused = sorted(({k.section for k in KINDS.values()} - {kind.section}) & set(config.stage_params))
    if unused:
        raise InputError(
            f"{config.path.name}: [{unused[0]}] does not apply to {kind.noun} (its calibration's settings are in "
            f"[{kind.section}]); remove the [{unused[0]}] section"
        )


def plate_orientations(config, units) -> tuple:
    """``(system, exposure, orientation, orbit_deg, tilt_deg)`` per frame of a kind taken at several orientations.

    () for a kind whose system is one orientation (a 3D phantom).

    Raises
    ------
    InputError
        A 3D phantom's system given several orientations (its frames are one orientation: the phantom
        moves, the C-arm does not).
    """
    from fluorocal.orientations import frame_orientations
    from fluorocal.stages.errors import InputError

    kind = config.phantom.kind
    if not kind.several_orientations:
        several = [s.name for s in config.systems if len(s.orientations) > 1]
        if several:
            raise InputError(
                f"{config.path.name}: [[systems]] {several[0]}: orientations: {kind.noun} calibrates a "
                "system at one C-arm orientation; give one project per orientation (or use a grid plate)"
            )
        return ()
    found = frame_orientations(config, units)
    return tuple((u.system, u.exposure, o.name, o.orbit_deg, o.tilt_deg) for u, o in zip(units, found))


#: the modules that read a source input (keyed by its file's bytes alone) into what a stage takes: their code is
#: in the key of every stage taking that input
SOURCE_CODE = {"frame": ("fluorocal.stages.io.frames",), "phantom": ("fluorocal.stages.io.tables",)}

#: the project's stages in execution order: (stage name, module, entry function, Params class, inputs, options);
#: a gather function is named ``"module:function"`` (imported with the stages, its module's code in the key)
REGISTRY = (
    ("detect", "fluorocal.stages.detect", "detect_beads", "DetectParams", ("frame",), {"context": _detect_context}),
    ("centroid", "fluorocal.stages.centroid", "centroid_beads", "CentroidParams", ("frame", "detect"), {}),
    (
        "label",
        "fluorocal.stages.kinds.labelling",
        "label_sequence",
        "LabelParams",
        ("centroid", "phantom"),
        {"per_system": True, "context": _label_context, "extras": _label_extras},
    ),
    (
        "learn",
        "fluorocal.stages.kinds.learning",
        "learn_calibration",
        "LearnParams",
        ("label", "phantom"),
        {
            "per_frame": False,
            "gather": "fluorocal.gather:observations_from_labels",
            "extras": _learn_extras,
            "takes_workers": True,
        },
    ),
)

#: config sections that are not a stage of their own, and their Params classes (keys split by field name)
EXTRA_SECTIONS = {
    "adjust": ("fluorocal.stages.adjust", ("SolverOptions", "DataSelection")),
    "plate": ("fluorocal.stages.plate", ("PlateParams",)),
}


def default_stages() -> list[Stage]:
    """The stages of a calibration, in topological order."""
    stages = []
    for name, module, entry, params, inputs, options in REGISTRY:
        mod = importlib.import_module(module)
        if "gather" in options:
            where, _, function = options["gather"].partition(":")
            options = {**options, "gather": getattr(importlib.import_module(where), function)}
        stages.append(Stage(name, getattr(mod, entry), getattr(mod, params), inputs, **options))
    return stages


def stage_params_classes() -> dict[str, type | tuple[type, ...]]:
    """Config section name -> Params class (or classes), for validating ``[detect]``, ``[adjust]`` etc."""
    sections = {s.name: s.params_cls for s in default_stages()}
    return {**sections, **{section: _section_classes(section) for section in EXTRA_SECTIONS}}


def _section_classes(section: str) -> tuple[type, ...]:
    module, names = EXTRA_SECTIONS[section]
    mod = importlib.import_module(module)
    return tuple(getattr(mod, name) for name in names)


def downstream(stages: list[Stage], names: set[str]) -> set[str]:
    """``names`` and every stage that depends on them, directly or not."""
    out = set(names)
    for stage in stages:
        if any(i in out for i in stage.inputs):
            out.add(stage.name)
    return out


def check_graph(stages: list[Stage]) -> None:
    """Raise ValueError unless every input names a source or an earlier stage."""
    seen = set(SOURCES)
    for stage in stages:
        missing = [i for i in stage.inputs if i not in seen]
        if missing:
            raise ValueError(f"stage {stage.name!r} needs {missing} before it")
        if not stage.per_frame and stage.gather is None:
            raise ValueError(f"per-project stage {stage.name!r} needs a gather function")
        if stage.per_system and not stage.per_frame:
            raise ValueError(f"per-system stage {stage.name!r} gives one artifact per frame: per_frame must be True")
        seen.add(stage.name)
