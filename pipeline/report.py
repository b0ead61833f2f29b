"""Plots of a calibration for people: residual maps, the learned field, convergence, per-frame RMS.

Each function draws one PNG with matplotlib's non-interactive backend and
writes it atomically; :func:`write_report` ties them into ``report.md``.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from fluorocal.stages.io import write_png


def rms_px(residual_px: np.ndarray) -> float:
    """RMS per coordinate of ``(N, 2)`` residuals, px (NaN when empty)."""
    return float(np.sqrt(np.mean(residual_px**2))) if len(residual_px) else float("nan")


def new_figure(n_panels: int = 1, *, width: float = 5.0, height: float = 4.6):
    """``(pyplot, figure, axes)``: ``n_panels`` side by side, each ``width`` x ``height`` inches (Agg, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, n_panels, figsize=(width * n_panels, height), squeeze=False, layout="constrained")
    return plt, fig, axes[0]


def save_figure(plt, fig, path: Path) -> Path:
    """Write ``fig`` to ``path`` as a PNG (atomically), close it, and return ``path``."""
    png = io.BytesIO()
    fig.savefig(png, dpi=90, format="png")
    plt.close(fig)
    write_png(path, png.getvalue())
    return path


def image_axes(ax, size_px, title):
    """Set ``ax`` to show an image of ``size_px = (w, h)`` in pixel coordinates, y down, with ``title``."""
    w, h = size_px
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)  # y down, as in the image
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")


def residual_maps(path: Path, panels: list[tuple[str, np.ndarray, np.ndarray]], size_px: tuple[int, int]) -> Path:
    """Residual vectors over the image on one colour scale; a panel per ``(title, xy (N, 2), residual (N, 2))``, px."""
    plt, fig, axes = new_figure(len(panels))
    vmax = max((np.percentile(np.linalg.norm(r, axis=1), 99) for _, _, r in panels if len(r)), default=1.0)
    for ax, (title, xy, res) in zip(axes, panels):
        mag = np.linalg.norm(res, axis=1)
        rms = rms_px(res)
        sc = ax.scatter(xy[:, 0], xy[:, 1], c=mag, s=2, cmap="viridis", vmin=0, vmax=vmax)
        step = max(len(xy) // 1500, 1)
        ax.quiver(
            xy[::step, 0],
            xy[::step, 1],
            res[::step, 0],
            res[::step, 1],
            angles="xy",
            color="k",
            width=0.002,
            scale=vmax * 25,
        )
        image_axes(ax, size_px, f"{title}\nRMS {rms:.3f} px per coordinate")
    fig.colorbar(sc, ax=list(axes), label="|residual| (px)", shrink=0.8)
    return save_figure(plt, fig, path)


def field_map(path: Path, field, title: str) -> Path:
    """The learned correction ``Δ``: magnitude image with arrows, unsupported nodes hatched out."""
    plt, fig, (ax,) = new_figure(1, width=6.0, height=5.2)
    mag = np.linalg.norm(field.delta_px, axis=-1)
    extent = (field.x_nodes_px[0], field.x_nodes_px[-1], field.y_nodes_px[-1], field.y_nodes_px[0])
    im = ax.imshow(np.where(field.support, mag, np.nan), extent=extent, cmap="magma", interpolation="bilinear")
    xx, yy = np.meshgrid(field.x_nodes_px, field.y_nodes_px)
    step = max(len(field.x_nodes_px) // 24, 1)
    sel = (slice(None, None, step), slice(None, None, step))
    if field.delta_px.any():  # arrows of a zero field (scheme none) have no length to scale: matplotlib divides by 0
        ax.quiver(
            xx[sel],
            yy[sel],
            field.delta_px[sel][..., 0],
            field.delta_px[sel][..., 1],
            angles="xy",
            color="c",
            width=0.003,
        )
    image_axes(ax, (field.width_px, field.height_px), title)
    fig.colorbar(im, ax=ax, label="|Δ| (px)", shrink=0.8)
    return save_figure(plt, fig, path)


def field_sigma_map(path: Path, field, title: str) -> Path:
    """The learned field's per-node σ (``sigma_px``), unsupported nodes left blank (docs/uncertainties.md)."""
    plt, fig, (ax,) = new_figure(1, width=6.0, height=5.2)
    extent = (field.x_nodes_px[0], field.x_nodes_px[-1], field.y_nodes_px[-1], field.y_nodes_px[0])
    im = ax.imshow(np.where(field.support, field.sigma_px, np.nan), extent=extent, cmap="viridis")
    image_axes(ax, (field.width_px, field.height_px), title)
    fig.colorbar(im, ax=ax, label="σ of Δ per component (px)", shrink=0.8)
    return save_figure(plt, fig, path)


def convergence(path: Path, history) -> Path:
    """Combined cost (equations 2 + 3) and inlier RMS per iteration of the alternation (the paper's Fig. 5)."""
    plt, fig, (ax1, ax2) = new_figure(2, width=4.6, height=3.6)
    it = [h.iteration for h in history]
    ax1.plot(it, [h.cost_total for h in history], "o-")
    ax1.set_xlabel("iteration")
    ax1.set_ylabel("cost (eq. 2 + eq. 3)")
    ax1.set_title("convergence", fontsize=10)
    ax2.plot(it, [h.rms_px for h in history], "o-", color="C1")
    ax2.set_xlabel("iteration")
    ax2.set_ylabel("inlier RMS (px, in-sample)")
    ax2.set_title("residual RMS", fontsize=10)
    return save_figure(plt, fig, path)


def frame_rms(path: Path, labels: list[str], before: np.ndarray, after: np.ndarray) -> Path:
    """Per-frame inlier residual RMS (px, in-sample) before and after the learned correction."""
    plt, fig, (ax,) = new_figure(1, width=max(5.0, 0.12 * len(labels) + 2), height=3.6)
    x = np.arange(len(labels))
    ax.bar(x - 0.2, before, 0.4, label="no correction")
    ax.bar(x + 0.2, after, 0.4, label="calibrated")
    ax.set_xticks(x)
    ax.set_xticklabels(labels, rotation=90, fontsize=6)
    ax.set_ylabel("RMS (px, in-sample)")
    ax.legend()
    return save_figure(plt, fig, path)
