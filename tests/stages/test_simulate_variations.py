"""The simulator's motion and marker options (issue 12), checked against their definitions.

``benchmarks/label_varied.py`` labels such sequences and scores them against the simulator's truth.
"""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.errors import InputError
from fluorocal.stages.geometry import quat_to_matrix
from fluorocal.stages.simulate import SimulateParams, make_phantom, simulate

#: the motion of issue 12: the turntable's axis wobbling by up to 5 deg, shifts of up to +-20 mm
WOBBLY = dict(turntable_wobble_deg=5.0, turntable_translation_mm=20.0, turntable_step_deg=10.0)


def test_marker_layouts():
    """Fixed slots (the first n of the design's eight) or a seeded random choice of any number of beads."""
    default, _, _ = make_phantom(SimulateParams())
    three, _, _ = make_phantom(SimulateParams(n_markers=3))
    is_marker = default.role == "marker"
    assert is_marker.sum() == 8 and (three.role == "marker").sum() == 3
    # the fixed layout's first three slots are three of the default's markers, with the marker diameter
    assert np.all(is_marker[three.role == "marker"]) and np.all(three.diameter_mm[three.role == "marker"] == 5.0)
    a, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=6, seed=1))
    b, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=6, seed=1))
    c, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=6, seed=2))
    assert (a.role == "marker").sum() == 6 and np.array_equal(a.role, b.role) and not np.array_equal(a.role, c.role)
    assert np.array_equal(a.xyz_mm, default.xyz_mm)  # only the roles and diameters change
    none, _, _ = make_phantom(SimulateParams(marker_layout="random", n_markers=0))
    assert not (none.role == "marker").any() and np.all(none.diameter_mm == 3.5)
    with pytest.raises(InputError, match="n_markers"):
        SimulateParams(n_markers=9)
    with pytest.raises(InputError, match="n_markers"):
        make_phantom(SimulateParams(marker_layout="random", n_markers=10_000))


def test_turntable_step_and_wobble():
    """Exposures step by the turn asked for; the turntable's axis tilts by up to the wobble, in every direction."""
    k = 40
    acq = simulate(SimulateParams(n_frames=k, **WOBBLY), render=False).truth.acquisition
    steps = np.degrees(np.diff(acq.turntable_angle_rad))
    assert np.allclose(steps, 10.0, atol=1e-9)
    # the phantom's vertical axis in the lab at each exposure
    up = np.array([quat_to_matrix(q) @ [0.0, 0.0, 1.0] for q in acq.lab_from_phantom_q])
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1, 1)))
    assert tilt.max() <= 5.0 + 1e-9
    # uniform up to 5 deg over 40 exposures: the largest is above 4 deg unless p = 0.8^40 ~ 1e-4
    assert tilt.max() > 4.0
    # tilted towards every quadrant (uniform directions: each is missed with p = 0.75^40 ~ 1e-5)
    quadrant = (np.degrees(np.arctan2(up[:, 1], up[:, 0])) // 90).astype(int) % 4
    assert set(quadrant) == {0, 1, 2, 3}
    still = simulate(SimulateParams(n_frames=3, turntable_step_deg=10.0), render=False).truth.acquisition
    assert np.allclose([quat_to_matrix(q)[2, 2] for q in still.lab_from_phantom_q], 1.0, atol=1e-15)


def test_hidden_markers_leave_the_frame_and_its_truth():
    """Frames drawn to hide markers lack 1 to all of them, in the truth and in the rendered image; all else is kept."""
    base = dict(n_frames=4, image_size_px=256, seed=3)
    shown = simulate(SimulateParams(**base))
    hidden = simulate(SimulateParams(**base, hidden_marker_fraction=1.0))
    markers = shown.phantom.ids[shown.phantom.role == "marker"]
    n_hidden = []
    for ft_s, ft_h, img_s, img_h in zip(
        shown.truth.frames[0], hidden.truth.frames[0], shown.frames[0], hidden.frames[0]
    ):
        gone = np.setdiff1d(ft_s.ids, ft_h.ids)
        assert np.all(np.isin(gone, markers)) and set(ft_h.ids) <= set(ft_s.ids)
        # the other beads' truth is unchanged, bit for bit (same geometry, same streams)
        keep = np.isin(ft_s.ids, ft_h.ids)
        assert np.array_equal(
            ft_s.outline_xy_px[keep & ~np.isin(ft_s.ids, gone)], ft_h.outline_xy_px[~np.isin(ft_h.ids, gone)]
        )
        n_hidden.append(len(gone))
        for b in gone:
            x, y = np.rint(ft_s.outline_xy_px[ft_s.ids == b][0]).astype(int)
            if ft_s.overlap[ft_s.ids == b][0]:
                continue
            # a 5 mm steel bead absorbs most of the beam at its centre (~90 % contrast): gone, the pixel is bright
            assert img_h.image[y, x] > 2.0 * img_s.image[y, x]
    # every frame hides at least one marker at fraction 1 (the visible ones; all 8 are in view here)
    assert min(n_hidden) >= 1
