"""The report's figures draw their ticks their own way (:func:`fluorocal.report.save_figure`), in matplotlib's pixels.

The ground truth is matplotlib itself: each figure is built twice, drawn once by matplotlib's Agg canvas with
its own tick artists and once by ``save_figure``, and the two images must be the same pixel for pixel, for
the kinds of axes the report and the other commands' plots use. Axes that ``save_figure`` leaves to matplotlib
(minor ticks, an offset text) must come out the same too.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal import report

#: a figure's kind -> whether its first axes' x and y ticks are drawn by fluorocal (False: left to matplotlib)
PLAIN = {
    "image": (True, True),
    "lines": (True, True),
    "rotated_names": (True, True),
    "categories": (True, True),
    "offset": (True, False),
    "log": (True, False),
    "shared": (False, False),
    "unclipped": (True, True),
}


def _build(kind: str):
    """A figure of the report's layout (:func:`fluorocal.report.new_figure`) showing ``kind`` of axes."""
    rng = np.random.default_rng(3)
    if kind == "image":  # panels of an image with a colour bar beside them, one grid cell left empty
        fig, axes = report.new_figure(3, width=4.2, height=4.0, n_cols=2, title_lines=2, colorbar=True)
        for ax in axes:
            im = ax.imshow(rng.random((12, 16)), extent=(-0.5, 1023.5, 767.5, -0.5))
            report.image_axes(ax, (1024, 768), "a title\non two lines")
        report.add_colorbar(fig, im, axes, "|Δ| (px)")
        return fig
    if kind == "shared":  # two panels sharing both axes (one locator): each keeps its ticks
        fig, axes = report.new_figure(2, width=4.0, height=3.6)
        axes[1].sharex(axes[0])
        axes[1].sharey(axes[0])
        for ax in axes:
            ax.plot(np.arange(8), np.arange(8) ** 2, "o-")
            ax.set_xlabel("x")
        return fig
    fig, (ax,) = report.new_figure(1, width=5.0, height=3.8, bottom_in=1.2)
    if kind == "lines":
        ax.plot(np.arange(8), 470000 / (1 + np.arange(8)), "o-")
        ax.set_xlabel("iteration")
        ax.set_ylabel("cost")
    elif kind == "rotated_names":  # as fluorocal.orientations' chart
        ax.bar(np.arange(4), [0.3, 0.1, 0.25, 0.05], 0.4)
        ax.set_xticks(np.arange(4))
        ax.set_xticklabels(["LAO 30", "RAO 15", "a longer name", "x"], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel("Δ (px)")
    elif kind == "categories":  # as fluorocal.cmd_check's trend: strings along x, rotated by tick_params
        ax.plot(["2026-01-02", "2026-02-03", "2026-03-04"], [0.2, 0.25, 0.22], "o-")
        ax.tick_params(axis="x", labelrotation=60, labelsize=6)
    elif kind == "unclipped":  # markers drawn across the spine, over the tick marks (the axis is drawn below lines)
        ax.plot(np.arange(8), np.zeros(8), "s", markersize=12, clip_on=False)
        ax.set_xlim(0, 7)
        ax.set_ylim(0, 1)
    elif kind == "offset":  # y labels need an offset text ("+1") beside them
        ax.plot(np.arange(5), 1 + 1e-6 * np.arange(5))
        ax.set_ylabel("value")
    elif kind == "log":  # minor ticks
        ax.plot(np.arange(1, 6), 10.0 ** -np.arange(5))
        ax.set_yscale("log")
    return fig


@pytest.mark.parametrize("kind", PLAIN)
def test_ticks_are_the_pixels_matplotlib_draws(tmp_path, kind):
    import matplotlib.style
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.ticker import NullLocator
    from PIL import Image

    with matplotlib.style.context("default"):
        canvas = FigureCanvasAgg(_build(kind))
        canvas.draw()
        matplotlibs = np.asarray(canvas.buffer_rgba())[..., :3]
        fig = _build(kind)
        ours = np.asarray(Image.open(report.save_figure(fig, tmp_path / "ours.png")).convert("RGB"))
    assert ours.shape == matplotlibs.shape
    differ = np.any(ours != matplotlibs, axis=-1)
    assert not differ.any(), f"{differ.sum()} pixels differ, rows {np.nonzero(differ.any(axis=1))[0][[0, -1]]}"
    plain = tuple(isinstance(a.get_major_locator(), NullLocator) for a in (fig.axes[0].xaxis, fig.axes[0].yaxis))
    assert plain == PLAIN[kind]


def test_the_room_for_rotated_labels_is_matplotlibs_measure_under_the_font_in_force():
    """:func:`fluorocal.report.text_height_in` keeps its measures between figures, but not across font settings."""
    import matplotlib.style
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    def matplotlibs(label):  # the height of the label drawn rotated by matplotlib at the PNGs' dpi, inches
        fig = Figure(dpi=report.DPI)
        text = fig.text(0.5, 0.5, label, rotation=90, fontsize=6)
        return text.get_window_extent(FigureCanvasAgg(fig).get_renderer()).height / report.DPI

    labels = ["frame_000", "a longer frame name"]
    with matplotlib.style.context("default"):
        default = report.text_height_in(labels, fontsize=6)
        assert default == pytest.approx(matplotlibs(labels[1]), abs=1e-9)
        with matplotlib.rc_context({"font.family": "monospace"}):
            mono = report.text_height_in(labels, fontsize=6)
            assert mono == pytest.approx(matplotlibs(labels[1]), abs=1e-9)
        assert report.text_height_in(labels, fontsize=6) == default
    assert mono > default * 1.05  # a monospace font's letters are wider: measured anew, not taken from before


def test_frames_are_named_without_their_shared_start_written_once_below_the_names(tmp_path, monkeypatch):
    """75 frames ``frame_000`` ...: each named ``000`` ... below its bars, ``frame_`` once, below them all."""
    drawn = []
    save = report.save_figure
    monkeypatch.setattr(report, "save_figure", lambda fig, path: save(drawn.append(fig) or fig, path))
    labels = [f"frame_{i:03d}" for i in range(75)]
    rms = np.linspace(0.5, 1.5, 75)
    report.frame_rms(tmp_path / "frames.png", labels, rms, rms / 10)
    (fig,) = drawn
    ax, renderer = fig.axes[0], fig.canvas.get_renderer()
    names = [t for t in ax.texts if t.get_rotation() == 90]
    assert [t.get_text() for t in names] == [label.removeprefix("frame_") for label in labels]
    assert ax.xaxis.label.get_text() == "frames (frame_…)"
    boxes = [t.get_window_extent(renderer) for t in names]
    label = ax.xaxis.label.get_window_extent(renderer)
    assert 0 <= label.y0 and label.y1 < min(b.y0 for b in boxes)  # in the figure, below the names, over none
    assert all(a.x1 < b.x0 for a, b in zip(boxes, boxes[1:]))  # the names, left to right, overlap no other
    assert min(b.y0 for b in boxes) > 0


@pytest.mark.parametrize(
    ("labels", "prefix", "names"),
    [
        (["frame_000"], "frame_", ["000"]),  # one frame
        (["a_1", "a_1"], "a_", ["1", "1"]),
        (["", "x"], "", ["", "x"]),
        (["001", "002"], "", ["001", "002"]),  # all digits: no separator
        (["frame1_0", "frame1_1"], "frame1_", ["0", "1"]),
        (["frame_01", "frame_010"], "frame_", ["01", "010"]),
        (["A_001", "B_001"], "", ["A_001", "B_001"]),
        (["frame_", "frame_1"], "", ["frame_", "frame_1"]),  # no name left empty
        (["tilt_1.5", "tilt_1.7"], "tilt_", ["1.5", "1.7"]),  # not "5", "7": a number is kept whole
        (["run_1.x", "run_1.55"], "run_", ["1.x", "1.55"]),  # not "x", "55"
        (["dx_-1", "dx_-2"], "dx_", ["-1", "-2"]),  # its sign
        (["p_1e-3", "p_1e-4"], "p_", ["1e-3", "1e-4"]),  # its exponent
        (["frame-001", "frame-002"], "frame-", ["001", "002"]),  # a dash between words separates them
        (["é_1", "é_2"], "é_", ["1", "2"]),
        (["Pra\u0308p1", "Pra\u0308p2"], "", ["Pra\u0308p1", "Pra\u0308p2"]),  # a decomposed accent is of its word
    ],
)
def test_the_shared_start_of_frame_names_leaves_each_name_and_number_whole(labels, prefix, names):
    assert report.common_prefix(labels) == (prefix, names)


def test_a_long_shared_start_of_few_frames_is_written_whole_inside_the_figure(tmp_path, monkeypatch):
    drawn = []
    save = report.save_figure
    monkeypatch.setattr(report, "save_figure", lambda fig, path: save(drawn.append(fig) or fig, path))
    start = "calibration_session_2026-12-04_morning_biplanar_system_A_orbit_30_tilt_15_exposure_"
    report.frame_rms(tmp_path / "frames.png", [f"{start}{i:03d}" for i in range(3)], np.ones(3), np.ones(3) / 10)
    (fig,) = drawn
    label = fig.axes[0].xaxis.label
    assert label.get_text() == f"frames ({start}…)"
    box = label.get_window_extent(fig.canvas.get_renderer())
    assert 0 <= box.x0 and box.x1 <= fig.bbox.width  # not cut off by the figure's sides
