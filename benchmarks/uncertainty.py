"""Benchmark of the stated uncertainties (issue 14): do the stated σ hold against repeated simulations.

Each seed is a new simulated set (simulator geometry, ``distortion="strong"``,
one system, no rendering): the true distorted projections of the bead centres
plus 0.05 px Gaussian noise, so the model is exact and only the noise and the
estimation make errors. Even exposures train, odd ones are held out. The
calibration is ``fluorocal``'s default (scheme ``knn+iop+smooth``, the
recommended preset).

The IOP is stated under the field gauge (README, "Uncertainties"): the field
has no least-squares component, at the training observations, along a
principal-point shift, a scaling about the principal point or a common camera
rotation. Its truth in that convention (``convention_truth``) is the true
configuration moved by the IOP change and common camera rotation that leave
the true correction no such component, exactly (the change acts on the ideal
points, a projective map). The field's truth at a node is the moved
correction there; an undistorted point's truth is the moved ideal projection.

Printed per seed: the IOP error and its stated σ (the joint one and the
adjustment's conditional one); then coverage with counts: ``|error| <= 2σ`` for
``xp``, ``yp``, ``c`` (target >= 90 %), and ``|error| <= 1σ`` per component for
the field at supported nodes and for the undistorted held-out observations
(target 60-80 %; 68 % for a Gaussian).

Usage: ``python benchmarks/uncertainty.py [--frames N] [--size PX] [--seeds a,b,...]``
(defaults: 15 training + 15 held-out exposures, 512 px, seeds 0-9).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from fluorocal.stages import simulate as sim  # noqa: E402
from fluorocal.stages.artifacts import Observations  # noqa: E402
from fluorocal.stages.field import bilinear_design  # noqa: E402
from fluorocal.stages.learn import calibrate  # noqa: E402
from fluorocal.stages.learn.uncertainty import convention_truth  # noqa: E402
from learn import _initial, _system_orientation  # noqa: E402

NOISE_PX = 0.05


def simulated_set(n_train: int, size: int, seed: int):
    """``(train, train_true, test, test_true, test_ideal, initial, phantom, system)``: observations and truth."""
    p = sim.SimulateParams(n_frames=2 * n_train, n_systems=1, seed=seed, image_size_px=size, distortion="strong")
    data = sim.simulate(p, render=False)
    acq = data.truth.acquisition
    rng = np.random.default_rng([seed, 7])
    out = []
    for part in (0, 1):
        frames = [f for f in data.truth.frames[0] if f.exposure % 2 == part]
        keep = [~(f.overlap | f.field_edge) for f in frames]
        exposure = np.concatenate([np.full(k.sum(), f.exposure // 2) for f, k in zip(frames, keep)])
        ids = np.concatenate([f.ids[k] for f, k in zip(frames, keep)])
        true_xy = np.concatenate([f.distorted_xy_px[k] for f, k in zip(frames, keep)])
        ideal_xy = np.concatenate([f.ideal_xy_px[k] for f, k in zip(frames, keep)])
        xy = true_xy + rng.normal(0, NOISE_PX, true_xy.shape)
        sigma = np.tile([NOISE_PX, NOISE_PX, 0.0], (len(xy), 1))
        system = np.zeros(len(xy), np.int64)
        obs = [Observations(system, exposure, ids, v, sigma, system_names=data.system_names) for v in (xy, true_xy)]
        out.append((*obs, ideal_xy))
    initial = _system_orientation(_initial(acq, np.arange(0, p.n_frames, 2), size, rng), acq, 0)
    return out, initial, data.phantom, acq.systems[0]


def best_grid_values(field, truth, size: int) -> np.ndarray:
    """``(n_nodes, 2)`` node values whose bilinear interpolation fits ``truth(xy)`` best on a 2 px sample.

    The node values a bilinear grid can hold of a curved field differ from the field at the nodes by up to a
    few hundredths of a pixel near the rim of a strong distortion; this is the grid's own truth.
    """
    from scipy.sparse.linalg import lsqr

    g = np.arange(-0.5, size, 2.0)
    xy = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    A = bilinear_design(field.x_nodes_px, field.y_nodes_px, xy)
    t = truth(xy)
    return np.column_stack([lsqr(A, t[:, c], atol=1e-12, btol=1e-12)[0] for c in range(2)])


def run_seed(args, seed: int) -> dict:
    t0 = time.perf_counter()
    ((train, train_true, _), (test, test_true, test_ideal)), initial, phantom, system = simulated_set(
        args.frames, args.size, seed
    )
    res = calibrate(train, phantom, initial, image_size=(args.size, args.size))
    wall = time.perf_counter() - t0
    adj, field = res.adjustment, res.fields[0]
    rows = np.flatnonzero(res.trained & adj.used)
    iop_true, component = convention_truth(train_true.xy_px[rows], system.distortion.correction_at, system.iop_px)
    unc = res.uncertainty[0]
    iop_err = adj.iop_px[0] - iop_true
    # the field at the supported nodes against the true correction less its gauge component: its value at the
    # node, and the node values of the grid that fits it best
    supported = field.support.ravel()
    nodes = field.nodes_px[supported]
    # the rim: supported nodes with an unsupported (or no) neighbour among their 8; the interior: the rest
    interior = binary_erosion(field.support, np.ones((3, 3), bool), border_value=0).ravel()[supported]

    def truth(xy):
        return xy - system.distortion.undistort_points(xy) - component(xy)

    estimate = field.delta_px.reshape(-1, 2)[supported]
    node_err = estimate - truth(nodes)
    grid_err = estimate - best_grid_values(field, truth, args.size)[supported]
    node_sd = field.sigma_px.ravel()[supported]
    node_z = float(np.sqrt(np.mean((node_err / node_sd[:, None]) ** 2)))
    # held-out observations, undistorted with the learned field, against the true ideal projection in the convention
    inside = field.support_at(test.xy_px)
    pt_err = (field.undistort_points(test.xy_px) - (test_ideal + component(test_true.xy_px)))[inside]
    pt_sd = res.point_std_px(0, test.xy_px[inside], test.sigma_px[inside, :2])
    print(
        f"seed {seed}: {len(train)} training observations, {wall:.1f} s; IOP error (xp, yp, c) "
        f"{np.array2string(iop_err, precision=2)} px, stated σ {np.array2string(unc.iop_std_px, precision=2)} "
        f"(adjustment's, field held: {np.array2string(adj.iop_std_px[0], precision=3)}); raw error against the "
        f"simulator's IOP {np.array2string(adj.iop_px[0] - system.iop_px, precision=1)} px; field RMS error "
        f"{np.sqrt(np.mean(node_err**2)):.3f} px (best grid {np.sqrt(np.mean(grid_err**2)):.3f} px), "
        f"median stated σ {np.median(node_sd):.3f} px, RMS of error / σ {node_z:.2f}; "
        f"IOP error / σ "
        f"{np.array2string(iop_err / unc.iop_std_px, precision=2)}",
        flush=True,
    )
    return {
        "iop": np.abs(iop_err) <= 2 * unc.iop_std_px,
        "iop_cond": np.abs(iop_err) <= 2 * adj.iop_std_px[0],
        "node": (np.abs(node_err) <= node_sd[:, None]).ravel(),
        "interior": np.repeat(interior, 2),
        "grid": (np.abs(grid_err) <= node_sd[:, None]).ravel(),
        "point": (np.abs(pt_err) <= pt_sd).ravel(),
    }


def _coverage(name: str, hits: np.ndarray, target: str) -> None:
    print(f"  {name}: {hits.sum()} / {hits.size} = {100 * hits.mean():.1f} % (target {target})")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=15, help="training (and held-out) exposures (default 15)")
    ap.add_argument("--size", type=int, default=512, help="image side px (default 512)")
    ap.add_argument("--seeds", default="0,1,2,3,4,5,6,7,8,9", help="comma-separated seeds (default 0-9)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    logging.getLogger("fluorocal.stages.adjust").setLevel(logging.ERROR)
    seeds = [int(v) for v in args.seeds.split(",")]
    results = [run_seed(args, s) for s in seeds]
    print(f"\ncoverage over {len(seeds)} seeds ({args.frames} + {args.frames} exposures, {args.size} px):")
    for i, name in enumerate(("xp", "yp", "c")):
        _coverage(f"{name} within 2σ (joint)", np.array([r["iop"][i] for r in results]), ">= 90 %")
    for i, name in enumerate(("xp", "yp", "c")):
        _coverage(f"{name} within 2σ (adjustment's, field held)", np.array([r["iop_cond"][i] for r in results]), "-")
    _coverage(
        "field nodes within 1σ (truth: the field at the node)", np.concatenate([r["node"] for r in results]), "60-80 %"
    )
    node, interior = (np.concatenate([r[k] for r in results]) for k in ("node", "interior"))
    _coverage("  of which interior nodes", node[interior], "60-80 %")
    _coverage("  of which rim nodes (an unsupported neighbour)", node[~interior], "60-80 %")
    _coverage(
        "field nodes within 1σ (truth: the best bilinear grid)", np.concatenate([r["grid"] for r in results]), "60-80 %"
    )
    _coverage("undistorted held-out points within 1σ", np.concatenate([r["point"] for r in results]), "60-80 %")


if __name__ == "__main__":
    import docpage

    docpage.run(__file__, main)
