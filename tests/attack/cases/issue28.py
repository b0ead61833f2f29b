"""The attack battery's cases of issue 28: outputs surviving every option, files proving what they are, any locale.

Each case as a careless user or a hostile file would try it.
"""

from __future__ import annotations

import json
import shutil

import numpy as np

from tests.attack.catalogue import Catalogue
from tests.attack.checks import same_as_clean, undistorted_ok
from tests.attack.harness import Ctx, fluorocal, undistort_first
from tests.attack.runners import with_env
from tests.attack.setups import cfg_append, cfg_edit, nothing, phantom_rows, read_frame, write_rows

CLASS = "issue28"
ASCII_LOCALE = {"LC_ALL": "C", "LANG": "C", "PYTHONUTF8": "0", "PYTHONIOENCODING": "ascii"}


def cases() -> list:
    """The cases of issue 28, in the battery's order."""
    table = Catalogue()
    for part in (_outputs, _files, _numbers_and_locale):
        part(table)
    return table


def run(*args: str):
    """The commands: ``fluorocal run fluorocal.toml ARGS``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("run", c.cfg, *args)]

    return commands


def _published_kept(c: Ctx) -> str | None:
    """``--until``: the published set (calibration, fields, report) is the clean run's; the partial tables beside."""
    missing = [n for n in ("calibration.json", "report.md", "field_A.npz") if not (c.proj / "out" / n).is_file()]
    if missing:
        return f"--until deleted {', '.join(missing)}"
    if not (c.proj / "out" / "until-label" / "label.csv").is_file():
        return "no partial label.csv in out/until-label"
    return same_as_clean(c)


def _other_project(out: str, extra: str = ""):
    """``proj/other.toml``: the project's config with its output folder ``out``, and ``extra`` appended."""

    def f(c: Ctx) -> None:
        text = c.cfg.read_text().replace('dir = "out"', f'dir = "{out}"')
        (c.proj / "other.toml").write_text(text + extra)

    return f


def _cache_kept(c: Ctx) -> str | None:
    learn = list((c.proj / ".fluorocal" / "learn").glob("*/manifest.json"))
    return None if learn else "cache clean of another project removed this project's learn entry"


def _clean_other_project(c: Ctx) -> list[list[str]]:
    return [
        fluorocal("cache", "clean", "--stale", c.proj / "other.toml"),
        fluorocal("cache", "clean", c.proj / "other.toml"),
    ]


def _outputs(table: Catalogue) -> None:
    add = table.add
    add("until_keeps_published", CLASS, nothing, run("--until", "label"), expect="ok", check=_published_kept)
    add(
        "second_project_same_out",
        CLASS,
        _other_project("out"),
        lambda c: [fluorocal("run", c.proj / "other.toml")],
        hints=("another project",),
    )
    add(
        "shared_cache_clean",
        CLASS,
        _other_project("out2", "\n[detect]\nmin_snr = 7.5\n"),
        _clean_other_project,
        expect="ok",
        check=_cache_kept,
    )


def _scale_field(factor: float):
    """field_A.npz's nodes (x and y) times ``factor``: a field for another image size."""

    def f(c: Ctx) -> None:
        p = c.proj / "out" / "field_A.npz"
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["x_nodes_px"] = arrays["x_nodes_px"] * factor
        arrays["y_nodes_px"] = arrays["y_nodes_px"] * factor
        np.savez(p, **arrays)

    return f


def _cal_edit(change):
    """calibration.json's document changed in place by ``change``."""

    def f(c: Ctx) -> None:
        doc = json.loads(c.cal.read_text())
        change(doc)
        c.cal.write_text(json.dumps(doc))

    return f


def _export_dlt(c: Ctx) -> list[list[str]]:
    return [fluorocal("export", c.cal, "--format", "dlt", "--out", c.proj / "exp")]


def _rotation(q: list):
    """A change for :func:`_cal_edit`: system B's rotation quaternion set to ``q``."""

    def change(d: dict) -> None:
        d["systems"][1]["rop"].update(q_cam_from_ref=q)

    return change


def _roles_upper(c: Ctx) -> None:
    rows = phantom_rows(c)
    write_rows(c, [rows[0]] + [[*r[:5], r[5].upper()] for r in rows[1:]])


def _files(table: Catalogue) -> None:
    add = table.add
    for factor in (2.0, 0.5):
        add(f"field_nodes_x{factor:g}", CLASS, _scale_field(factor), undistort_first(), hints=("field_A.npz",))
    for name, q in (("rop_q_nan", [float("nan"), 0, 0, 0]), ("rop_q_zero", [0, 0, 0, 0]), ("rop_q_three", [1, 0, 0])):
        add(name, CLASS, _cal_edit(_rotation(q)), _export_dlt, hints=("q_cam_from_ref",))
    add(
        "exposure_source_nan",
        CLASS,
        _cal_edit(lambda d: d["exposures"][0].update(source_mm=[0, float("nan"), 0])),
        _export_dlt,
        hints=("source_mm",),
    )
    seven = ["999", "1", "2", "3", "4", "", "x"]  # under the six columns id,x,y,z,diameter,role
    add("phantom_row_extra_value", CLASS, lambda c: write_rows(c, phantom_rows(c) + [seven]), hints=("phantom.csv",))
    add("phantom_role_upper", CLASS, _roles_upper, expect="ok")
    add(
        "system_b_given_a_frames",
        CLASS,
        cfg_edit('frames = "frames/B/*.tif"', 'frames = "frames/A/*.tif"'),
        hints=("frames",),
    )


def _frame_copy(name: str):
    """Frame A's first, as ``frames/NAME``: an 8-bit JPEG, a 2-frame MJPEG AVI, or the TIFF itself (other names)."""

    def f(c: Ctx) -> None:
        import cv2

        source, target = c.frames("A")[0], c.proj / "frames" / name
        eight = (read_frame(source) >> 4).astype(np.uint8)
        if name.endswith(".jpg"):
            cv2.imwrite(str(target), eight, [cv2.IMWRITE_JPEG_QUALITY, 95])
        elif name.endswith(".avi"):
            writer = cv2.VideoWriter(str(target), cv2.VideoWriter_fourcc(*"MJPG"), 10, eight.shape[::-1], False)
            for _ in range(2):
                writer.write(eight)
            writer.release()
        else:
            shutil.copyfile(source, target)

    return f


def _undistort_frame(name: str):
    """The commands: ``fluorocal undistort`` of ``frames/NAME`` with system A into ``proj/und``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.proj / "frames" / name)]

    return commands


def _numbers_and_locale(table: Catalogue) -> None:
    add = table.add
    for name, text, key in (
        ("n_arcs_1e21", "[centroid]\nn_arcs = " + str(10**21), "n_arcs"),
        ("seed_negative", "[learn]\nseed = -1", "seed"),
        ("int_5000_digits", "[learn]\nseed = " + "9" * 5000, "seed"),
        ("float_1e400", "[detect]\nmin_snr = 1e400", "min_snr"),
    ):
        add(name, CLASS, cfg_append(text), hints=(key,))
    huge = "99999999999999999999"
    add("threads_env_huge", CLASS, nothing, runner=with_env(FLUOROCAL_THREADS=huge), hints=("FLUOROCAL_THREADS",))
    add("locale_c_ascii_run", CLASS, nothing, run("--force", "learn"), expect="ok", runner=with_env(**ASCII_LOCALE))
    for name in ("lossy.jpg", "mjpeg.avi"):  # re-encoded lossily: refused (a frame comes back exactly or not at all)
        add(f"undistort_{name.replace('.', '_')}", CLASS, _frame_copy(name), _undistort_frame(name), hints=(name,))
    greek = "fr\u00e4me_\u0394.tif"  # read and written under the C locale (OpenImageIO refused the name)
    add(
        "undistort_non_ascii_name_c_locale",
        CLASS,
        _frame_copy(greek),
        _undistort_frame(greek),
        expect="ok",
        check=undistorted_ok("proj/und", 1),
        allow=("proj/und",),
        runner=with_env(**ASCII_LOCALE),
    )
