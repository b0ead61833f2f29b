"""Detection-like centroids made from the simulator's truth, for the labelling tests.

The distorted outline centre of every visible bead is turned into a centroid by :func:`detections_from_truth`
(heavily overlapping beads merge into one blob or vanish, as a detector would make of them).
"""

from __future__ import annotations

import numpy as np
from fluorocal.stages.artifacts import Phantom
from fluorocal.stages.centroid import Centroids
from fluorocal.stages.label import LabelParams
from fluorocal.stages.simulate import SimulateParams
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def make_centroids(xy_px, diameter_px, *, sigma_px=0.05, major_px=None) -> Centroids:
    """A Centroids artifact of round detections at ``xy_px`` with apparent diameters ``diameter_px``."""
    xy_px = np.asarray(xy_px, dtype=np.float64).reshape(-1, 2)
    n = len(xy_px)
    minor = np.broadcast_to(np.asarray(diameter_px, dtype=np.float64) / 2, (n,))
    major = minor if major_px is None else np.asarray(major_px, dtype=np.float64)
    return Centroids(
        xy_px,
        np.full(n, sigma_px),
        np.full(n, sigma_px),
        np.zeros(n),
        major,
        minor,
        np.zeros(n),
        np.full(n, 0.05),
        np.full(n, 40, np.int64),
        np.full(n, 50.0),
        np.ones(n, bool),
        np.full(n, ""),
        np.arange(n),
    )


def params_of(sp: SimulateParams) -> LabelParams:
    """The labelling's geometry parameters of a simulated set (source distance, pixel pitch, image size)."""
    return LabelParams(
        source_image_distance_mm=sp.source_image_distance_mm,
        pixel_pitch_mm=sp.pixel_pitch_mm,
        image_size_px=(sp.image_size_px, sp.image_size_px),
    )


def detections_from_truth(ft, rng, *, noise_px=0.05, dropout=0.01, merged_keep=0.5, n_false=1, image_size_px=1024):
    """Detection-like centroids of one simulated frame, and the true bead id of each (-1: not one bead).

    Beads whose outlines overlap by more than touching (centres closer than their mean diameter) merge
    into one blob, kept with probability ``merged_keep`` at the area-weighted centre with the larger
    minor axis; touching beads get 4x the centroid noise; beads at the field edge are not detected;
    ``dropout`` of the rest are missed; ``n_false`` spurious detections are added away from the beads.
    """
    xy0, d0 = ft.outline_xy_px, ft.diameter_px
    n = len(xy0)
    pairs = cKDTree(xy0).query_pairs(float(d0.max()), output_type="ndarray")
    dist = np.linalg.norm(xy0[pairs[:, 0]] - xy0[pairs[:, 1]], axis=1)
    mean_d = 0.5 * (d0[pairs[:, 0]] + d0[pairs[:, 1]])
    merge = pairs[dist < mean_d]
    touching = np.zeros(n, bool)
    touching[pairs[dist < 1.15 * mean_d].ravel()] = True
    _, comp = connected_components(
        coo_matrix((np.ones(len(merge)), (merge[:, 0], merge[:, 1])), shape=(n, n)), directed=False
    )
    xy, ids, minor, major = [], [], [], []
    for c in np.unique(comp):
        m = np.flatnonzero(comp == c)
        if ft.field_edge[m].any():
            continue
        if len(m) == 1:
            if rng.random() < dropout:
                continue
            i = m[0]
            xy.append(xy0[i] + rng.normal(scale=noise_px * (4 if touching[i] else 1), size=2))
            ids.append(ft.ids[i])
            size = d0[i] * rng.uniform(0.97, 1.03)
            minor.append(size / 2)
            major.append(size / 2)
        elif rng.random() < merged_keep:
            w = d0[m] ** 2
            xy.append((xy0[m] * w[:, None]).sum(0) / w.sum())
            ids.append(-1)
            minor.append(d0[m].max() / 2)
            major.append((np.ptp(xy0[m], axis=0).max() + d0[m].max()) / 2)
    xy, ids, minor, major = np.array(xy).reshape(-1, 2), np.array(ids, np.int64), np.array(minor), np.array(major)
    if n_false:
        # spurious blobs (dust, noise) away from every bead: one on a missed bead would be labelled as it
        r = rng.uniform(0, 0.45 * image_size_px, 50 * n_false)
        a = rng.uniform(0, 2 * np.pi, 50 * n_false)
        spurious = image_size_px / 2 + np.column_stack([r * np.cos(a), r * np.sin(a)])
        spurious = spurious[cKDTree(xy0).query(spurious)[0] > d0.max()][:n_false]
        n_false = len(spurious)
        xy = np.vstack([xy, spurious])
        ids = np.append(ids, np.full(n_false, -1))
        minor = np.append(minor, np.full(n_false, np.median(minor)))
        major = np.append(major, np.full(n_false, np.median(minor)))
    perm = rng.permutation(len(xy))
    return make_centroids(xy[perm], 2 * minor[perm], sigma_px=noise_px, major_px=major[perm]), ids[perm]


def unambiguous_ids(ft, factor: float = 1.0) -> np.ndarray:
    """Ids of visible beads away from the field edge with no other outline centre within ``factor`` mean diameters."""
    xy0, d0 = ft.outline_xy_px, ft.diameter_px
    d, i = cKDTree(xy0).query(xy0, k=2)
    clear = d[:, 1] >= factor * 0.5 * (d0 + d0[i[:, 1]])
    return ft.ids[clear & ~ft.field_edge]


def without_roles(phantom: Phantom) -> Phantom:
    return Phantom(phantom.ids, phantom.xyz_mm, phantom.diameter_mm, np.full(phantom.n_beads, ""))


def seeds_from_truth(ft, rng, n=6, click_noise_px=1.0):
    """``n`` unambiguous beads spread over the frame, as a user would click them (1 px off)."""
    clear = unambiguous_ids(ft)
    pos = {t: k for k, t in enumerate(ft.ids)}
    pick = clear[np.linspace(0, len(clear) - 1, n).astype(int)]
    return tuple((float(i), *(ft.outline_xy_px[pos[i]] + rng.normal(scale=click_noise_px, size=2))) for i in pick)


#: the first configuration of benchmarks/label_varied.py: six markers at random, 9 deg steps, markers hidden in
#: one frame in ten
VARIED = dict(
    marker_layout="random",
    n_markers=6,
    turntable_step_deg=9.0,
    turntable_wobble_deg=5.0,
    turntable_translation_mm=20.0,
    turntable_height_mm=15.0,
    hidden_marker_fraction=0.1,
)
