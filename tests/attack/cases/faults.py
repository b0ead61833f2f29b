"""The attack battery's faults: SIGKILL in every stage then a rerun (``kill``), concurrent runs, a full disk.

After the fault the rerun's results must be the clean run's, with nothing left behind.
"""

from __future__ import annotations

from tests.attack.catalogue import Catalogue
from tests.attack.checks import clean_and_no_leftovers, undistorted_ok
from tests.attack.harness import Ctx, fluorocal
from tests.attack.runners import concurrently, full_disk, kill_after, kill_when, one_of_two_ok
from tests.attack.setups import nothing


def cases() -> list:
    """The fault cases, in the battery's order."""
    table = Catalogue()
    for part in (_kill, _concurrency, _disk):
        part(table)
    return table


def rerun(*args: str):
    """The commands: ``fluorocal run fluorocal.toml ARGS`` (the one the fault hits), then a plain rerun."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("run", c.cfg, *args), fluorocal("run", c.cfg)]

    return commands


def _kill(table: Catalogue) -> None:
    def add(name, commands, runner):
        table.add(name, "kill", nothing, commands, expect="ok", check=clean_and_no_leftovers, runner=runner)

    for stage in ("detect", "centroid", "label"):
        add(f"kill_during_{stage}_store", rerun("--force", stage), kill_when(f".fluorocal/{stage}/.tmp-*"))
    add("kill_during_learn_store", rerun("--force", "learn"), kill_when(".fluorocal/learn/.tmp-*"))
    add("kill_during_publish", rerun(), kill_when(".out.fluorocal-staging-*"))
    add("kill_during_publish_late", rerun(), kill_when(".out.fluorocal-staging-*/report.md"))
    for t in (1.5, 3.0, 6.0):
        add(f"kill_after_{t:g}s", rerun("--force", "detect"), kill_after(t))
    add(
        "kill_during_clean",
        lambda c: [
            fluorocal("cache", "clean", c.cfg),
            fluorocal("run", c.cfg, "--until", "label"),
            fluorocal("run", c.cfg),
        ],
        kill_after(1.2),
    )


def _concurrency(table: Catalogue) -> None:
    def add(name, commands, runner, **kw):
        table.add(name, "concurrency", nothing, commands, runner=runner, **kw)

    ok = {"expect": "ok", "check": clean_and_no_leftovers}
    add(
        "concurrent_4_warm_runs",
        lambda c: [fluorocal("run", c.cfg)] * 4 + [fluorocal("run", c.cfg)],
        concurrently(4),
        **ok,
    )
    add(
        "concurrent_3_force_label",
        lambda c: [fluorocal("run", c.cfg, "--force", "label", "--until", "label")] * 3 + [fluorocal("run", c.cfg)],
        concurrently(3),
        **ok,
    )
    add(
        "concurrent_run_and_inspect",
        lambda c: [fluorocal("run", c.cfg), fluorocal("inspect", c.cfg), fluorocal("run", c.cfg)],
        concurrently(2),
        **ok,
    )
    add(
        "concurrent_undistort_same_out",
        lambda c: (
            [fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "und", c.frames("A")[0])] * 2
            + [fluorocal("inspect", c.cal, "--out", c.proj / "insp")]
        ),
        one_of_two_ok,
        expect="either",
        check=undistorted_ok("proj/und", 1),
        allow=("proj/und", "proj/insp"),
        note="two undistorts into one folder at once: one writes, the other refuses the existing file",
    )


def _undistort_twice(c: Ctx) -> list[list[str]]:
    """Frames A undistorted into ``out/und`` (the disk full), then into ``out/und2``."""
    return [
        fluorocal("undistort", c.cal, "--system", "A", "--out", c.proj / "out" / out, c.proj / "frames" / "A")
        for out in ("und", "und2")
    ]


def _disk(table: Catalogue) -> None:
    def add(name, commands, free_kb, check=clean_and_no_leftovers):
        runner = full_disk(free_kb)
        table.add(
            name, "disk", nothing, commands, expect="ok", check=check, runner=runner, hints=("space", "too large")
        )

    # the run's arguments and the disk's free space in kB
    add("full_disk_cache", rerun("--force", "label"), 40)
    add("full_disk_outputs", rerun(), 200)
    add("full_disk_outputs_tiny", rerun(), 8)
    add("full_disk_undistort", _undistort_twice, 300, check=undistorted_ok("proj/out/und2", 4))
