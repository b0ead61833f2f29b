"""The attack battery's cases of the other commands' inputs: detect, label, adjust, export, evaluate, simulate."""

from __future__ import annotations

import os

import numpy as np

from tests.attack.catalogue import Catalogue
from tests.attack.checks import accepted
from tests.attack.harness import Ctx, fluorocal
from tests.attack.setups import chain, nothing, phantom_cell, scale_phantom, tiff, write_bytes

CLASS = "commands"
DETECTIONS_HEAD = "file,frame,x,y,sigma_x,sigma_y,rho,major,minor\n"


def cases() -> list:
    """The cases of the other commands, in the battery's order."""
    table = Catalogue()
    for part in (_detect, _label, _adjust, _export, _evaluate_and_simulate):
        part(table)
    return table


def detect(*args: str):
    """The commands: ``fluorocal detect ARGS`` of frame A's first into ``proj/det``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("detect", *args, "--out", c.proj / "det", c.frames("A")[0])]

    return commands


def _many_detections(c: Ctx) -> str | None:
    return None if len((c.proj / "det" / "detections.csv").read_text().splitlines()) > 50 else "few detections"


def _no_detection(c: Ctx) -> str | None:
    return None if len((c.proj / "det" / "detections.csv").read_text().splitlines()) <= 1 else "beads in a 1x1 frame"


def _detect(table: Catalogue) -> None:
    add = table.add
    det = ("proj/det",)
    add("detect_ok", CLASS, nothing, detect(), expect="ok", allow=det, check=_many_detections)
    add(
        "detect_missing_file",
        CLASS,
        nothing,
        lambda c: [fluorocal("detect", "--out", c.proj / "det", c.proj / "no.tif")],
        hints=("no.tif",),
        allow=det,
    )
    add(
        "detect_binary_file",
        CLASS,
        write_bytes("bad.tif", os.urandom(999)),
        lambda c: [fluorocal("detect", "--out", c.proj / "det", c.proj / "bad.tif")],
        hints=("bad.tif",),
        allow=det,
    )
    add(
        "detect_out_is_dir",
        CLASS,
        lambda c: (c.proj / "det" / "detections.csv").mkdir(parents=True),
        detect(),
        hints=("detections.csv",),
        allow=det,
    )
    add("detect_diameter_garbage", CLASS, nothing, detect("--diameter", "a:b"), hints=("diameter",), allow=det)
    add("detect_diameter_negative", CLASS, nothing, detect("--diameter", "-5:3"), hints=("diameter",), allow=det)
    add("detect_diameter_nan", CLASS, nothing, detect("--diameter", "nan:inf"), hints=("diameter",), allow=det)
    add(
        "detect_overlay_traversal",
        CLASS,
        nothing,
        detect("--overlay", "../../sibling_overlay"),
        expect="either",
        allow=("proj/det", "sibling_overlay"),
        check=accepted,
        note="--overlay names the user's own folder",
    )
    add(
        "detect_1x1",
        CLASS,
        tiff("one.tif", np.full((1, 1), 5, np.uint16)),
        lambda c: [fluorocal("detect", "--out", c.proj / "det", c.proj / "one.tif")],
        hints=("one.tif",),
        allow=det,
        expect="either",
        check=_no_detection,
        note="DEBATABLE: the debugging command reports the frame (no field of view, no candidates), writes no row",
    )


def detections(text):
    """The setup: ``proj/det.csv`` holding ``text`` (str or bytes)."""
    return write_bytes("det.csv", text.encode() if isinstance(text, str) else text)


def label(*args: str):
    """The commands: ``fluorocal label det.csv`` with the phantom and system A's geometry, into ``proj/lab``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [
            fluorocal(
                "label",
                c.proj / "det.csv",
                "--phantom",
                c.proj / "phantom.csv",
                "--source-image-distance",
                "1100",
                "--pixel-pitch",
                "0.5",
                "--image-size",
                "512",
                "512",
                "--out",
                c.proj / "lab",
                *args,
            )
        ]

    return commands


def _no_labels(c: Ctx) -> str | None:
    return None if len((c.proj / "lab" / "labels.csv").read_text().splitlines()) <= 1 else "labels from nothing"


NON_FINITE_NOTE = (
    "DEBATABLE: a non-finite detection is a failed fit by the CSV's definition (README); the frame's "
    "labelling fails with its reason, no label is written"
)


def _label(table: Catalogue) -> None:
    add, head = table.add, DETECTIONS_HEAD
    for name, text in (
        ("empty", ""),
        ("header_only", head),
        ("binary", os.urandom(2000)),
        ("missing_column", "file,frame,x,y\nf.tif,0,1,2\n"),
        ("nan_x", head + "f.tif,0,nan,2,0.1,0.1,0,5,5\n"),
        ("text_y", head + "f.tif,0,1,abc,0.1,0.1,0,5,5\n"),
        ("inf_sigma", head + "f.tif,0,1,2,inf,0.1,0,5,5\n"),
        ("negative_frame", head + "f.tif,-1,1,2,0.1,0.1,0,5,5\n"),
    ):
        documented = name in ("nan_x", "inf_sigma", "negative_frame")
        add(
            f"label_detections_{name}",
            CLASS,
            detections(text),
            label(),
            hints=("det.csv",),
            allow=("proj/lab",),
            expect="either" if documented else "refuse",
            check=_no_labels,
            note=NON_FINITE_NOTE if documented else "",
        )
    lab = ("proj/lab",)
    add(
        "label_sid_nan",
        CLASS,
        detections(head),
        label("--source-image-distance", "nan"),
        hints=("source-image-distance",),
        allow=lab,
    )
    add(
        "label_image_size_negative",
        CLASS,
        detections(head),
        label("--image-size", "-1", "-1"),
        hints=("image-size", "image size"),
        allow=lab,
    )
    add(
        "label_phantom_metres",
        CLASS,
        chain(detections(head), scale_phantom(0.001)),
        label(),
        hints=("phantom", "metres"),
        allow=lab,
    )


def adjust(*args: str):
    """The commands: ``fluorocal adjust --observations obs.csv --phantom phantom.csv`` into ``proj/adj``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [
            fluorocal(
                "adjust",
                "--observations",
                c.proj / "obs.csv",
                "--phantom",
                c.proj / "phantom.csv",
                "--out",
                c.proj / "adj",
                *args,
            )
        ]

    return commands


def observations(fn):
    """The setup: ``proj/obs.csv`` holding the clean run's observations.csv, its lines changed by ``fn``."""

    def f(c: Ctx) -> None:
        lines = (c.proj / "out" / "observations.csv").read_text().splitlines()
        (c.proj / "obs.csv").write_text("\n".join(fn(lines)) + "\n")

    return f


def _as_they_are(lines: list[str]) -> list[str]:
    return lines


def _nan_in_row_5(lines: list[str]) -> list[str]:
    """Data line 5's fifth value (its first occurrence in the line) replaced by nan."""
    return lines[:5] + [lines[5].replace(lines[5].split(",")[4], "nan", 1)] + lines[6:]


def _observations_latin1(c: Ctx) -> None:
    (c.proj / "obs.csv").write_bytes(
        (c.proj / "out" / "observations.csv").read_bytes().replace(b",A,", ",\xc4,".encode("latin-1"), 1)
    )


def _adjust(table: Catalogue) -> None:
    add, adj, same = table.add, ("proj/adj",), observations(_as_they_are)
    add("adjust_obs_empty", CLASS, write_bytes("obs.csv", b""), adjust(), hints=("obs.csv",), allow=adj)
    add("adjust_obs_binary", CLASS, write_bytes("obs.csv", os.urandom(3000)), adjust(), hints=("obs.csv",), allow=adj)
    add("adjust_obs_nan", CLASS, observations(_nan_in_row_5), adjust(), hints=("obs.csv",), allow=adj)
    add("adjust_obs_latin1", CLASS, _observations_latin1, adjust(), hints=("obs.csv",), allow=adj)
    add("adjust_nu_nan", CLASS, same, adjust("--nu", "nan"), hints=("nu",), allow=adj)
    add("adjust_nu_negative", CLASS, same, adjust("--nu", "-2"), hints=("nu",), allow=adj)
    add(
        "adjust_sid_inf",
        CLASS,
        same,
        adjust("--source-image-distance", "inf"),
        hints=("source-image-distance",),
        allow=adj,
    )
    add(
        "adjust_out_is_file",
        CLASS,
        chain(same, lambda c: (c.proj / "adj").write_text("x")),
        adjust(),
        hints=("adj",),
        allow=adj,
    )
    add(
        "adjust_phantom_nan", CLASS, chain(same, phantom_cell(3, 1, "nan")), adjust(), hints=("phantom.csv",), allow=adj
    )


def export(fmt: str, out: str = "exp", *args: str):
    """The commands: ``fluorocal export --format FMT --out proj/OUT ARGS`` of the project's calibration."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("export", "--format", fmt, "--out", c.proj / out, *args, c.cal)]

    return commands


def _export(table: Catalogue) -> None:
    add = table.add
    add("export_format_unknown", CLASS, nothing, export("evil"), hints=("format",), allow=("proj/exp",))
    add(
        "export_out_is_file",
        CLASS,
        lambda c: (c.proj / "exp").write_text("x"),
        export("opencv"),
        hints=("exp",),
        allow=("proj/exp",),
    )
    add(
        "export_out_in_frames_overwrite",
        CLASS,
        nothing,
        export("opencv", "frames/A", "--overwrite"),
        expect="either",
        allow=("proj/frames/A/*",),
        check=lambda c: None if len(c.frames("A")) == 4 else "frames lost",
        note="export into the frames' folder: only new files, the frames stay",
    )


def evaluate(*args: str):
    """The commands: ``fluorocal evaluate fluorocal.toml --out proj/ev ARGS``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("evaluate", c.cfg, "--out", c.proj / "ev", *args)]

    return commands


def _evaluate_and_simulate(table: Catalogue) -> None:
    add = table.add
    for name, args in (
        ("holdout_garbage", ("--holdout", "sometimes")),
        ("holdout_missing_file", ("--holdout", "nope.tif")),
        ("train_sizes_negative", ("--train-sizes", "-1")),
        ("train_sizes_zero", ("--train-sizes", "0")),
        ("train_sizes_text", ("--train-sizes", "abc")),
        ("train_sizes_huge", ("--train-sizes", "99")),
        ("schemes_unknown", ("--schemes", "magic")),
        ("reference_missing", ("--reference", "nope.csv")),
        ("reference_binary", ("--reference", "phantom_bin.csv")),
        ("random_seed_text", ("--holdout", "random:x")),
    ):
        add(
            f"evaluate_{name}",
            CLASS,
            write_bytes("phantom_bin.csv", os.urandom(500)),
            evaluate(*args),
            hints=("holdout", "train", "schemes", "reference", "nope", "phantom_bin", "random"),
            allow=("proj/ev",),
        )
    add(
        "simulate_into_project",
        CLASS,
        nothing,
        lambda c: [fluorocal("simulate", c.proj, "--frames", "2")],
        hints=("simulate", "exists", "force", "proj"),
        note="simulate over an existing project refuses without --overwrite",
    )
    add(
        "simulate_frames_negative",
        CLASS,
        nothing,
        lambda c: [fluorocal("simulate", c.proj / "sim2", "--frames", "-3")],
        hints=("frames",),
        allow=("proj/sim2",),
    )
    add(
        "simulate_image_size_huge",
        CLASS,
        nothing,
        lambda c: [fluorocal("simulate", c.proj / "sim2", "--image-size", "10000000", "10000000")],
        hints=("image-size", "image size"),
        allow=("proj/sim2",),
    )
