"""The attack battery's cache cases (``run``, ``inspect``): entries tampered with, forged, linked out, left over.

A tampered entry is a cache miss: the run recomputes it and its results are the clean run's; no code runs.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from tests.attack.catalogue import Catalogue
from tests.attack.checks import accepted, clean_and_no_leftovers, same_as_clean, sibling_intact
from tests.attack.harness import Ctx, fluorocal
from tests.attack.setups import nothing
from tests.attack.tampering import (
    code_ref,
    edit_array,
    edit_summary,
    entry_edit,
    entry_links_to_sibling,
    flip_byte,
    manifest_payload,
    pickle_npz,
    stage_links_to_sibling,
    touch_cmd,
    truncate,
)

CLASS = "cache"
CODE_REFS = ("os:system", "subprocess:getoutput", "builtins:eval", "posix:system", "pty:spawn")


def cases() -> list:
    """The cache cases, in the battery's order."""
    table = Catalogue()
    for part in (_code_in_manifests, _broken_entries, _links_and_leftovers, _inspect_arguments):
        part(table)
    return table


def command(cmd: str):
    """The commands: ``fluorocal CMD fluorocal.toml``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal(cmd, c.cfg)]

    return commands


def _nested_code_ref(c: Ctx) -> dict:
    return {
        "__dataclass__": "fluorocal.stages.label:Labels",
        "fields": {"x": {"__dataclass__": "os:system", "fields": {"command": touch_cmd(c)}}},
    }


def _code_in_manifests(table: Catalogue) -> None:
    add = table.add
    for stage in ("label", "learn"):
        for ref in CODE_REFS if stage == "label" else CODE_REFS[:1]:  # a learn entry recomputed costs a learning run
            for cmd in ("run", "inspect"):
                add(
                    f"manifest_{ref.replace(':', '_')}_{stage}_{cmd}",
                    CLASS,
                    manifest_payload(stage, code_ref(ref)),
                    command(cmd),
                    expect="ok",
                    check=same_as_clean if cmd == "run" else accepted,
                )
    add(
        "manifest_code_ref_no_rehash",
        CLASS,
        manifest_payload("label", code_ref("os:system"), rehash_it=False),
        expect="ok",
    )
    add(
        "manifest_array_ref_traversal",
        CLASS,
        manifest_payload("label", lambda c: {"__array__": "../../../sibling/precious.txt"}),
        expect="ok",
    )
    add("manifest_nested_code_ref", CLASS, manifest_payload("label", _nested_code_ref), expect="ok")
    add(
        "manifest_dict_payload",
        CLASS,
        manifest_payload("label", lambda c: {"__dict__": {"__reduce__": touch_cmd(c)}}),
        expect="ok",
    )
    add("arrays_npz_pickled_label", CLASS, pickle_npz("label"), expect="ok")
    add("arrays_npz_pickled_learn", CLASS, pickle_npz("learn"), expect="ok")
    add(
        "arrays_npz_pickled_inspect",
        CLASS,
        pickle_npz("label"),
        lambda c: [fluorocal("inspect", c.cfg, "label")],
        expect="ok",
        check=accepted,
    )


def _manifest_is_dir(e: Path) -> None:
    (e / "manifest.json").unlink()
    (e / "manifest.json").mkdir()


def _entry_is_file(e: Path) -> None:
    shutil.rmtree(e)
    e.write_text("x")


def _arrays_link_etc(e: Path) -> None:
    (e / "arrays.npz").unlink()
    (e / "arrays.npz").symlink_to("/etc/passwd")


def _broken_entries(table: Catalogue) -> None:
    add = table.add
    for stage in ("detect", "label"):
        for name, fn in (
            ("arrays_bitflip", flip_byte("arrays.npz")),
            ("arrays_truncated", truncate("arrays.npz")),
            ("manifest_edited", edit_summary),
            ("manifest_deleted", lambda e: (e / "manifest.json").unlink()),
            ("checksum_deleted", lambda e: (e / "manifest.sha256").unlink()),
            ("manifest_garbage", lambda e: (e / "manifest.json").write_bytes(os.urandom(900))),
            ("manifest_is_dir", _manifest_is_dir),
            ("entry_is_file", _entry_is_file),
            ("arrays_symlink_etc", _arrays_link_etc),
        ):
            add(f"{stage}_{name}", CLASS, entry_edit(stage, fn), expect="ok")
    add("learn_manifest_edited", CLASS, entry_edit("learn", edit_summary), expect="ok")
    add(
        "learn_arrays_forged_rehashed",
        CLASS,
        entry_edit("learn", edit_array),
        expect="either",
        check=accepted,
        note="DEBATABLE: a forger who rewrites the data and every checksum is indistinguishable from the cache's "
        "own writer (the checksum guards faults, not forgery); the run must not crash or run code; its "
        "result is the forged one",
    )


def _sibling_intact_and_clean(c: Ctx) -> str | None:
    return sibling_intact(c) or same_as_clean(c)


def _links(table: Catalogue) -> None:
    add = table.add
    add(
        "stage_folder_symlink_sibling",
        CLASS,
        stage_links_to_sibling,
        expect="either",
        hints=("label", "link", "cache"),
        allow=("sibling",),
        check=_sibling_intact_and_clean,
        note="a stage folder linked out of the cache: recomputing into it writes where it points",
    )
    add(
        "entry_symlink_sibling",
        CLASS,
        entry_edit("label", entry_links_to_sibling),
        expect="either",
        hints=("label", "link", "cache"),
        check=_sibling_intact_and_clean,
    )
    add(
        "cache_marker_deleted",
        CLASS,
        lambda c: (c.proj / ".fluorocal" / ".fluorocal-cache").unlink(),
        expect="either",
        hints=("cache",),
    )
    add(
        "cache_marker_garbage",
        CLASS,
        lambda c: (c.proj / ".fluorocal" / ".fluorocal-cache").write_bytes(os.urandom(50)),
        expect="either",
        hints=("cache",),
    )


def _tmp_leftover(c: Ctx) -> None:
    (c.proj / ".fluorocal" / "label" / f".tmp-{'a' * 64}-xyz1").mkdir()
    (c.proj / ".fluorocal" / "label" / f".tmp-{'a' * 64}-xyz1" / "x").write_text("x")


def _staging_leftover(c: Ctx) -> None:
    (c.proj / ".out.fluorocal-staging-999999-abcdef01").mkdir()
    (c.proj / ".out.fluorocal-staging-999999-abcdef01" / "calibration.json").write_text("{}")


def _outputs_manifest_lists_user_file(c: Ctx) -> None:
    (c.proj / "out" / "mine.txt").write_text("user")
    (c.proj / "out" / ".fluorocal-outputs.json").write_text(json.dumps({"entries": ["mine.txt", "../phantom.csv"]}))


def _links_and_leftovers(table: Catalogue) -> None:
    _links(table)
    add = table.add
    add("cache_tmp_leftovers", CLASS, _tmp_leftover, expect="ok", check=clean_and_no_leftovers)
    add("out_staging_leftovers", CLASS, _staging_leftover, expect="ok", check=clean_and_no_leftovers)
    add(
        "out_manifest_lists_user_file",
        CLASS,
        _outputs_manifest_lists_user_file,
        expect="ok",
        check=same_as_clean,
        note="a hand-edited outputs manifest may at most lose files inside the output folder",
    )
    add(
        "out_is_symlink_sibling",
        CLASS,
        lambda c: (shutil.rmtree(c.proj / "out"), (c.proj / "out").symlink_to(c.root / "sibling")),
        expect="either",
        hints=("out",),
        allow=("sibling", "proj/out"),
        check=sibling_intact,
        note="DEBATABLE: the output folder is a link to the user's other folder",
    )
    add(
        "cache_is_symlink_sibling",
        CLASS,
        lambda c: (shutil.rmtree(c.proj / ".fluorocal"), (c.proj / ".fluorocal").symlink_to(c.root / "sibling")),
        expect="either",
        hints=("cache", ".fluorocal", "sibling"),
        allow=(),
        check=sibling_intact,
    )


def _inspect_arguments(table: Catalogue) -> None:
    add = table.add
    add(
        "inspect_frame_overlay_huge_index",
        CLASS,
        nothing,
        lambda c: [fluorocal("inspect", c.cfg, "detect", "--frame", "999")],
        hints=("frame", "999"),
    )
    add(
        "inspect_frame_negative",
        CLASS,
        nothing,
        lambda c: [fluorocal("inspect", c.cfg, "detect", "--frame", "-1")],
        hints=("frame",),
    )
    add("inspect_stage_unknown", CLASS, nothing, lambda c: [fluorocal("inspect", c.cfg, "bogus")], hints=("bogus",))
    add(
        "inspect_stage_traversal",
        CLASS,
        nothing,
        lambda c: [fluorocal("inspect", c.cfg, "../../sibling")],
        hints=("sibling", "stage"),
    )
