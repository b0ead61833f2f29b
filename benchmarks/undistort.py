"""Undistortion speed and memory: in memory against a bare cv2.remap, end to end against OpenCV, memory against count.

All on a synthetic calibration of a 1024 x 1024 px system (a pincushion correction up to ~15 px at the
corners, on a 32 px grid) and synthetic 12-bit frames stored as 16-bit TIFF (smooth structure + noise):

1. In memory: ``Calibration.undistort_image`` against ``cv2.remap`` with the same float32 maps on the same
   uint16 frames, in interleaved rounds (medians); the maps' cost computed and read back from the cache
   beside the calibration; the DN difference to the earlier float path (``undistort_frame`` on a float32
   Radiograph, rounded back) and the speed and DN difference of OpenCV's fixed-point maps (``CV_16SC2``).
2. Writers, per frame: fluorocal's (``write_stored_like``: TIFF and PNG through ``cv2.imencode``, DICOM
   streamed) against ``cv2.imwrite`` of the same frame, and the earlier OpenImageIO TIFF writer (zip).
3. End to end: ``fluorocal undistort`` of a folder of 100 frames (a subprocess, maps cached; and once with
   no cache) against a subprocess that reads, remaps and writes them with OpenCV (``cv2.imread``,
   ``cv2.remap`` with the maps from a ``.npy``, ``cv2.imwrite``: TIFF with LZW), interleaved, medians; with
   each process's peak memory (``ru_maxrss`` from ``os.wait4`` in a small launcher process: see :func:`_run`).
4. Memory against count: ``fluorocal undistort`` of ``--frames``/10 and ``--frames`` frames (a folder of
   links to 10 distinct frames; outputs deleted after each run): peak memory of each; and of one FFV1 AVI
   of ``--video-frames``/4 and ``--video-frames`` 8-bit frames (video streamed like a multi-page file).

Usage: ``python benchmarks/undistort.py [--frames 10000] [--video-frames 1000] [--rounds 5] [--keep DIR]``.
Targets (issue 15): in memory >= 90 % of the bare remap; end to end within 1.5x of OpenCV; peak memory
that does not grow with the number of frames.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SIZE = 1024
N_DISTINCT = 10
BASELINE = """
import sys, pathlib, cv2, numpy as np
src, out, maps = map(pathlib.Path, sys.argv[1:4])
map_x, map_y = np.load(maps)
for path in sorted(src.iterdir()):
    frame = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(out / path.name), cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
"""


LAUNCHER = """
import os, subprocess, sys, time
t0 = time.perf_counter()
proc = subprocess.Popen(sys.argv[2:])
_, status, usage = os.wait4(proc.pid, 0)
wall = time.perf_counter() - t0
open(sys.argv[1], "w").write(f"{wall} {usage.ru_maxrss} {os.waitstatus_to_exitcode(status)}")
"""


def _env() -> dict:
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def make_calibration(folder: Path) -> Path:
    """A one-system calibration of SIZE² px whose field is a pincushion of up to ~15 px."""
    from fluorocal.calibration import Calibration, SystemCalibration
    from fluorocal.stages.field import CorrectionField, grid_nodes

    x, y = grid_nodes(SIZE, SIZE, 32.0)
    yy, xx = np.meshgrid(y, x, indexing="ij")
    c = SIZE / 2
    r2 = ((xx - c) ** 2 + (yy - c) ** 2) / c**2
    delta = 7.5 * np.stack([(xx - c) / c * r2, (yy - c) / c * r2], axis=-1)  # 15 px at the corners (r² = 2)
    ones = np.ones(xx.shape)
    field = CorrectionField(x, y, delta, 0.01 * ones, ones.astype(bool), SIZE, SIZE)
    iop = np.array([c, c, 4000.0])
    system = SystemCalibration("A", (SIZE, SIZE), iop, np.zeros(3), np.array([1.0, 0, 0, 0]), np.zeros(3), field)
    path = folder / "calibration.json"
    Calibration([system], {}, {"scheme": "benchmark"}).save(path)
    return path


def make_frames(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(15)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    base = 2000 + 1200 * np.sin(xx / 37.0) * np.cos(yy / 53.0)
    return [np.clip(base + rng.normal(0, 25, base.shape), 0, 4095).astype(np.uint16) for _ in range(n)]


def _median_ms(fn, args_list) -> float:
    times = []
    for args in args_list:
        t0 = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def in_memory(cal_path: Path, frames: list[np.ndarray], rounds: int) -> None:
    import cv2
    from fluorocal.calibration import Calibration
    from fluorocal.maps import maps_folder
    from fluorocal.stages.artifacts import Radiograph
    from fluorocal.stages.io.pixels import to_source_dtype
    from fluorocal.stages.undistort import UndistortParams, undistort_frame

    shutil.rmtree(maps_folder(cal_path), ignore_errors=True)
    t0 = time.perf_counter()
    map_x, map_y = Calibration.load(cal_path).remap_maps("A")
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    cal = Calibration.load(cal_path)
    cal.remap_maps("A")
    warm = time.perf_counter() - t0
    print(f"maps 1024²: computed {cold:.2f} s (first call); load + read from the cache {1e3 * warm:.0f} ms")

    def bare(frame):
        return cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    fixed = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)

    def fixed_point(frame):
        return cv2.remap(frame, *fixed, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    methods = {
        "cv2.remap float32 maps": bare,
        "Calibration.undistort_image": lambda f: cal.undistort_image("A", f),
        "cv2.remap CV_16SC2 maps": fixed_point,
    }
    per_frame = {name: [] for name in methods}
    batch = frames * 2
    n_rounds = 6 * rounds  # short rounds, the order alternating: a busy machine slows all methods alike
    for r in range(n_rounds):
        for name in list(methods) if r % 2 == 0 else list(reversed(methods)):
            t0 = time.perf_counter()
            for f in batch:
                methods[name](f)
            per_frame[name].append((time.perf_counter() - t0) / len(batch))
    bare_times = per_frame["cv2.remap float32 maps"]
    for name, times in per_frame.items():
        med = statistics.median(times)
        print(
            f"in memory, {name:28s}: {1 / med:7.1f} frames/s (median of {n_rounds} rounds of {len(batch)} frames; "
            f"{statistics.median(b / t for b, t in zip(bare_times, times)):6.1%} of the bare remap's speed, median of "
            f"the rounds' ratios; rounds {min(times) * 1e3:.2f}-{max(times) * 1e3:.2f} ms/frame)"
        )

    def old_path(frame):  # the frame as a float32 Radiograph, remapped, rounded back to its integers
        return to_source_dtype(undistort_frame(Radiograph(frame, 12), map_x, map_y, UndistortParams()))

    old_dn = max(int(np.abs(cal.undistort_image("A", f).astype(int) - old_path(f)).max()) for f in frames)
    fixed_dn = max(int(np.abs(bare(f).astype(int) - fixed_point(f)).max()) for f in frames)
    print(f"DN difference, undistort_image vs the float path (remap of float32, np.rint): max {old_dn} DN")
    print(f"DN difference, CV_16SC2 fixed-point maps vs float32 maps: max {fixed_dn} DN")


def writers(folder: Path, frames: list[np.ndarray], rounds: int) -> None:
    import cv2
    import pydicom
    from fluorocal.stages.io import write_still, write_stored_like
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, SecondaryCaptureImageStorage, generate_uid

    folder.mkdir()
    cv2.imwrite(str(folder / "src.tif"), frames[0])
    cv2.imwrite(str(folder / "src.png"), frames[0])
    ds = pydicom.Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID = SecondaryCaptureImageStorage
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID = generate_uid()
    ds.Modality, ds.PhotometricInterpretation, ds.Rows, ds.Columns, ds.SamplesPerPixel = (
        "XA",
        "MONOCHROME2",
        SIZE,
        SIZE,
        1,
    )
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.PixelData = frames[0].tobytes()
    ds.save_as(folder / "src.dcm", enforce_file_format=True)

    def pydicom_plain(frame, out):
        d = pydicom.dcmread(folder / "src.dcm")
        d.PixelData = frame.tobytes()
        d.save_as(out, enforce_file_format=True)

    def ours(suffix):
        return lambda f: write_stored_like(folder / f"src.{suffix}", [f], folder / f"o.{suffix}", 1)

    cases = [
        ("TIFF", "fluorocal write_stored_like", ours("tif")),
        ("TIFF", "cv2.imwrite (LZW)", lambda f: cv2.imwrite(str(folder / "c.tif"), f)),
        ("TIFF", "OpenImageIO zip (the earlier writer)", lambda f: write_still(folder / "z.tif", f)),
        ("PNG", "fluorocal write_stored_like", ours("png")),
        ("PNG", "cv2.imwrite", lambda f: cv2.imwrite(str(folder / "c.png"), f)),
        ("DICOM", "fluorocal write_stored_like", ours("dcm")),
        ("DICOM", "pydicom dcmread + save_as", lambda f: pydicom_plain(f, folder / "p.dcm")),
    ]
    times = {(fmt, name): [] for fmt, name, _ in cases}
    for r in range(rounds):
        for fmt, name, fn in cases if r % 2 == 0 else reversed(cases):
            times[(fmt, name)].append(_median_ms(fn, [(f,) for f in frames[:4]]))
    for (fmt, name), ms in times.items():
        print(f"writer {fmt:5s} {name:38s}: {statistics.median(ms):6.1f} ms/frame (median of {rounds} rounds)")


def _run(cmd: list[str], log: Path) -> tuple[float, float, int]:
    """Wall seconds, peak RSS in MiB and exit code of a subprocess, measured by a small launcher process.

    Linux keeps a process's peak RSS across ``exec``, so a child forked straight from this (large)
    process would report this process's peak as its own; forked from the launcher, it starts small.
    """
    with open(log, "wb") as err:
        subprocess.run(
            [sys.executable, "-c", LAUNCHER, str(log) + ".rusage", *cmd],
            env=_env(),
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    wall, maxrss_kib, code = (float(v) for v in Path(str(log) + ".rusage").read_text().split())
    return wall, maxrss_kib / 1024, int(code)


def _fluorocal(cal: Path, src: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "fluorocal.cli", "undistort", str(cal), str(src), "--system", "A", "--out", str(out)]


def end_to_end(root: Path, cal: Path, frames: list[np.ndarray], rounds: int, n: int = 100) -> None:
    import cv2
    from fluorocal.calibration import Calibration
    from fluorocal.maps import maps_folder

    src = root / "e2e_in"
    src.mkdir()
    for i in range(n):
        cv2.imwrite(str(src / f"f{i:05d}.tif"), frames[i % len(frames)])
    np.save(root / "maps.npy", np.stack(Calibration.load(cal).remap_maps("A")))
    (root / "baseline.py").write_text(BASELINE)
    shutil.rmtree(maps_folder(cal), ignore_errors=True)
    out = root / "e2e_out"
    wall, rss, code = _run(_fluorocal(cal, src, out), root / "cold.log")
    print(f"end to end, fluorocal undistort, no cached maps: {wall:.2f} s, peak {rss:.0f} MiB (exit {code})")
    results = {"fluorocal undistort": [], "OpenCV read + remap + write": []}
    for r in range(rounds):
        for name in results if r % 2 == 0 else reversed(list(results)):
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            cmd = (
                _fluorocal(cal, src, out)
                if name == "fluorocal undistort"
                else [sys.executable, str(root / "baseline.py"), str(src), str(out), str(root / "maps.npy")]
            )
            results[name].append(_run(cmd, root / "run.log"))
            assert results[name][-1][2] == 0, (root / "run.log").read_text()
            if name == "fluorocal undistort":
                summary = (root / "run.log").read_text().strip().splitlines()[-1]
    walls = {name: statistics.median(w for w, _, _ in runs) for name, runs in results.items()}
    for name, runs in results.items():
        print(
            f"end to end, {name:28s}: {walls[name]:.2f} s for {n} frames (median of {rounds}; "
            f"runs {', '.join(f'{w:.2f}' for w, _, _ in runs)} s), peak {max(m for _, m, _ in runs):.0f} MiB"
        )
    print(f"end to end, fluorocal / OpenCV: {walls['fluorocal undistort'] / walls['OpenCV read + remap + write']:.2f}x")
    print(f"fluorocal's summary line: {summary}")


def memory_against_count(root: Path, cal: Path, frames: list[np.ndarray], n_large: int) -> None:
    import cv2

    distinct = root / "distinct"
    distinct.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(distinct / f"d{i}.tif"), f)
    for n in (n_large // 10, n_large):
        src, out = root / f"links_{n}", root / f"out_{n}"
        src.mkdir()
        for i in range(n):
            (src / f"f{i:05d}.tif").symlink_to(distinct / f"d{i % len(frames)}.tif")
        wall, rss, code = _run(_fluorocal(cal, src, out), root / "mem.log")
        written = len(list(out.iterdir())) if out.exists() else 0
        print(
            f"memory, fluorocal undistort of {n:5d} frames: peak {rss:.0f} MiB, {wall:.1f} s "
            f"({n / wall:.1f} frames/s), {written} written (exit {code})"
        )
        shutil.rmtree(out, ignore_errors=True)
        shutil.rmtree(src)


def video_memory_against_count(root: Path, cal: Path, frames: list[np.ndarray], n_large: int) -> None:
    import cv2

    for n in (n_large // 4, n_large):
        src, out = root / f"video_{n}.avi", root / f"video_out_{n}"
        writer = cv2.VideoWriter(str(src), cv2.VideoWriter_fourcc(*"FFV1"), 25, (SIZE, SIZE), isColor=False)
        for i in range(n):
            writer.write((frames[i % len(frames)] >> 4).astype(np.uint8))
        writer.release()
        wall, rss, code = _run(_fluorocal(cal, src, out), root / "mem.log")
        print(f"memory, fluorocal undistort of a {n:5d}-frame AVI: peak {rss:.0f} MiB, {wall:.1f} s (exit {code})")
        shutil.rmtree(out, ignore_errors=True)
        src.unlink()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=10000, help="frames of the memory run (default 10000)")
    parser.add_argument("--video-frames", type=int, default=1000, help="frames of the video run (default 1000)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds of each comparison (default 5)")
    parser.add_argument("--keep", type=Path, help="work in this folder and keep it (default: a temporary one)")
    args = parser.parse_args()
    os.environ.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    root = Path(tempfile.mkdtemp(prefix="fluorocal-undistort-")) if args.keep is None else args.keep
    root.mkdir(parents=True, exist_ok=True)
    try:
        cal = make_calibration(root / "cal")
        frames = make_frames(N_DISTINCT)
        in_memory(cal, frames, args.rounds)
        writers(root / "writers", frames, args.rounds)
        end_to_end(root, cal, frames, max(3, args.rounds // 2 + 1))
        memory_against_count(root, cal, frames, args.frames)
        video_memory_against_count(root, cal, frames, args.video_frames)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    import docpage

    docpage.run(__file__, main)
