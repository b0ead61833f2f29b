"""The attack battery's config cases (``fluorocal run``): the project file, its values, paths and names."""

from __future__ import annotations

import os
import shutil

from tests.attack.catalogue import Catalogue
from tests.attack.checks import sibling_intact
from tests.attack.harness import Ctx, fluorocal
from tests.attack.setups import (
    cfg_append,
    cfg_edit,
    cfg_key,
    cfg_replace,
    chain,
    make_dir,
    nothing,
    symlink,
    write_bytes,
)

CLASS = "config"


def cases() -> list:
    """The config cases (and the names of systems and orientations, class ``names``), in the battery's order."""
    table = Catalogue()
    for part in (_the_file, _system_values, _files_and_frames, _names_and_folders, _stages_and_compute):
        part(table)
    return table


def _the_file(table: Catalogue) -> None:
    add = table.add
    add("config_missing", CLASS, nothing, lambda c: [fluorocal("run", c.proj / "nope.toml")], hints=("nope.toml",))
    add("config_empty", CLASS, write_bytes("fluorocal.toml", b""), hints=("phantom",))
    add("config_binary", CLASS, write_bytes("fluorocal.toml", bytes(range(256)) * 8), hints=("fluorocal.toml",))
    add(
        "config_latin1",
        CLASS,
        lambda c: c.cfg.write_bytes(c.cfg.read_bytes() + "# café\n".encode("latin-1")),
        hints=("fluorocal.toml", "UTF-8"),
    )
    add(
        "config_utf16",
        CLASS,
        lambda c: c.cfg.write_bytes(c.cfg.read_text().encode("utf-16")),
        hints=("fluorocal.toml",),
    )
    add("config_bom", CLASS, lambda c: c.cfg.write_bytes(b"\xef\xbb\xbf" + c.cfg.read_bytes()), expect="ok")
    add("config_crlf", CLASS, lambda c: c.cfg.write_bytes(c.cfg.read_bytes().replace(b"\n", b"\r\n")), expect="ok")
    add("config_is_directory", CLASS, make_dir("fluorocal.toml"), hints=("fluorocal.toml",))
    add("config_toml_syntax", CLASS, cfg_append("[output\ndir = "), hints=("fluorocal.toml", "TOML"))
    add(
        "config_huge",
        CLASS,
        lambda c: c.cfg.write_text(c.cfg.read_text() + "# " + "x" * 20_000_000 + "\n"),
        expect="ok",
        note="a 20 MB comment is still a valid config",
    )
    add("config_deep_nesting", CLASS, cfg_append("x = " + "[" * 5000 + "]" * 5000), hints=("fluorocal.toml",))
    add(
        "config_nul_byte", CLASS, lambda c: c.cfg.write_bytes(c.cfg.read_bytes() + b"\x00\n"), hints=("fluorocal.toml",)
    )
    add(
        "config_symlink_outside",
        CLASS,
        chain(
            lambda c: shutil.copy(c.cfg, c.root / "sibling" / "elsewhere.toml"),
            symlink("fluorocal.toml", "sibling/elsewhere.toml"),
        ),
        hints=("phantom",),
        note="the config's folder is where the link points: its relative paths resolve there",
    )
    add("no_phantom_table", CLASS, cfg_replace("[phantom]", "[phantomx]"), hints=("phantom",))
    add("unknown_top_key", CLASS, cfg_append("[outputs]\ndir = 'x'"), hints=("outputs",))
    add("unknown_system_key", CLASS, cfg_key("source_image_distance", "1100\npixelpitch = 0.5"), hints=("pixelpitch",))
    add(
        "systems_not_table",
        CLASS,
        lambda c: c.cfg.write_text(c.cfg.read_text().split("[[systems]]")[0] + "systems = 3\n[output]\ndir = 'out'\n"),
        hints=("systems",),
    )
    add(
        "three_systems",
        CLASS,
        cfg_replace(
            "[calibration]",
            "[[systems]]\nname = 'C'\nframes = 'frames/A/*.tif'\n"
            "source_image_distance = 1100\npixel_pitch = 0.5\n\n[calibration]",
        ),
        hints=("systems",),
    )


def _without_key(key: str):
    """Every line of the config setting ``key`` removed (in every system)."""

    def f(c: Ctx) -> None:
        lines = c.cfg.read_text().splitlines()
        c.cfg.write_text("\n".join(ln for ln in lines if not ln.startswith(key + " ") or 'name = "B"' in ln) + "\n")

    return f


def _system_values(table: Catalogue) -> None:
    values = (
        ("nan", "nan"),
        ("inf", "inf"),
        ("neg_inf", "-inf"),
        ("negative", "-1.0"),
        ("zero", "0"),
        ("huge", "1e300"),
        ("string", '"1mm"'),
        ("bool", "true"),
        ("array", "[1, 2]"),
        ("missing", None),
    )
    for key in ("source_image_distance", "pixel_pitch"):
        for label, value in values:
            setup = _without_key(key) if value is None else cfg_key(key, value)
            table.add(f"{key}_{label}", CLASS, setup, hints=(key,))
    table.add("pixel_pitch_tiny", CLASS, cfg_key("pixel_pitch", "0.0005"), hints=("pixel_pitch",))
    table.add("sid_in_metres", CLASS, cfg_key("source_image_distance", "1.1"), hints=("source_image_distance",))


def _files_and_frames(table: Catalogue) -> None:
    add = table.add
    for label, value in (
        ("missing_file", '"nope.csv"'),
        ("directory", '"frames"'),
        ("int", "3"),
        ("absolute_etc", '"/etc/passwd"'),
        ("outside", '"../sibling/precious.txt"'),
        ("empty_string", '""'),
        ("nul", '"phan\\u0000tom.csv"'),
    ):
        add(
            f"phantom_file_{label}",
            CLASS,
            cfg_edit('file = "phantom.csv"', f"file = {value}"),
            hints=("phantom", "file"),
        )
    add("lattice_bad", CLASS, cfg_edit('file = "phantom.csv"', 'lattice = "tri"\npitch = 5'), hints=("lattice",))
    add("pitch_nan", CLASS, cfg_edit('file = "phantom.csv"', 'lattice = "hex"\npitch = nan'), hints=("pitch",))
    for label, value in (
        ("no_match", '"frames/A/*.dcm"'),
        ("matches_folder", '"frames/*"'),
        ("empty_list", "[]"),
        ("list_missing", '["frames/A/nope.tif"]'),
        ("list_folder", '["frames/A"]'),
        ("int", "7"),
        ("etc", '"/etc/host*"'),
        ("nul", '"frames/A/\\u0000*.tif"'),
        ("list_of_int", "[1, 2]"),
    ):
        add(f"frames_{label}", CLASS, cfg_key("frames", value), hints=("frames", "/etc/"))
    add(
        "frames_outside_project",
        CLASS,
        chain(
            lambda c: shutil.copytree(c.proj / "frames" / "A", c.root / "sibling" / "A"),
            cfg_key("frames", '"../sibling/A/*.tif"'),
        ),
        expect="ok",
        note="reading frames from anywhere is the user's choice; nothing may be written there",
    )


def _names_and_folders(table: Catalogue) -> None:
    add = table.add
    for label, value in (
        ("traversal", '"B/../../../escaped"'),
        ("absolute", '"/tmp/escaped"'),
        ("dotdot", '".."'),
        ("empty", '""'),
        ("slash", '"a/b"'),
        ("long", '"' + "a" * 300 + '"'),
        ("int", "1"),
        ("hidden", '".hidden"'),
        ("nul", '"A\\u0000"'),
        ("backslash", '"..\\\\..\\\\x"'),
        ("newline", '"A\\nB"'),
    ):
        add(f"system_name_{label}", "names", cfg_key("name", value, 1), hints=("name",))
    add("system_name_duplicate", "names", cfg_key("name", '"A"', 1), hints=("name",))
    add(
        "system_name_unicode",
        "names",
        cfg_key("name", '"Ä"', 1),
        expect="either",
        check=lambda c: None if (c.proj / "out" / "field_Ä.npz").is_file() else "no field_Ä.npz",
        hints=("name",),
        note="either refused as not a safe file name or calibrated under that name",
    )
    for label, value in (
        ("dot", '"."'),
        ("dotdot", '".."'),
        ("file", '"phantom.csv"'),
        ("frames", '"frames"'),
        ("cache", '".fluorocal"'),
        ("int", "1"),
        ("nul", '"out\\u0000"'),
        ("etc_file", '"/etc/passwd"'),
        ("proc", '"/proc/self"'),
    ):
        add(
            f"output_dir_{label}",
            CLASS,
            cfg_replace('dir = "out"', f"dir = {value}"),
            hints=("output", "dir", "phantom.csv", "folder"),
        )
    add(
        "output_dir_sibling",
        CLASS,
        cfg_replace('dir = "out"', 'dir = "../sibling"'),
        expect="either",
        allow=("sibling",),
        hints=("output",),
        check=lambda c: (
            sibling_intact(c) or (None if (c.root / "sibling" / "calibration.json").is_file() else "no calibration")
        ),
        note="an [output] dir outside the project is the user's choice; the sibling's own files must survive",
    )
    _cache_dirs(table)


def _cache_dirs(table: Catalogue) -> None:
    for label, value in (
        ("dot", '"."'),
        ("dotdot", '".."'),
        ("file", '"phantom.csv"'),
        ("frames", '"frames"'),
        ("out", '"out"'),
        ("sibling", '"../sibling"'),
        ("int", "1"),
        ("nul", '"c\\u0000"'),
        ("etc", '"/etc"'),
    ):
        table.add(f"cache_dir_{label}", CLASS, cfg_append(f"[cache]\ndir = {value}"), hints=("cache", "dir", "folder"))


def _stages_and_compute(table: Catalogue) -> None:
    add = table.add
    add("scheme_unknown", CLASS, cfg_edit('scheme = "knn+iop+smooth"', 'scheme = "magic"'), hints=("scheme",))
    add("scheme_int", CLASS, cfg_edit('scheme = "knn+iop+smooth"', "scheme = 3"), hints=("scheme",))
    add("compute_scheduler", CLASS, cfg_append("[compute]\nscheduler = 'tcp://evil:8786'"), hints=("scheduler",))
    for label, value in (("neg", "-1"), ("zero", "0"), ("str", '"x"'), ("float", "1.5")):
        add(f"compute_jobs_{label}", CLASS, cfg_append(f"[compute]\njobs = {value}"), hints=("jobs",))
    add(
        "compute_jobs_huge",
        CLASS,
        cfg_append("[compute]\njobs = 100000000"),
        expect="either",
        note="DEBATABLE: accepted; the pool starts min(jobs, frames to compute) workers, so the number is bounded "
        "by the work, not refused",
    )
    add("compute_threads_zero", CLASS, cfg_append("[compute]\nthreads = 0"), hints=("threads",))
    add("stage_unknown_key", CLASS, cfg_append("[detect]\nbogus = 1"), hints=("bogus",))
    add("stage_owned_key", CLASS, cfg_append("[learn]\nsmooth = true"), hints=("smooth",))
    add("stage_owned_label_pitch", CLASS, cfg_append("[label]\npixel_pitch_mm = 0.5"), hints=("pixel_pitch_mm",))
    add("stage_param_wrong_type", CLASS, cfg_append("[adjust]\nnu = 'four'"), hints=("nu",))
    add("stage_param_nan", CLASS, cfg_append("[adjust]\nnu = nan"), hints=("nu",))
    add("stage_param_negative", CLASS, cfg_append("[adjust]\nnu = -4"), hints=("nu",))
    add("stage_table_not_table", CLASS, cfg_append("detect = 3"), hints=("detect",))
    add(
        "orientations_wrong_type",
        CLASS,
        cfg_key("frames", '"frames/A/*.tif"\norientations = 5'),
        hints=("orientations",),
    )
    add(
        "orientations_traversal_name",
        "names",
        cfg_key(
            "frames",
            '"frames/A/*.tif"\norientations = [{name = "../../x", frames = "frames/A/*.tif", orbit = 0, tilt = 0}]',
        ),
        hints=("orientation", "name"),
    )
    add("seeds_missing", CLASS, cfg_key("frames", '"frames/A/*.tif"\nseeds = "nope.csv"'), hints=("seeds",))
    add(
        "seeds_binary",
        CLASS,
        chain(write_bytes("seeds.csv", os.urandom(3000)), cfg_key("frames", '"frames/A/*.tif"\nseeds = "seeds.csv"')),
        hints=("seeds",),
    )
