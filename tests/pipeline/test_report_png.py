"""The report's PNGs (:func:`fluorocal.report.save_figure`): matplotlib's pixels, whatever was drawn before.

The ground truth is matplotlib itself: each figure is built twice, drawn once on a canvas of its own by
matplotlib's Agg backend and once by ``save_figure`` (which shares one renderer among the figures of a size), and
the PNG, as Pillow, OpenCV and OpenImageIO read it, must hold the canvas' pixels exactly: 8-bit RGB, opaque.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal import report

#: the figures' background, RGB: a colour whose channels all differ (a swapped channel shows)
FACE = (255, 128, 0)


def _build(kind: str, k: int, *, dpi: float = report.DPI, **layout):
    """A figure of the report's layout drawing ``kind`` (variant ``k``) on a background of :data:`FACE`.

    ``layout``: :func:`fluorocal.report.new_figure`'s sizes; ``dpi`` the figure's.
    """
    rng = np.random.default_rng(k)
    fig, (ax,) = report.new_figure(1, colorbar=kind == "image", **layout)
    fig.set_dpi(dpi)
    fig.set_facecolor(np.array(FACE) / 255)
    if kind == "hatch":
        ax.bar(np.arange(4), rng.random(4), hatch=["//", "xx", ".."][k % 3], color="none", edgecolor=f"C{k}")
    elif kind == "clip":  # an image clipped to an ellipse: a clip path, not a box
        from matplotlib.patches import Ellipse

        im = ax.imshow(rng.random((10, 10)), extent=(0, 10, 0, 10))
        im.set_clip_path(Ellipse((3 + k, 5), 4 + k, 6, transform=ax.transData))
    elif kind == "image":
        im = ax.imshow(rng.random((20, 30)), interpolation=["nearest", "bilinear"][k % 2], cmap="magma")
        report.add_colorbar(fig, im, [ax], "|Δ| (px)")
    elif kind == "text":  # the same texts at other sizes and angles: the renderer keeps each text's measures
        ax.plot(np.arange(5), rng.random(5), "o--", alpha=0.5, label="a line")
        ax.set_title(rf"$\sigma_x$ = {k}", fontsize=8 + k)
        ax.text(1, 0.5, "a text", fontsize=6 + k, rotation=30 * k)
        ax.legend(fontsize=7)
    elif kind == "quiver":
        xx, yy = np.meshgrid(np.arange(6), np.arange(5))
        ax.quiver(xx, yy, rng.random(xx.shape), rng.random(xx.shape), color="c", width=0.004)
    return fig


def _matplotlibs(fig) -> np.ndarray:
    """``fig`` drawn on a canvas of its own by matplotlib's Agg backend: (H, W, 4) RGBA."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba()).copy()


def test_the_png_is_the_canvas_as_8_bit_rgb_for_every_reader(tmp_path):
    import cv2
    import OpenImageIO as oiio
    from PIL import Image

    canvas = _matplotlibs(_build("image", 0))
    assert (canvas[..., 3] == 255).all()  # opaque: nothing is lost with the alpha channel
    path = report.save_figure(_build("image", 0), tmp_path / "fig.png")
    header = path.read_bytes()[:26]
    assert (header[12:16], header[24], header[25]) == (b"IHDR", 8, 2)  # 8 bits per channel, colour type RGB
    with Image.open(path) as im:
        assert im.mode == "RGB"
        pillow = np.asarray(im)
    opencv = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1]  # BGR
    spec_in = oiio.ImageInput.open(str(path))
    assert (spec_in.spec().nchannels, spec_in.spec().format) == (3, oiio.UINT8)
    openimageio = spec_in.read_image(oiio.UINT8)
    spec_in.close()
    for name, pixels in (("Pillow", pillow), ("OpenCV", opencv), ("OpenImageIO", openimageio)):
        assert pixels.shape == canvas.shape[:2] + (3,), name
        assert (pixels == canvas[..., :3]).all(), f"{name}: {np.any(pixels != canvas[..., :3], axis=-1).sum()} px"
    assert tuple(pillow[0, 0]) == FACE


def test_figures_drawn_one_after_the_other_have_the_pixels_of_a_fresh_canvas(tmp_path):
    """Hatches, clip paths, images, texts and arrows of figures of one size, drawn in turn.

    And a figure of as many pixels at another dpi, figures of a size in pixels not whole (as the frames' bar chart's).
    """
    from PIL import Image

    rng = np.random.default_rng(0)
    figures = [(kind, int(k), {}) for kind in ("hatch", "clip", "image", "text", "quiver") for k in range(3)]
    figures += [("text", 1, {"width": 10.0, "dpi": report.DPI / 2})]  # as many pixels, another dpi
    figures += [(kind, 1, {"height": 4.6 + 1 / 3 / report.DPI}) for kind in ("text", "image")]
    for i in rng.permutation(len(figures)):
        kind, k, size = figures[i]
        ours = np.asarray(Image.open(report.save_figure(_build(kind, k, **size), tmp_path / "fig.png")))
        theirs = _matplotlibs(_build(kind, k, **size))[..., :3]
        assert ours.shape == theirs.shape
        differ = np.any(ours != theirs, axis=-1)
        assert not differ.any(), f"{kind} {k} {size}: {differ.sum()} pixels differ"


@pytest.mark.parametrize("height", [3.6, 3.6 + 1 / 3 / report.DPI])  # whole pixels, and a third of one more
def test_the_shared_renderer_is_the_one_matplotlibs_canvas_makes(tmp_path, height):
    """Its size as matplotlib's canvas gives it: whole pixels or not (the versions differ), texts go by it."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig, _ = report.new_figure(1, height=height)
    report.save_figure(fig, tmp_path / "fig.png")
    shared, (own_fig, _) = fig.canvas.renderer, report.new_figure(1, height=height)
    own = FigureCanvasAgg(own_fig).get_renderer()
    assert [(v, type(v)) for v in (shared.width, shared.height, shared.dpi)] == [
        (v, type(v)) for v in (own.width, own.height, own.dpi)
    ]
