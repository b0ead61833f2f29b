"""Cholesky factor of a banded symmetric positive definite matrix in dense blocks, and its inverse's diagonal.

The gridded field's normal matrix ``S = A^T W A + D^T D / τ² + ridge`` (row-major nodes) is banded: the
smoothness prior couples node rows up to its order apart and the bilinear data term adjacent ones. Cut
into blocks of the bandwidth it is block tridiagonal, so its Cholesky factor is block bidiagonal and
everything the uncertainty needs of ``S^-1`` is dense BLAS-3 work on ``b x b`` blocks: solves with
many right-hand sides, and the diagonal of ``S^-1`` by the backward recurrence of the inverse's
diagonal blocks (Takahashi's equations by blocks), without solving for a column of the identity per node.

The factor's blocks are triangular: ``L_kk`` lower and, within the band, ``L_k+1,k`` upper (row ``i`` of
block ``k+1`` reaches back at most the bandwidth, to column ``i`` of block ``k``). The solves multiply by
them and by the diagonal blocks' inverses (kept with the factor) as triangular matrices, half a general
product's work, instead of triangular solves, which BLAS does at half a product's speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from fluorocal.stages.learn.nogil import cholesky_lower, inverse_lower, trmm
from scipy.sparse import issparse


@dataclass(frozen=True)
class BlockCholesky:
    """``S = L L^T`` with ``L`` block lower bidiagonal: diagonal blocks ``L_kk`` and sub-diagonal ``L_k+1,k``."""

    block: int
    diagonal: tuple  # of (b_k, b_k) lower-triangular float64 ndarrays
    below: tuple  # of (b_k+1, b_k) float64 ndarrays, upper triangular (module docstring)
    inverse: tuple  # of (b_k, b_k) lower-triangular float64 ndarrays: L_kk^-1, Fortran order

    def _rows(self, k: int) -> slice:
        return slice(k * self.block, k * self.block + len(self.diagonal[k]))

    def solve(self, X: np.ndarray) -> np.ndarray:
        """``S^-1 X`` for ``X`` ``(n, m)``: a forward and a backward block substitution."""
        return self.backward(self.forward(X), overwrite=True)

    def forward(self, X) -> np.ndarray:
        """``L^-1 X`` for ``X`` ``(n, m)``, dense or sparse, block by block.

        A column's substitution starts at its first non-zero block (the blocks above stay zero): the columns
        are taken in the order of their first non-zero row, so that each block's are a leading slice (without
        copying them when they come in that order). A sparse ``X`` is made dense a block of rows at a time.
        """
        X = X.tocsr() if issparse(X) else np.asarray(X, dtype=np.float64)
        first = first_rows(X) // self.block
        by_first = None if np.all(np.diff(first) >= 0) else np.argsort(first, kind="stable")
        if by_first is not None:
            X, first = X[:, by_first], first[by_first]
        Y = np.zeros(X.shape)
        for k in range(len(self.diagonal)):
            m, rows = int(np.searchsorted(first, k, side="right")), self._rows(k)
            rhs = X[rows, :m].toarray() if issparse(X) else X[rows, :m]
            if k > 0:
                rhs = rhs - _tri_mul(self.below[k - 1], Y[self._rows(k - 1), :m], lower=False)
            Y[rows, :m] = _tri_mul(self.inverse[k], rhs, lower=True, overwrite=k > 0 or issparse(X))
        if by_first is None:
            return Y
        out = np.empty(X.shape)
        out[:, by_first] = Y
        return out

    def backward(self, Y: np.ndarray, *, overwrite: bool = False) -> np.ndarray:
        """``L^-T Y`` for ``Y`` ``(n, m)``, block by block; in place in ``Y`` with ``overwrite``."""
        Y = np.array(Y, dtype=np.float64, copy=not overwrite)
        # block k of Y is read once, where block k of the result goes
        last = len(self.diagonal) - 1
        for k in range(last, -1, -1):
            rhs = Y[self._rows(k)]
            if k < last:
                rhs -= _tri_mul(self.below[k], Y[self._rows(k + 1)], lower=False, transpose=True)
            Y[self._rows(k)] = _tri_mul(self.inverse[k], rhs, lower=True, transpose=True, overwrite=True)
        return Y

    def diag_inverse(self) -> np.ndarray:
        """The diagonal ``(n,)`` of ``S^-1``.

        With ``Z = S^-1`` (``L^T Z = L^-1``, lower triangular): ``Z_NN = L_NN^-T L_NN^-1`` and, going up
        with ``X = L_k+1,k L_kk^-1``, ``Z_k+1,k = -Z_k+1,k+1 X`` and
        ``Z_kk = L_kk^-T L_kk^-1 + X^T Z_k+1,k+1 X``: only the diagonal blocks are kept. (``(Z B)^T = B^T Z`` and
        ``(Y L^-1)^T = L^-T Y`` for the symmetric ``Z`` and ``Y``: every product is a triangular one from the left.)
        """
        out = np.empty(sum(len(L) for L in self.diagonal))
        Z = None
        for k in range(len(self.diagonal) - 1, -1, -1):
            # Z_kk = L_kk^-T (I + B^T Z_k+1,k+1 B) L_kk^-1 with B = L_k+1,k: triangular products of symmetric ones
            L_inv = self.inverse[k]
            inner = np.eye(len(L_inv))
            if Z is not None:
                B = self.below[k]
                inner += _tri_mul(B, _tri_mul(B, Z, lower=False, transpose=True).T, lower=False, transpose=True)
            Z = _tri_mul(L_inv, _tri_mul(L_inv, inner, lower=True, transpose=True).T, lower=True, transpose=True)
            out[self._rows(k)] = np.diag(Z)
        return out


def first_rows(X) -> np.ndarray:
    """Each column's first non-zero row ``(m,)`` of ``X`` ``(n, m)``, dense or sparse CSR; ``n`` for a zero column."""
    if issparse(X):
        Xc = X.tocsc()
        first = np.full(X.shape[1], X.shape[0])
        touched = np.diff(Xc.indptr) > 0
        first[touched] = np.minimum.reduceat(Xc.indices, Xc.indptr[:-1][touched])
        return first
    nonzero = X != 0
    return np.where(nonzero.any(axis=0), np.argmax(nonzero, axis=0), len(X))


def _tri_mul(T: np.ndarray, X: np.ndarray, *, lower: bool, transpose: bool = False, overwrite: bool = False):
    """``T X`` (``T^T X`` with ``transpose``) for a triangular ``T`` and a C-ordered ``X``, by BLAS ``trmm`` (GIL free).

    ``trmm`` works in Fortran order: ``X^T`` is ``X``'s Fortran view, and ``(T X)^T = X^T T^T``. With ``overwrite``,
    a contiguous ``X`` may hold the result.
    """
    if X.shape[1] == 0 or T.shape[0] != T.shape[1]:  # the last block's coupling may be rectangular
        return (T.T if transpose else T) @ X
    Xt = np.asarray(X, dtype=np.float64).T
    if not (overwrite and Xt.flags.f_contiguous and Xt.flags.writeable):
        Xt = np.array(Xt, order="F")
    return trmm(T, Xt, side=1, lower=int(lower), trans_a=int(not transpose)).T


def block_cholesky(S) -> BlockCholesky:
    """:class:`BlockCholesky` of a sparse symmetric positive definite ``S``, in blocks of its bandwidth.

    Raises ``numpy.linalg.LinAlgError`` when ``S`` is not positive definite.
    """
    S = S.tocsr()
    coo = S.tocoo()
    block = max(int(np.max(np.abs(coo.row - coo.col), initial=0)), 1)
    n = S.shape[0]
    diagonal, below, inverse = [], [], []
    for lo in range(0, n, block):
        hi = min(lo + block, n)
        S_kk = S[lo:hi, lo:hi].toarray()
        if diagonal:
            # L_k,k-1 = S_k,k-1 L_k-1,k-1^-T; upper triangular where S_k,k-1 is (the band), exactly
            C = np.triu(S[lo:hi, lo - block : lo].toarray() @ inverse[-1].T)
            S_kk -= C @ C.T
            below.append(C)
        L = cholesky_lower(S_kk)
        diagonal.append(L)
        inverse.append(inverse_lower(L))
    return BlockCholesky(block, tuple(diagonal), tuple(below), tuple(inverse))


__all__ = ["BlockCholesky", "block_cholesky", "first_rows"]
