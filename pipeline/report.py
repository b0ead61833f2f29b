"""Plots of a calibration for people: residual maps, the learned field, convergence, per-frame RMS.

Each function draws one PNG with matplotlib's Agg renderer and writes it atomically;
:func:`fluorocal.export_beads.write_report` ties them into ``report.md``.

The figures are laid out once, with margins fixed in inches (:func:`new_figure`), not by a layout
engine: matplotlib draws a figure twice to save it under one (the first draw measures every label),
which made the report's figures cost several seconds of a run. What matplotlib draws item by item (a
marker, a bar, a tick) costs far more than its pixels: thousands of dots are drawn into an image
(:func:`dot_image`), bars into one collection, and an axis' ticks as one line of marks and their labels
(:func:`save_figure`), in the pixels matplotlib's own tick artists would give.
"""

from __future__ import annotations

import functools
import unicodedata
from pathlib import Path

import numpy as np
from fluorocal.compute import no_collection
from fluorocal.stages.errors import InputError
from fluorocal.stages.io import write_png

#: resolution of the PNGs, dots per inch
DPI = 90
#: room left of the panels for the y tick labels (up to 7 characters: "-250000", "0.00025") and axis label, inches
LEFT_IN = 1.0
#: room below the panels for the x tick labels and axis label, inches
BOTTOM_IN = 0.55
#: room above the panels: a margin, and a line per line of the panels' titles, inches
TOP_IN, TITLE_LINE_IN = 0.12, 0.2
#: room right of the panels without a colour bar (half the last x tick label), between panels (a y axis' labels)
#: and for a colour bar, inches
RIGHT_IN, GAP_IN, COLORBAR_IN = 0.35, 1.1, 1.3


def rms_px(residual_px: np.ndarray) -> float:
    """RMS per coordinate of ``(N, 2)`` residuals, px (NaN when empty)."""
    return float(np.sqrt(np.mean(residual_px**2))) if len(residual_px) else float("nan")


def new_figure(
    n_panels: int = 1,
    *,
    width: float = 5.0,
    height: float = 4.6,
    n_cols: int | None = None,
    title_lines: int = 1,
    colorbar: bool = False,
    bottom_in: float = BOTTOM_IN,
):
    """``(figure, axes)``: ``n_panels`` in rows of ``n_cols`` (default: one row), each ``width`` x ``height`` inches.

    ``title_lines`` lines of title above each panel, a colour bar's room on the right when ``colorbar``
    (:func:`add_colorbar`), ``bottom_in`` inches below the panels (more for rotated tick labels:
    :func:`text_height_in`: the figure grows by the extra room, the panels keep their height). The figure is
    matplotlib's own (no pyplot: no global state, nothing to close).
    """
    from matplotlib.figure import Figure

    n_cols = n_cols or n_panels
    n_rows = -(-n_panels // n_cols)
    fig_w, fig_h = width * n_cols, (height + max(0.0, bottom_in - BOTTOM_IN)) * n_rows
    top_in = TOP_IN + TITLE_LINE_IN * title_lines
    left, right = LEFT_IN, COLORBAR_IN if colorbar else RIGHT_IN
    panel_w = (fig_w - left - right - GAP_IN * (n_cols - 1)) / n_cols
    panel_h = (fig_h - bottom_in - top_in - (bottom_in + top_in) * (n_rows - 1)) / n_rows
    fig = Figure(figsize=(fig_w, fig_h), dpi=DPI)
    grid = fig.subplots(
        n_rows,
        n_cols,
        squeeze=False,
        gridspec_kw={
            "left": left / fig_w,
            "right": 1 - right / fig_w,
            "bottom": bottom_in / fig_h,
            "top": 1 - top_in / fig_h,
            "wspace": GAP_IN / panel_w,
            "hspace": (bottom_in + top_in) / panel_h,
        },
    )
    axes = grid.ravel()
    for ax in axes[n_panels:]:
        ax.set_visible(False)
    return fig, axes[:n_panels]


def add_colorbar(fig, mappable, axes, label: str) -> None:
    """A colour bar labelled ``label`` right of ``axes`` (as drawn, with their aspect), 80 % of their height."""
    for ax in axes:
        ax.apply_aspect()  # an equal-aspect image shrinks inside its box: the bar goes beside the image
    boxes = [ax.get_position() for ax in axes]
    x1, y0, y1 = max(b.x1 for b in boxes), min(b.y0 for b in boxes), max(b.y1 for b in boxes)
    fig_w = fig.get_figwidth()
    cax = fig.add_axes((x1 + 0.15 / fig_w, y0 + 0.1 * (y1 - y0), 0.15 / fig_w, 0.8 * (y1 - y0)))
    fig.colorbar(mappable, cax=cax, label=label)


def text_height_in(labels, *, fontsize: float, rotation: float = 90.0) -> float:
    """Height of the tallest of ``labels`` rotated by ``rotation`` degrees, inches: room for rotated tick labels."""
    settings = _text_settings()
    sizes = [_text_size_px(str(s), fontsize, settings) for s in labels]
    a = np.deg2rad(rotation)
    return max((abs(w * np.sin(a)) + abs(h * np.cos(a)) for w, h in sizes), default=0.0) / DPI


def _text_settings() -> tuple:
    """The settings a text's size depends on: matplotlib's ``font.*`` and ``text.*`` rcParams, as a hashable key."""
    from matplotlib import rcParams

    # by key: reading every value would read ``backend``, and resolving that imports pyplot
    return tuple((k, repr(rcParams[k])) for k in sorted(rcParams) if k.startswith(("font.", "text.")))


@functools.lru_cache(maxsize=4096)
def _text_size_px(text: str, fontsize: float, settings: tuple) -> tuple[float, float]:
    """Width and height of ``text`` at ``fontsize`` points, pixels at the PNGs' dpi, under ``settings``.

    Kept: a text costs ~0.2 ms to measure, and a report's figures of each system name the same frames.
    """
    renderer, font = _measurer(fontsize, settings)
    return renderer.get_text_width_height_descent(text, font, ismath=False)[:2]


@functools.lru_cache(maxsize=8)
def _measurer(fontsize: float, settings: tuple):
    """A renderer at the PNGs' dpi (glyphs are hinted) and the font of ``fontsize`` points under ``settings``."""
    from matplotlib.backends.backend_agg import RendererAgg
    from matplotlib.font_manager import FontProperties

    return RendererAgg(1, 1, DPI), FontProperties(size=fontsize)


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` to ``path`` as an RGB PNG (atomically) and return ``path``."""
    import cv2
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    with no_collection():
        for ax in fig.axes:
            if ax.get_visible():
                ax.apply_aspect()  # the ticks of an equal-aspect image's axes depend on its final box
                for axis in (ax.xaxis, ax.yaxis):
                    _plain_ticks(axis, canvas.get_renderer())
        canvas.draw()
    bgr = cv2.cvtColor(np.asarray(canvas.buffer_rgba()), cv2.COLOR_RGBA2BGR)  # opaque: no alpha channel to encode
    # zlib's level 3 on the rows as they are: PNG's prediction filters take twice the time for files about as large
    # (a plot is mostly areas of flat colour; the report's PNGs are 0.8 to 1.1 times the size of filtered ones)
    params = [cv2.IMWRITE_PNG_COMPRESSION, 3, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
    ok, png = cv2.imencode(".png", bgr, params)
    if not ok:
        raise InputError(f"{path}: cannot encode the figure as PNG")
    write_png(path, png.tobytes())
    return path


def _plain_ticks(axis, renderer) -> None:
    """Draw ``axis``' major ticks as one line of marks and a text per label instead of matplotlib's tick artists.

    Matplotlib makes each tick five artists (two marks, two labels, a grid line) and works the ticks out three
    times per draw: a millisecond or more a tick, and a report has a few hundred. Here one tick is made as the
    axis makes it and copied: its marks at every location in one line of markers, its labels as texts of the
    same properties at the same places (the same pixels); the axis label goes beyond the labels as the axis
    puts it. An axis with minor ticks, a grid, an offset text (``1e-5``), no tick in view, no label on its
    label's side or shared with another axes' is left to matplotlib.
    """
    formatter = axis.get_major_formatter()
    locs = np.asarray(axis.get_majorticklocs(), float)
    labels = formatter.format_ticks(locs)  # of every location, as the axis formats them
    to_view = axis.get_transform().transform
    lo, hi = np.sort(to_view(np.asarray(axis.get_view_interval(), float)))
    shown = np.abs(to_view(locs) - (lo + hi) / 2) <= (hi - lo) / 2 * (1 + 2e-10)  # the axis' own test of "in view"
    if not (axis.get_visible() and shown.any()) or len(axis.get_minorticklocs()) or formatter.get_offset():
        return
    ax = axis.axes
    if len((ax.get_shared_x_axes() if axis is ax.xaxis else ax.get_shared_y_axes()).get_siblings(ax)) > 1:
        return  # shared axes share one locator: the NullLocator set below would take the other axes' ticks too
    tick = axis.get_major_ticks(1)[0]  # the model
    near = tick.label1 if axis.get_label_position() in ("bottom", "left") else tick.label2
    if tick.gridline.get_visible() or not near.get_visible():
        return
    from matplotlib.lines import Line2D
    from matplotlib.text import Text
    from matplotlib.ticker import NullLocator

    locs, labels = locs[shown], [text for text, s in zip(labels, shown) if s]
    is_x = axis is axis.axes.xaxis
    for mark in (m for m in (tick.tick1line, tick.tick2line) if m.get_visible()):
        line = Line2D([], [])
        line.update_from(mark)
        at = np.full(len(locs), (mark.get_ydata() if is_x else mark.get_xdata())[0], float)
        line.set_data((locs, at) if is_x else (at, locs))
        _add_unclipped(axis, line)
    boxes = []
    for model in (m for m in (tick.label1, tick.label2) if m.get_visible()):
        for loc, label in zip(locs, labels):
            text = Text(text=label)
            text.update_from(model)
            text.set_rotation_mode(model.get_rotation_mode())
            text.set_position((loc, model.get_position()[1]) if is_x else (model.get_position()[0], loc))
            _add_unclipped(axis, text)
            if model is near:
                boxes.append(text.get_window_extent(renderer))
    axis.set_major_locator(NullLocator())  # no tick of its own any more
    _place_label(axis, boxes, renderer)


def _add_unclipped(axis, artist) -> None:
    """Put ``artist`` on ``axis``' axes at the axis' z-order, not clipped to the axes (as ticks are).

    The axis' z-order, not its tick parts' own (2 and 3): matplotlib draws every tick when it draws the axis
    (1.5 by default, below lines), so that a marker drawn unclipped across the spine covers the tick marks.
    """
    axis.axes.add_artist(artist)
    artist.set_clip_on(False)
    artist.set_zorder(axis.get_zorder())


def _place_label(axis, boxes, renderer) -> None:
    """Put ``axis``' label ``labelpad`` points beyond its spine and its tick labels' ``boxes``, as matplotlib does."""
    from matplotlib.transforms import Bbox

    side = axis.get_label_position()
    box = Bbox.union([*boxes, axis.axes.spines.get(side, axis.axes).get_window_extent(renderer)])
    pad = axis.labelpad * axis.axes.figure.dpi / 72  # not get_figure(root=True): matplotlib 3.10 and later only
    x, y = axis.label.get_position()
    beyond = {
        "bottom": (x, box.y0 - pad),
        "top": (x, box.y1 + pad),
        "left": (box.x0 - pad, y),
        "right": (box.x1 + pad, y),
    }
    axis.set_label_coords(*beyond[side], transform=axis.label.get_transform())


def dot_image(ax, xy: np.ndarray, rgba: np.ndarray, diameter_px: float) -> np.ndarray:
    """An RGBA image of ``ax``'s box at the figure's resolution holding a round dot per point.

    ``xy`` in ``ax``'s data coordinates (N, 2), ``rgba`` the dots' colours (N, 4) in [0, 1], ``diameter_px`` at
    the figure's dpi. The dots are drawn at twice the resolution and averaged down (antialiased edges); where
    dots overlap, one of them covers the others (as a scatter plot draws them).
    """
    box = ax.get_window_extent()  # after the axes' aspect is applied
    w, h = max(int(round(box.width)), 1), max(int(round(box.height)), 1)
    # the nearest sub-pixel (2 per pixel) to each centre, counted right and down from the box's top-left corner
    p = ax.transData.transform(xy) - [box.x0, box.y0]
    col = np.round(2 * p[:, 0] * w / box.width - 0.5).astype(np.int64)
    row = np.round(2 * (box.height - p[:, 1]) * h / box.height - 0.5).astype(np.int64)
    # a disc of the dots' diameter in sub-pixels; the centres kept are at most m outside the box, drawn on a
    # canvas with a margin of 2 m, so no disc reaches past the canvas' edge into the next row
    m = int(diameter_px) + 1
    span = np.arange(-m, m + 1)
    dr, dc = (a.ravel() for a in np.meshgrid(span, span, indexing="ij"))
    disc = np.hypot(dr, dc) <= diameter_px
    tall, wide = 2 * h + 4 * m, 2 * w + 4 * m
    stamp = dr[disc] * wide + dc[disc]
    keep = (col >= -m) & (col < 2 * w + m) & (row >= -m) & (row < 2 * h + m)
    colours = np.round(255 * np.asarray(rgba)[keep]).astype(np.uint8).view(np.uint32).ravel()  # RGBA packed
    fine = np.zeros(tall * wide, np.uint32)
    at = (row[keep] + 2 * m) * wide + col[keep] + 2 * m
    fine[(at[:, None] + stamp).ravel()] = np.repeat(colours, len(stamp))
    fine = fine.view(np.uint8).reshape(tall, wide, 4)[2 * m : 2 * m + 2 * h, 2 * m : 2 * m + 2 * w]
    # the mean of each pixel's 4 sub-pixels: their sum (exact in 16 bits) / 4, in single precision: matplotlib then
    # draws the image in single precision, in 0.6 of the time (in double, 0.4 % of the pixels, at dots' edges, are
    # one level of 255 apart)
    covered = sum(fine[i::2, j::2].astype(np.uint16) for i in (0, 1) for j in (0, 1))
    image = covered.astype(np.float32) / np.float32(4 * 255)  # colours weighted by their cover (premultiplied)
    alpha = image[..., 3:]
    image[..., :3] /= np.where(alpha > 0, alpha, np.float32(1))  # matplotlib takes colours not weighted by alpha
    return image


def image_axes(ax, size_px, title):
    """Set ``ax`` to show an image of ``size_px = (w, h)`` in pixel coordinates, y down, with ``title``."""
    w, h = size_px
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)  # y down, as in the image
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=10, y=1.0)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")


def residual_maps(path: Path, panels: list[tuple[str, np.ndarray, np.ndarray]], size_px: tuple[int, int]) -> Path:
    """Residual vectors over the image on one colour scale; a panel per ``(title, xy (N, 2), residual (N, 2))``, px."""
    fig, axes = new_figure(len(panels), title_lines=2, colorbar=True)
    vmax = max((np.percentile(np.linalg.norm(r, axis=1), 99) for _, _, r in panels if len(r)), default=1.0)
    vmax = vmax if vmax > 0 else 1.0  # residuals all 0 (or nan): no scale of their own, no arrow of length 0 / 0
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    norm, w, h = Normalize(0, vmax), *size_px
    for ax, (title, xy, res) in zip(axes, panels):
        mag = np.linalg.norm(res, axis=1)
        rms = rms_px(res)
        image_axes(ax, size_px, f"{title}\nRMS {rms:.3f} px per coordinate")
        ax.apply_aspect()
        # filled dots as large as matplotlib's default dot of s=2 with its 1 pt edge: sqrt(5.83) pt across
        dots = dot_image(ax, xy, colormaps["viridis"](norm(mag)), np.sqrt(5.83) * DPI / 72)
        ax.imshow(dots, extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="nearest", aspect="equal")
        # up to 1500 arrows, vmax 1/25 of the axes' width long; one shorter than its shaft is wide (0.002 of the axes'
        # width) matplotlib draws as a speck that wide (0.6 px) on its dot: left out (most of a calibrated map's)
        width, scale = 0.002, vmax * 25
        step = max(len(xy) // 1500, 1)
        shown = np.flatnonzero(mag[::step] >= scale * width) * step
        if len(shown):
            ax.quiver(*xy[shown].T, *res[shown].T, angles="xy", color="k", width=width, scale=scale)
    add_colorbar(fig, ScalarMappable(norm, "viridis"), axes, "|residual| (px)")
    return save_figure(fig, path)


def field_map(path: Path, field, title: str) -> Path:
    """The learned correction ``Δ``: magnitude image with arrows, unsupported nodes hatched out."""
    fig, (ax,) = new_figure(1, width=6.0, height=5.2, colorbar=True)
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
    add_colorbar(fig, im, [ax], "|Δ| (px)")
    return save_figure(fig, path)


def field_sigma_map(path: Path, field, title: str) -> Path:
    """The learned field's per-node σ (``sigma_px``), unsupported nodes left blank (docs/uncertainties.md)."""
    fig, (ax,) = new_figure(1, width=6.0, height=5.2, colorbar=True)
    extent = (field.x_nodes_px[0], field.x_nodes_px[-1], field.y_nodes_px[-1], field.y_nodes_px[0])
    im = ax.imshow(np.where(field.support, field.sigma_px, np.nan), extent=extent, cmap="viridis")
    image_axes(ax, (field.width_px, field.height_px), title)
    add_colorbar(fig, im, [ax], "σ of Δ per component (px)")
    return save_figure(fig, path)


def convergence(path: Path, history) -> Path:
    """Combined cost (equations 2 + 3) and inlier RMS per iteration of the alternation (the paper's Fig. 5)."""
    fig, (ax1, ax2) = new_figure(2, width=4.6, height=3.6)
    it = [h.iteration for h in history]
    ax1.plot(it, [h.cost_total for h in history], "o-")
    ax1.set_xlabel("iteration")
    ax1.set_ylabel("cost (eq. 2 + eq. 3)")
    ax1.set_title("convergence", fontsize=10, y=1.0)
    ax2.plot(it, [h.rms_px for h in history], "o-", color="C1")
    ax2.set_xlabel("iteration")
    ax2.set_ylabel("inlier RMS (px, in-sample)")
    ax2.set_title("residual RMS", fontsize=10, y=1.0)
    return save_figure(fig, path)


def frame_rms(path: Path, labels: list[str], before: np.ndarray, after: np.ndarray) -> Path:
    """Per-frame inlier residual RMS (px, in-sample) before and after the learned correction.

    The frames' names are written below their bars without the start all share (:func:`common_prefix`), which
    is written once below them: ``000``, ``001`` ... over ``frames (frame_…)``.
    """
    prefix, names = common_prefix(labels)
    below_names = text_height_in(names, fontsize=6) + 0.15  # the names, rotated, below their ticks
    axis_label = f"frames ({prefix}…)" if prefix else ""
    label_in = text_height_in([axis_label], fontsize=10, rotation=0) + 0.05 if prefix else 0.0
    # the panel as wide as that label at least (a long shared start, centred below it, cut off by the figure's sides)
    label_w = text_height_in([axis_label], fontsize=10, rotation=90) + LEFT_IN + RIGHT_IN if prefix else 0.0
    width = max(5.0, 0.12 * len(names) + 2, label_w)
    fig, (ax,) = new_figure(1, width=width, height=3.6, bottom_in=below_names + label_in)
    from matplotlib.collections import PolyCollection
    from matplotlib.markers import TICKDOWN
    from matplotlib.patches import Patch
    from matplotlib.transforms import blended_transform_factory

    x = np.arange(len(names), dtype=float)
    for offset, height, colour in ((-0.2, before, "C0"), (0.2, after, "C1")):  # bars of 0.4 beside each tick
        left, right, zero = x + offset - 0.2, x + offset + 0.2, np.zeros_like(x)
        height = np.nan_to_num(np.asarray(height, float))
        corners = [(left, zero), (left, height), (right, height), (right, zero)]
        ax.add_collection(PolyCollection(np.stack([np.column_stack(c) for c in corners], axis=1), facecolors=colour))
    top = max(np.nanmax(before, initial=0.0), np.nanmax(after, initial=0.0))
    ax.set_xlim(-0.8, len(names) - 0.2)
    ax.set_ylim(0, 1.05 * top if top > 0 else 1.0)
    # the frames' names as one text each below a tick mark (an axis' tick is several artists, each costly)
    ax.set_xticks([])
    below = blended_transform_factory(ax.transData, ax.transAxes)
    ax.plot(x, np.zeros_like(x), linestyle="none", marker=TICKDOWN, color="k", transform=below, clip_on=False)
    pad = blended_transform_factory(ax.transData, ax.transAxes) + _down(fig, 7 / 72)
    for xi, name in zip(x, names):
        ax.text(xi, 0, name, rotation=90, fontsize=6, ha="center", va="top", transform=pad)
    if prefix:
        ax.set_xlabel(axis_label, fontsize=10)
        ax.xaxis.set_label_coords(0.5, 0, transform=ax.transAxes + _down(fig, below_names))
    ax.set_ylabel("RMS (px, in-sample)")
    handles = [Patch(color="C0", label="no correction"), Patch(color="C1", label="calibrated")]
    # above the bars, right (inside, it hid the bars of the frames under it)
    ax.legend(handles=handles, loc="lower right", bbox_to_anchor=(1.0, 1.0), ncols=2, fontsize=8, frameon=False)
    return save_figure(fig, path)


def common_prefix(labels) -> tuple[str, list[str]]:
    """``(prefix, rest)``: the start all ``labels`` share up to a separator (:func:`_separates`), and their rests.

    Every label keeps at least one character, and every number and word its whole; labels sharing no such start
    are returned whole.

    Examples
    --------
    >>> common_prefix(["frame_008", "frame_010", "frame_011"])
    ('frame_', ['008', '010', '011'])
    >>> common_prefix(["A-LAO 30", "A-RAO 15"]), common_prefix(["exp1", "exp2"]), common_prefix(["a_", "a_1"])
    (('A-', ['LAO 30', 'RAO 15']), ('', ['exp1', 'exp2']), ('', ['a_', 'a_1']))
    >>> common_prefix(["tilt_1.5", "tilt_1.7"]), common_prefix(["dx_-1", "dx_-2"])
    (('tilt_', ['1.5', '1.7']), ('dx_', ['-1', '-2']))
    """
    labels = [str(s) for s in labels]
    shortest = min(labels, key=len, default="")
    shared = next((i for i, c in enumerate(shortest[:-1]) if any(s[i] != c for s in labels)), len(shortest) - 1)
    cut = max((i + 1 for i in range(shared) if all(_separates(s, i) for s in labels)), default=0)
    return shortest[:cut], [s[cut:] for s in labels]


def _separates(s: str, i: int) -> bool:
    """Whether ``s[i]`` ends a word: not a letter, digit or combining accent, nor a number's point or sign.

    >>> [_separates(s, 4) for s in ("tilt_1", "tilt.5", "tilt-5", "cafe\u0301", "abc1.5", "dx__-1", "p_1e-3")]
    [True, True, True, False, False, False, False]
    """
    c, before, after = s[i], s[i - 1 : i], s[i + 1 : i + 2]
    if c.isalnum() or unicodedata.category(c).startswith("M"):  # an accent decomposed ("e\u0301") is of its word
        return False
    if after.isdigit() and c in ".,":
        return not before.isdigit()  # "1.5": a decimal point
    if after.isdigit() and c in "+-":
        return before.isalnum() and not (before in "eE" and s[i - 2 : i - 1].isdigit())  # "_-1", "1e-3": a sign
    return True


def _down(fig, inches: float):
    """A shift ``inches`` down on the figure."""
    from matplotlib.transforms import ScaledTranslation

    return ScaledTranslation(0, -inches, fig.dpi_scale_trans)
