"""The residual maps' arrows (:func:`fluorocal.report.residual_maps`), against matplotlib's own quiver rules.

matplotlib draws an arrow shorter than ``minlength`` shaft widths as a dot of that width instead
(``Axes.quiver``: with ``scale_units`` unset, an arrow is ``|(u, v)| / scale`` axes widths long and its
shaft ``width`` axes widths wide): such dots may be left out, no longer arrow.
"""

from __future__ import annotations

import numpy as np
from fluorocal import report


def _quivers(tmp_path, monkeypatch, panels):
    """The quivers ``residual_maps`` draws for ``panels``, each panel's list (empty: none)."""
    drawn = []
    save = report.save_figure
    monkeypatch.setattr(report, "save_figure", lambda fig, path: save(drawn.append(fig) or fig, path))
    report.residual_maps(tmp_path / "residuals.png", panels, (200, 100))
    (fig,) = drawn
    from matplotlib.quiver import Quiver

    return [[c for c in ax.collections if isinstance(c, Quiver)] for ax in fig.axes[: len(panels)]]


def test_every_arrow_longer_than_its_shaft_is_wide_is_drawn_and_only_those_left_out(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 100, (400, 2))
    angle = rng.uniform(0, 2 * np.pi, 400)
    mag = np.exp(rng.uniform(np.log(1e-4), np.log(2.0), 400))  # from far under a shaft's width to 2 px
    mag[:5] = 0.0
    res = mag[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    ((q,),) = _quivers(tmp_path, monkeypatch, [("t", xy, res)])
    arrow = mag / (q.scale * q.width) >= q.minlength  # long enough to be drawn as an arrow, in shaft widths
    assert 0 < arrow.sum() < 400 - 50  # some of either
    assert np.array_equal(np.column_stack([q.U, q.V]), res[arrow])
    assert np.array_equal(q.XY, xy[arrow])


def test_residuals_all_zero_draw_their_dots_without_arrows(tmp_path, monkeypatch):
    """Their 99th percentile (the colour scale's top, the arrows' scale) is 0: no 0 / 0 (an error in the tests)."""
    xy = np.random.default_rng(6).uniform(0, 100, (50, 2))
    assert _quivers(tmp_path, monkeypatch, [("zero", xy, np.zeros((50, 2))), ("none", xy[:0], xy[:0])]) == [[], []]
