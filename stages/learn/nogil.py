"""SciPy's BLAS and LAPACK routines of the systems' own work, called without holding Python's GIL.

SciPy's wrappers (:func:`scipy.linalg.blas.dtrmm`, :func:`scipy.linalg.cholesky_banded`,
:func:`~scipy.linalg.cho_solve_banded`, :func:`~scipy.linalg.cholesky`, :func:`scipy.linalg.lapack.dtrtri`) hold
the GIL while BLAS or LAPACK works (measured: two threads of them take as long as one after the other), so a
biplanar learning's two systems' joint uncertainties (mostly triangular products and block factorizations:
:mod:`fluorocal.stages.learn.blocktri`) and smoothness cross-validations (banded factorizations and solves:
:mod:`fluorocal.stages.learn.grid`) could not run side by side (:mod:`fluorocal.stages.learn.threads`). These
call the same routines of the same library, through the function pointers :mod:`scipy.linalg.cython_blas` and
:mod:`scipy.linalg.cython_lapack` publish for compiled callers, by :mod:`ctypes`, which lets go of the GIL for the
call: the same numbers to the last bit, the same errors. A pointer whose C signature is not the expected one is
not called: SciPy's wrapper is.
"""

from __future__ import annotations

import ctypes
import re
from functools import lru_cache

import numpy as np
from scipy.linalg import blas, cho_solve_banded, cholesky, cholesky_banded, lapack

_INT, _DOUBLE, _ADDRESS = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_double), ctypes.c_void_p
#: cython_blas's ``void dtrmm(char *side, char *uplo, char *transa, char *diag, int *m, int *n, double *alpha,
#: double *a, int *lda, double *b, int *ldb)``
_SIGNATURE = ctypes.CFUNCTYPE(None, *[ctypes.c_char_p] * 4, _INT, _INT, _DOUBLE, _ADDRESS, _INT, _ADDRESS, _INT)
_INT_MAX = 2**31 - 1  # BLAS's (LP64) int
#: the capsule's name, Cython's C signature of the pointer, its double typedef (``__pyx_t_<module>_d``) as ``double``:
#: any other (64-bit ints of an ILP64 build, a changed SciPy) is not called, :func:`blas.dtrmm` is
_CAPSULE_NAME = "void (char *, char *, char *, char *, int *, int *, double *, double *, int *, double *, int *)"
# the C-API of capsules, as private prototypes (ctypes.pythonapi's shared function objects are left as they are)
_NAME_OF = ctypes.PYFUNCTYPE(ctypes.c_char_p, ctypes.py_object)(("PyCapsule_GetName", ctypes.pythonapi))
_POINTER_OF = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi)
)


def _c_signature(capsule_name: bytes | None) -> str:
    """A Cython capsule's name with its typedefs of double (``__pyx_t_..._d``) written ``double``.

    >>> _c_signature(b"void (int *, __pyx_t_5scipy_6linalg_11cython_blas_d *)")
    'void (int *, double *)'
    """
    return re.sub(r"\b__pyx_t_\w+?_d\b", "double", (capsule_name or b"").decode("ascii", "replace"))


def capsule_function(module, routine: str, c_signature: str, prototype):
    """``module``'s (``cython_blas``, ``cython_lapack``) ``routine`` as a ctypes ``prototype``, or None if not found.

    The :mod:`ctypes` function releases the GIL for the call. None also where the pointer's C signature (its
    capsule's name, :func:`_c_signature`) is not ``c_signature``: called with the wrong types it would crash or
    write wrong numbers.
    """
    try:
        capsule = module.__pyx_capi__[routine]
        name = _NAME_OF(capsule)
        if _c_signature(name) != c_signature:
            return None
        return prototype(_POINTER_OF(capsule, name))
    except (AttributeError, KeyError, TypeError, ValueError):
        return None


def int_refs(*values: int) -> tuple:
    """Each of ``values`` as the ``int *`` a Fortran routine takes (LP64), alive as long as the tuple."""
    if max(values, default=0) > _INT_MAX:  # ctypes would wrap a larger one silently
        raise ValueError(f"a dimension beyond BLAS's int: {max(values)}")
    return tuple(ctypes.byref(ctypes.c_int(v)) for v in values)


@lru_cache(maxsize=1)
def _dtrmm():
    """SciPy's BLAS ``dtrmm`` as a :mod:`ctypes` function, or None (:func:`capsule_function`)."""
    try:
        from scipy.linalg import cython_blas
    except ImportError:
        return None
    return capsule_function(cython_blas, "dtrmm", _CAPSULE_NAME, _SIGNATURE)


def trmm(a: np.ndarray, b: np.ndarray, *, side: int, lower: int, trans_a: int, diag: int = 0) -> np.ndarray:
    """``op(a) b`` (``side=0``) or ``b op(a)`` (``side=1``), in place in ``b``: ``blas.dtrmm(1.0, ...)``'s result.

    ``a`` ``(k, k)`` triangular (``lower``; ``op`` its transpose with ``trans_a``; a unit diagonal with ``diag``);
    ``b`` ``(m, n)`` float64, Fortran-contiguous and writeable (the result); ``a`` is read in Fortran order
    (copied to it if given otherwise, as SciPy's wrapper copies it). Falls back to :func:`blas.dtrmm` (the GIL
    held) where SciPy's BLAS pointer is not found.

    Examples
    --------
    >>> a = np.asfortranarray([[2.0, 0.0], [1.0, 3.0]])  # lower triangular
    >>> trmm(a, np.asfortranarray([[1.0], [1.0]]), side=0, lower=1, trans_a=0).ravel()
    array([2., 4.])
    """
    _check_fortran("trmm: b", b)
    m, n = b.shape
    k = m if side == 0 else n
    if np.shape(a) != (k, k):
        raise ValueError(f"trmm: a must be ({k}, {k}) for b {b.shape}; got {np.shape(a)}")
    function = _dtrmm()
    if function is None:
        return blas.dtrmm(1.0, a, b, side=side, lower=lower, trans_a=trans_a, diag=diag, overwrite_b=1)
    a = np.require(a, np.float64, ["F_CONTIGUOUS", "ALIGNED"])  # a copy where needed, alive through the call
    flags = (b"R" if side else b"L", b"L" if lower else b"U", b"T" if trans_a else b"N", b"U" if diag else b"N")
    m_, n_, lda, ldb = int_refs(m, n, max(k, 1), max(m, 1))
    function(*flags, m_, n_, ctypes.byref(ctypes.c_double(1.0)), a.ctypes.data, lda, b.ctypes.data, ldb)
    return b


_CHAR = ctypes.c_char_p
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


def _check_fortran(what: str, a: np.ndarray) -> None:
    """Refuse ``a`` (named ``what``) unless a routine may work on it in place: 2-d, writeable, Fortran float64."""
    if a.ndim != 2 or a.dtype != np.float64 or not (a.flags.f_contiguous and a.flags.writeable and a.flags.aligned):
        raise ValueError(f"{what} must be 2-d, writeable, aligned Fortran float64; got {a.shape} {a.dtype}")


def cholesky_band(ab: np.ndarray) -> np.ndarray:
    """The Cholesky factor of the lower band ``ab`` ``(bandwidth + 1, n)``, in place in ``ab`` (LAPACK ``dpbtrf``).

    :func:`scipy.linalg.cholesky_banded` ``(ab, overwrite_ab=True, lower=True, check_finite=False)``'s result and
    errors (``numpy.linalg.LinAlgError`` where not positive definite). ``ab`` Fortran-contiguous float64, writeable.

    >>> cholesky_band(np.asfortranarray([[4.0, 9.0], [2.0, 0.0]]))  # [[4, 2], [2, 9]] = L L^T
    array([[2.        , 2.82842712],
           [1.        , 0.        ]])
    """
    _check_fortran("cholesky_band: ab", ab)
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


__all__ = ["cholesky_band", "cholesky_lower", "inverse_lower", "solve_band", "trmm"]
