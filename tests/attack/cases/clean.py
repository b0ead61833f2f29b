"""The attack battery's ``cache clean`` cases: a cache folder that is the project, a sibling, forged or linked out."""

from __future__ import annotations

import json

from tests.attack.catalogue import Catalogue
from tests.attack.checks import accepted, sibling_intact
from tests.attack.harness import Ctx, fluorocal
from tests.attack.setups import cfg_append, nothing, write_bytes
from tests.attack.tampering import entries, entry_edit, entry_links_to_sibling, stage_links_to_sibling

CLASS = "clean"
FORGED_MARKER = json.dumps({"format": "fluorocal-cache", "version": 2})


def cases() -> list:
    """The cache clean cases, in the battery's order."""
    table = Catalogue()
    for part in (_cache_dirs, _forged_and_linked, _kept_and_cleaned):
        part(table)
    return table


def _clean(
    table: Catalogue, name, setup, expect="refuse", hints=("cache",), check=accepted, allow=(), extra=(), note=""
):
    """Add a case running ``fluorocal cache clean fluorocal.toml EXTRA``."""

    def commands(c: Ctx) -> list[list[str]]:
        return [fluorocal("cache", "clean", c.cfg, *extra)]

    table.add(name, CLASS, setup, commands, expect=expect, hints=hints, check=check, allow=allow, note=note)


def _cache_in_sibling_absolute(c: Ctx) -> None:
    c.append_cfg(f'[cache]\ndir = "{c.root / "sibling"}"')


def _cache_dirs(table: Catalogue) -> None:
    for label, value in (
        ("dot", '"."'),
        ("dotdot", '".."'),
        ("sibling", '"../sibling"'),
        ("frames", '"frames"'),
        ("out", '"out"'),
        ("phantom_file", '"phantom.csv"'),
        ("absolute_sibling", None),
        ("nonexistent", '"nothing_here"'),
    ):
        _clean(
            table,
            f"clean_dir_{label}",
            cfg_append(f"[cache]\ndir = {value}") if value else _cache_in_sibling_absolute,
            expect="either" if label == "nonexistent" else "refuse",
            hints=("cache", "dir", "marker", "fluorocal-cache"),
        )


def _marker_forged_in_sibling(c: Ctx) -> None:
    c.append_cfg('[cache]\ndir = "../sibling"')
    (c.root / "sibling" / ".fluorocal-cache").write_text(FORGED_MARKER)


def _key_named_folder_in_forged_cache(c: Ctx) -> None:
    _marker_forged_in_sibling(c)
    (c.root / "sibling" / "work" / ("b" * 64)).mkdir()
    (c.root / "sibling" / "work" / ("b" * 64) / "data.txt").write_text("mine")


def _forged_and_linked(table: Catalogue) -> None:
    _clean(
        table,
        "clean_forged_marker_sibling",
        _marker_forged_in_sibling,
        expect="either",
        allow=("sibling/.fluorocal-cache",),
        check=sibling_intact,
        note="a marker forged into a folder: clean may delete only entries it writes, none of the user's",
    )
    _clean(
        table,
        "clean_forged_marker_key_named",
        _key_named_folder_in_forged_cache,
        expect="either",
        allow=("sibling/.fluorocal-cache", "sibling/work/" + "b" * 64),
        check=sibling_intact,
        note="DEBATABLE: a folder named like a key inside a forged cache is the cache's by its own rules",
    )
    _clean(
        table,
        "clean_entry_symlink_outside",
        entry_edit("label", entry_links_to_sibling),
        expect="ok",
        check=sibling_intact,
    )
    _clean(table, "clean_stage_symlink_outside", stage_links_to_sibling, expect="either", check=sibling_intact)


def _user_file_kept(c: Ctx) -> str | None:
    return None if (c.proj / ".fluorocal" / "my_notes.txt").is_file() else "user file deleted"


def _no_entries_left(c: Ctx) -> str | None:
    return None if not any((c.proj / ".fluorocal").glob("*/*")) else "entries left"


def _learn_entry_kept(c: Ctx) -> str | None:
    return None if len(entries(c, "learn")) == 1 else "entries lost"


def _kept_and_cleaned(table: Catalogue) -> None:
    _clean(
        table,
        "clean_user_file_in_cache",
        lambda c: (c.proj / ".fluorocal" / "my_notes.txt").write_text("mine"),
        expect="ok",
        check=_user_file_kept,
        allow=("proj/.fluorocal",),
    )
    _clean(table, "clean_ok", nothing, expect="ok", check=_no_entries_left)
    _clean(table, "clean_stale", nothing, expect="ok", extra=("--stale",), check=_learn_entry_kept)
    _clean(table, "clean_config_broken", write_bytes("fluorocal.toml", b"[[[["), hints=("fluorocal.toml",))
