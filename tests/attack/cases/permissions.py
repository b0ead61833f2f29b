"""The attack battery's permission cases: read-only and unreadable files, run as an unprivileged user.

As root, the commands run without the capabilities that override permissions (``setpriv``), so read-only is
read-only.
"""

from __future__ import annotations

from tests.attack.catalogue import Catalogue
from tests.attack.checks import accepted
from tests.attack.harness import fluorocal, run_cfg
from tests.attack.setups import nothing
from tests.attack.tampering import entries

CLASS = "permissions"


def cases() -> list:
    """The permission cases, in the battery's order."""
    table = Catalogue()

    def ro(name, readonly, setup=nothing, expect="refuse", hints=(), commands=run_cfg, **kw):
        table.add(name, CLASS, setup, commands, expect=expect, hints=hints, as_nobody=True, readonly=readonly, **kw)

    ro("readonly_project", ("proj",), hints=("not writable", "permission", "proj"))
    ro("readonly_output", ("proj/out",), hints=("out",), expect="either")
    ro("readonly_cache", ("proj/.fluorocal",), hints=(".fluorocal", "cache"))
    ro("readonly_cache_stage", ("proj/.fluorocal/label",), hints=("label", "permission"), expect="either")
    ro("readonly_frame", (), lambda c: (c.frames("A")[0]).chmod(0), hints=("frame_000",))
    ro("unreadable_phantom", (), lambda c: (c.proj / "phantom.csv").chmod(0), hints=("phantom",))
    ro("unreadable_config", (), lambda c: c.cfg.chmod(0), hints=("fluorocal.toml",))
    ro("unreadable_cache_entry", (), lambda c: (entries(c, "label")[0] / "manifest.json").chmod(0), expect="either")
    ro(
        "readonly_inspect",
        ("proj", "proj/.fluorocal"),
        expect="ok",
        commands=lambda c: [fluorocal("inspect", c.cfg)],
        check=accepted,
    )
    ro(
        "readonly_undistort_out",
        ("proj",),
        hints=("und", "permission", "writable"),
        commands=lambda c: [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.frames("A")[0])],
    )
    return table
