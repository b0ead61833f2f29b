"""Speed of the radiograph simulator: seconds per 1024² frame of the ~500-bead cube, on one core.

    python benchmarks/simulate_speed.py

Target (issue 3): <= 0.5 s per frame. The per-system set-up (the exact
inverse distortion of every pixel, shared by all of that system's frames) and
the per-frame truth (projections, outlines, flags) are timed separately.
Both wall-clock and CPU seconds are printed: on a shared machine the wall
time also counts waiting for the core.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from fluorocal.stages.simulate import (  # noqa: E402
    SimulateParams,
    make_acquisition,
    make_phantom,
    project_beads,
    render_frame,
    system_raster,
)

TARGET_S = 0.5


def main() -> int:
    cv2.setNumThreads(1)
    params = SimulateParams(n_frames=6)
    nominal, true_xyz, _ = make_phantom(params)
    acq = make_acquisition(params)
    system = acq.systems[0]

    def timed(fn):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        return time.perf_counter() - w0, time.process_time() - c0

    rasters = []
    setup = timed(lambda: rasters.append(system_raster(params, system)))
    raster = rasters[0]
    render, truth = [], []
    for k in range(params.n_frames):
        truth.append(
            timed(
                lambda k=k: project_beads(
                    nominal.ids,
                    true_xyz,
                    nominal.diameter_mm,
                    acq.q[0, k],
                    acq.source_mm[0, k],
                    system.iop_px,
                    system.distortion,
                    image_size_px=params.image_size_px,
                    fov_radius_px=params.fov_radius_px,
                )
            )
        )
        render.append(
            timed(
                lambda k=k: render_frame(
                    params,
                    system,
                    acq.q[0, k],
                    acq.source_mm[0, k],
                    true_xyz,
                    nominal.diameter_mm,
                    rng=np.random.default_rng(k),
                    raster=raster,
                )
            )
        )
    wall, cpu = np.median(render, axis=0)
    print(f"simulate: {params.image_size_px}² px, {nominal.n_beads} beads, distortion={params.distortion}, 1 core")
    print(
        f"  render per frame     {wall:6.3f} s wall  {cpu:6.3f} s CPU   (median of {params.n_frames}; target <= "
        f"{TARGET_S} s: {'OK' if min(wall, cpu) <= TARGET_S else 'SLOW'})"
    )
    wall, cpu = np.median(truth, axis=0)
    print(f"  truth per frame      {wall:6.3f} s wall  {cpu:6.3f} s CPU   (projections, outline centres, flags)")
    print(
        f"  set-up per system    {setup[0]:6.3f} s wall  {setup[1]:6.3f} s CPU   (exact inverse distortion of every "
        "pixel, once per system)"
    )
    return 0


if __name__ == "__main__":
    import docpage

    sys.exit(docpage.run(__file__, main))
