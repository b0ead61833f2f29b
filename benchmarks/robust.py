"""Benchmark of the learning loop under gross errors (issue 13, finding 5).

The simulated set of ``benchmarks/learn.py`` (simulator geometry, strong
distortion, true distorted outline centres + 0.05 px noise, even exposures
train, odd ones are held out), one system. The training observations are
contaminated in turn by

- ``gross``: 5 % of the observations moved by a random vector of uniform
  length 3-15 px and uniform direction;
- ``swaps``: 2 % of the labels swapped between neighbouring beads: disjoint
  pairs of observations of one frame, each with its nearest neighbour in the
  image, exchange their bead ids (so 2 % of the observations carry a wrong
  id);
- ``occlusion``: in 10 % of the frames the observations inside a random disc
  covering 25 % of the field of view (radius half the field's, centre within
  0.5 field radii of the image centre) are dropped;
- ``all``: the three at once (occlusion first, then the swaps, then the
  gross errors, drawn among the remaining observations);

and each set calibrated with the recommended preset (``LearnParams()``,
scheme ``knn+iop+smooth``). Per set:

- field vs clean: RMS px of the learned correction minus the clean run's,
  on a 96 x 96 grid over the inner 80 % (radius) of the field of view where
  both fields are supported; raw, and after the best homography between the
  two sets of ideal coordinates (what IOP and pose can absorb);
- field error against the truth modulo a homography (as ``learn.py``: covered / inner 80 %);
- out-of-sample 3D error (mm): the held-out exposures adjusted with the
  learned correction and IOP held fixed, RMS 3D distance to the true bead
  centres after a similarity, and its ratio to the clean run's; on the clean
  held-out exposures, and on held-out exposures contaminated alike ("cont.",
  the ratio to the clean run's calibration on the same contaminated exposures:
  the held-out adjustment's own loss under gross errors cancels);
- in-sample RMS (px) of the final adjustment's residuals on the training
  observations left uncontaminated;
- the share of the contaminated observations the final adjustment flags as
  outliers, and how many observations it flags the last regression still
  learned from (contaminated ones / all);
- principal point shift from the clean run's (px; and over the principal
  point's standard deviation in the contaminated run) and principal distance change (px);
- iterations and wall time.

Usage: ``python benchmarks/robust.py [--frames N] [--size PX] [--seed N] [--sets a,b,...]``
(defaults: 40 training + 40 held-out exposures, 1024 px, seed 0, every set).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[0]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluorocal.stages.adjust import Orientation  # noqa: E402
from fluorocal.stages.artifacts import Observations, Phantom  # noqa: E402
from fluorocal.stages.learn import LearnParams, calibrate  # noqa: E402
from fluorocal.stages.simulate import ImageDistortion  # noqa: E402
from learn import _modulo_homography, _one_system, _system_orientation, field_error_px, held_out, simulated_sets  # noqa: E402

GROSS_FRACTION, GROSS_PX = 0.05, (3.0, 15.0)
SWAP_FRACTION = 0.02
OCCLUDED_FRAMES, OCCLUDED_AREA = 0.10, 0.25
SETS = ("clean", "gross", "swaps", "occlusion", "all")


def contaminate(obs: Observations, kind: str, fov_radius_px: float, size: int, rng) -> tuple[Observations, np.ndarray]:
    """The observations contaminated by ``kind`` and the mask ``(N',)`` of those left untouched."""
    xy, ids, exposure = obs.xy_px.copy(), obs.bead_id.copy(), obs.exposure
    keep = np.ones(len(xy), bool)
    if kind in ("occlusion", "all"):
        keep = ~_occluded(exposure, xy, fov_radius_px, size, rng)
    xy, ids, exposure, sigma = xy[keep], ids[keep], exposure[keep], obs.sigma_px[keep]
    clean = np.ones(len(xy), bool)
    if kind in ("swaps", "all"):
        swapped = _swap_neighbours(exposure, xy, ids, rng)
        clean[swapped] = False
    if kind in ("gross", "all"):
        moved = rng.choice(np.flatnonzero(clean), int(round(GROSS_FRACTION * len(xy))), replace=False)
        length = rng.uniform(*GROSS_PX, len(moved))
        angle = rng.uniform(0, 2 * np.pi, len(moved))
        xy[moved] += length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
        clean[moved] = False
    out = Observations(obs.system[keep], exposure, ids, xy, sigma, system_names=obs.system_names)
    return out, clean


def _occluded(exposure, xy, fov_radius_px, size, rng) -> np.ndarray:
    """Mask of the observations inside one random disc in each of ``OCCLUDED_FRAMES`` of the frames."""
    frames = np.unique(exposure)
    hit = rng.choice(frames, max(1, int(round(OCCLUDED_FRAMES * len(frames)))), replace=False)
    radius = np.sqrt(OCCLUDED_AREA) * fov_radius_px
    c = (size - 1) / 2
    out = np.zeros(len(xy), bool)
    for e in hit:
        rho, phi = 0.5 * fov_radius_px * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        centre = c + rho * np.array([np.cos(phi), np.sin(phi)])
        out |= (exposure == e) & (np.hypot(*(xy - centre).T) < radius)
    return out


def _swap_neighbours(exposure, xy, ids, rng) -> np.ndarray:
    """Swap the ids of disjoint nearest-neighbour pairs in place until ``SWAP_FRACTION`` are wrong; their rows."""
    target = int(round(SWAP_FRACTION * len(xy)))
    taken = np.zeros(len(xy), bool)
    for i in rng.permutation(len(xy)):
        if taken.sum() >= target:
            break
        if taken[i]:
            continue
        same = np.flatnonzero((exposure == exposure[i]) & ~taken)
        same = same[same != i]
        if len(same) == 0:
            continue
        j = same[np.argmin(np.hypot(*(xy[same] - xy[i]).T))]
        ids[i], ids[j] = ids[j], ids[i]
        taken[[i, j]] = True
    return np.flatnonzero(taken)


def field_difference(field, clean_field, size: int, fov_radius_px: float) -> tuple[float, float]:
    """RMS px of ``field - clean_field`` where both are supported (inner 80 %): raw and modulo a homography."""
    import cv2

    g = np.linspace(0, size - 1, 96)
    pts = np.column_stack([a.ravel() for a in np.meshgrid(g, g)])
    c = (size - 1) / 2
    pts = pts[np.hypot(pts[:, 0] - c, pts[:, 1] - c) < 0.8 * fov_radius_px]
    pts = pts[field.support_at(pts) & clean_field.support_at(pts)]
    a, b = field.correction_at(pts), clean_field.correction_at(pts)
    raw = float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))
    H, _ = cv2.findHomography(pts - a, pts - b, 0)
    mod = np.linalg.norm(cv2.perspectiveTransform((pts - a)[None], H)[0] - (pts - b), axis=1)
    return raw, float(np.sqrt(np.mean(mod**2)))


class Setup(NamedTuple):
    """One system's training and held-out observations with their start values, and the truth to score against."""

    train: Observations
    test: Observations
    init_train: Orientation
    init_test: Orientation
    nominal: Phantom
    true_xyz: np.ndarray
    distortion: ImageDistortion
    fov_radius_px: float
    size: int
    seed: int


def main(argv=None) -> None:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    logging.getLogger("fluorocal.stages.adjust").setLevel(logging.ERROR)
    kinds = [k.strip() for k in args.sets.split(",") if k.strip()]
    if "clean" not in kinds:
        kinds.insert(0, "clean")
    (train, test), nominal, true_xyz, acq, p = simulated_sets(args.frames, 1, args.size, args.seed)
    tr, te = _one_system(train[0], train[0].system == 0), _one_system(test[0], test[0].system == 0)
    init_tr, init_te = _system_orientation(train[1], acq, 0), _system_orientation(test[1], acq, 0)
    setup = Setup(
        tr, te, init_tr, init_te, nominal, true_xyz, acq.systems[0].distortion, p.fov_radius_px, args.size, args.seed
    )
    print(
        f"seed {args.seed}: {len(tr)} training + {len(te)} held-out observations ({args.frames} + {args.frames} "
        f"exposures, {args.size} px), recommended preset"
    )
    rows, clean = [], None
    for kind in kinds:
        row, clean = one_set(kind, setup, clean)
        rows.append(row)
    print_table(rows)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=40, help="training (and held-out) exposures (default 40)")
    ap.add_argument("--size", type=int, default=1024, help="image side px (default 1024)")
    ap.add_argument("--seed", type=int, default=0, help="simulation and contamination seed (default 0)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated sets (default: {','.join(SETS)})")
    ap.add_argument("-v", "--verbose", action="store_true", help="log the alternation")
    return ap


def one_set(kind: str, setup: Setup, clean) -> tuple[tuple, tuple]:
    """Calibrate on the training set contaminated by ``kind`` and score it; its table row and the clean reference.

    ``clean`` is ``(field, IOP, out-of-sample 3D error)`` of the clean run, None for the clean run itself (the first).
    """
    s = setup
    rng = np.random.default_rng([s.seed, 13, SETS.index(kind)])
    obs, untouched = contaminate(s.train, kind, s.fov_radius_px, s.size, rng)
    te_c, _ = contaminate(s.test, kind, s.fov_radius_px, s.size, rng)
    t = time.perf_counter()
    res = calibrate(obs, s.nominal, s.init_train, image_size=(s.size, s.size), params=LearnParams())
    wall = time.perf_counter() - t
    field, adj = res.fields[0], res.adjustment
    e3 = held_out(s.test, s.init_test, s.nominal, s.true_xyz, field.correction_at(s.test.xy_px), adj.iop_px)[0]
    e3c = held_out(te_c, s.init_test, s.nominal, s.true_xyz, field.correction_at(te_c.xy_px), adj.iop_px)[0]
    if clean is not None:
        # the reference on contaminated held-out data: the clean run's calibration on the same data
        e3c_ref = held_out(
            te_c, s.init_test, s.nominal, s.true_xyz, clean[0].correction_at(te_c.xy_px), clean[1][None]
        )[0]
    truth = field_error_px(field.correction_at, field.support_at, s.distortion, s.size, s.fov_radius_px)
    ok = untouched & adj.used
    rms = float(np.sqrt(np.mean(adj.residual_px[ok] ** 2)))
    flagged = float(np.mean(~adj.inlier[~untouched])) if (~untouched).any() else float("nan")
    # observations the final adjustment flags, yet the field learned from (contaminated ones, and all)
    pulled = (
        int(np.sum(res.trained & ~adj.inlier & ~untouched)),
        int(np.sum(res.trained & ~adj.inlier & adj.used)),
    )
    pp_sigma = float(np.hypot(*adj.iop_std_px[0, :2]))
    if clean is None:
        clean = (field, adj.iop_px[0], e3)
        e3c_ref = e3c
    diff = field_difference(field, clean[0], s.size, s.fov_radius_px)
    dpp = float(np.hypot(*(adj.iop_px[0, :2] - clean[1][:2])))
    dc = float(adj.iop_px[0, 2] - clean[1][2])
    at_test = _modulo_homography(field.correction_at, s.distortion, s.test.xy_px, np.ones(len(s.test), bool))[0]
    print(
        f"  {kind}: field vs clean {diff[0]:.4f} px (mod H {diff[1]:.4f}), 3D {e3:.4f} mm ({e3 / clean[2]:.3f}x), "
        f"RMS {rms:.4f} px, pp shift {dpp:.2f} px, {len(res.history) - 1} it, {wall:.1f} s",
        flush=True,
    )
    row = (
        kind,
        len(obs),
        diff,
        truth,
        at_test,
        e3,
        e3 / clean[2],
        e3c,
        e3c / e3c_ref,
        rms,
        flagged,
        pulled,
        dpp,
        dpp / pp_sigma,
        dc,
        len(res.history) - 1,
        wall,
    )
    return row, clean


def print_table(rows) -> None:
    """The sets' table and the verdict on the targets."""
    print()
    print(
        "| set | obs | field vs clean (px) | same mod H (px) | field err. mod H, covered / inner 80 % (px) "
        "| same at held-out obs (px) | out-of-sample 3D (mm) | / clean | 3D, cont. held-out (mm) | / clean "
        "| in-sample RMS, clean obs (px) "
        "| contaminated flagged | flagged yet trained on: contaminated / all | pp shift (px) | / its std "
        "| c change (px) | it | wall (s) |"
    )
    print("|---" * 18 + "|")
    for kind, n, diff, truth, at_test, e3, r3, e3c, r3c, rms, flagged, pulled, dpp, zpp, dc, it, wall in rows:
        print(
            f"| {kind} | {n} | {diff[0]:.4f} | {diff[1]:.4f} | {truth[0]:.4f} / {truth[1]:.4f} | {at_test:.4f} "
            f"| {e3:.4f} | {r3:.3f} | {e3c:.4f} | {r3c:.3f} | {rms:.4f} | {100 * flagged:.0f} % "
            f"| {pulled[0]} / {pulled[1]} "
            f"| {dpp:.2f} | {zpp:.1f} "
            f"| {dc:+.2f} | {it} | {wall:.0f} |"
        )
    worst_field = max(row[2][0] for row in rows)
    worst_3d = max(max(row[6], row[8]) for row in rows)
    print(
        f"targets: field within 0.05 px RMS of the clean run's: {_verdict(worst_field <= 0.05)} "
        f"(worst {worst_field:.4f} px); "
        f"out-of-sample 3D within 10 % of the clean run's: {_verdict(worst_3d <= 1.10)} (worst {worst_3d:.3f}x)"
    )


def _verdict(met: bool) -> str:
    return "met" if met else "NOT met"


if __name__ == "__main__":
    import docpage

    docpage.run(__file__, main)
