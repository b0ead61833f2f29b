"""Biplanar two-ray spatial intersection (benchmarks/biplanar.py, issue 7) against the simulator's truth.

The data are ``simulated_sets`` (``tests/stages/ba_synthetic.py``, as ``benchmarks/learn.py`` uses): two systems with
the simulator's strong distortion, true distorted outline centres + 0.05 px
noise, even epochs for training and odd ones held out; here 8 + 8 epochs at
512 px (the benchmark: 75 + 75 at 1024 px).
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.evaluate import biplanar_errors, biplanar_pairs, ideal_points, summarise
from fluorocal.stages.geometry import project
from fluorocal.stages.learn import LearnParams, calibrate

from tests.stages.ba_synthetic import simulated_sets, true_rig

#: the schemes compared (benchmarks/biplanar.py's default pair): none, and the recommended [learn] block
SCHEMES = {"none": ("none", {}), "recommended": ("knn+iop+smooth", {"preset": "recommended", "max_iterations": 3})}

N_EPOCHS = 8
SIZE = 512


@pytest.fixture(scope="module")
def biplanar():
    (train, test), nominal, true_xyz, acq, _ = simulated_sets(N_EPOCHS, 2, SIZE, 0)
    return train, test, nominal, true_xyz, acq


def _exact_observations(test_obs, true_xyz, ids, acq):
    """Noise-free measured points of the held-out rows: true centres projected, then truly distorted."""
    xy = np.empty_like(test_obs.xy_px)
    for s, system in enumerate(acq.systems):
        for e in np.unique(test_obs.exposure):
            sel = (test_obs.system == s) & (test_obs.exposure == e)
            k = 2 * e + 1  # held-out epochs are the odd exposures of the acquisition
            ideal = project(
                true_xyz[np.searchsorted(ids, test_obs.bead_id[sel])], acq.q[s, k], acq.source_mm[s, k], system.iop_px
            )
            xy[sel] = system.distortion.distort_points(ideal)
    return xy


def test_true_rig_and_true_correction_reproduce_the_true_beads(biplanar):
    _, (test_obs, _), nominal, true_xyz, acq = biplanar
    assert np.all(np.diff(nominal.ids) > 0)
    measured = _exact_observations(test_obs, true_xyz, nominal.ids, acq)
    # hand each system its true correction Δ = measured - ideal
    ideal = np.empty_like(measured)
    for s, system in enumerate(acq.systems):
        sel = test_obs.system == s
        ideal[sel] = system.distortion.undistort_points(measured[sel])
    iop, rop_q, rop_source = true_rig(acq)
    err = biplanar_errors(test_obs, ideal, iop, rop_q, rop_source, nominal.ids, true_xyz)
    assert len(err) == len(biplanar_pairs(test_obs)[0]) > 50 * N_EPOCHS
    # an analytic invariant: only the inversion tolerance of undistort (1e-10 px) and rounding remain,
    # ~1e-10 px x 0.2 mm/px at the phantom (measured 7e-12 mm); 1e-6 mm is far below the 0.01 mm asked
    assert np.abs(err).max() < 1e-6, np.abs(err).max()
    # the rigid fit has no scale: a 0.5 % longer baseline must show (measured 0.34 mm mean)
    long = biplanar_errors(test_obs, ideal, iop, rop_q, 1.005 * rop_source, nominal.ids, true_xyz)
    assert summarise(long)["mean"] > 0.05


@pytest.mark.check  # the paper's accuracy target: two full calibrations; make test's test_evaluate scores the same
def test_calibration_improves_the_intersection_at_least_as_much_as_the_paper(biplanar):
    (train_obs, train_init), (test_obs, _), nominal, true_xyz, _ = biplanar
    means = {}
    for name, (scheme, over) in SCHEMES.items():
        res = calibrate(
            train_obs, nominal, train_init, image_size=(SIZE, SIZE), scheme=scheme, params=LearnParams(**over)
        )
        adj = res.adjustment
        # the observations undistorted by each system's learned correction (none for "none")
        learned = ideal_points(test_obs, [res.field(s).correction_at for s in range(len(test_obs.system_names))])
        err = biplanar_errors(test_obs, learned, adj.iop_px, adj.rop_q, adj.rop_source_mm, nominal.ids, true_xyz)
        means[name] = summarise(err)["mean"]
    improvement = 1 - means["recommended"] / means["none"]
    # the paper's TABLE I: 46.2-53.8 % (47 % with 75 pairs), the target; measured here
    # 0.425 -> 0.133 mm (69 %; with 12 + 12 epochs 0.418 -> 0.085 mm, 80 %)
    assert improvement >= 0.47, means
