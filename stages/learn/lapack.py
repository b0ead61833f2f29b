"""LAPACK's Cholesky routines of the systems' own work, called without holding Python's GIL.

SciPy's wrappers of LAPACK (:func:`scipy.linalg.cholesky_banded`, :func:`~scipy.linalg.cho_solve_banded`,
:func:`~scipy.linalg.cholesky`, :func:`scipy.linalg.lapack.dtrtri`) hold the GIL while LAPACK works, so a
biplanar learning's smoothness cross-validations (banded factorizations and solves: :mod:`.grid`) and its joint
uncertainties' block factorizations (:mod:`.blocktri`) gained nothing in threads (:mod:`.threads`). These call
the same routines of the same library through the pointers :mod:`scipy.linalg.cython_lapack` publishes, by
:mod:`ctypes`, with :mod:`.trmm`'s checks (the capsule's C signature, else SciPy's wrapper): the same numbers to
the last bit, the same errors.
"""

from __future__ import annotations

import ctypes
from functools import lru_cache

import numpy as np
from fluorocal.stages.learn.trmm import capsule_function, int_refs
from scipy.linalg import cho_solve_banded, cholesky, cholesky_banded, lapack

_INT, _CHAR, _ADDRESS = ctypes.POINTER(ctypes.c_int), ctypes.c_char_p, ctypes.c_void_p
#: cython_lapack's C signature of each routine (its typedef of double written ``double``) and its ctypes prototype
_ROUTINES = {
    "dpbtrf": (
        "void (char *, int *, int *, double *, int *, int *)",
        ctypes.CFUNCTYPE(None, _CHAR, _INT, _INT, _ADDRESS, _INT, _INT),
    ),
    "dpbtrs": (
        "void (char *, int *, int *, int *, double *, int *, double *, int *, int *)",
        ctypes.CFUNCTYPE(None, _CHAR, _INT, _INT, _INT, _ADDRESS, _INT, _ADDRESS, _INT, _INT),
    ),
    "dpotrf": (
        "void (char *, int *, double *, int *, int *)",
        ctypes.CFUNCTYPE(None, _CHAR, _INT, _ADDRESS, _INT, _INT),
    ),
    "dtrtri": (
        "void (char *, char *, int *, double *, int *, int *)",
        ctypes.CFUNCTYPE(None, _CHAR, _CHAR, _INT, _ADDRESS, _INT, _INT),
    ),
}


@lru_cache(maxsize=None)
def _routine(name: str):
    """SciPy's LAPACK ``name`` as a :mod:`ctypes` function, or None (:func:`~.trmm.capsule_function`)."""
    try:
        from scipy.linalg import cython_lapack
    except ImportError:
        return None
    return capsule_function(cython_lapack, name, *_ROUTINES[name])


def _call(name: str, *args) -> int:
    """LAPACK ``name`` on ``args`` (its ``info`` appended): that ``info``."""
    info = ctypes.c_int(0)
    _routine(name)(*args, ctypes.byref(info))
    return info.value


def _check_fortran(name: str, a: np.ndarray) -> None:
    if a.ndim != 2 or a.dtype != np.float64 or not (a.flags.f_contiguous and a.flags.writeable and a.flags.aligned):
        raise ValueError(f"{name}: the array must be 2-d, writeable, aligned Fortran float64; got {a.shape} {a.dtype}")


def cholesky_band(ab: np.ndarray) -> np.ndarray:
    """The Cholesky factor of the lower band ``ab`` ``(bandwidth + 1, n)``, in place in ``ab`` (LAPACK ``dpbtrf``).

    :func:`scipy.linalg.cholesky_banded` ``(ab, overwrite_ab=True, lower=True, check_finite=False)``'s result and
    errors (``numpy.linalg.LinAlgError`` where not positive definite). ``ab`` Fortran-contiguous float64, writeable.

    >>> cholesky_band(np.asfortranarray([[4.0, 9.0], [2.0, 0.0]]))  # [[4, 2], [2, 9]] = L L^T
    array([[2.        , 2.82842712],
           [1.        , 0.        ]])
    """
    _check_fortran("cholesky_band", ab)
    if _routine("dpbtrf") is None or ab.size == 0:
        return cholesky_banded(ab, overwrite_ab=True, lower=True, check_finite=False)
    info = _call("dpbtrf", b"L", *int_refs(ab.shape[1], ab.shape[0] - 1), ab.ctypes.data, *int_refs(ab.shape[0]))
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor not positive definite")
    if info < 0:
        raise ValueError(f"illegal value in {-info}-th argument of internal pbtrf")
    return ab


def solve_band(cb: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` of ``L L^T x = b``, ``cb`` the lower band of ``L`` (:func:`cholesky_band`'s); ``b`` ``(n,)`` or ``(n, m)``.

    :func:`scipy.linalg.cho_solve_banded` ``((cb, True), b, check_finite=False)``'s result (LAPACK ``dpbtrs``);
    ``b`` is not overwritten.

    >>> solve_band(np.asfortranarray([[2.0, 8.0**0.5], [1.0, 0.0]]), np.array([6.0, 11.0]))
    array([1., 1.])
    """
    cb, x = np.require(cb, np.float64, ["F_CONTIGUOUS", "ALIGNED"]), np.array(b, np.float64, order="F")
    if cb.ndim != 2 or x.ndim not in (1, 2) or cb.shape[1] != x.shape[0]:
        raise ValueError("shapes of cb and b are not compatible.")
    if _routine("dpbtrs") is None or x.size == 0:
        return cho_solve_banded((cb, True), b, check_finite=False)
    n, nrhs = x.shape[0], x.size // x.shape[0]
    info = _call(
        "dpbtrs",
        b"L",
        *int_refs(n, cb.shape[0] - 1, nrhs),
        cb.ctypes.data,
        *int_refs(cb.shape[0]),
        x.ctypes.data,
        *int_refs(n),
    )
    if info < 0:
        raise ValueError(f"illegal value in {-info}th argument of internal pbtrs")
    return x


def cholesky_lower(a) -> np.ndarray:
    """:func:`scipy.linalg.cholesky` ``(a, lower=True)``: the lower factor (zeros above), ``a`` not overwritten.

    LAPACK ``dpotrf`` on a Fortran copy of the square ``a``; ``numpy.linalg.LinAlgError`` where not positive
    definite, ``ValueError`` where not finite, as SciPy's.

    >>> cholesky_lower([[4.0, 2.0], [2.0, 9.0]])
    array([[2.        , 0.        ],
           [1.        , 2.82842712]])
    """
    c = np.array(np.asarray_chkfinite(a), np.float64, order="F", ndmin=2)
    if _routine("dpotrf") is None or c.ndim != 2 or c.shape[0] != c.shape[1] or c.size == 0:
        return cholesky(a, lower=True)
    n = c.shape[0]
    info = _call("dpotrf", b"L", *int_refs(n), c.ctypes.data, *int_refs(n))
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor of the array is not positive definite")
    if info < 0:
        raise ValueError(f'LAPACK reported an illegal value in {-info}-th argument on entry to "POTRF".')
    c[np.triu_indices(n, 1)] = 0.0  # SciPy's clean=True
    return c


def inverse_lower(a, *, unit: bool = False) -> np.ndarray:
    """The inverse of the lower triangle of square ``a`` (a unit diagonal with ``unit``), Fortran order.

    :func:`scipy.linalg.lapack.dtrtri` ``(a, lower=1, unitdiag=unit)[0]`` (LAPACK ``dtrtri`` on a copy of ``a``):
    above the diagonal, ``a``'s entries are left as they are; ``numpy.linalg.LinAlgError`` where singular.

    >>> inverse_lower([[2.0, 0.0], [1.0, 4.0]])
    array([[ 0.5  ,  0.   ],
           [-0.125,  0.25 ]])
    """
    c = np.array(a, np.float64, order="F")
    if c.ndim != 2 or c.shape[0] != c.shape[1]:
        raise ValueError(f"inverse_lower: a must be square; got {c.shape}")
    if _routine("dtrtri") is None or c.size == 0:
        c, info = lapack.dtrtri(a, lower=1, unitdiag=int(unit))
    else:
        info = _call(
            "dtrtri", b"L", b"U" if unit else b"N", *int_refs(c.shape[0]), c.ctypes.data, *int_refs(c.shape[0])
        )
    if info > 0:
        raise np.linalg.LinAlgError(f"inverse_lower: the triangle is singular (diagonal entry {info} zero)")
    return c


__all__ = ["cholesky_band", "cholesky_lower", "inverse_lower", "solve_band"]
