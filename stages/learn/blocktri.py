"""Cholesky factor of a banded symmetric positive definite matrix in dense blocks, and its inverse's diagonal.

The gridded field's normal matrix ``S = A^T W A + D^T D / τ² + ridge`` (row-major nodes) is banded: the
smoothness prior couples node rows up to its order apart and the bilinear data term adjacent ones. Cut
into blocks of the bandwidth it is block tridiagonal, so its Cholesky factor is block bidiagonal and
everything the uncertainty needs of ``S^-1`` is dense BLAS-3 work on ``b x b`` blocks: solves with
many right-hand sides, and the diagonal of ``S^-1`` by the backward recurrence of the inverse's
diagonal blocks (Takahashi's equations by blocks), without solving for a column of the identity per node.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cholesky, solve_triangular


@dataclass(frozen=True)
class BlockCholesky:
    """``S = L L^T`` with ``L`` block lower bidiagonal: diagonal blocks ``L_kk`` and sub-diagonal ``L_k+1,k``."""

    block: int
    diagonal: tuple  # of (b_k, b_k) lower-triangular float64 ndarrays
    below: tuple  # of (b_k+1, b_k) float64 ndarrays

    def _rows(self, k: int) -> slice:
        return slice(k * self.block, k * self.block + len(self.diagonal[k]))

    def solve(self, X: np.ndarray) -> np.ndarray:
        """``S^-1 X`` for ``X`` ``(n, m)``: a forward and a backward block substitution."""
        Y = np.empty(X.shape)
        for k, L in enumerate(self.diagonal):
            rhs = X[self._rows(k)] if k == 0 else X[self._rows(k)] - self.below[k - 1] @ Y[self._rows(k - 1)]
            Y[self._rows(k)] = solve_triangular(L, rhs, lower=True)
        Z = np.empty(X.shape)
        last = len(self.diagonal) - 1
        for k in range(last, -1, -1):
            rhs = Y[self._rows(k)] if k == last else Y[self._rows(k)] - self.below[k].T @ Z[self._rows(k + 1)]
            Z[self._rows(k)] = solve_triangular(self.diagonal[k], rhs, lower=True, trans="T")
        return Z

    def diag_inverse(self) -> np.ndarray:
        """The diagonal ``(n,)`` of ``S^-1``.

        With ``Z = S^-1`` (``L^T Z = L^-1``, lower triangular): ``Z_NN = L_NN^-T L_NN^-1`` and, going up
        with ``X = L_k+1,k L_kk^-1``, ``Z_k+1,k = -Z_k+1,k+1 X`` and
        ``Z_kk = L_kk^-T L_kk^-1 + X^T Z_k+1,k+1 X``: only the diagonal blocks are kept.
        """
        out = np.empty(sum(len(L) for L in self.diagonal))
        Z = None
        for k in range(len(self.diagonal) - 1, -1, -1):
            L_inv = solve_triangular(self.diagonal[k], np.eye(len(self.diagonal[k])), lower=True)
            if Z is None:
                Z = L_inv.T @ L_inv
            else:
                X = self.below[k] @ L_inv
                Z = L_inv.T @ L_inv + X.T @ (Z @ X)
            out[self._rows(k)] = np.diag(Z)
        return out


def block_cholesky(S) -> BlockCholesky:
    """:class:`BlockCholesky` of a sparse symmetric positive definite ``S``, in blocks of its bandwidth.

    Raises ``numpy.linalg.LinAlgError`` when ``S`` is not positive definite.
    """
    S = S.tocsr()
    coo = S.tocoo()
    block = max(int(np.max(np.abs(coo.row - coo.col), initial=0)), 1)
    n = S.shape[0]
    diagonal, below = [], []
    for lo in range(0, n, block):
        hi = min(lo + block, n)
        S_kk = S[lo:hi, lo:hi].toarray()
        if diagonal:
            # L_k,k-1 = S_k,k-1 L_k-1,k-1^-T
            C = solve_triangular(diagonal[-1], S[lo:hi, lo - block : lo].toarray().T, lower=True).T
            S_kk -= C @ C.T
            below.append(C)
        diagonal.append(cholesky(S_kk, lower=True))
    return BlockCholesky(block, tuple(diagonal), tuple(below))


__all__ = ["BlockCholesky", "block_cholesky"]
