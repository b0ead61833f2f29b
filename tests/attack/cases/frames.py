"""The attack battery's frame cases: broken, odd and hostile frame files, and the biplanar pairing (``pairing``)."""

from __future__ import annotations

import os
import shutil

import numpy as np

from tests.attack.catalogue import Catalogue
from tests.attack.checks import accepted, same_as_clean
from tests.attack.harness import Ctx
from tests.attack.setups import huge_header_tiff, make_dir, png, read_frame, symlink, tiff, with_inf, write_bytes

CLASS = "frames"
FRAME = "frames/A/frame_001.tif"


def cases() -> list:
    """The frame and pairing cases, in the battery's order."""
    table = Catalogue()
    for part in (_broken, _content, _pairing, _kinds_of_file):
        part(table)
    return table


def _broken(table: Catalogue) -> None:
    add = table.add
    add("frame_empty_file", CLASS, write_bytes(FRAME, b""), hints=("frame_001",))
    add(
        "frame_truncated",
        CLASS,
        lambda c: c.frames("A")[1].write_bytes(c.frames("A")[1].read_bytes()[:3000]),
        hints=("frame_001",),
    )
    add("frame_random_bytes", CLASS, write_bytes(FRAME, os.urandom(80_000)), hints=("frame_001",))
    add(
        "frame_bitflip_header",
        CLASS,
        lambda c: c.frames("A")[1].write_bytes(b"II*\x00\xff\xff\xff\x7f" + c.frames("A")[1].read_bytes()[8:]),
        hints=("frame_001",),
    )
    add("frame_1x1", CLASS, tiff(FRAME, np.full((1, 1), 1000, np.uint16)), hints=("frame_001",))
    add("frame_3x3", CLASS, tiff(FRAME, np.full((3, 3), 1000, np.uint16)), hints=("frame_001",))
    add("frame_other_size", CLASS, tiff(FRAME, np.full((300, 400), 1000, np.uint16)), hints=("frame_001", "size"))


def _content(table: Catalogue) -> None:
    add = table.add
    rng = np.random.default_rng(0)
    add(
        "frame_all_black",
        CLASS,
        tiff(FRAME, np.zeros((512, 512), np.uint16)),
        expect="either",
        check=accepted,
        hints=("frame_001", "label"),
        note="a blank frame: excluded with its reason or refused",
    )
    add(
        "frame_all_white",
        CLASS,
        tiff(FRAME, np.full((512, 512), 65535, np.uint16)),
        expect="either",
        check=accepted,
        hints=("frame_001", "label"),
    )
    add(
        "frame_noise",
        CLASS,
        tiff(FRAME, rng.integers(0, 4096, (512, 512)).astype(np.uint16)),
        expect="either",
        check=accepted,
        hints=("frame_001", "label"),
    )
    add("frame_float_nan", CLASS, tiff(FRAME, np.full((512, 512), np.nan, np.float32)), hints=("frame_001",))
    add(
        "frame_float_inf",
        CLASS,
        lambda c: tiff(FRAME, with_inf(c))(c),
        hints=("frame_001",),
        expect="either",
        check=accepted,
    )
    add(
        "frame_rgb",
        CLASS,
        lambda c: tiff(FRAME, np.repeat(read_frame(c.frames("A")[1])[..., None], 3, 2))(c),
        expect="either",
        check=accepted,
        hints=("frame_001",),
    )
    add(
        "frame_8bit",
        CLASS,
        lambda c: tiff(FRAME, (read_frame(c.frames("A")[1]) // 16).astype(np.uint8))(c),
        expect="either",
        check=accepted,
    )


def _missing_in_b_and_extra(c: Ctx) -> None:
    """B's first frame deleted and its second copied to a new last name: equal counts, the names shifted."""
    c.frames("B")[0].unlink()
    shutil.copy(c.frames("B")[1], c.proj / "frames" / "B" / "frame_009.tif")


def _pairing(table: Catalogue) -> None:
    add = table.add
    add(
        "frame_multipage_in_B",
        "pairing",
        lambda c: tiff("frames/B/frame_001.tif", np.stack([read_frame(c.frames("B")[1])] * 2))(c),
        hints=("frame", "B"),
    )
    add("frame_missing_in_B", "pairing", lambda c: c.frames("B")[1].unlink(), hints=("frame", "B"))
    add(
        "frame_extra_in_A",
        "pairing",
        lambda c: shutil.copy(c.frames("A")[1], c.proj / "frames" / "A" / "frame_004.tif"),
        hints=("frame", "A"),
    )
    add(
        "frame_missing_in_B_and_extra",
        "pairing",
        _missing_in_b_and_extra,
        expect="either",
        check=accepted,
        note="equal counts with the names shifted: pairing is by sorted order (README); debatable",
    )
    add("frame_B_all_missing", "pairing", lambda c: [p.unlink() for p in c.frames("B")], hints=("frames", "B"))


def _linked_from_sibling(c: Ctx) -> None:
    shutil.copy(c.frames("A")[1], c.root / "sibling" / "f.tif")
    symlink(FRAME, "sibling/f.tif")(c)


def _kinds_of_file(table: Catalogue) -> None:
    add = table.add
    add("frame_directory", CLASS, make_dir(FRAME), hints=("frame",))
    add(
        "frame_symlink_outside",
        CLASS,
        _linked_from_sibling,
        expect="ok",
        note="a frame linked from elsewhere is read, nothing written there",
    )
    add("frame_symlink_dangling", CLASS, symlink(FRAME, "sibling/nope.tif"), hints=("frame_001",))
    add("frame_symlink_devzero", CLASS, symlink(FRAME, "/dev/zero"), hints=("frame_001",))
    add(
        "frame_duplicate_content",
        CLASS,
        lambda c: shutil.copy(c.frames("A")[0], c.frames("A")[1]),
        expect="either",
        check=accepted,
        hints=("frame",),
    )
    add("frame_png_named_tif", CLASS, lambda c: png(c.frames("A")[1]), expect="either", check=same_as_clean)
    add(
        "frame_decompression_bomb",
        CLASS,
        tiff(FRAME, np.zeros((20000, 20000), np.uint16), compression="zlib"),
        hints=("frame_001", "size"),
    )
    add("frame_huge_header", CLASS, lambda c: huge_header_tiff(c.frames("A")[1]), hints=("frame_001",))
    add("frame_zero_width", CLASS, tiff(FRAME, np.zeros((0, 512), np.uint16)), hints=("frame_001",))
    add(
        "frame_name_spaces_unicode",
        CLASS,
        lambda c: [p.rename(p.with_name(f"ä b {p.name}")) for p in c.frames("A")],
        expect="ok",
        note="names with spaces and umlauts are fine",
    )
