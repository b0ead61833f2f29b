"""Outputs of ``fluorocal evaluate``: the scores as a CSV, a Markdown table like the paper's TABLE I, and plots.

Written as one set into the evaluation folder (:func:`fluorocal.outputs.publish`):
``evaluation.csv`` (one row per scheme and training size), ``evaluation.md`` (the
table, the peers' wins, how it was made) and ``evaluation_*.png`` (each figure
against the training size, one line per scheme; the improvement over no calibration;
per system the held-out residuals of every scheme at the largest training size).
"""

from __future__ import annotations

import dataclasses
import math
import textwrap
from pathlib import Path

from fluorocal.outputs import inside, publish, safe_name
from fluorocal.report import new_figure, residual_maps, save_figure
from fluorocal.stages.io import write_csv
from fluorocal.stages.learn.params import Scheme


def headline(scores) -> str:
    """The out-of-sample 3D figure of these scores: two-ray mean when biplanar, else check points (rigid)."""
    if any(s.tworay_pairs for s in scores):
        return "tworay_mean_mm"
    if any(math.isfinite(s.out_3d_rigid_mm) for s in scores):
        return "out_3d_rigid_mm"
    return "out_rms_px"


def peer_wins(scores, ours: str, part) -> list[str]:
    """One line per (figure of the kind's ``part``, training size) where a peer's is lower than scheme ``ours``'s."""
    lines = []
    by = {(s.scheme, s.n_train): s for s in scores}
    unit = part.trained_on
    for name, heading in part.figures.items():
        for s in scores:
            mine = by.get((ours, s.n_train))
            if s.scheme == ours or mine is None:
                continue
            theirs, own = getattr(s, name), getattr(mine, name)
            if math.isfinite(theirs) and math.isfinite(own) and theirs < own:
                lines.append(
                    f"- peer **{s.scheme}** beats {ours} on {heading} with {s.n_train} training {unit}: "
                    f"{theirs:.4f} against {own:.4f}"
                )
    return lines


def _cell(value) -> str:
    if isinstance(value, float):
        return "" if not math.isfinite(value) else f"{value:.4f}"
    return str(value)


def markdown(scores, ours: str, notes: list[str], part) -> str:
    """The table (TABLE I's columns where they apply), the improvement of each scheme over ``none``, the peers' wins.

    ``part``: the pipeline part of the phantom's kind (:class:`~fluorocal.kinds.KindPart`), which says the
    figures compared, the table's RMS columns and what a training size counts.
    """
    key = headline(scores)
    names = part.figures
    base = {s.n_train: getattr(s, key) for s in scores if s.scheme == Scheme.NONE}
    biplanar = any(s.tworay_pairs for s in scores)
    checks = any(math.isfinite(s.out_3d_rigid_mm) for s in scores)
    head = [f"training {part.trained_on}", "scheme"]
    cols = []
    if biplanar:
        cols += ["tworay_x_rmse_mm", "tworay_y_rmse_mm", "tworay_z_rmse_mm", "tworay_avg_rmse_mm", "tworay_mean_mm"]
        head += ["X RMSE (mm)", "Y RMSE (mm)", "Z RMSE (mm)", "average RMSE (mm)", "mean 3D (mm)"]
    if checks:
        cols += ["in_3d_rigid_mm", "in_3d_similarity_mm", "out_3d_rigid_mm", "out_3d_similarity_mm"]
        head += ["in-sample 3D rigid (mm)", "in-sample 3D similarity (mm)", "out-of-sample 3D rigid (mm)"]
        head += ["out-of-sample 3D similarity (mm)"]
    cols += list(part.rms_columns)
    head += list(part.rms_columns.values())
    head += [f"% improvement ({names[key]})", "wall (s)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    previous = None
    for s in scores:
        b = base.get(s.n_train, math.nan)
        better = 100 * (1 - getattr(s, key) / b) if s.scheme != Scheme.NONE and math.isfinite(b) and b > 0 else math.nan
        size = str(s.n_train) if s.n_train != previous else ""
        previous = s.n_train
        shown = f"{better:.1f}" if math.isfinite(better) else "N/A"
        row = [size, s.scheme, *(_cell(getattr(s, c)) for c in cols), shown, f"{s.wall_s:.1f}"]
        lines.append("| " + " | ".join(row) + " |")
    wins = peer_wins(scores, ours, part)
    lines += ["", *(wins or [f"No peer beats {ours} on any figure at any training size."])]
    return "\n".join(["# Evaluation", "", *notes, "", *lines, ""])


def write_csv_table(path: Path, scores) -> Path:
    """``evaluation.csv``: every :class:`~fluorocal.stages.evaluate.Score` field, one row per scheme and size."""
    names = [f.name for f in dataclasses.fields(scores[0])]
    write_csv(path, names, ([_cell(getattr(s, n)) for n in names] for s in scores))
    return path


def write_plots(folder: Path, scores, ours: str, part) -> list[Path]:
    """Each applicable figure of the kind's ``part`` against the training size, a line per scheme; gain over none."""
    from matplotlib.ticker import FixedLocator, MaxNLocator

    headings = part.figures
    names = [n for n in headings if any(math.isfinite(getattr(s, n)) for s in scores)]
    schemes = list(dict.fromkeys(s.scheme for s in scores))
    sizes = sorted({s.n_train for s in scores})

    def size_ticks():  # a training size is a whole number: each size a tick, or whole numbers where they crowd
        return FixedLocator(sizes) if len(sizes) <= 8 else MaxNLocator(integer=True)

    fig, axes = new_figure(len(names), width=4.2, height=3.6, n_cols=min(3, len(names)), title_lines=2)
    for ax, name in zip(axes, names):
        for scheme in schemes:
            rows = [s for s in scores if s.scheme == scheme]
            ax.plot([s.n_train for s in rows], [getattr(s, name) for s in rows], "o-", label=scheme)
        ax.set_yscale("log")
        ax.xaxis.set_major_locator(size_ticks())
        ax.set_xlabel(f"training {part.trained_on}")
        ax.set_title(textwrap.fill(headings[name], 36), fontsize=9)  # wider than its panel on one line
    if len(schemes) > 1:
        axes[0].legend(fontsize=8)
    written = [save_figure(fig, inside(folder, "evaluation_errors.png"))]
    key = headline(scores)
    base = {s.n_train: getattr(s, key) for s in scores if s.scheme == Scheme.NONE}
    if base and set(schemes) - {Scheme.NONE}:
        fig, (ax,) = new_figure(1, width=5.0, height=3.8)
        for scheme in schemes:
            rows = [s for s in scores if s.scheme == scheme and s.scheme != Scheme.NONE and s.n_train in base]
            if rows:
                better = [100 * (1 - getattr(s, key) / base[s.n_train]) for s in rows]
                ax.plot([s.n_train for s in rows], better, "o-", label=scheme)
        ax.xaxis.set_major_locator(size_ticks())
        ax.set_xlabel(f"training {part.trained_on}")
        ax.set_ylabel("% improvement over none")
        ax.set_title(headings[key], fontsize=9)
        ax.legend(fontsize=8)
        written.append(save_figure(fig, inside(folder, "evaluation_improvement.png")))
    return written


def write_residual_maps(folder: Path, residuals, system_names, image_size_px, unit: str = "epochs") -> list[Path]:
    """Per system, the held-out inlier residuals of each scheme at the largest training size, a panel each."""
    written = []
    for s, name in enumerate(system_names):
        panels = [
            (f"{r.scheme}, {r.n_train} {unit}, held out", r.xy_px[r.system == s], r.residual_px[r.system == s])
            for r in residuals
        ]
        path = inside(folder, f"evaluation_residuals_{safe_name(name, what='system name')}.png")
        written.append(residual_maps(path, panels, image_size_px[s]))
    return written


def publish_evaluation(
    out_dir: Path, evaluation, ours: str, notes: list[str], *, part, systems, image_size_px, owner
) -> list[Path]:
    """Write the CSV, the Markdown table and the plots into ``out_dir`` as one set, of project ``owner``.

    ``part``: the pipeline part of the phantom's kind (:class:`~fluorocal.kinds.KindPart`), what it scores.
    """
    scores = evaluation.scores

    def write(staging: Path) -> list[Path]:
        md = inside(staging, "evaluation.md")
        md.write_text(markdown(scores, ours, notes, part), encoding="utf-8")
        maps = write_residual_maps(staging, evaluation.residuals, systems, image_size_px, part.trained_on)
        return [
            write_csv_table(inside(staging, "evaluation.csv"), scores),
            md,
            *write_plots(staging, scores, ours, part),
            *maps,
        ]

    return publish(out_dir, write, owner=owner)
