"""The attack battery's phantom cases: phantom.csv empty, binary, in other units, with bad cells, rows or files."""

from __future__ import annotations

import os

from tests.attack.catalogue import Catalogue
from tests.attack.checks import same_as_clean
from tests.attack.harness import Ctx
from tests.attack.setups import make_dir, phantom_cell, phantom_rows, scale_phantom, symlink, write_bytes, write_rows

CLASS = "phantom"


def cases() -> list:
    """The phantom cases, in the battery's order."""
    table = Catalogue()
    for part in (_the_file, _cells, _rows, _kinds_of_file):
        part(table)
    return table


def _the_file(table: Catalogue) -> None:
    add = table.add
    add("phantom_empty", CLASS, write_bytes("phantom.csv", b""), hints=("phantom.csv",))
    add("phantom_header_only", CLASS, write_bytes("phantom.csv", b"id,x,y,z,diameter,role\n"), hints=("phantom.csv",))
    add("phantom_binary", CLASS, write_bytes("phantom.csv", os.urandom(5000)), hints=("phantom.csv",))
    add(
        "phantom_latin1",
        CLASS,
        lambda c: (c.proj / "phantom.csv").write_bytes(
            (c.proj / "phantom.csv").read_bytes() + "999,1,2,3,3.5,é\n".encode("latin-1")
        ),
        hints=("phantom.csv",),
    )
    add(
        "phantom_bom",
        CLASS,
        lambda c: (c.proj / "phantom.csv").write_bytes(b"\xef\xbb\xbf" + (c.proj / "phantom.csv").read_bytes()),
        expect="ok",
    )
    add(
        "phantom_crlf",
        CLASS,
        lambda c: (c.proj / "phantom.csv").write_bytes((c.proj / "phantom.csv").read_bytes().replace(b"\n", b"\r\n")),
        expect="ok",
    )
    add("phantom_metres", CLASS, scale_phantom(0.001), hints=("metres", "phantom.csv"))
    add("phantom_inches", CLASS, scale_phantom(1 / 25.4), hints=("inches", "phantom.csv"))
    add(
        "phantom_cm",
        CLASS,
        scale_phantom(0.1),
        hints=("phantom.csv", "cm", "centimetres"),
        note="a cube of 12 instead of 120: no unit of the three named, but as wrong",
    )
    add("phantom_x1000", CLASS, scale_phantom(1000.0), hints=("phantom.csv",))


def _nan_diameter_right(c: Ctx) -> str | None:
    return same_as_clean(c, tol_mm=0.05)


def _renamed_right(c: Ctx) -> str | None:
    # the bead of id 2 (data row 3) renamed -1: the same points, listed first
    return same_as_clean(c, renamed={-1: 2})


#: the cases of one cell whose exit 0 is right too: their expectation and check
_EITHER = {
    "id_negative": {"expect": "either", "check": _renamed_right},
    "role_garbage": {"expect": "either"},
    "nan_diameter": {
        "expect": "either",
        "check": _nan_diameter_right,
        "note": "DEBATABLE: 'nan' reads as an empty cell, a diameter not given (the column is optional)",
    },
}


def _cells(table: Catalogue) -> None:
    for label, value, col in (
        ("nan_x", "nan", 1),
        ("inf_y", "inf", 2),
        ("neginf_z", "-inf", 3),
        ("text_x", "abc", 1),
        ("empty_z", "", 3),
        ("neg_diameter", "-3.5", 4),
        ("zero_diameter", "0", 4),
        ("nan_diameter", "nan", 4),
        ("huge_x", "1e300", 1),
        ("id_text", "bead", 0),
        ("id_float", "1.5", 0),
        ("id_negative", "-1", 0),
        ("id_huge", "99999999999999999999999", 0),
        ("role_garbage", "evil", 5),
    ):
        table.add(
            f"phantom_{label}", CLASS, phantom_cell(3, col, value), hints=("phantom.csv",), **_EITHER.get(label, {})
        )


def _duplicate_point(c: Ctx) -> None:
    """The fourth data row given the third's coordinates (its own id kept)."""
    r = phantom_rows(c)
    write_rows(c, r[:4] + [[r[4][0]] + r[3][1:]] + r[5:])


def _rows(table: Catalogue) -> None:
    add = table.add
    add(
        "phantom_missing_column",
        CLASS,
        lambda c: write_rows(c, [r[:3] + r[4:] for r in phantom_rows(c)]),
        hints=("phantom.csv", "z"),
    )
    add(
        "phantom_extra_column",
        CLASS,
        lambda c: write_rows(c, [r + (["extra"] if i == 0 else ["1"]) for i, r in enumerate(phantom_rows(c))]),
        expect="either",
    )
    add(
        "phantom_short_row",
        CLASS,
        lambda c: write_rows(c, [r if i != 5 else r[:2] for i, r in enumerate(phantom_rows(c))]),
        hints=("phantom.csv",),
    )
    add("phantom_duplicate_id", CLASS, phantom_cell(4, 0, "2"), hints=("phantom.csv", "id"))
    add("phantom_duplicate_point", CLASS, _duplicate_point, hints=("phantom.csv",))
    add("phantom_one_bead", CLASS, lambda c: write_rows(c, phantom_rows(c)[:2]), hints=("phantom.csv",))
    add(
        "phantom_semicolons",
        CLASS,
        lambda c: (c.proj / "phantom.csv").write_text((c.proj / "phantom.csv").read_text().replace(",", ";")),
        hints=("phantom.csv",),
    )
    add(
        "phantom_huge_rows",
        CLASS,
        lambda c: (c.proj / "phantom.csv").write_text(
            "id,x,y,z,diameter,role\n" + "".join(f"{i},{i % 1000}.5,{i // 1000}.25,0,3.5,\n" for i in range(2_000_000))
        ),
        hints=("phantom.csv",),
    )
    add(
        "phantom_long_line",
        CLASS,
        lambda c: (c.proj / "phantom.csv").write_text(
            (c.proj / "phantom.csv").read_text() + "1," + "9" * 10_000_000 + ",0,0,3.5,\n"
        ),
        hints=("phantom.csv",),
    )


def _kinds_of_file(table: Catalogue) -> None:
    add = table.add
    add("phantom_directory", CLASS, make_dir("phantom.csv"), hints=("phantom",))
    add("phantom_symlink_etc", CLASS, symlink("phantom.csv", "/etc/passwd"), hints=("phantom",))
    add(
        "phantom_symlink_loop",
        CLASS,
        lambda c: ((c.proj / "phantom.csv").unlink(), (c.proj / "phantom.csv").symlink_to(c.proj / "phantom.csv")),
        hints=("phantom",),
    )
    add(
        "phantom_fifo",
        CLASS,
        lambda c: ((c.proj / "phantom.csv").unlink(), os.mkfifo(c.proj / "phantom.csv")),
        hints=("phantom",),
    )
    add(
        "phantom_quoted",
        CLASS,
        lambda c: write_rows(c, [[f'"{v}"' for v in r] for r in phantom_rows(c)]),
        expect="either",
    )
    add(
        "phantom_formula_injection",
        CLASS,
        phantom_cell(3, 5, "=cmd|' /C calc'!A0"),
        expect="either",
        hints=("phantom.csv", "role"),
    )
