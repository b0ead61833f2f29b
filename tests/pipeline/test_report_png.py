"""The report's PNGs (:func:`fluorocal.report.save_figure`): matplotlib's pixels.

The ground truth is matplotlib itself: a figure is built twice, drawn once on a canvas of its own by
matplotlib's Agg backend and once by ``save_figure``, and the PNG, as Pillow, OpenCV and OpenImageIO read it,
must hold the canvas' pixels exactly: 8-bit RGB, opaque.
"""

from __future__ import annotations

import numpy as np
from fluorocal import report

#: the figures' background, RGB: a colour whose channels all differ (a swapped channel shows)
FACE = (255, 128, 0)


def _build():
    """A figure of the report's layout (an image and its colour bar) on a background of :data:`FACE`."""
    rng = np.random.default_rng(0)
    fig, (ax,) = report.new_figure(1, colorbar=True)
    fig.set_facecolor(np.array(FACE) / 255)
    im = ax.imshow(rng.random((20, 30)), cmap="magma")
    report.add_colorbar(fig, im, [ax], "|Δ| (px)")
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

    canvas = _matplotlibs(_build())
    assert (canvas[..., 3] == 255).all()  # opaque: nothing is lost with the alpha channel
    path = report.save_figure(_build(), tmp_path / "fig.png")
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
