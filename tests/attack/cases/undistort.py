"""The attack battery's undistort cases: bad fields, inputs, output folders, systems and orientations."""

from __future__ import annotations

import os
import shutil

import numpy as np

from tests.attack.catalogue import Catalogue
from tests.attack.checks import sibling_intact, undistorted_ok
from tests.attack.harness import Ctx, fluorocal, undistort_first
from tests.attack.setups import field_npz, nothing, tiff, write_bytes

CLASS = "undistort"
OUT = ("proj/und",)


def cases() -> list:
    """The undistort cases, in the battery's order."""
    table = Catalogue()
    for part in (_fields_and_outputs, _inputs, _arguments, _folders):
        part(table)
    return table


def undistort(*inputs):
    """The commands: ``fluorocal undistort`` of ``inputs`` (each ``Ctx -> Path``) with system A into ``proj/und``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", *(p(c) for p in inputs))]

    return commands


def _other_same_name(c: Ctx) -> None:
    """B's first frame as ``sibling/A/frame_000.tif``: A's first frame's name."""
    (c.root / "sibling" / "A").mkdir()
    shutil.copy(c.frames("B")[0], c.root / "sibling" / "A" / "frame_000.tif")


def _existing_output(c: Ctx) -> None:
    (c.proj / "und").mkdir()
    (c.proj / "und" / "frame_000.tif").write_text("x")


def _fields_and_outputs(table: Catalogue) -> None:
    add = table.add
    add("undistort_ok", CLASS, nothing, undistort_first(), expect="ok", check=undistorted_ok("proj/und", 1), allow=OUT)
    add(
        "undistort_field_1e30",
        CLASS,
        field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"] * 1e30)),
        undistort_first(),
        hints=("field", "calibration"),
        allow=OUT,
    )
    add(
        "undistort_field_200px",
        CLASS,
        field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"] + 600.0)),
        undistort_first(),
        hints=("field", "calibration"),
        allow=OUT,
        note="a field moving every pixel out of the image",
    )
    add(
        "undistort_same_names",
        CLASS,
        _other_same_name,
        undistort(lambda c: c.frames("A")[0], lambda c: c.root / "sibling" / "A" / "frame_000.tif"),
        hints=("frame_000",),
        allow=OUT,
    )
    add(
        "undistort_out_is_file",
        CLASS,
        lambda c: (c.proj / "und").write_text("x"),
        undistort_first(),
        hints=("und",),
        allow=OUT,
    )
    add(
        "undistort_out_is_input_folder",
        CLASS,
        nothing,
        lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "frames" / "A", c.frames("A")[0])],
        hints=("frame_000", "exists"),
    )
    add(
        "undistort_overwrite_inputs",
        CLASS,
        nothing,
        lambda c: [
            fluorocal(
                "undistort", c.cal, "--system", "A", "--out", c.proj / "frames" / "A", "--overwrite", c.frames("A")[0]
            )
        ],
        hints=("frame_000", "input"),
        note="--overwrite onto its own input: refusing is right (reading and writing one file); debatable",
    )
    add("undistort_existing_output", CLASS, _existing_output, undistort_first(), hints=("frame_000",), allow=())


def _inputs(table: Catalogue) -> None:
    add = table.add
    add(
        "undistort_input_missing",
        CLASS,
        nothing,
        undistort(lambda c: c.proj / "nope.tif"),
        hints=("nope.tif",),
        allow=OUT,
    )
    add(
        "undistort_input_empty_folder",
        CLASS,
        lambda c: (c.proj / "empty").mkdir(),
        undistort(lambda c: c.proj / "empty"),
        hints=("empty",),
        allow=("proj/und", "proj/empty"),
    )
    add(
        "undistort_input_binary",
        CLASS,
        write_bytes("bad.tif", os.urandom(5000)),
        undistort(lambda c: c.proj / "bad.tif"),
        hints=("bad.tif",),
        allow=OUT,
    )
    add(
        "undistort_input_other_size",
        CLASS,
        tiff("small.tif", np.full((100, 100), 1000, np.uint16)),
        undistort(lambda c: c.proj / "small.tif"),
        hints=("small.tif", "size"),
        allow=OUT,
    )
    add(
        "undistort_input_1x1",
        CLASS,
        tiff("one.tif", np.full((1, 1), 1000, np.uint16)),
        undistort(lambda c: c.proj / "one.tif"),
        hints=("one.tif", "size"),
        allow=OUT,
    )


def _arguments(table: Catalogue) -> None:
    add = table.add
    add("undistort_system_unknown", CLASS, nothing, undistort_first(system="Z"), hints=("Z",), allow=OUT)
    add(
        "undistort_system_traversal",
        CLASS,
        nothing,
        undistort_first(system="../../etc"),
        hints=("etc", "system"),
        allow=OUT,
    )
    add(
        "undistort_orientation_garbage",
        CLASS,
        nothing,
        undistort_first("--orientation", "orbit=abc,tilt=0"),
        hints=("orientation",),
        allow=OUT,
    )
    add(
        "undistort_orientation_nan",
        CLASS,
        nothing,
        undistort_first("--orientation", "orbit=nan,tilt=0"),
        hints=("orientation",),
        allow=OUT,
    )
    add(
        "undistort_calibration_missing",
        CLASS,
        lambda c: c.cal.unlink(),
        undistort_first(),
        hints=("calibration.json",),
        allow=OUT,
    )
    add(
        "undistort_calibration_is_dir",
        CLASS,
        lambda c: (c.cal.unlink(), c.cal.mkdir()),
        undistort_first(),
        hints=("calibration.json",),
        allow=OUT,
    )


def _folders(table: Catalogue) -> None:
    add = table.add
    add(
        "undistort_two_frames_folder",
        CLASS,
        nothing,
        undistort(lambda c: c.proj / "frames" / "A"),
        expect="ok",
        check=undistorted_ok("proj/und", 4),
        allow=OUT,
    )
    add(
        "undistort_input_is_calibration_npz",
        CLASS,
        nothing,
        undistort(lambda c: c.proj / "out" / "field_A.npz"),
        hints=("field_A.npz",),
        allow=OUT,
    )
    add(
        "undistort_out_symlink_outside",
        CLASS,
        lambda c: (c.proj / "und").symlink_to(c.root / "sibling"),
        undistort_first(),
        expect="either",
        allow=("sibling/frame_000.tif", "proj/und"),
        check=sibling_intact,
        note="an --out that is the user's own link: writing through it is the user's choice; nothing else touched",
    )
