"""Labelling benchmark on varied sequences (issue 12): layouts, motion and hidden markers fluorocal was not tuned on.

Each configuration is a one-system turntable sequence of the simulator's cube (494 beads, strong
distortion) with the turntable's axis wobbling by up to 5 deg, shifts of up to +-20 mm across the floor
and +-15 mm in height (so up to 40 mm between neighbouring frames), steps of 9-10 deg, and one frame in
ten with 1 to all of its markers hidden. The marker layouts differ from the default (8 markers in fixed
slots): 6 or 3 markers drawn at random among the beads, or none (6 seeds clicked on the first frame only).
Every configuration runs over several simulator seeds (each seed another layout and motion).

Detections come from the simulator's geometric truth made detection-like by
``tests.stages.test_label.detections_from_truth``, as in ``benchmarks/label.py`` (0.05 px centroid
noise, 1 % dropouts, heavily overlapping beads merged, 20 % of the merged blobs kept, one spurious blob
per frame, beads at the field edge not detected). Each sequence is labelled by ``label_sequence``, as
``fluorocal run`` does.

Figures per configuration and overall:
- labelled: clean beads (detected as a single bead, no other bead's outline centre within one mean
  diameter, not at the field edge) that received their correct id, over all frames, failed frames
  included — target >= 99 %;
- wrong: labelled detections whose id is not the true one — target <= 0.05 %;
- lost: failed frames with a labelled neighbour on each side (or on its one side, at a sequence's
  end) — target 0;
- failed: all failed frames, and their reasons.

A few rendered frames go through the stage graph's detect + centroid (``graph_run.py``, as ``fluorocal run``)
and ``label_sequence`` as a cross-check (``--rendered``).

``--cut K`` labels each sequence in pieces of K frames, each on its own (seeds on each piece's first frame
in the seeded configuration): short sequences, where a frame has few neighbours or none.

``--steps`` shares each configuration's labelling time (CPU) out among its costly steps (:data:`STEPS`), over all
frames and on the slowest: where the time goes.

``--outcomes`` counts the searches' full labellings (from their starts, from rivals) and the distinct labellings they
reach: how many of them a search could have spared.

Run: .venv/bin/python benchmarks/label_varied.py [--frames 40] [--seeds 3] [--rendered 6] [--cut K] [--slowest N]
[--steps] [--outcomes]
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluorocal.stages.kinds.labelling import label_sequence  # noqa: E402
from fluorocal.stages.label import LabelParams, cube, prior, rivals, sequence, votes  # noqa: E402
from fluorocal.stages.label.iterate import agreement  # noqa: E402
from fluorocal.stages.simulate import SimulateParams, simulate  # noqa: E402

from tests.stages.test_label import detections_from_truth, seeds_from_truth, unambiguous_ids  # noqa: E402

#: the motion of every configuration (issue 12): wobble, shifts, one frame in ten with hidden markers
MOTION = dict(
    turntable_wobble_deg=5.0,
    turntable_translation_mm=20.0,
    turntable_height_mm=15.0,
    hidden_marker_fraction=0.1,
    distortion="strong",
)
#: (name, SimulateParams overrides, seeds on frame 0)
CONFIGS = (
    ("6 random markers, 9 deg steps", dict(marker_layout="random", n_markers=6, turntable_step_deg=9.0), False),
    ("3 random markers, 10 deg steps", dict(marker_layout="random", n_markers=3, turntable_step_deg=10.0), False),
    ("no markers, seeds on frame 0, 9 deg", dict(marker_layout="random", n_markers=0, turntable_step_deg=9.0), True),
    ("8 fixed markers, 10 deg steps", dict(turntable_step_deg=10.0), False),
    # most frames' markers do not suffice alone (as on an independent simulator's set, issue 31): 3 random
    # markers, 1 to 3 of them hidden in 80 % of the frames, steps of 12 deg; most frames are labelled
    # through their neighbours
    (
        "3 random markers, 80 % hidden, 12 deg",
        dict(marker_layout="random", n_markers=3, turntable_step_deg=12.0, hidden_marker_fraction=0.8),
        False,
    ),
    # turntable steps from a face-on view (0, 15, 30 deg, ...): the near and far walls' beads pair up and merge, so
    # a right labelling leaves beads undetected that are clear of the ambiguity gate
    ("8 fixed markers, 15 deg steps from face-on", dict(turntable_step_deg=15.0), False),
)
#: the labelling's steps that ``--steps`` times: (step, function, the modules whose calls of it are timed). None of
#: them calls another, so their times add up; the rest is the searches' own work (grids, turn scans, settling).
STEPS = (
    ("full labellings", "iterate", (cube, prior, rivals)),
    ("evidence", "evidence", (prior, rivals)),
    ("coarse evidence", "coarse_evidence", (prior,)),
    ("polish", "polish", (prior, rivals)),
    ("shift strengths", "shift_strengths", (prior, votes)),
    ("shift peaks", "shift_peaks", (prior, rivals, votes)),
)
#: CPU seconds of each step while :func:`steps_timed` is on
STEP_SECONDS: collections.Counter = collections.Counter()


@contextlib.contextmanager
def steps_timed():
    """While inside, the :data:`STEPS` add their CPU seconds to :data:`STEP_SECONDS` (the functions restored after)."""

    def timed(step, inner):
        @functools.wraps(inner)
        def call(*args, **kwargs):
            t = time.process_time()
            try:
                return inner(*args, **kwargs)
            finally:
                STEP_SECONDS[step] += time.process_time() - t

        return call

    saved = [(module, name, getattr(module, name)) for _, name, modules in STEPS for module in modules]
    for step, name, modules in STEPS:
        for module in modules:
            setattr(module, name, timed(step, getattr(module, name)))
    try:
        yield
    finally:
        for module, name, inner in saved:
            setattr(module, name, inner)


#: every full labelling while :func:`outcomes_recorded` is on: (where it started, its result or None)
OUTCOMES: list = []


@contextlib.contextmanager
def outcomes_recorded():
    """While inside, the searches' full labellings (from starts, from rivals) are appended to :data:`OUTCOMES`."""

    def recorded(site, inner):
        @functools.wraps(inner)
        def call(*args, **kwargs):
            result = inner(*args, **kwargs)
            OUTCOMES.append((site, result))
            return result

        return call

    saved = [(prior, prior.iterate), (rivals, rivals.iterate)]
    prior.iterate, rivals.iterate = recorded("start", prior.iterate), recorded("rival", rivals.iterate)
    try:
        yield
    finally:
        for module, inner in saved:
            module.iterate = inner


def outcome_counts(calls: list) -> collections.Counter:
    """Full labellings in ``calls`` (of :data:`OUTCOMES`) by where they started, and how many distinct ones they reach.

    Two labellings are one outcome when each gives 90 % of its labelled detections the other's bead (as the search
    merges them).
    """
    distinct: list = []
    for _, result in calls:
        if result is not None and not any(
            agreement(result, d) >= 0.9 and agreement(d, result) >= 0.9 for d in distinct
        ):
            distinct.append(result)
    sites = collections.Counter(f"{site} labellings" for site, _ in calls)
    return sites + collections.Counter({"distinct outcomes": len(distinct)})


@dataclass
class Tally:
    """Counts over the frames of one configuration."""

    frames: int = 0
    failed: int = 0
    recovered: int = 0
    lost: int = 0
    eligible: int = 0
    correct: int = 0
    labels: int = 0
    wrong: int = 0
    seconds: float = 0.0
    slowest: float = 0.0
    # (CPU s, seed, frame, how it was labelled, CPU s per step) of every frame: where the slowest frames are
    timings: list = field(default_factory=list)

    def add_sequence(self, labs, dets, fts, seconds: list, reasons: dict) -> None:
        self.seconds += sum(seconds)
        self.slowest = max(self.slowest, *seconds)
        ok = [lab.ok for lab in labs]
        for i, (lab, (_, ids), ft) in enumerate(zip(labs, dets, fts)):
            self.frames += 1
            eligible = np.intersect1d(unambiguous_ids(ft), ids)
            self.eligible += len(eligible)
            if not lab.ok:
                self.failed += 1
                neighbours = [ok[j] for j in (i - 1, i + 1) if 0 <= j < len(labs)]
                self.lost += all(neighbours)
                # the last attempt's reason (from the neighbouring frames), numbers masked
                last = lab.reason.split("from the neighbouring frames: ")[-1]
                key = re.sub(r"[0-9.]+", "N", last)[:110]
                reasons[key] = reasons.get(key, 0) + 1
                continue
            truth = ids[lab.det_index]
            self.recovered += lab.pose_source == "prior"
            self.labels += len(lab)
            self.wrong += int((truth != lab.bead_id).sum())
            self.correct += int(np.isin(eligible, lab.bead_id[truth == lab.bead_id]).sum())

    def merge(self, other: "Tally") -> None:
        slowest = max(self.slowest, other.slowest)
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.slowest = slowest

    def row(self, name: str) -> str:
        pct = 100.0 * self.correct / max(self.eligible, 1)
        wrong = 100.0 * self.wrong / max(self.labels, 1)
        ms = 1e3 * self.seconds / max(self.frames, 1)
        return (
            f"{name:<38} {self.frames:>6} {self.failed:>6} {self.recovered:>5} {self.lost:>5} {self.eligible:>8} "
            f"{pct:>8.2f}% {self.labels:>8} {self.wrong:>6} {wrong:>7.3f}% {ms:>7.0f} {1e3 * self.slowest:>7.0f}"
        )


HEADER = (
    f"{'configuration':<38} {'frames':>6} {'failed':>6} {'nbour':>5} {'lost':>5} {'eligible':>8} {'labelled':>9} "
    f"{'labels':>8} {'wrong':>6} {'wrong%':>8} {'ms/fr':>7} {'max ms':>7}"
)


def label_params(sp: SimulateParams) -> LabelParams:
    return LabelParams(
        source_image_distance_mm=sp.source_image_distance_mm,
        pixel_pitch_mm=sp.pixel_pitch_mm,
        image_size_px=(sp.image_size_px,) * 2,
    )


def timed_sequence(cents, phantom, params, seeds_by_frame) -> tuple[tuple, list, list]:
    """``label_sequence``, the CPU seconds spent on each frame (its own attempt and every retry), and their steps'.

    Every attempt at a frame goes through ``label_bead_frame`` (alone, from its neighbours, weighed as a suspect):
    its calls are timed per frame; the sequence's own bookkeeping between them is shared out evenly. The steps'
    seconds (a Counter per frame) are those :func:`steps_timed` counts, empty without it.
    """
    per_frame = [0.0] * len(cents)
    steps = [collections.Counter() for _ in cents]
    index = {id(c): i for i, c in enumerate(cents)}
    inner = sequence.label_bead_frame

    def timed(centroids, *args, **kwargs):
        t, before, n_outcomes = time.process_time(), STEP_SECONDS.copy(), len(OUTCOMES)
        try:
            return inner(centroids, *args, **kwargs)
        finally:
            per_frame[index[id(centroids)]] += time.process_time() - t
            steps[index[id(centroids)]].update(STEP_SECONDS - before)
            steps[index[id(centroids)]].update(outcome_counts(OUTCOMES[n_outcomes:]))
            del OUTCOMES[n_outcomes:]

    t0 = time.process_time()
    sequence.label_bead_frame = timed
    try:
        labs = label_sequence(cents, phantom, params, seeds_by_frame)
    finally:
        sequence.label_bead_frame = inner
    rest = (time.process_time() - t0 - sum(per_frame)) / max(len(cents), 1)
    return labs, [s + rest for s in per_frame], steps


def label_table(labs) -> dict:
    """The labels of a sequence as arrays (per frame: ok, detection indices, bead ids), for comparing runs."""
    out = {}
    for i, lab in enumerate(labs):
        out[f"{i}.ok"] = np.array(lab.ok)
        out[f"{i}.det"] = np.asarray(lab.det_index)
        out[f"{i}.id"] = np.asarray(lab.bead_id)
    return out


def run_config(
    overrides: dict, seeded: bool, seeds: list, n_frames: int, reasons: dict, cut: int = 0, tables: dict | None = None
) -> Tally:
    """One configuration over the simulator ``seeds``: detections from the truth, labelled as a sequence.

    ``cut``: each sequence cut into sequences of that many frames, each labelled on its own (seeded: seeds
    on the first frame of each). ``tables`` receives each sequence's :func:`label_table`.
    """
    tally = Tally()
    for seed in seeds:
        sp = SimulateParams(n_frames=n_frames, seed=seed, **{**MOTION, **overrides})
        data = simulate(sp, render=False)
        fts = data.truth.frames[0]
        rng = np.random.default_rng([seed, 12])
        dets = [detections_from_truth(ft, rng, merged_keep=0.2) for ft in fts]
        step = cut or n_frames
        for a in range(0, n_frames, step):
            piece = slice(a, a + step)
            frame_seeds = {0: seeds_from_truth(fts[a], rng)} if seeded else {}
            labs, seconds, steps = timed_sequence(
                [c for c, _ in dets[piece]], data.phantom, label_params(sp), frame_seeds
            )
            tally.add_sequence(labs, dets[piece], fts[piece], seconds, reasons)
            tally.timings += [
                (s, seed, a + i, lab.pose_source if lab.ok else "failed", st)
                for i, (s, lab, st) in enumerate(zip(seconds, labs, steps))
            ]
            if tables is not None:
                tables.update({f"{seed}.{a}.{k}": v for k, v in label_table(labs).items()})
    return tally


def rendered_check(overrides: dict, n_frames: int, seed: int, tables: dict) -> tuple[str, list]:
    """Rendered frames of one configuration through the graph's detect + centroid, then ``label_sequence``.

    Ids against the truth. Returns the summary and each frame's labelling time (CPU s); ``tables`` receives the
    :func:`label_table`.
    """
    from graph_run import simulated_outputs

    sp = SimulateParams(n_frames=n_frames, seed=seed, **{**MOTION, **overrides})
    t = time.perf_counter()
    data = simulate(sp)
    t_render = time.perf_counter() - t
    cents = simulated_outputs(data, "centroid", names=())["centroid"][0]
    labs, seconds, _ = timed_sequence(cents, data.phantom, label_params(sp), {})
    tables.update({f"rendered.{k}": v for k, v in label_table(labs).items()})
    n_failed = n_labels = n_wrong = n_found = n_visible = 0
    for lab, ft, c in zip(labs, data.truth.frames[0], cents):
        found, _, _ = ft.match(c.xy_px[c.ok])
        n_visible += int(ft.visible.sum())
        n_found += int(found.sum())
        if not lab.ok:
            n_failed += 1
            continue
        pos = {b: k for k, b in enumerate(ft.ids)}
        # a label is right when its detection lies within a quarter diameter of that bead's true outline centre
        k = np.array([pos.get(b, -1) for b in lab.bead_id])
        d = np.linalg.norm(ft.outline_xy_px[np.maximum(k, 0)] - lab.xy_px, axis=1)
        n_labels += len(lab)
        n_wrong += int(np.sum((k < 0) | (d > 0.25 * ft.diameter_px[np.maximum(k, 0)])))
    return (
        f"{n_frames} frames rendered in {t_render:.0f} s: {n_failed} failed, {n_labels} labels "
        f"({n_found} of {n_visible} non-overlapping beads detected), {n_wrong} wrong; labelling "
        f"{1e3 * np.mean(seconds):.0f} ms per frame, slowest {1e3 * max(seconds):.0f} ms"
    ), seconds


def compare_tables(tables: dict, reference: dict) -> str:
    """Whether ``tables`` hold the labels of ``reference`` (frames labelled, detections, ids): a one-line verdict."""
    keys = set(tables) | set(reference)
    differ = sorted({k.rsplit(".", 1)[0] for k in keys if not np.array_equal(tables.get(k), reference.get(k))})
    shown = ", ".join(differ[:8]) + (" ..." if len(differ) > 8 else "")
    return "yes" if not differ else f"no ({len(differ)} frames differ: {shown})"


def slowest_frames(tally: Tally, n: int) -> str:
    """The ``n`` slowest frames of ``tally``: seed, frame, CPU ms and how each was labelled (or failed)."""
    top = sorted(tally.timings, key=lambda t: -t[0])[:n]
    return ", ".join(f"seed {seed} frame {i} {1e3 * s:.0f} ms ({how})" for s, seed, i, how, _ in top)


def step_shares(tally: Tally) -> str:
    """The share of ``tally``'s CPU time in each of the :data:`STEPS`, over all frames and on the slowest one."""
    total = sum(t[0] for t in tally.timings)
    steps = sum((t[4] for t in tally.timings), collections.Counter())
    s, seed, i, _, slow = max(tally.timings, key=lambda t: t[0])
    shares = ", ".join(f"{step} {100 * steps[step] / max(total, 1e-9):.0f} %" for step, _, _ in STEPS)
    ms = ", ".join(f"{step} {1e3 * slow[step]:.0f}" for step, _, _ in STEPS)
    return f"{shares}; slowest frame (seed {seed} frame {i}, {1e3 * s:.0f} ms): {ms} ms"


def outcome_summary(tally: Tally) -> str:
    """The full labellings of ``tally``'s frames and the distinct labellings they reach, overall and per frame."""
    counts = [t[4] for t in tally.timings]
    total = sum(counts, collections.Counter())
    n, d = total["start labellings"] + total["rival labellings"], total["distinct outcomes"]
    most = max(counts, key=lambda c: c["start labellings"] + c["rival labellings"])
    return (
        f"{n} full labellings ({total['start labellings']} from starts, {total['rival labellings']} from rivals) reach "
        f"{d} distinct labellings ({n / max(d, 1):.2f} per distinct one); the frame with the most: "
        f"{most['start labellings']} + {most['rival labellings']} reach {most['distinct outcomes']}"
    )


def print_config(name: str, tally: Tally, args) -> None:
    """One configuration's row, and the lines its options ask for (slowest frames, steps, outcomes)."""
    print(tally.row(name), flush=True)
    if args.slowest:
        print(f"  slowest: {slowest_frames(tally, args.slowest)}", flush=True)
    if args.steps:
        print(f"  steps (CPU): {step_shares(tally)}", flush=True)
    if args.outcomes:
        print(f"  outcomes: {outcome_summary(tally)}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40, help="exposures per sequence (default: 40)")
    ap.add_argument("--seeds", type=int, default=3, help="simulator seeds per configuration (default: 3)")
    ap.add_argument(
        "--rendered", type=int, default=6, help="rendered frames of the first configuration (default: 6; 0 = skip)"
    )
    ap.add_argument(
        "--cut",
        type=int,
        default=0,
        help="cut each sequence into sequences of this many frames, labelled each on its own (default: 0 = uncut)",
    )
    ap.add_argument("--configs", type=int, nargs="*", help="configurations to run, by index (default: all)")
    ap.add_argument("--slowest", type=int, default=0, help="list each configuration's N slowest frames (default: 0)")
    ap.add_argument("--steps", action="store_true", help="share each configuration's time out among the steps")
    ap.add_argument(
        "--outcomes", action="store_true", help="count the full labellings and the distinct labellings they reach"
    )
    ap.add_argument("--save-labels", metavar="NPZ", help="write every frame's labels here (for --reference)")
    ap.add_argument("--reference", metavar="NPZ", help="compare every frame's labels with those saved by --save-labels")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    configs = [CONFIGS[i] for i in args.configs] if args.configs is not None else list(CONFIGS)
    tables: dict = {}
    seeds = list(range(args.seeds))
    print(
        f"{len(configs)} configurations x {args.seeds} seeds x {args.frames} frames; motion: wobble "
        f"+-{MOTION['turntable_wobble_deg']:.0f} deg, shifts +-{MOTION['turntable_translation_mm']:.0f} mm "
        f"(height +-{MOTION['turntable_height_mm']:.0f} mm), markers hidden in "
        f"{MOTION['hidden_marker_fraction']:.0%} of frames"
        + (f"; cut into sequences of {args.cut}" if args.cut else "")
    )
    print()
    print(HEADER)
    total = Tally()
    all_reasons = []
    for name, overrides, seeded in configs:
        reasons: dict = {}
        config_tables: dict = {}
        with steps_timed() if args.steps else contextlib.nullcontext():
            with outcomes_recorded() if args.outcomes else contextlib.nullcontext():
                tally = run_config(overrides, seeded, seeds, args.frames, reasons, args.cut, config_tables)
        tables.update({f"{name}.{k}": v for k, v in config_tables.items()})
        print_config(name, tally, args)
        total.merge(tally)
        all_reasons += [(name, r, n) for r, n in reasons.items()]
    print(total.row("overall"))
    for name, reason, n in all_reasons:
        print(f"  {name}: {n} frames failed: {reason}")
    if args.rendered:
        name, overrides, _ = CONFIGS[0]
        print()
        summary, seconds = rendered_check(overrides, args.rendered, 100, tables)
        print(f"rendered cross-check ({name}, seed 100): {summary}")
        total.slowest = max(total.slowest, *seconds)
        total.seconds += sum(seconds)
        total.frames += len(seconds)
    pct = 100.0 * total.correct / max(total.eligible, 1)
    wrong = 100.0 * total.wrong / max(total.labels, 1)
    print()
    print(
        f"targets (overall): labelled >= 99 %: {'met' if pct >= 99.0 else 'NOT met'} ({pct:.2f} %); "
        f"wrong <= 0.05 %: {'met' if wrong <= 0.05 else 'NOT met'} ({wrong:.3f} %); "
        f"no frame lost between labelled neighbours: {'met' if total.lost == 0 else 'NOT met'} ({total.lost} lost)"
    )
    ms = 1e3 * total.seconds / max(total.frames, 1)
    print(
        f"speed (all {total.frames} frames, 1024 px, CPU): mean {ms:.0f} ms per frame <= 50: "
        f"{'met' if ms <= 50 else 'NOT met'}; slowest {1e3 * total.slowest:.0f} ms <= 1000: "
        f"{'met' if total.slowest <= 1.0 else 'NOT met'}"
    )
    if args.save_labels:
        np.savez_compressed(args.save_labels, **tables)
    if args.reference:
        with np.load(args.reference) as ref:
            verdict = compare_tables(tables, {k: ref[k] for k in ref.files})
        print(f"same labels as reference: {verdict}, wrong: {total.wrong}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
