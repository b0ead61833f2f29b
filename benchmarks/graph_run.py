"""Stage outputs for the benchmarks, computed through the stage graph as ``fluorocal run`` computes them.

A benchmark that measures one stage takes that stage's inputs from here, never by calling the earlier
stages' functions itself: a simulated data set is written as a project (``fluorocal simulate``'s layout,
:func:`fluorocal.cmd_simulate.write_dataset`), the graph (:func:`fluorocal.graph.default_stages`) runs up to
a stage by :class:`fluorocal.run.Runner` into the project's cache, and the artifacts are read back by
:meth:`fluorocal.run.Runner.get`. So a benchmark's detections carry what the graph gives them (the bead
appearance estimated once per system, the frames as decoded from their files).

- :func:`simulated_outputs`: a simulated data set's artifacts of the named stages, per system and exposure;
- :func:`run_until`: a project (a config on disk) run up to a stage; its runner, to read artifacts from;
- :func:`per_system`, :func:`labelled_observations`: a run's artifacts per system, its labelled observations;
- :func:`stage_call`: a per-project stage's function and what the graph calls it with, to time it alone.

Not every benchmark starts from frames: those of the learning (``learn.py``, ``biplanar.py``, ``robust.py``,
``order_and_limit.py``, ``uncertainty.py``, ``evaluate.py``) hand it observations made from the simulator's
truth (true outline centres + known noise) and those of the labelling (``label.py``, ``label_varied.py``)
detections made from the truth: no earlier stage runs there, so that the figure is the measured stage's alone.
"""

from __future__ import annotations

import tempfile
from pathlib import Path


def write_project(data, root: Path) -> Path:
    """Write the simulated ``data`` as a project in ``root`` (an earlier set's frames replaced); its config's path."""
    from fluorocal.cmd_simulate import write_dataset

    write_dataset(data, root, replace=True)
    return root / "fluorocal.toml"


def runner_for(config_path: Path, until: str, *, cache_dir: Path | None = None, compute=None):
    """A :class:`~fluorocal.run.Runner` of the project at ``config_path`` up to stage ``until`` (nothing run yet).

    ``cache_dir`` replaces the project's cache folder; ``compute`` (a ``ComputeConfig``) its ``[compute]``.
    """
    from fluorocal.cache import ArtifactCache
    from fluorocal.config import load_config
    from fluorocal.graph import default_stages, stage_params_classes
    from fluorocal.run import Runner

    config = load_config(config_path, stage_params_allowed=stage_params_classes())
    cache = ArtifactCache(config.cache_dir if cache_dir is None else cache_dir)
    return Runner(config, default_stages(), cache, until=until, progress=False, compute=compute)


def run_until(config_path: Path, until: str):
    """Run the project at ``config_path`` up to stage ``until`` (into its cache); the runner that ran it."""
    runner = runner_for(config_path, until)
    runner.run()
    return runner


def per_system(runner, name: str) -> list[list]:
    """The artifacts of stage ``name`` (or the source ``"frame"``: the frames as decoded) as ``[system][exposure]``."""
    out: list[list] = [[] for _ in runner.config.systems]
    for u in sorted(range(len(runner.units)), key=lambda u: (runner.units[u].system, runner.units[u].exposure)):
        out[runner.units[u].system].append(runner.get(name, u))
    return out


def simulated_outputs(data, until: str, names=("frame",)) -> dict[str, list[list]]:
    """``data`` (a simulated data set) through the graph up to ``until``: ``until``'s and ``names``' artifacts.

    The project is written to a temporary folder, removed afterwards. Returns ``{name: [system][exposure]}``
    for ``until`` and every name in ``names`` (stages up to ``until``, or ``"frame"``).
    """
    with tempfile.TemporaryDirectory(prefix="fluorocal-bench-") as tmp:
        runner = run_until(write_project(data, Path(tmp)), until)
        return {name: per_system(runner, name) for name in dict.fromkeys((*names, until))}


def labelled_observations(runner):
    """The observations table of a run up to ``label`` (or later), as the learn stage gathers it."""
    from fluorocal.gather import observations_from_labels

    labels = [runner.get("label", u) for u in range(len(runner.units))]
    return observations_from_labels(runner.units, labels, runner.config)


def stage_call(config_path: Path, name: str) -> tuple:
    """``(func, inputs, params, extras)`` of the per-project stage ``name``: ``func(*inputs, params, **extras)``.

    Every stage before it is run first (and cached), as ``fluorocal run --until`` the one before would run it;
    the inputs are what the graph hands the stage, and ``extras`` its hashed extras with the run's options (the
    worker count of a stage that takes one, :meth:`~fluorocal.run.Runner.run_options`).
    """
    from fluorocal.graph import default_stages

    names = [s.name for s in default_stages()]
    if names.index(name) > 0:  # the first stage has nothing before it to run
        run_until(config_path, names[names.index(name) - 1])
    runner = runner_for(config_path, name)
    stage = runner.by_name[name]
    params, extras = runner.params[(name, None)]
    return stage.func, runner.inputs(stage, None), params, {**extras, **runner.run_options(stage)}
