"""The attack battery's calibration cases: calibration.json and its field files broken, read by undistort etc.

Each bad file is given to ``undistort``; the ones in :data:`ALL_COMMANDS` to ``inspect`` and ``export`` as well.
"""

from __future__ import annotations

import json
import os

import numpy as np

from tests.attack.catalogue import Catalogue
from tests.attack.checks import accepted
from tests.attack.harness import Ctx, fluorocal, undistort_first
from tests.attack.setups import field_npz
from tests.attack.tampering import flip_byte, pickle_field, truncate

CLASS = "calibration"
#: where undistort, inspect and export write
ALLOW = ("proj/und", "proj/insp", "proj/exp")
HINTS = ("calibration.json", "field_A.npz", "field", "image_size", "passwd", "precious")
#: the bad files given to each of the three commands; the others go to undistort only
ALL_COMMANDS = (
    "list",
    "binary",
    "deep_nesting",
    "image_size_negative",
    "field_file_absolute",
    "field_npz_truncated",
    "field_npz_bitflip",
    "field_npz_pickled",
    "latin1",
    "system_name_traversal",
)
#: the bad files whose exit 0 is right too
EITHER = ("version_future", "field_npz_nodes_unsorted")


def cases() -> list:
    """The calibration cases, in the battery's order."""
    table = Catalogue()
    for label, setup in [*_bad_json(), *_bad_fields()]:
        for cmd in ("undistort", "inspect", "export") if label in ALL_COMMANDS else ("undistort",):
            either = {"expect": "either", "check": accepted} if label in EITHER else {}
            table.add(f"cal_{label}_{cmd}", CLASS, setup, on_cal(cmd), hints=HINTS, allow=ALLOW, **either)
    return table


def on_cal(cmd: str):
    """The commands: ``cmd`` (undistort, inspect or export) given the project's calibration."""
    if cmd == "undistort":
        return undistort_first()
    if cmd == "inspect":
        return lambda c: [fluorocal("inspect", c.cal, "--out", c.proj / "insp")]
    return lambda c: [fluorocal("export", "--format", "opencv", "--out", c.proj / "exp", c.cal)]


def cal_json(fn):
    """calibration.json's document changed by ``fn(doc, c)``, in place or by what it returns (not None)."""

    def f(c: Ctx) -> None:
        d = json.loads(c.cal.read_text())
        r = fn(d, c)
        c.cal.write_text(json.dumps(d if r is None else r))

    return f


def set_sys(key, value):
    """A change for :func:`cal_json`: the first system's ``key`` set to ``value``."""

    def fn(d, c):
        d["systems"][0][key] = value

    return fn


def _set_field_file(value):
    """A change for :func:`cal_json`: the first system's field file named ``value`` (or ``value(c)``)."""

    def fn(d, c):
        d["systems"][0]["field"]["file"] = value(c) if callable(value) else value

    return fn


def _bad_json() -> list:
    """(label, setup) of calibration.json broken."""
    return [
        ("list", cal_json(lambda d, c: [d])),
        ("empty", lambda c: c.cal.write_bytes(b"")),
        ("binary", lambda c: c.cal.write_bytes(os.urandom(4000))),
        ("latin1", lambda c: c.cal.write_bytes(c.cal.read_bytes().replace(b'"A"', '"\xc4"'.encode("latin-1"), 1))),
        ("not_json", lambda c: c.cal.write_text("{'systems': [}")),
        ("deep_nesting", lambda c: c.cal.write_text("[" * 100_000 + "]" * 100_000)),
        ("missing_systems", cal_json(lambda d, c: d.pop("systems"))),
        ("systems_not_list", cal_json(lambda d, c: d.__setitem__("systems", "A"))),
        ("schema_wrong", cal_json(lambda d, c: d.__setitem__("schema", "other"))),
        ("version_future", cal_json(lambda d, c: d.__setitem__("schema_version", 99))),
        ("image_size_negative", cal_json(set_sys("image_size_px", [-512, 512]))),
        ("image_size_huge", cal_json(set_sys("image_size_px", [10**9, 10**9]))),
        ("image_size_nan", cal_json(set_sys("image_size_px", [float("nan"), 512]))),
        ("image_size_string", cal_json(set_sys("image_size_px", "512x512"))),
        ("iop_nan", cal_json(lambda d, c: d["systems"][0]["iop_px"].__setitem__("c", float("nan")))),
        ("iop_negative_c", cal_json(lambda d, c: d["systems"][0]["iop_px"].__setitem__("c", -2000.0))),
        ("iop_missing", cal_json(lambda d, c: d["systems"][0].pop("iop_px"))),
        ("field_file_absolute", cal_json(_set_field_file(lambda c: str(c.proj / "out" / "field_B.npz")))),
        ("field_file_dotdot", cal_json(_set_field_file("../out/field_B.npz"))),
        ("field_file_etc", cal_json(_set_field_file("/etc/passwd"))),
        ("field_file_int", cal_json(_set_field_file(5))),
    ]


def _field_is_directory(c: Ctx) -> None:
    (c.proj / "out" / "field_A.npz").unlink()
    (c.proj / "out" / "field_A.npz").mkdir()


def _field_links_to_sibling(c: Ctx) -> None:
    (c.proj / "out" / "field_A.npz").unlink()
    (c.proj / "out" / "field_A.npz").symlink_to(c.root / "sibling" / "precious.txt")


def _bad_fields() -> list:
    """(label, setup) of the field files broken, and two systems' names in calibration.json."""
    return [
        ("field_file_missing", lambda c: (c.proj / "out" / "field_A.npz").unlink()),
        ("field_file_directory", _field_is_directory),
        ("field_npz_truncated", lambda c: truncate("field_A.npz")(c.proj / "out")),
        ("field_npz_bitflip", lambda c: flip_byte("field_A.npz", 0.6)(c.proj / "out")),
        ("field_npz_empty", lambda c: (c.proj / "out" / "field_A.npz").write_bytes(b"")),
        ("field_npz_not_zip", lambda c: (c.proj / "out" / "field_A.npz").write_bytes(os.urandom(3000))),
        ("field_npz_missing_array", field_npz(lambda a: a.pop("delta_px"))),
        ("field_npz_wrong_shape", field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"][:5, :7]))),
        ("field_npz_nan", field_npz(lambda a: a["delta_px"].__setitem__((3, 3, 0), np.nan))),
        ("field_npz_1e30", field_npz(lambda a: a.__setitem__("delta_px", a["delta_px"] * 1e30))),
        ("field_npz_nodes_unsorted", field_npz(lambda a: a.__setitem__("x_nodes_px", a["x_nodes_px"][::-1].copy()))),
        ("field_npz_string_array", field_npz(lambda a: a.__setitem__("delta_px", np.array(["x"] * 4)))),
        ("field_npz_pickled", pickle_field),
        ("field_npz_symlink_other", _field_links_to_sibling),
        ("duplicate_system", cal_json(lambda d, c: d["systems"].append(dict(d["systems"][0])))),
        ("system_name_traversal", cal_json(lambda d, c: d["systems"][0].__setitem__("name", "../../x"))),
    ]
