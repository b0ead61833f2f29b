"""BLAS ``dtrmm`` (a triangular matrix times a matrix, in place) called without holding Python's GIL.

:func:`scipy.linalg.blas.dtrmm` holds the GIL while BLAS works (measured: two threads of it take as long as
one after the other), so a biplanar learning's two systems' joint uncertainties, whose solves are mostly these
products (:mod:`fluorocal.stages.learn.blocktri`), could not run side by side
(:mod:`fluorocal.stages.learn.threads`). :func:`trmm` calls the same routine of the same library, SciPy's
own BLAS through the function pointer :mod:`scipy.linalg.cython_blas` publishes for compiled callers, by
:mod:`ctypes`, which lets go of the GIL for the call: the same numbers to the last bit.
"""

from __future__ import annotations

import ctypes
import re
from functools import lru_cache

import numpy as np
from scipy.linalg import blas

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
    if b.ndim != 2 or b.dtype != np.float64 or not (b.flags.f_contiguous and b.flags.writeable and b.flags.aligned):
        raise ValueError(f"trmm: b must be 2-d, writeable, aligned Fortran float64; got {b.shape} {b.dtype}")
    m, n = b.shape
    k = m if side == 0 else n
    if np.shape(a) != (k, k):
        raise ValueError(f"trmm: a must be ({k}, {k}) for b {b.shape}; got {np.shape(a)}")
    if max(m, n) > _INT_MAX:  # BLAS's int dimensions: ctypes would wrap a larger one silently
        raise ValueError(f"trmm: b {b.shape} has a dimension beyond BLAS's int")
    function = _dtrmm()
    if function is None:
        return blas.dtrmm(1.0, a, b, side=side, lower=lower, trans_a=trans_a, diag=diag, overwrite_b=1)
    a = np.require(a, np.float64, ["F_CONTIGUOUS", "ALIGNED"])  # a copy where needed, alive through the call
    flags = (b"R" if side else b"L", b"L" if lower else b"U", b"T" if trans_a else b"N", b"U" if diag else b"N")
    m_, n_, lda, ldb = int_refs(m, n, max(k, 1), max(m, 1))
    function(*flags, m_, n_, ctypes.byref(ctypes.c_double(1.0)), a.ctypes.data, lda, b.ctypes.data, ldb)
    return b


__all__ = ["capsule_function", "int_refs", "trmm"]
