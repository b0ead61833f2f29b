"""Tests of the learning's systems side by side in threads (stages/learn/threads.py, stages/learn/trmm.py).

The calibration's data: ``simulated_sets`` (``tests/stages/ba_synthetic.py``), two systems with the simulator's
strong distortion, true outline centres + 0.05 px noise, 8 + 8 epochs at 512 px; the recommended loop (its
gridded refinement and joint uncertainty included).
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.learn import LearnParams, calibrate, uncertainty
from fluorocal.stages.learn.threads import each_system
from fluorocal.stages.learn.trmm import trmm
from scipy.linalg import blas

from tests.stages.ba_synthetic import simulated_sets

SIZE = 512


@pytest.fixture(scope="module")
def two_systems():
    (train, _), nominal, _, _, _ = simulated_sets(8, 2, SIZE, 0)
    return train, nominal


def test_threads_give_the_serial_calibration_bit_for_bit(two_systems, monkeypatch):
    (obs, initial), nominal = two_systems
    before, threads = threading.active_count(), []
    computed = uncertainty.joint_uncertainty

    def watched(*args, **kw):  # the real computation, and the thread it ran in
        threads.append(threading.current_thread())
        return computed(*args, **kw)

    monkeypatch.setattr(uncertainty, "joint_uncertainty", watched)
    serial = calibrate(obs, nominal, initial, image_size=(SIZE, SIZE), workers=1)
    assert threads == [threading.current_thread()] * 2  # workers=1: the caller's thread alone
    threads.clear()
    threaded = calibrate(obs, nominal, initial, image_size=(SIZE, SIZE), workers=2)
    assert len(set(threads)) == 2 and threading.current_thread() not in threads  # two threads of their own
    assert serial.uncertainty is not None and serial.history[-1].phase == "grid"  # the refinement ran, σ too
    # each system's work reads only its own data and writes nothing shared: the same operations on the same
    # numbers, so the same bits (no tolerance)
    for f, g in zip(serial.fields, threaded.fields):
        np.testing.assert_array_equal(f.delta_px, g.delta_px)
        np.testing.assert_array_equal(f.sigma_px, g.sigma_px)
    for u, v in zip(serial.uncertainty, threaded.uncertainty):
        np.testing.assert_array_equal(u.iop_cov_px2, v.iop_cov_px2)
        np.testing.assert_array_equal(u.node_std_px, v.node_std_px)
    np.testing.assert_array_equal(serial.adjustment.xyz_mm, threaded.adjustment.xyz_mm)
    np.testing.assert_array_equal(serial.adjustment.iop_px, threaded.adjustment.iop_px)
    np.testing.assert_array_equal(serial.corrections_px, threaded.corrections_px)
    assert repr(serial.history) == repr(threaded.history)
    assert threading.active_count() == before  # no thread outlives the calibration


def test_an_error_in_the_threads_is_the_serial_ones(two_systems):
    """Every system too small for the cross-validation's folds: the first system's error, whether threaded or not."""
    (obs, initial), nominal = two_systems
    params = LearnParams(n_folds=10_000)
    before, messages = threading.active_count(), []
    for workers in (1, 2):
        with pytest.raises(EstimationError, match="system A has") as caught:
            calibrate(obs, nominal, initial, image_size=(SIZE, SIZE), params=params, workers=workers)
        messages.append(str(caught.value))
    assert messages[0] == messages[1]
    assert threading.active_count() == before


def _checked(s: int, bad: set) -> int:
    if s in bad:
        raise InputError(f"system {s}: no observations")
    return 10 * s


@pytest.mark.parametrize("workers", [1, 2, 8])
def test_each_system_raises_the_first_failing_system_in_order(workers):
    before = threading.active_count()
    assert each_system(lambda s: _checked(s, set()), 3, workers) == (0, 10, 20)
    with pytest.raises(InputError, match="^system 1: no observations$"):
        each_system(lambda s: _checked(s, {1}), 3, workers)
    with pytest.raises(InputError, match="^system 0: no observations$"):  # system 2 fails too, later in order
        each_system(lambda s: _checked(s, {0, 2}), 3, workers)
    assert threading.active_count() == before


def test_one_system_or_one_worker_starts_no_thread():
    main = threading.current_thread()
    assert each_system(lambda s: threading.current_thread() is main, 1, workers=4) == (True,)
    assert each_system(lambda s: threading.current_thread() is main, 3, workers=1) == (True,) * 3
    assert not any(each_system(lambda s: threading.current_thread() is main, 2, workers=2))


@pytest.mark.parametrize("side, lower, trans_a, diag", [(0, 1, 0, 1), (1, 1, 1, 0), (1, 0, 1, 0), (1, 0, 0, 0)])
def test_trmm_is_scipys_dtrmm_to_the_bit(side, lower, trans_a, diag):
    rng = np.random.default_rng(5)
    k, other = 37, 23
    a = rng.normal(size=(k, k))
    a = np.asfortranarray(np.tril(a) if lower else np.triu(a))
    b = np.asfortranarray(rng.normal(size=(k, other) if side == 0 else (other, k)))
    want = blas.dtrmm(1.0, a, b, side=side, lower=lower, trans_a=trans_a, diag=diag)
    # the same routine of the same library: not a tolerance, the same bits
    np.testing.assert_array_equal(trmm(a, b.copy(order="F"), side=side, lower=lower, trans_a=trans_a, diag=diag), want)
    # C-ordered a is read as SciPy reads it (copied to Fortran order)
    got = trmm(np.ascontiguousarray(a), b.copy(order="F"), side=side, lower=lower, trans_a=trans_a, diag=diag)
    np.testing.assert_array_equal(got, want)


def test_trmm_refuses_what_blas_would_misread():
    a = np.asfortranarray(np.eye(3))
    with pytest.raises(ValueError, match="Fortran float64"):
        trmm(a, np.ones((3, 4)), side=0, lower=1, trans_a=0)  # C order: BLAS would read its transpose
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        trmm(a, np.ones((3, 4), order="F"), side=1, lower=1, trans_a=0)
