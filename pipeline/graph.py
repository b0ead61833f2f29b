"""The stage registry and graph.

A :class:`Stage` declares its name, its inputs (upstream stages or the
sources ``frame`` and ``phantom``), its frozen ``Params`` class, its
implementation ``VERSION`` and its pure function. Per-frame stages run once
per frame; a gathering stage runs once per project on all frames' outputs of
its first input, which its ``gather`` function (pipeline side) turns into one
input artifact.

Stage modules are imported only when the graph is built, so ``--help`` stays
instant.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
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
    version : int
        Implementation version: bump it when the output's meaning changes.
    inputs : tuple of str
        Upstream stage names or sources (``"frame"``, ``"phantom"``).
    per_frame : bool
        Run once per frame (True) or once per project (False).
    gather : callable, optional
        For a per-project stage: ``gather(units, artifacts, context)`` turns the
        per-frame artifacts of the first input into one artifact.
    context : callable, optional
        ``context(config, unit, units) -> dict`` of Params fields the pipeline
        fills from the project (the system's geometry, the frame's size, the
        scheme); ``unit`` is the frame (None for a per-project stage).
    """

    name: str
    func: Callable
    params_cls: type
    version: int
    inputs: tuple[str, ...]
    per_frame: bool = True
    gather: Callable | None = None
    context: Callable | None = None


#: the project's stages in execution order: (stage name, module, entry function, Params class, inputs)
REGISTRY = (
    ("detect", "stages.detect", "detect_beads", "DetectParams", ("frame",)),
    ("centroid", "stages.centroid", "centroid_beads", "CentroidParams", ("frame", "detect")),
)


def default_stages() -> list[Stage]:
    """The stages of a calibration, in topological order."""
    stages = []
    for name, module, entry, params, inputs in REGISTRY:
        mod = importlib.import_module(module)
        stages.append(Stage(name, getattr(mod, entry), getattr(mod, params), int(mod.VERSION), inputs))
    return stages


def stage_params_classes() -> dict[str, type]:
    """Config section name -> Params class, for validating ``[detect]`` etc."""
    return {s.name: s.params_cls for s in default_stages()}


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
        seen.add(stage.name)
