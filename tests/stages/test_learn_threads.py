"""Tests of the learning's systems side by side in threads (stages/learn/threads.py, and nogil.py's trmm).

The calibration's data: ``simulated_sets`` (``tests/stages/ba_synthetic.py``), two systems with the simulator's
strong distortion, true outline centres + 0.05 px noise, 8 + 8 epochs at 512 px; the recommended loop (its
gridded refinement and joint uncertainty included).
"""

from __future__ import annotations

import ctypes
import signal
import sys
import threading
import time
from concurrent.futures import Future

import numpy as np
import pytest
from fluorocal.stages.errors import EstimationError, InputError
from fluorocal.stages.learn import calibrate, loop, threads, uncertainty
from fluorocal.stages.learn import nogil as trmm_module
from fluorocal.stages.learn.nogil import trmm
from fluorocal.stages.learn.threads import each_system
from scipy.linalg import blas

from tests.stages.ba_synthetic import simulated_sets

SIZE = 512


@pytest.fixture(scope="module")
def two_systems():
    (train, _), nominal, _, _, _ = simulated_sets(8, 2, SIZE, 0)
    return train, nominal


#: each system's own work run in threads: (module, function, the index of its system argument)
PER_SYSTEM = [(uncertainty, "joint_uncertainty", 3), (loop, "_smoothness", 2), (loop, "_regress_system", 2)]


def test_threads_give_the_serial_calibration_bit_for_bit(two_systems, monkeypatch):
    (obs, initial), nominal = two_systems
    before, threads = threading.active_count(), {name: [] for _, name, _ in PER_SYSTEM}

    def watched(computed, name):  # the real computation, and the thread it ran in
        def run(*args, **kw):
            threads[name].append(threading.current_thread())
            return computed(*args, **kw)

        return run

    for module, name, _ in PER_SYSTEM:
        monkeypatch.setattr(module, name, watched(getattr(module, name), name))
    serial = calibrate(obs, nominal, initial, image_size=(SIZE, SIZE), workers=1)
    calls = {name: len(ran) for name, ran in threads.items()}  # per system, per refinement step for the CV's
    for ran in threads.values():  # workers=1: the caller's thread alone
        assert set(ran) == {threading.current_thread()} and len(ran) % 2 == 0
        ran.clear()
    threaded = calibrate(obs, nominal, initial, image_size=(SIZE, SIZE), workers=2)
    for name, ran in threads.items():  # threads of their own (a pool per step), as many calls
        assert len(set(ran)) >= 2 and threading.current_thread() not in ran and len(ran) == calls[name]
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
    assert [cv.order for cv in serial.cv] == [cv.order for cv in threaded.cv] and len(serial.cv) == 2
    for a, b in zip(serial.cv, threaded.cv):  # the refinement's smoothness CVs, each in its thread
        np.testing.assert_array_equal(a.cv_cost, b.cv_cost)
    assert threading.active_count() == before  # no thread outlives the calibration


@pytest.mark.parametrize("module, name, at", PER_SYSTEM)
def test_an_error_in_the_threads_is_the_serial_ones(two_systems, monkeypatch, module, name, at):
    """Both systems' work (uncertainty, CV, regression) fails, B's at once, A's after computing it: A's error raised."""
    (obs, initial), nominal = two_systems
    computed = getattr(module, name)

    def failing(*args, **kw):
        system = args[at]
        if system == 0:
            computed(*args, **kw)
        raise EstimationError(f"system {'AB'[system]}: failed")

    monkeypatch.setattr(module, name, failing)
    before, messages = threading.active_count(), []
    for workers in (1, 2):
        with pytest.raises(EstimationError, match="^system A: failed$") as caught:
            calibrate(obs, nominal, initial, image_size=(SIZE, SIZE), workers=workers)
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


FLAGS = [(side, lower, trans_a, diag) for side in (0, 1) for lower in (0, 1) for trans_a in (0, 1) for diag in (0, 1)]


@pytest.mark.parametrize("side, lower, trans_a, diag", FLAGS)
@pytest.mark.parametrize("k, other", [(1, 1), (0, 3), (3, 0), (0, 0), (5, 1), (1, 6), (19, 11)])
def test_trmm_is_scipys_dtrmm_for_every_flag_and_shape(side, lower, trans_a, diag, k, other):
    rng = np.random.default_rng(k * 100 + other)
    a = rng.normal(size=(k, k))
    a = np.tril(a) if lower else np.triu(a)
    b = np.asfortranarray(rng.normal(size=(k, other) if side == 0 else (other, k)))
    flags = dict(side=side, lower=lower, trans_a=trans_a, diag=diag)
    want = blas.dtrmm(1.0, np.asfortranarray(a), b, **flags)
    # a read through a reversed, strided view (copied for BLAS); b a Fortran view into a wider array (its ldb)
    wide_a = np.zeros((k, 2 * k))
    wide_a[:, ::-2] = a
    wide_b = np.zeros((b.shape[0], b.shape[1] + 4), order="F")
    wide_b[:, 2 : 2 + b.shape[1]] = b
    view = wide_b[:, 2 : 2 + b.shape[1]]
    got = trmm(wide_a[:, ::-2], view, **flags)
    np.testing.assert_array_equal(got, want)  # the same routine: the same bits
    assert np.shares_memory(got, wide_b) or got.size == 0  # in place
    assert not wide_b[:, :2].any() and not wide_b[:, 2 + b.shape[1] :].any()  # nothing written beside the view


def test_trmm_refuses_what_blas_would_misread_on_either_path(monkeypatch):
    """A C-ordered, unaligned, read-only or 1-d ``b``: a ValueError, with SciPy's pointer or without it."""
    a = np.asfortranarray(np.eye(3))
    raw = np.zeros(3 * 4 * 8 + 1, dtype=np.uint8)[1:]  # 8-byte values one byte off their alignment
    unaligned = raw.view(np.float64).reshape((3, 4), order="F")
    assert unaligned.flags.f_contiguous and not unaligned.flags.aligned
    read_only = np.ones((3, 4), order="F")
    read_only.flags.writeable = False
    for pointer in (trmm_module._dtrmm(), None):
        monkeypatch.setattr(trmm_module, "_dtrmm", lambda p=pointer: p)
        for b in (np.ones((3, 4)), unaligned, read_only, np.ones(3)):
            with pytest.raises(ValueError, match="^trmm: b must be 2-d, writeable, aligned Fortran float64"):
                trmm(a, b, side=0, lower=1, trans_a=0)
        with pytest.raises(ValueError, match=r"^trmm: a must be \(4, 4\)"):
            trmm(a, np.ones((3, 4), order="F"), side=1, lower=1, trans_a=0)


def _capsule_named(name: bytes, of):
    """A capsule with ``of``'s pointer under ``name`` (what another build of SciPy would publish)."""
    new = ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p)(
        ("PyCapsule_New", ctypes.pythonapi)
    )
    return new(trmm_module._POINTER_OF(of, trmm_module._NAME_OF(of)), name, None)


def test_trmm_calls_scipys_pointer_only_with_the_expected_signature(monkeypatch):
    """Today's SciPy's pointer is taken; an ILP64 build's (``int`` -> ``int64_t``) or an unknown one is not."""
    from scipy.linalg import cython_blas

    trmm_module._dtrmm.cache_clear()
    assert trmm_module._dtrmm() is not None  # this SciPy's: its typedef of double accepted
    real = cython_blas.__pyx_capi__["dtrmm"]
    d = b"__pyx_t_5scipy_6linalg_11cython_blas_d *"
    ilp64 = b"void (char *, char *, char *, char *, int64_t *, int64_t *, %s, %s, int64_t *, %s, int64_t *)" % (d, d, d)
    names = [ilp64, b"void (char *, char *, char *, char *, int *, int *, double *, double *, int *, double *)"]
    a, b = np.asfortranarray(np.tril(np.ones((3, 3)))), np.asfortranarray(np.arange(6.0).reshape(3, 2))
    for name in names:
        monkeypatch.setitem(cython_blas.__pyx_capi__, "dtrmm", _capsule_named(name, real))
        trmm_module._dtrmm.cache_clear()
        try:
            assert trmm_module._dtrmm() is None
            got = trmm(a, b.copy(order="F"), side=0, lower=1, trans_a=0)  # SciPy's wrapper instead
        finally:
            trmm_module._dtrmm.cache_clear()
        np.testing.assert_array_equal(got, [[0.0, 1.0], [2.0, 4.0], [6.0, 9.0]])  # running sums of the columns


class _Recorded(threads.ThreadPoolExecutor):
    """each_system's pool, its futures kept (:func:`_until` waits for the queued ones' cancellation)."""

    futures: list = []

    def submit(self, function, s):
        future = super().submit(function, s)
        self.futures.append(future)
        return future


def _until(condition, timeout: float = 20.0) -> bool:
    """Wait for ``condition()`` (a state of the other threads, not a duration); False after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def _waiting_for_a_result(thread: threading.Thread) -> bool:
    """``thread`` blocked in ``Future.result()`` (a signal there interrupts the wait: no other code runs)."""
    frame = sys._current_frames().get(thread.ident)
    return (
        frame is not None
        and frame.f_code is threading.Condition.wait.__code__
        and frame.f_back.f_code is Future.result.__code__
    )


def test_ctrl_c_while_the_systems_run_starts_no_other_and_leaves_no_thread(monkeypatch):
    """SIGINT to the waiting main thread: KeyboardInterrupt once the running systems end; the rest never start.

    Ordered by events, not sleeps: system 0 interrupts the main thread once system 1 runs and the main thread
    waits for the results; the running systems end once the queued ones are cancelled. SIGINT's handler (it
    records that it ran) and mask are the test's own: another test's leave nothing here.
    """
    main, before, started, finished, handled = threading.main_thread(), threading.active_count(), [], [], []
    assert threading.current_thread() is main
    monkeypatch.setattr(_Recorded, "futures", [])
    monkeypatch.setattr(threads, "ThreadPoolExecutor", _Recorded)

    def interrupt(signum, frame):
        handled.append(threading.current_thread())
        raise KeyboardInterrupt

    def system(s: int) -> int:
        started.append(s)
        if s == 0:
            assert _until(lambda: 1 in started) and _until(lambda: _waiting_for_a_result(main))
            signal.pthread_kill(main.ident, signal.SIGINT)
        _until(lambda: len(_Recorded.futures) == 4 and all(f.cancelled() for f in _Recorded.futures[2:]))
        finished.append(s)
        return s

    previous = signal.signal(signal.SIGINT, interrupt)
    mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    try:
        with pytest.raises(KeyboardInterrupt):
            each_system(system, 4, workers=2)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        signal.signal(signal.SIGINT, previous)
    assert handled == [main]
    # the running ones finished before it was raised; systems 2 and 3 never started
    assert sorted(started) == sorted(finished) == [0, 1]
    assert threading.active_count() == before


def test_ctrl_c_while_the_systems_are_handed_out_starts_no_queued_one(monkeypatch):
    """KeyboardInterrupt in ``submit`` of system 3: system 2, queued behind the two running, never starts."""
    before, started, finished = threading.active_count(), [], []

    class Interrupted(_Recorded):
        def submit(self, function, s):
            if s == 3:
                raise KeyboardInterrupt
            return super().submit(function, s)

    def system(s: int) -> int:
        started.append(s)
        # both threads busy while the main thread submits and is interrupted: until system 2 is cancelled
        _until(lambda: len(Interrupted.futures) == 3 and Interrupted.futures[2].cancelled())
        finished.append(s)
        return s

    monkeypatch.setattr(_Recorded, "futures", [])
    monkeypatch.setattr(threads, "ThreadPoolExecutor", Interrupted)
    with pytest.raises(KeyboardInterrupt):
        each_system(system, 4, workers=2)
    assert sorted(started) == sorted(finished) == [0, 1]
    assert threading.active_count() == before
