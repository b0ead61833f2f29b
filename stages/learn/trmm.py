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
from functools import lru_cache

import numpy as np
from scipy.linalg import blas

_INT, _DOUBLE, _ADDRESS = ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_double), ctypes.c_void_p
#: cython_blas's ``void dtrmm(char *side, char *uplo, char *transa, char *diag, int *m, int *n, double *alpha,
#: double *a, int *lda, double *b, int *ldb)``
_SIGNATURE = ctypes.CFUNCTYPE(None, *[ctypes.c_char_p] * 4, _INT, _INT, _DOUBLE, _ADDRESS, _INT, _ADDRESS, _INT)


@lru_cache(maxsize=1)
def _dtrmm():
    """SciPy's BLAS ``dtrmm`` as a :mod:`ctypes` function (which releases the GIL), or None where not found."""
    try:
        from scipy.linalg import cython_blas

        capsule = cython_blas.__pyx_capi__["dtrmm"]
        name_of = ctypes.pythonapi.PyCapsule_GetName
        name_of.restype, name_of.argtypes = ctypes.c_char_p, [ctypes.py_object]
        pointer_of = ctypes.pythonapi.PyCapsule_GetPointer
        pointer_of.restype, pointer_of.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
        return _SIGNATURE(pointer_of(capsule, name_of(capsule)))
    except (ImportError, AttributeError, KeyError, ValueError):
        return None


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
    function = _dtrmm()
    if function is None:
        return blas.dtrmm(1.0, a, b, side=side, lower=lower, trans_a=trans_a, diag=diag, overwrite_b=1)
    a = np.asfortranarray(a, dtype=np.float64)
    m, n = b.shape
    k = m if side == 0 else n
    if a.shape != (k, k) or b.dtype != np.float64 or not b.flags.f_contiguous or not b.flags.writeable:
        raise ValueError(f"trmm: a must be ({k}, {k}), b writeable Fortran float64; got {a.shape}, {b.dtype}")
    flags = (b"R" if side else b"L", b"L" if lower else b"U", b"T" if trans_a else b"N", b"U" if diag else b"N")
    m_, n_, lda, ldb = (ctypes.byref(ctypes.c_int(v)) for v in (m, n, max(k, 1), max(m, 1)))
    function(*flags, m_, n_, ctypes.byref(ctypes.c_double(1.0)), a.ctypes.data, lda, b.ctypes.data, ldb)
    return b


__all__ = ["trmm"]
