"""The attack battery's clean project, built once per test session however many workers run."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.attack.harness import build_base
from tests.conftest import built_once


@pytest.fixture(scope="session")
def attack_base(tmp_path_factory) -> Path:
    """The folder every case copies: ``proj`` (simulated and run once, its cache warm) beside ``sibling``.

    Built by :func:`tests.attack.harness.build_base` once per session (:func:`built_once`). Shared by every
    xdist worker: never write into it (each case runs on its own copy).
    """
    return built_once(tmp_path_factory, "attack", build_base)
