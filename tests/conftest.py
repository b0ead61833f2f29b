"""Shared test fixtures: the real radiographs and the simulated projects built once per session.

The real radiographs live in ../shared/data (skipped when absent); a test that reads them is a `make check` test.
"""

import contextlib
import json
import logging
import os
import warnings
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
#: the grid plate moved by hand between three frames at one orientation: the 1024-px default's pixel pitch, holes
#: and look on half the detector (512², a quarter of the holes)
GRID_SIM = {"phantom": "grid", "n_frames": 3, "seed": 4, "image_size_px": 512, "detector_size_mm": 128.0}
#: the grid plate at the C-arm tilts 0, 15, 30, 45 and 60° (tests/pipeline/plate_orientation.py's ANGLES_DEG), one
#: frame each: the 1024-px default's pixel pitch, hole size and look on half the detector (a quarter of the holes);
#: the orientation change doubled because it is quoted for the whole 1024-px image and scales with it, so that it
#: stays the real C-arm's in px (~0.2 px at 15°, ~0.64 at 60°)
GRID_TILTS_SIM = {
    "phantom": "grid",
    "n_frames": 1,
    "orientations_deg": ((0, 0), (0, 15), (0, 30), (0, 45), (0, 60)),
    "image_size_px": 512,
    "detector_size_mm": 128.0,
    "orientation_distortion_px": 1.92,
    "seed": 0,
}


def built_once(tmp_path_factory, name: str, build) -> Path:
    """``root / "project"`` made by ``build(root / "project")`` once per test session, however many workers run.

    Under pytest-xdist the workers' temporary folders share a parent that is new for each session; the first
    worker to take the lock builds the project there, the others wait and reuse it (the recipe of the
    pytest-xdist documentation). A build that failed leaves no marker, so the next worker tries again.
    """
    if not os.environ.get("PYTEST_XDIST_WORKER"):  # no xdist: this process is the whole session
        project = tmp_path_factory.mktemp(name) / "project"
        build(project)
        return project
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp().parent / name
    with FileLock(f"{root}.lock"):
        if not (root / ".complete").is_file():
            import shutil

            shutil.rmtree(root, ignore_errors=True)
            build(root / "project")
            (root / ".complete").touch()
    return root / "project"


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


def _calibrate(root: Path, sim: dict) -> None:
    """Simulate ``sim`` into ``root`` and run the whole pipeline on it; what the run logged goes to ``run_log.json``.

    The log sits beside ``root`` (one file per build, whichever worker built it).
    """
    from fluorocal.cli import main
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    write_dataset(simulate(SimulateParams(**sim)), root)
    # warnings are errors here whichever test's filters the build runs under (it is built once for all)
    with logged() as records, warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["--quiet", "run", str(root / "fluorocal.toml")]) == 0
    rows = [{"levelno": r.levelno, "levelname": r.levelname, "name": r.name, "msg": r.getMessage()} for r in records]
    (root.parent / "run_log.json").write_text(json.dumps(rows), encoding="utf-8")


@pytest.fixture(scope="session")
def calibrated_run(tmp_path_factory) -> tuple[Path, list[logging.LogRecord]]:
    """A simulated project after one `fluorocal run`, and the records it logged at INFO or above.

    Simulated and calibrated once per test session (:func:`built_once`); warnings are errors there as everywhere
    in the suite. Modules that change the project take a copy (:func:`copy_project`); the cache comes along, so
    their own runs recompute only what they change. Shared by every xdist worker: never write into it.
    """
    project = built_once(tmp_path_factory, "calibrated", lambda root: _calibrate(root, E2E_SIM))
    rows = json.loads((project.parent / "run_log.json").read_text(encoding="utf-8"))
    return project, [logging.makeLogRecord(row) for row in rows]


@pytest.fixture(scope="session")
def calibrated_project(calibrated_run) -> Path:
    """The project of :func:`calibrated_run`."""
    return calibrated_run[0]


@pytest.fixture(scope="session")
def simulated_grid(tmp_path_factory) -> Path:
    """A simulated plate moved by hand between three frames (:data:`GRID_SIM`) at one orientation, calibrated once.

    Modules that change it take a copy (:func:`copy_project`).
    Shared by every xdist worker (:func:`built_once`): never write into it.
    """
    return built_once(tmp_path_factory, "grid", lambda root: _calibrate(root, GRID_SIM))


def _simulate_dicom(root: Path, sim: dict) -> None:
    """Simulate ``sim`` into ``root`` as `fluorocal simulate --format dicom` writes it (frames, config, truth.json)."""
    from fluorocal.cmd_simulate import write_dataset
    from fluorocal.stages.simulate import SimulateParams, simulate

    write_dataset(simulate(SimulateParams(**sim)), root, fmt="dicom")


@pytest.fixture(scope="session")
def simulated_tilts(tmp_path_factory) -> Path:
    """The grid plate's frames at five C-arm tilts (:data:`GRID_TILTS_SIM`), single-frame DICOMs; not calibrated.

    Simulated once per session for the orientation tests of the plate and of `fluorocal undistort`. Modules that
    run the pipeline on it take a copy (:func:`copy_project`). Shared by every xdist worker: never write into it.
    """
    return built_once(tmp_path_factory, "tilts", lambda root: _simulate_dicom(root, GRID_TILTS_SIM))


def _calibrated_arcadis(arcadis_dir, tmp_path_factory, name: str) -> Path:
    """``fixtures/arcadis/<name>.toml`` run on the real frames from a copy of the config; its calibration.json."""
    from fluorocal.cli import main

    root = tmp_path_factory.mktemp(name)
    text = (ROOT / "fixtures" / "arcadis" / f"{name}.toml").read_text()
    (root / f"{name}.toml").write_text(text.replace("../../../shared/data/arcadis", str(Path(arcadis_dir).resolve())))
    assert main(["--quiet", "run", str(root / f"{name}.toml")]) == 0
    return root / f"out-{name}" / "calibration.json"


@pytest.fixture(scope="session")
def arcadis_calibration(arcadis_dir, tmp_path_factory) -> Path:
    """The real ARCADIS grid plate calibrated at its six orientations (fixtures/arcadis/orientations.toml)."""
    return _calibrated_arcadis(arcadis_dir, tmp_path_factory, "orientations")


@pytest.fixture(scope="session")
def centred_calibration(arcadis_dir, tmp_path_factory) -> Path:
    """The real ARCADIS grid plate calibrated at the centred orientation (fixtures/arcadis/centred.toml)."""
    return _calibrated_arcadis(arcadis_dir, tmp_path_factory, "centred")


#: the session projects that :func:`built_once` shares between the workers, in the order the workers start them
SHARED_PROJECTS = ("calibrated_run", "simulated_grid", "simulated_tilts")


@pytest.fixture(scope="session", autouse=True)
def _start_a_shared_project(request):
    """Under xdist, each worker first builds another of the shared projects that the session's tests use.

    Otherwise the workers' first tests tend to ask for the same project, and all but one wait for it while the
    next project waits its turn; started side by side, each is ready (or nearly) when the others ask for it.
    A build that fails is left to the tests that use the project to report (the others run on).
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    wanted = {name for item in request.session.items for name in getattr(item, "fixturenames", ())}
    used = [name for name in SHARED_PROJECTS if name in wanted]
    if worker.startswith("gw") and used:
        with contextlib.suppress(Exception, pytest.skip.Exception):
            request.getfixturevalue(used[int(worker[2:]) % len(used)])


def copy_project(source: Path, destination: Path) -> Path:
    """A copy of a project folder (frames, config, cache and outputs) at ``destination``."""
    import shutil

    shutil.copytree(source, destination, symlinks=True)
    return destination


def pytest_collection_modifyitems(items):
    """Every test that reads the real radiographs (../shared/data) is one of `make check`'s long checks."""
    for item in items:
        if "arcadis_dir" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.check)
