"""Toy stages for testing the orchestrator: cheap, pure, and counting their calls."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fluorocal.graph import Stage
from fluorocal.stages.artifacts import freeze
from fluorocal.stages.io import write_still

CALLS: Counter = Counter()


@dataclass(frozen=True)
class Value:
    value: np.ndarray
    note: str = ""

    def __post_init__(self):
        object.__setattr__(self, "value", np.asarray(self.value, dtype=np.float64))
        freeze(self)

    def to_table(self):
        return ["value"], [[float(v)] for v in self.value.ravel()]


@dataclass(frozen=True)
class MeanParams:
    offset: float = 0.0


@dataclass(frozen=True)
class ScaleParams:
    factor: float = 2.0


@dataclass(frozen=True)
class TotalParams:
    pass


def mean(radiograph, params: MeanParams) -> Value:
    CALLS["mean"] += 1
    return Value(np.array([radiograph.image.mean() + params.offset]), note=Path(radiograph.source).name)


def scale(value: Value, params: ScaleParams) -> Value:
    CALLS["scale"] += 1
    return Value(value.value * params.factor)


def total(values: Value, params: TotalParams) -> Value:
    CALLS["total"] += 1
    return Value(np.array([values.value.sum()]))


@dataclass(frozen=True)
class RunningParams:
    start: float = 0.0


def running(values: list, params: RunningParams) -> tuple[Value, ...]:
    """A per-system toy: the running sum over a system's frames, so each frame depends on those before it."""
    CALLS["running"] += 1
    out, acc = [], params.start
    for v in values:
        acc += float(v.value.sum())
        out.append(Value(np.array([acc])))
    return tuple(out)


def gather(units, artifacts, config) -> Value:
    return Value(np.concatenate([a.value for a in artifacts]))


def toy_stages() -> list[Stage]:
    return [
        Stage("mean", mean, MeanParams, ("frame",)),
        Stage("scale", scale, ScaleParams, ("mean",)),
        Stage("total", total, TotalParams, ("scale",), per_frame=False, gather=gather),
    ]


def sequence_stages() -> list[Stage]:
    return [
        Stage("mean", mean, MeanParams, ("frame",)),
        Stage("running", running, RunningParams, ("mean",), per_system=True),
        Stage("total", total, TotalParams, ("running",), per_frame=False, gather=gather),
    ]


def make_two_system_project(root: Path, n_frames: int = 3, extra_toml: str = "") -> Path:
    """Systems A and B of ``n_frames`` constant frames each (A: 100, 200, ...; B: 1000, 2000, ...)."""
    for name, scale in (("A", 100), ("B", 1000)):
        (root / "frames" / name).mkdir(parents=True, exist_ok=True)
        for i in range(n_frames):
            write_still(root / "frames" / name / f"f{i}.tif", np.full((8, 10), scale * (i + 1), np.uint16))
    (root / "phantom.csv").write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n4,0,0,10\n")
    systems = "".join(
        f'\n[[systems]]\nname = "{name}"\nframes = "frames/{name}/*.tif"\n'
        "source_image_distance = 1100\npixel_pitch = 0.25\n"
        for name in ("A", "B")
    )
    cfg = root / "project.toml"
    cfg.write_text('[phantom]\nfile = "phantom.csv"\n' + systems + extra_toml)
    return cfg


def make_project(root: Path, n_frames: int = 3, extra_toml: str = "") -> Path:
    """A tiny project: n 16-bit TIFF frames of constant value, a phantom CSV and a config."""
    (root / "frames").mkdir(parents=True, exist_ok=True)
    for i in range(n_frames):
        write_still(root / "frames" / f"f{i}.tif", np.full((8, 10), 100 * (i + 1), np.uint16))
    (root / "phantom.csv").write_text("id,x,y,z\n1,0,0,0\n2,10,0,0\n3,0,10,0\n4,0,0,10\n")
    cfg = root / "project.toml"
    cfg.write_text(
        '[phantom]\nfile = "phantom.csv"\n\n[[systems]]\nname = "A"\nframes = "frames/*.tif"\n'
        "source_image_distance = 1100\npixel_pitch = 0.25\n" + extra_toml
    )
    return cfg
