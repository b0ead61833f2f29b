"""The attack battery's cases, one table (module) per theme; :func:`all_cases` lists them in the battery's order."""

from __future__ import annotations

from tests.attack.cases import (
    cache,
    calibration,
    clean,
    commands,
    config,
    faults,
    frames,
    issue28,
    permissions,
    phantom,
    undistort,
)

#: the tables in the battery's order
TABLES = (config, permissions, phantom, frames, calibration, undistort, cache, clean, commands, faults, issue28)


def all_cases() -> list:
    """Every case of the battery, table after table."""
    return [case for table in TABLES for case in table.cases()]
