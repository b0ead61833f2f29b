"""The report's figures are drawn again only when what they show changed (issue 31).

A published set records each figure's content key and its PNG's sha256 (``.fluorocal-figures.json``); the
next set copies a figure of the same key whose file still has that checksum, and draws every other one.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
from pathlib import Path

import numpy as np
import pytest
from fluorocal import report
from fluorocal.cache import ArtifactCache
from fluorocal.cli import main
from fluorocal.figures import RECORD, Figures, figure_key
from fluorocal.outputs import publish
from fluorocal.stages.io import write_png

from tests.conftest import copy_project

#: a PNG of one black pixel: what the stand-in plot below draws
ONE_PIXEL = np.zeros((1, 1), np.uint8)
PLOTS = ("residual_maps", "field_map", "field_sigma_map", "frame_rms", "convergence")


def dots(path, xy, title):
    """A stand-in plotting function: a 1-pixel PNG, whatever its content (the content is in the key)."""
    dots.calls.append(path.name)
    write_png(path, ONE_PIXEL)
    return path


dots.calls = []


def _publish(out, xy, title="t"):
    """Publish a set of one figure ``a.png`` made from ``xy`` and ``title``; the :class:`Figures` that made it."""
    figures = Figures(out)

    def write(staging):
        return [figures.draw(staging / "a.png", dots, xy, title), figures.write_record(staging)]

    publish(out, write)
    return figures


@pytest.fixture(autouse=True)
def _no_calls():
    dots.calls.clear()


def test_the_same_content_is_copied_and_other_content_drawn(tmp_path):
    out, xy = tmp_path / "out", np.arange(6.0).reshape(3, 2)
    assert _publish(out, xy).drawn == ["a.png"]
    first = (out / "a.png").read_bytes()
    again = _publish(out, xy.copy())
    assert (again.drawn, again.copied, dots.calls) == ([], ["a.png"], ["a.png"])
    assert (out / "a.png").read_bytes() == first
    # one number, the dtype, or the title changed: drawn again
    assert _publish(out, xy + [[0, 0], [0, 0], [0, 1e-12]]).drawn == ["a.png"]
    assert _publish(out, xy.astype(np.float32)).drawn == ["a.png"]
    assert _publish(out, xy.astype(np.float32), "another title").drawn == ["a.png"]


def test_a_published_figure_not_as_recorded_is_drawn_again(tmp_path):
    out, xy = tmp_path / "out", np.arange(6.0).reshape(3, 2)
    _publish(out, xy)
    (out / "a.png").write_bytes((out / "a.png").read_bytes()[:-3])  # truncated
    assert _publish(out, xy).drawn == ["a.png"]
    (out / "a.png").unlink()
    assert _publish(out, xy).drawn == ["a.png"]
    (out / RECORD).write_text("{not json")
    assert _publish(out, xy).drawn == ["a.png"]
    (out / RECORD).write_text("[" * 200_000)  # nested too deep for the decoder
    assert _publish(out, xy).drawn == ["a.png"]
    record = json.loads((out / RECORD).read_text())
    assert record["a.png"]["sha256"] == hashlib.sha256((out / "a.png").read_bytes()).hexdigest()


@pytest.mark.parametrize("where", ["outside", "inside", "record"])
def test_a_symlinked_figure_or_record_is_drawn_again(tmp_path, where):
    """A link in the published set, to a file of the same bytes out of the set or in it, is not copied: drawn again."""
    out, xy = tmp_path / "out", np.arange(6.0).reshape(3, 2)
    _publish(out, xy)
    name = RECORD if where == "record" else "a.png"
    target = (tmp_path if where != "inside" else out) / f"copy-{name}"
    target.write_bytes((out / name).read_bytes())
    (out / name).unlink()
    (out / name).symlink_to(target)
    assert _publish(out, xy).drawn == ["a.png"]


def test_the_key_covers_the_code_and_refuses_what_it_cannot_hash():
    args = (np.ones(3), "title")
    assert figure_key(dots, args, "code 1") != figure_key(dots, args, "code 2")
    assert figure_key(dots, args, "code") != figure_key(report.field_map, args, "code")
    with pytest.raises(TypeError, match="object"):
        figure_key(dots, (object(),), "code")


@pytest.mark.parametrize(
    "value",
    [
        np.ma.masked_array([1.0, 2.0], mask=[False, True]),  # its mask is not in its bytes
        np.zeros(2, dtype=[("x", "f8"), ("y", "f8")]),  # its field names are not in its dtype's str ('|V16')
        np.zeros(1, dtype=[("x", "f8")])[0],  # a structured scalar
        np.array([object()]),
    ],
)
def test_the_key_refuses_arrays_whose_bytes_do_not_hold_their_content(value):
    with pytest.raises(TypeError, match="plain arrays of numbers"):
        figure_key(dots, (value,), "code")


def test_a_figure_is_drawn_under_matplotlibs_defaults_whatever_the_processs_settings(tmp_path):
    """Settings changed in the process (as a matplotlibrc would) change no drawn PNG; they are left as they were."""
    import matplotlib

    history = [Step(i, 10.0 / (i + 1), 1.0 / (i + 1)) for i in range(4)]
    plain = Figures().draw(tmp_path / "plain.png", report.convergence, history).read_bytes()
    changed = {"axes.facecolor": "red", "lines.linewidth": 9.0, "font.size": 20.0, "figure.dpi": 30.0}
    changed["text.hinting"] = "force_autohint"  # the report's own text setting (figures.STYLE) is not the process's
    with matplotlib.rc_context(changed):
        styled = Figures().draw(tmp_path / "styled.png", report.convergence, history).read_bytes()
        assert matplotlib.rcParams["axes.facecolor"] == "red"  # the process's own settings are left as they were
        report.convergence(tmp_path / "direct.png", history)  # drawn outside Figures: the settings do show
    assert styled == plain
    assert (tmp_path / "direct.png").read_bytes() != plain


def test_a_figure_is_drawn_under_the_reports_settings_and_the_processs_come_back_even_when_it_fails(tmp_path):
    import matplotlib
    from fluorocal.figures import STYLE

    seen = []

    def failing(path, xy):
        seen.append(matplotlib.rcParams.copy())
        raise ValueError("drawing failed")

    with matplotlib.rc_context({"axes.facecolor": "red", "text.hinting": "auto", "font.size": 3.0}):
        before = matplotlib.rcParams.copy()
        with pytest.raises(ValueError, match="drawing failed"):
            Figures().draw(tmp_path / "a.png", failing, np.ones(2))
        # every setting as it was (the backend, first chosen when needed, is no setting of the figures)
        assert {k: v for k, v in dict.items(matplotlib.rcParams) if k != "backend"} == {
            k: v for k, v in dict.items(before) if k != "backend"
        }
    (inside,) = seen
    assert {k: inside[k] for k in STYLE} == STYLE
    assert (inside["axes.facecolor"], inside["font.size"]) == ("white", 10.0)  # matplotlib's defaults


def test_a_figure_drawn_under_other_settings_of_the_report_is_drawn_again(tmp_path, monkeypatch):
    from fluorocal import figures

    out, xy = tmp_path / "out", np.arange(6.0).reshape(3, 2)
    _publish(out, xy)
    monkeypatch.setattr(figures, "STYLE", {**figures.STYLE, "text.hinting": "auto"})
    assert _publish(out, xy).drawn == ["a.png"]
    assert _publish(out, xy).copied == ["a.png"]


@dataclasses.dataclass(frozen=True)
class Step:
    """What :func:`fluorocal.report.convergence` reads of an iteration's record."""

    iteration: int
    cost_total: float
    rms_px: float


# --- a whole run ---------------------------------------------------------------------------------------------


@pytest.fixture()
def project(tmp_path, calibrated_project):
    return copy_project(calibrated_project, tmp_path / "project")


def _count_plots(monkeypatch):
    """Wrap the report's plotting functions; the names of the PNGs they draw.

    The wrappers keep the functions' names: a figure's key holds its plotting function's.
    """
    drawn = []
    for name in PLOTS:
        real = getattr(report, name)

        @functools.wraps(real)
        def counted(path, *args, _real=real):
            drawn.append(path.name)
            return _real(path, *args)

        monkeypatch.setattr(report, name, counted)
    return drawn


def _pngs(out):
    return {p.name: p.read_bytes() for p in sorted(out.glob("*.png"))}


def test_a_run_with_nothing_changed_draws_no_figure_and_keeps_the_set(project, monkeypatch, caplog):
    out = project / "out"
    before, listing = _pngs(out), sorted(p.name for p in out.iterdir())
    drawn = _count_plots(monkeypatch)
    with caplog.at_level(logging.INFO):
        assert main(["run", str(project / "fluorocal.toml")]) == 0
    assert "nothing recomputed" in caplog.text
    assert drawn == []
    assert _pngs(out) == before and len(before) == 9  # 4 per system (2) and the convergence
    assert sorted(p.name for p in out.iterdir()) == listing  # the whole set, and nothing else
    assert "9 unchanged and copied" in caplog.text


def test_a_run_keeps_the_analyses_of_the_figures_code(project):
    """The memo the run saved before its export is saved again with the plotting modules' analyses."""
    import importlib.util

    from fluorocal.codehash import AnalysisMemo
    from fluorocal.config import load_config

    memo_path = ArtifactCache(load_config(project / "fluorocal.toml").cache_dir).code_memo().path
    memo_path.unlink()
    assert main(["--quiet", "run", str(project / "fluorocal.toml")]) == 0
    path = Path(importlib.util.find_spec("fluorocal.report").origin)
    assert (
        AnalysisMemo.key("fluorocal.report", path, path.read_text(encoding="utf-8")) in AnalysisMemo(memo_path).entries
    )


def test_a_changed_input_redraws_the_figures_that_show_it(project, monkeypatch):
    """A frame renamed: its name is on system A's per-frame figure; its pixels, and so every other figure, are not."""
    (project / "frames" / "A" / "frame_000.tif").rename(project / "frames" / "A" / "frame_000a.tif")
    before = _pngs(project / "out")
    drawn = _count_plots(monkeypatch)
    assert main(["--quiet", "run", str(project / "fluorocal.toml")]) == 0
    assert drawn == ["frames_A.png"]
    after = _pngs(project / "out")
    assert [n for n in before if before[n] != after[n]] == ["frames_A.png"]


def test_two_figures_of_one_name_are_refused_not_overwritten(tmp_path):
    """Systems ``x`` and ``sigma_x``: ``field_sigma_x.png`` is both the σ map of ``x`` and the field of ``sigma_x``."""
    from fluorocal.stages.errors import InputError

    figures, xy = Figures(), np.arange(6.0).reshape(3, 2)
    figures.draw(tmp_path / "field_sigma_x.png", dots, xy, "σ of the correction, system x")
    with pytest.raises(InputError, match="both be written as field_sigma_x.png"):
        figures.draw(tmp_path / "field_sigma_x.png", dots, xy + 1, "learned correction Δ, system sigma_x")
    assert dots.calls == ["field_sigma_x.png"]  # the first figure stands
