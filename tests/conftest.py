"""Shared test fixtures: the real radiographs in ../shared/data (skipped when absent)."""

import contextlib
import logging
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data" / "arcadis"


@pytest.fixture(scope="session")
def arcadis_dir() -> Path:
    """Directory of the real ARCADIS frames; skips the test on machines without ../shared/data."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real radiographs not present at {SHARED_DATA} (they live only in ../shared/data)")
    return SHARED_DATA


#: the small biplanar project the end-to-end modules share (4 + 4 frames of 512 px)
E2E_SIM = {"n_frames": 4, "n_systems": 2, "image_size_px": 512, "seed": 3}


@contextlib.contextmanager
def logged(level: int = logging.INFO):
    """The records fluorocal's loggers (and ``py.warnings``) emit at ``level`` or above within the block."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler(level)
    handler.emit = records.append
    root, ours = logging.getLogger(), logging.getLogger("fluorocal")
    before = ours.level
    ours.setLevel(level)
    root.addHandler(handler)
    try:
        yield records
    finally:
        root.removeHandler(handler)
        ours.setLevel(before)


@pytest.fixture(scope="session")
def calibrated_run(tmp_path_factory) -> tuple[Path, list[logging.LogRecord]]:
    """A simulated project after one `fluorocal run`, and the records it logged at INFO or above.

    Simulated and calibrated once per test session; warnings are errors there as everywhere in the suite.
    """
    from fluorocal.cli import main
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    root = tmp_path_factory.mktemp("calibrated") / "project"
    write_dataset(simulate(SimulateParams(**E2E_SIM)), root)
    with logged() as records:
        assert main(["--quiet", "run", str(root / "fluorocal.toml")]) == 0
    return root, records


@pytest.fixture(scope="session")
def calibrated_project(calibrated_run) -> Path:
    """The project of :func:`calibrated_run`.

    Modules that change it take a copy (:func:`copy_project`); the cache comes along, so their own runs
    recompute only what they change.
    """
    return calibrated_run[0]


@pytest.fixture(scope="session")
def simulated_grid(tmp_path_factory) -> Path:
    """A simulated plate moved by hand between three 1024² frames at one C-arm orientation, calibrated once.

    (A 512 px frame cannot resolve the holes.) Modules that change it take a copy (:func:`copy_project`).
    """
    from fluorocal.cli import main
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    root = tmp_path_factory.mktemp("grid") / "project"
    write_dataset(simulate(SimulateParams(phantom="grid", n_frames=3, seed=4)), root)
    assert main(["--quiet", "run", str(root / "fluorocal.toml")]) == 0
    return root


def copy_project(source: Path, destination: Path) -> Path:
    """A copy of a project folder (frames, config, cache and outputs) at ``destination``."""
    import shutil

    shutil.copytree(source, destination, symlinks=True)
    return destination
