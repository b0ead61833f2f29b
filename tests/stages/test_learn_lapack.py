"""Tests of LAPACK's Cholesky routines called through SciPy's cython_lapack pointers (stages/learn/nogil.py).

The reference is SciPy's own wrapper of the same routine of the same library: the same numbers to the bit (no
tolerance), the same errors; and, to a tolerance, the factorisation's definition (``L L^T = M``, ``M x = b``).
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from fluorocal.stages.learn import nogil as lapack
from fluorocal.stages.learn.nogil import cholesky_band, cholesky_lower, inverse_lower, solve_band
from scipy.linalg import cho_solve_banded, cholesky, cholesky_banded
from scipy.linalg import lapack as scipy_lapack

from tests.stages.test_learn_threads import _capsule_named

ROUTINES = ("dpbtrf", "dpbtrs", "dpotrf", "dtrtri")


def _band_spd(n: int, bandwidth: int, seed: int) -> np.ndarray:
    """A random symmetric positive definite band matrix (diagonally dominant), dense ``(n, n)``."""
    rng = np.random.default_rng(seed)
    M = np.zeros((n, n))
    for k in range(1, bandwidth + 1):
        off = rng.uniform(-1, 1, max(n - k, 0))
        M += np.diag(off, -k) + np.diag(off, k)
    return M + np.diag(rng.uniform(1, 2, n) + 2 * bandwidth)


def _lower_band(M: np.ndarray, bandwidth: int) -> np.ndarray:
    n = len(M)
    ab = np.zeros((bandwidth + 1, n), order="F")
    for k in range(bandwidth + 1):
        ab[k, : max(n - k, 0)] = np.diag(M, -k)
    return ab


@pytest.fixture(params=["pointer", "fallback"])
def path(request, monkeypatch):
    """Each test on both paths: SciPy's pointers by ctypes, and (pointer not found) SciPy's wrappers."""
    if request.param == "fallback":
        monkeypatch.setattr(lapack, "_routine", lambda name: None)
    else:
        assert all(lapack._routine(name) is not None for name in ROUTINES)  # this SciPy's pointers taken
    return request.param


@pytest.mark.parametrize("n, bandwidth", [(1, 0), (7, 1), (40, 3), (200, 12), (5, 6)])
def test_banded_cholesky_and_solve_are_scipys_to_the_bit(path, n, bandwidth):
    M = _band_spd(n, min(bandwidth, n - 1), n + bandwidth)
    ab = _lower_band(M, bandwidth)
    want = cholesky_banded(ab.copy(order="F"), lower=True, check_finite=False)
    got = cholesky_band(ab)
    assert got is ab or path == "fallback"  # in place where the pointer is called
    np.testing.assert_array_equal(got, want)
    L = np.zeros((n, n))
    for k in range(bandwidth + 1):
        L += np.diag(got[k, : max(n - k, 0)], -k) if k < n else 0.0
    np.testing.assert_allclose(L @ L.T, M, rtol=0, atol=1e-12 * np.abs(M).max())  # the factor's definition
    rng = np.random.default_rng(n)
    for b in (rng.normal(size=n), rng.normal(size=(n, 3)), np.asfortranarray(rng.normal(size=(n, 2)))[:, ::-1]):
        before = b.copy()
        x = solve_band(got, b)
        np.testing.assert_array_equal(x, cho_solve_banded((want, True), b, check_finite=False))
        assert x.shape == b.shape and np.array_equal(b, before)  # b not overwritten
        np.testing.assert_allclose(M @ x, b, rtol=0, atol=1e-10 * np.abs(b).max())


def test_banded_cholesky_raises_scipys_errors(path):
    M = _band_spd(6, 1, 0)
    M[3, 3] = -1.0  # not positive definite at the 4th leading minor
    with pytest.raises(np.linalg.LinAlgError, match="^4-th leading minor not positive definite$"):
        cholesky_band(_lower_band(M, 1))
    with pytest.raises(ValueError, match="Fortran float64"):
        cholesky_band(np.ascontiguousarray(_lower_band(M, 1)))  # C order: LAPACK would read it transposed
    with pytest.raises(ValueError, match="^shapes of cb and b are not compatible"):
        solve_band(_lower_band(_band_spd(6, 1, 0), 1), np.ones(5))


@pytest.mark.parametrize("n", [1, 2, 17, 64])
def test_dense_cholesky_and_triangular_inverse_are_scipys_to_the_bit(path, n):
    rng = np.random.default_rng(n)
    G = rng.normal(size=(n, n))
    M = G @ G.T + n * np.eye(n)  # C order, as the block factorisation hands its blocks
    L = cholesky_lower(M)
    np.testing.assert_array_equal(L, cholesky(M, lower=True))
    assert not np.triu(L, 1).any()  # zeros above, as SciPy's clean=True
    np.testing.assert_allclose(L @ L.T, M, rtol=0, atol=1e-12 * np.abs(M).max())
    for unit in (False, True):
        T = np.tril(rng.uniform(-1, 1, (n, n)), -1) / n + np.diag(rng.uniform(1, 2, n))  # well conditioned
        T[np.triu_indices(n, 1)] = 7.0  # above the diagonal: not read, left as it is
        inverse = inverse_lower(T, unit=unit)
        np.testing.assert_array_equal(inverse, scipy_lapack.dtrtri(T, lower=1, unitdiag=int(unit))[0])
        assert inverse.flags.f_contiguous
        product = _as_read(inverse, unit) @ _as_read(T, unit)
        np.testing.assert_allclose(product, np.eye(n), rtol=0, atol=1e-12)


def _as_read(A: np.ndarray, unit: bool) -> np.ndarray:
    """The triangle LAPACK reads of ``A``: below the diagonal, and the diagonal unless ``unit``."""
    return np.tril(A, -1) + (np.eye(len(A)) if unit else np.diag(np.diag(A)))


def test_dense_cholesky_raises_scipys_errors(path):
    M = np.eye(3)
    M[2, 2] = -1.0
    with pytest.raises(np.linalg.LinAlgError, match="^3-th leading minor of the array is not positive definite$"):
        cholesky_lower(M)
    with pytest.raises(ValueError, match="must not contain infs or NaNs"):
        cholesky_lower(np.full((2, 2), np.nan))
    with pytest.raises(np.linalg.LinAlgError):  # a zero on the diagonal: singular
        inverse_lower(np.diag([1.0, 0.0, 2.0]))


@pytest.mark.parametrize("name", ROUTINES)
def test_a_pointer_of_another_signature_is_not_called(monkeypatch, name):
    """An ILP64 build's pointer (``int`` -> ``int64_t``) or a changed one: not taken; SciPy's wrapper instead."""
    from scipy.linalg import cython_lapack

    lapack._routine.cache_clear()
    real = cython_lapack.__pyx_capi__[name]
    assert lapack._routine(name) is not None  # this SciPy's: its typedef of double accepted
    expected = lapack._ROUTINES[name][0]
    # the names alive through the test: a capsule keeps a pointer to its name, not a copy
    others = [expected.replace("int *", "int64_t *").encode(), expected.replace("double *", "float *").encode()]
    for other in others:
        monkeypatch.setitem(cython_lapack.__pyx_capi__, name, _capsule_named(other, real))
        lapack._routine.cache_clear()
        try:
            assert lapack._routine(name) is None
            M = _band_spd(4, 1, 0)
            ab = _lower_band(M, 1)
            x = solve_band(cholesky_band(ab), np.ones(4))
            np.testing.assert_allclose(x, np.linalg.solve(M, np.ones(4)), rtol=0, atol=1e-14)
        finally:
            lapack._routine.cache_clear()


def test_the_pointers_are_called_without_the_gil():
    """The :mod:`ctypes` functions release the GIL: a CFUNCTYPE does, a PYFUNCTYPE (FUNCFLAG_PYTHONAPI) not."""
    for name in ROUTINES:
        assert not lapack._routine(name)._flags_ & ctypes._FUNCFLAG_PYTHONAPI
