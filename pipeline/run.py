"""Execution of the stage graph over a project's frames, with the artifact cache.

Keys are computed for every (stage, frame) first, from the frames' content
hashes up; only entries missing from the cache (or forced) are computed, and
an upstream artifact is read only when something downstream must be
recomputed. A corrupt entry found on reading is recomputed with a warning.
A per-system stage (label) is computed for a whole system at once, on its
frames in exposure order, and stores one artifact per frame.

The per-frame stages that need only the frame and each other (detect,
centroid) run first, on a local process pool or a Dask cluster when
``[compute]`` asks for one (:mod:`fluorocal.parallel`); then a per-system
stage's systems side by side on the local pool, one process per system; the
main process alone writes their entries.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import sys
import time
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

from fluorocal.artifact_codec import artifact_types, decode, stage_kinds
from fluorocal.cache import ArtifactCache, artifact_key, file_sha256
from fluorocal.compute import ComputeConfig
from fluorocal.config import Config, params_from_dict
from fluorocal.graph import SOURCES, Stage, check_graph, downstream
from fluorocal.stages.errors import CalibError, InputError
from fluorocal.units import FrameUnit, frame_units

log = logging.getLogger(__name__)


@dataclass
class RunReport:
    """What a run did: per stage, how many artifacts were computed and how many came from the cache.

    ``outcomes[stage][unit]`` is ``"computed"`` or ``"cached"``; an artifact counted
    cached and then recomputed (its entry turned out unreadable) counts computed.
    """

    outcomes: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)

    def record(self, stage: str, units, how: str) -> None:
        """Count ``units`` of ``stage`` as ``how`` (``"computed"`` or ``"cached"``); computed is final."""
        slots = self.outcomes.setdefault(stage, {})
        for unit in units:
            if slots.get(unit) != "computed":
                slots[unit] = how

    @property
    def computed(self) -> dict:
        return {name: sum(h == "computed" for h in slots.values()) for name, slots in self.outcomes.items()}

    @property
    def cached(self) -> dict:
        return {name: sum(h == "cached" for h in slots.values()) for name, slots in self.outcomes.items()}

    @property
    def total_computed(self) -> int:
        return sum(self.computed.values())

    def lines(self) -> list[str]:
        out = []
        computed, cached = self.computed, self.cached
        for name in self.outcomes:
            c, k = computed[name], cached[name]
            took = f" in {self.seconds.get(name, 0.0):.2f} s" if c else ""
            out.append(f"{name}: {c} computed{took}, {k} cached")
        if not self.total_computed:
            out.append(f"nothing recomputed: all {sum(cached.values())} artifacts were cached")
        return out


@lru_cache(maxsize=2)
def _read_file_frames(path: Path, content_sha256: str):
    """All frames of a file whose content is ``content_sha256`` before and after the read (:mod:`~fluorocal.steady`)."""
    from fluorocal.steady import read_steady

    return read_steady(path, content_sha256)


def stage_params(stage: Stage, config: Config, unit: FrameUnit | None, units: list[FrameUnit]):
    """The stage's Params from its config section, with the fields its context fills from the project."""
    params = params_from_dict(
        stage.params_cls, config.stage_params.get(stage.name, {}), where=f"{config.path.name}: [{stage.name}] "
    )
    if stage.context is not None:
        params = dataclasses.replace(params, **stage.context(config, unit, units))
    return params


class Runner:
    """Runs ``stages`` over ``config``'s frames with ``cache``.

    Parameters
    ----------
    force : set of str
        Stages to recompute even when cached (their downstream stages follow).
    until : str, optional
        Last stage to run.
    progress : bool
        Show progress bars (on a terminal).
    compute : ComputeConfig, optional
        Where the per-frame stages run (default: the config's ``[compute]``).
    start_pool : bool
        Start the local pool's fork server before planning when the cache holds no entry of the first
        per-frame stage (a first run): its imports overlap the planning (``fluorocal run``).
    """

    def __init__(
        self,
        config: Config,
        stages: list[Stage],
        cache: ArtifactCache,
        *,
        force=(),
        until=None,
        progress=True,
        compute: ComputeConfig | None = None,
        start_pool: bool = False,
    ):
        check_graph(stages)
        names = [s.name for s in stages]
        unknown = [n for n in list(force) + ([until] if until else []) if n not in names]
        if unknown:
            raise InputError(f"unknown stage {unknown[0]!r}; stages are {', '.join(names)}")
        if until:
            stages = stages[: names.index(until) + 1]
        self.config, self.stages, self.cache = config, stages, cache
        # what entries may decode into (these stages' artifact classes), and what each stage's entries hold
        cache.register(artifact_types(stages), stage_kinds(stages))
        self.by_name = {s.name: s for s in stages}
        self.force = downstream(stages, set(force)) if force else set()
        self.progress = progress
        self.compute = compute if compute is not None else config.compute
        if start_pool:
            self._start_pool_early()
        self.units = frame_units(config)
        self.phantom_key = self._phantom_key()
        self.keys: dict[tuple[str, int | None], str] = {}
        self.params: dict[tuple[str, int | None], tuple] = {}  # (Params, extras) of each slot, as hashed
        self.memory: dict[tuple[str, int | None], object] = {}
        self.codes: dict[str, str] = {}  # stage name -> digest of the code that computes it
        self.report = RunReport()
        self.code_memo = cache.code_memo()  # the code analyses of earlier runs: kept by run()
        self._plan()

    # --- keys ---------------------------------------------------------------------------------

    def _phantom_key(self) -> str:
        ph = self.config.phantom
        content = file_sha256(ph.file) if ph.file else ""
        return hashlib.sha256(f"{content}:{ph.lattice}:{ph.pitch_mm}".encode()).hexdigest()

    def _input_key(self, name: str, unit: int | None) -> list[str]:
        if name == "frame":
            return [self.units[unit].key]
        if name == "phantom":
            return [self.phantom_key]
        if self.by_name[name].per_frame and unit is None:
            return [self.keys[(name, u)] for u in range(len(self.units))]
        return [self.keys[(name, unit if self.by_name[name].per_frame else None)]]

    def _plan(self) -> None:
        for stage in self.stages:
            code = self.codes[stage.name] = stage.code_digest(self.code_memo)
            if stage.per_system:
                self._plan_systems(stage, code)
                continue
            for unit in self._stage_units(stage):
                inputs = [k for name in stage.inputs for k in self._input_key(name, unit)]
                if not stage.per_frame:  # the grouping of frames is part of what a gathering stage sees
                    inputs.append(
                        repr([(u.system, u.exposure) for u in self.units]) + repr([s.name for s in self.config.systems])
                    )
                params = stage_params(stage, self.config, None if unit is None else self.units[unit], self.units)
                extras = stage.extras(self.config, self.units) if stage.extras else {}
                self.params[(stage.name, unit)] = (params, extras)
                self.keys[(stage.name, unit)] = artifact_key(stage.name, code, {"params": params, **extras}, inputs)

    def _plan_systems(self, stage: Stage, code: str) -> None:
        """Keys of a per-system stage: each frame's covers every input of its system, in exposure order."""
        for group in self._systems():
            units = [self.units[u] for u in group]
            params = stage_params(stage, self.config, None, units)
            extras = stage.extras(self.config, units) if stage.extras else {}
            inputs = [k for name in stage.inputs for k in self._group_input_keys(name, group)]
            for position, unit in enumerate(group):
                self.params[(stage.name, unit)] = (params, extras)
                where = f"frame {position} of {len(group)}"
                self.keys[(stage.name, unit)] = artifact_key(
                    stage.name, code, {"params": params, **extras}, [*inputs, where]
                )

    def _systems(self) -> list[list[int]]:
        """Per system with frames: the indices of its units, in exposure order."""
        groups: dict[int, list[int]] = {}
        for i, unit in enumerate(self.units):
            groups.setdefault(unit.system, []).append(i)
        return [sorted(g, key=lambda i: self.units[i].exposure) for g in groups.values()]

    def _group_input_keys(self, name: str, group: list[int]) -> list[str]:
        if name == "phantom" or (name != "frame" and not self.by_name[name].per_frame):
            return self._input_key(name, None)
        return [k for u in group for k in self._input_key(name, u)]

    def _stage_units(self, stage: Stage) -> list[int | None]:
        return list(range(len(self.units))) if stage.per_frame else [None]

    # --- execution ----------------------------------------------------------------------------

    def run(self) -> RunReport:
        """Compute every entry missing from the cache (or unreadable there); the cache is complete afterwards."""
        from tqdm import tqdm

        self.cache.prepare_root()
        self.code_memo.save()
        self.cache.sweep()
        self.cache.record_use(self.config.path, {(name, key) for (name, _), key in self.keys.items()})
        todo = {}
        for stage in self.stages:
            units = self._stage_units(stage)
            pending = [
                u
                for u in units
                if stage.name in self.force or not self.cache.verify(stage.name, self.keys[(stage.name, u)])
            ]
            todo[stage.name] = pending
            missing = set(pending)
            self.report.record(stage.name, [u for u in units if u not in missing], "cached")
            self.report.outcomes.setdefault(stage.name, {})
        self._run_frame_stages(todo)
        self._run_system_stages(todo)
        for stage in self.stages:
            units = todo[stage.name]
            if stage.per_system:  # one computation per system with a frame to do
                units = [g[0] for g in self._systems() if set(g) & set(units)]
            bar = tqdm(
                units,
                desc=f"{stage.name:>9}",
                unit="system" if stage.per_system else "frame" if stage.per_frame else "run",
                leave=False,
                disable=not (self.progress and sys.stderr.isatty()) or not units,
            )
            for unit in bar:
                self._compute(stage, unit)
        for line in self.report.lines():
            log.info(line)
        return self.report

    # --- the per-frame stages on workers ------------------------------------------------------

    def pool_modules(self) -> tuple[str, ...]:
        """The modules of the stages the local pool may run (the frame chain's, the per-system ones'): its preload."""
        chain = self.frame_chain()
        return tuple(dict.fromkeys(s.func.__module__ for s in self.stages if s in chain or s.per_system))

    def _start_pool_early(self) -> None:
        """Start the pool's fork server if this run will certainly use it: a first run of enough frame files."""
        from fluorocal.parallel import MIN_POOL_FRAMES, start_fork_server

        chain = self.frame_chain()
        files = sum(len(system.frames) for system in self.config.systems)
        if self.compute.scheduler or self.compute.workers < 2 or files < MIN_POOL_FRAMES or not chain:
            return
        if not self.cache.keys(chain[0].name):
            start_fork_server(self.compute, self.pool_modules())

    def frame_chain(self) -> list[Stage]:
        """The per-frame stages whose inputs are the frame and each other: what workers can compute alone."""
        chain: list[Stage] = []
        for stage in self.stages:
            if stage.per_frame and not stage.per_system and all(i == "frame" or i in chain for i in stage.inputs):
                chain.append(stage.name)
        return [self.by_name[name] for name in chain]

    def _run_frame_stages(self, todo: dict[str, list]) -> None:
        """Compute the frame chain's missing entries on the pool or cluster, if ``compute`` asks for one.

        In this process, a frame at a time (:meth:`_run_frames_here`), with ``jobs = 1`` and
        when a local pool would get fewer than :data:`~fluorocal.parallel.MIN_POOL_FRAMES` frames to do.
        """
        from fluorocal.parallel import MIN_POOL_FRAMES, run_tasks

        chain = self.frame_chain()
        units = sorted({u for stage in chain for u in todo[stage.name]})
        local = not self.compute.scheduler
        if not units:
            return
        if local and (self.compute.workers < 2 or len(units) < MIN_POOL_FRAMES):
            self._run_frames_here(chain, todo, units)
            return
        tasks = self._frame_tasks(chain, todo, units)
        where = self.compute.scheduler or f"{min(self.compute.workers, len(tasks))} local processes"
        log.info("%s: %d frames on %s", ", ".join(s.name for s in chain), len(units), where)
        for results in run_tasks(tasks, self.compute, preload=self.pool_modules()):
            for result in results:
                self._accept(result)
        for stage in chain:
            todo[stage.name] = []

    def _run_frames_here(self, chain: list[Stage], todo: dict[str, list], units: list[int]) -> None:
        """The frame chain in this process, one frame at a time: each frame is read once for all its stages.

        (Stage by stage, every frame was read again by each stage that takes it: detect, then centroid.)
        """
        from tqdm import tqdm

        pending = {s.name: set(todo[s.name]) for s in chain}
        shown = self.progress and sys.stderr.isatty()
        desc = f"{'+'.join(s.name for s in chain):>9}"
        for u in tqdm(units, desc=desc, unit="frame", leave=False, disable=not shown):
            for stage in chain:
                if u in pending[stage.name]:
                    self._compute(stage, u)
        for stage in chain:
            todo[stage.name] = []

    def _frame_tasks(self, chain: list[Stage], todo: dict[str, list], units: list[int]) -> list:
        """One task per file (split so a multi-frame file gives every worker some), in unit order."""
        from fluorocal.parallel import FrameJob, FrameTask, Step

        pending = {s.name: set(todo[s.name]) for s in chain}
        by_file: dict[Path, list] = {}
        for u in units:
            steps = tuple(
                Step(s, *self.params[(s.name, u)], code=self.codes[s.name]) for s in chain if u in pending[s.name]
            )
            computed = {step.stage.name for step in steps}
            needed = {i for step in steps for i in step.stage.inputs if i != "frame" and i not in computed}
            given = {name: self.get(name, u) for name in sorted(needed)}
            by_file.setdefault(self.units[u].path, []).append(
                FrameJob(u, self.units[u].index, self.units[u].label, steps, given)
            )
        chunk = max(1, -(-len(units) // (4 * max(1, self.compute.workers))))
        on_cluster = bool(self.compute.scheduler)
        return [
            FrameTask(
                str(path),
                self.units[jobs[0].unit].file_sha256,
                tuple(jobs[i : i + chunk]),
                on_cluster,
                self.compute.threads,
            )
            for path, jobs in by_file.items()
            for i in range(0, len(jobs), chunk)
        ]

    # --- the per-system stages' systems side by side -------------------------------------------

    def _run_system_stages(self, todo: dict[str, list]) -> None:
        """Compute each per-system stage's missing systems on the local pool, one task per system.

        In this process (as :meth:`run` goes on), on a cluster, with ``jobs = 1``, for a single system to do
        and for fewer than :data:`~fluorocal.parallel.MIN_POOL_FRAMES` frames.
        """
        from fluorocal.parallel import MIN_POOL_FRAMES, on_local_pool, run_system_task

        if self.compute.scheduler or self.compute.workers < 2:
            return
        for stage in (s for s in self.stages if s.per_system):
            groups = {g[0]: g for g in self._systems() if set(g) & set(todo[stage.name])}
            if len(groups) < 2 or sum(map(len, groups.values())) < MIN_POOL_FRAMES:
                continue
            tasks = [self._system_task(stage, group) for group in groups.values()]
            workers = min(self.compute.workers, len(tasks))
            log.info("%s: %d systems on %d local processes", stage.name, len(tasks), workers)
            for result in on_local_pool(run_system_task, tasks, self.compute, preload=self.pool_modules()):
                for message, category in result.warnings:
                    warnings.warn(message, category, stacklevel=2)
                artifacts = [decode(tree, arrays, self.cache.types) for tree, arrays in result.outputs]
                self._keep_system(stage, groups[result.unit], artifacts, result.seconds)
            todo[stage.name] = []

    def _system_task(self, stage: Stage, group: list[int]):
        """The task of a per-system stage on the system of units ``group``: its parameters and inputs travel."""
        from fluorocal.parallel import Step, SystemTask

        step = Step(stage, *self.params[(stage.name, group[0])], code=self.codes[stage.name])
        inputs = tuple(self._group_input(name, group) for name in stage.inputs)
        return SystemTask(group[0], self._system_name(group), step, inputs)

    def _system_name(self, group: list[int]) -> str:
        return self.config.systems[self.units[group[0]].system].name

    def _accept(self, result) -> None:
        """Decode, store and keep a worker's artifacts of one frame; re-raise its warnings here."""
        for message, category in result.warnings:
            warnings.warn(message, category, stacklevel=2)
        for name, tree, arrays, took in result.outputs:
            artifact = decode(tree, arrays, self.cache.types)
            params, _ = self.params[(name, result.unit)]
            self._keep(self.by_name[name], result.unit, artifact, params, took)
            self.report.seconds[name] = self.report.seconds.get(name, 0.0) + took  # the workers' time, summed

    def get(self, name: str, unit: int | None):
        """The artifact of ``name`` for ``unit`` (a frame index, or None for per-project stages)."""
        if name == "frame":
            u = self.units[unit]
            return _read_file_frames(u.path, u.file_sha256)[u.index]
        if name == "phantom":
            return self._phantom()
        stage = self.by_name[name]
        slot = (name, unit if stage.per_frame else None)
        if slot in self.memory:
            return self.memory[slot]
        if name not in self.force:
            artifact = self.cache.load(name, self.keys[slot])
            if artifact is not None:
                self.memory[slot] = artifact
                return artifact
        return self._compute(stage, slot[1])

    def _phantom(self):
        from fluorocal.stages.artifacts import Phantom
        from fluorocal.stages.io import read_phantom

        ph = self.config.phantom
        if ph.file:
            return read_phantom(ph.file, lattice=ph.lattice, pitch_mm=ph.pitch_mm)
        return Phantom([], [], [], [], ph.lattice, ph.pitch_mm)

    def inputs(self, stage: Stage, unit: int | None) -> list:
        """What ``stage``'s function is called with for ``unit``, in its order (upstream artifacts computed if missing).

        A per-project stage takes its first input gathered (``stage.gather``) and its other per-frame ones as lists.
        """
        inputs = []
        for i, name in enumerate(stage.inputs):
            per_frame_input = name == "frame" or (name not in SOURCES and self.by_name[name].per_frame)
            if unit is None and per_frame_input:
                artifacts = [self.get(name, u) for u in range(len(self.units))]
                inputs.append(stage.gather(self.units, artifacts, self.config) if i == 0 else artifacts)
            else:
                inputs.append(self.get(name, unit))
        return inputs

    def _compute(self, stage: Stage, unit: int | None):
        """Compute (and store) the artifact of ``stage`` for ``unit``, under the entry's lock.

        Another process may have stored the entry while this one waited for the
        lock: then it is read, not computed again.
        """
        if stage.per_system:
            self._compute_system(stage, next(g for g in self._systems() if unit in g))
            return self.memory[(stage.name, unit)]
        slot = (stage.name, unit)
        with self.cache.lock(stage.name, self.keys[slot]):
            if stage.name not in self.force:
                artifact = self.cache.load(stage.name, self.keys[slot], warn=False)
                if artifact is not None:
                    self.memory[slot] = artifact
                    self.report.record(stage.name, [unit], "cached")
                    return artifact
            return self._compute_one(stage, unit)

    def _compute_one(self, stage: Stage, unit: int | None):
        slot = (stage.name, unit)
        params, extras = self.params[slot]
        inputs = self.inputs(stage, unit)
        t0 = time.perf_counter()
        try:
            artifact = stage.func(*inputs, params, **extras, **self.run_options(stage))
        except CalibError as exc:
            where = f"{self.units[unit].label}: " if unit is not None else ""
            raise type(exc)(f"{where}{stage.name}: {exc}") from exc
        took = time.perf_counter() - t0
        self._keep(stage, unit, artifact, params, took)
        self.report.seconds[stage.name] = self.report.seconds.get(stage.name, 0.0) + took
        return artifact

    def run_options(self, stage: Stage) -> dict:
        """What ``stage``'s function is given besides its inputs, parameters and extras: not hashed into its key.

        A stage that takes it (:attr:`~fluorocal.graph.Stage.takes_workers`) gets the run's worker count.
        """
        return {"workers": self.compute.workers} if stage.takes_workers else {}

    def _keep(self, stage: Stage, unit: int | None, artifact, params, took: float) -> None:
        """Store ``artifact`` (computed in ``took`` s) with its provenance, keep it in memory and count it."""
        provenance = self._provenance(stage, unit, params, took)
        self._store(stage.name, self.keys[(stage.name, unit)], artifact, provenance)
        self.memory[(stage.name, unit)] = artifact
        self.report.record(stage.name, [unit], "computed")

    def _provenance(self, stage: Stage, unit: int | None, params, took: float) -> dict:
        frame = {} if unit is None else {"frame": {"file": str(self.units[unit].path), "index": self.units[unit].index}}
        code, inputs, p = self.codes[stage.name], list(stage.inputs), dataclasses.asdict(params)
        return {"code_digest": code, "params": p, "inputs": inputs, "wall_seconds": took, **frame}

    def _store(self, name: str, key: str, artifact, provenance: dict) -> None:
        """Store an entry; a cache that cannot be written (full, read-only) loses the entry, never the result."""
        try:
            self.cache.store(name, key, artifact, provenance=provenance)
        except OSError as exc:  # kept in memory: the run goes on and publishes what it computed
            log.warning("could not cache %s/%s (%s); kept for this run, recomputed next time", name, key[:12], exc)

    def _compute_system(self, stage: Stage, group: list[int]) -> None:
        """Compute a per-system stage on the system of units ``group`` and store each frame's artifact.

        Under the lock of the system's first entry; if another process stored the
        whole system meanwhile, its entries are read instead.
        """
        with self.cache.lock(stage.name, self.keys[(stage.name, group[0])]):
            if stage.name not in self.force:
                found = [self.cache.load(stage.name, self.keys[(stage.name, u)], warn=False) for u in group]
                if all(a is not None for a in found):
                    self.memory.update({(stage.name, u): a for u, a in zip(group, found)})
                    self.report.record(stage.name, group, "cached")
                    return
            self._compute_system_now(stage, group)

    def _compute_system_now(self, stage: Stage, group: list[int]) -> None:
        from fluorocal.parallel import compute_sequence

        params, extras = self.params[(stage.name, group[0])]
        inputs = [self._group_input(name, group) for name in stage.inputs]
        artifacts, took = compute_sequence(stage, inputs, params, extras, self._system_name(group))
        self._keep_system(stage, group, artifacts, took)

    def _keep_system(self, stage: Stage, group: list[int], artifacts, took: float) -> None:
        """Store a per-system stage's ``artifacts`` (one per frame) of the units ``group``, computed in ``took`` s."""
        system = self._system_name(group)
        if len(artifacts) != len(group):
            raise CalibError(f"system {system}: {stage.name} gave {len(artifacts)} artifacts for {len(group)} frames")
        params, _ = self.params[(stage.name, group[0])]
        for position, (unit, artifact) in enumerate(zip(group, artifacts)):
            provenance = self._provenance(stage, unit, params, took)
            provenance["sequence"] = {"system": system, "position": position, "n_frames": len(group)}
            self._store(stage.name, self.keys[(stage.name, unit)], artifact, provenance)
            self.memory[(stage.name, unit)] = artifact
        self.report.record(stage.name, group, "computed")
        self.report.seconds[stage.name] = self.report.seconds.get(stage.name, 0.0) + took

    def _group_input(self, name: str, group: list[int]):
        if name == "phantom" or (name != "frame" and not self.by_name[name].per_frame):
            return self.get(name, None)
        return [self.get(name, u) for u in group]

    def status(self) -> list[dict]:
        """Per stage: key(s), status (cached / stale / missing) and size, without computing anything."""
        rows = []
        for stage in self.stages:
            keys = [self.keys[(stage.name, u)] for u in self._stage_units(stage)]
            # intact entries only: a tampered or corrupt one is what `run` recomputes, not "cached"
            present = [k for k in keys if self.cache.verify(stage.name, k, warn=False)]
            others = set(self.cache.keys(stage.name)) - set(keys)
            status = "cached" if len(present) == len(keys) else ("stale" if others or present else "missing")
            size = sum(self.cache.size_bytes(stage.name, k) for k in present)
            summary = ""
            if present:
                manifest = self.cache.manifest(stage.name, present[-1])
                summary = (manifest or {}).get("summary", "")
            rows.append(
                {
                    "stage": stage.name,
                    "key": keys[0][:12] if keys else "",
                    "n": len(keys),
                    "cached": len(present),
                    "status": status,
                    "bytes": size,
                    "summary": summary,
                }
            )
        return rows
