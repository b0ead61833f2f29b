"""Tests of stages/learn/blocktri.py: the block Cholesky of a banded SPD matrix against dense linear algebra."""

from __future__ import annotations

import numpy as np
import pytest
from fluorocal.stages.field import bilinear_design
from fluorocal.stages.learn.blocktri import block_cholesky
from fluorocal.stages.learn.grid import difference_operator
from scipy.sparse import csr_matrix, diags, identity


def grid_normal(order: int, n_x: int = 9, n_y: int = 7, seed: int = 0):
    """A gridded field's normal matrix: bilinear data at random points with random weights, a difference prior."""
    rng = np.random.default_rng(seed)
    xn, yn = np.arange(n_x) * 16.0, np.arange(n_y) * 16.0
    xy = rng.uniform(0, [xn[-1], yn[-1]], (300, 2))
    A = bilinear_design(xn, yn, xy)
    D = difference_operator(n_y, n_x, order)
    w = rng.uniform(100, 400, len(xy))
    return A.T.multiply(w) @ A + (D.T @ D) / 0.3**2 + 1e-8 * identity(n_x * n_y)


@pytest.mark.parametrize("order", [2, 3, 4])
def test_diagonal_of_the_inverse_and_solves_match_dense(order):
    S = grid_normal(order)
    dense = S.toarray()
    factor = block_cholesky(S)
    # 63 nodes in blocks of the bandwidth (order rows of 9 + order): the last block is partial for every order here
    assert len(dense) % factor.block != 0
    inv = np.linalg.inv(dense)
    X = np.random.default_rng(1).normal(size=(len(dense), 5))
    # both backward-stable, on a matrix of condition 40-700: round-off is ~1e-15 (measured), bounded at 1e-12;
    # a wrong block (a coupling dropped) is off by O(1)
    np.testing.assert_allclose(factor.diag_inverse(), np.diag(inv), rtol=1e-12)
    np.testing.assert_allclose(factor.solve(X), inv @ X, rtol=1e-12, atol=1e-12 * np.abs(inv @ X).max())


def test_a_diagonal_matrix_is_its_own_blocks():
    d = np.array([1.0, 2.0, 4.0, 8.0])
    factor = block_cholesky(diags(d).tocsr())
    assert factor.block == 1
    # square roots and reciprocals: a few ulps
    np.testing.assert_allclose(factor.diag_inverse(), 1 / d, rtol=1e-15)
    np.testing.assert_allclose(factor.solve(np.ones((4, 1)))[:, 0], 1 / d, rtol=1e-15)


def test_an_indefinite_matrix_is_refused():
    S = csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]))
    with pytest.raises(np.linalg.LinAlgError):
        block_cholesky(S)


def test_solve_of_columns_zero_above_a_block_matches_dense():
    """The forward substitution starts at each column's first non-zero block: columns of every start, and a zero one."""
    S = grid_normal(4, n_x=11, n_y=13)
    factor = block_cholesky(S)
    n, n_blocks = S.shape[0], -(-S.shape[0] // factor.block)
    assert n_blocks >= 3
    X = np.random.default_rng(2).normal(size=(n, 2 * n_blocks + 1))
    for j in range(n_blocks):  # two columns starting in each block, mid-block and at its first row
        X[: j * factor.block + factor.block // 2, 2 * j] = 0
        X[: j * factor.block, 2 * j + 1] = 0
    X[:, -1] = 0
    inv = np.linalg.inv(S.toarray())
    # condition ~1e3 here: round-off ~1e-14 relative to the largest entry; a column started a block late or
    # a coupling dropped is off by O(1)
    np.testing.assert_allclose(factor.solve(X), inv @ X, rtol=0, atol=1e-12 * np.abs(inv @ X).max())
    assert not np.any(factor.solve(X)[:, -1])


def test_forward_of_a_sparse_operand_matches_dense():
    """A sparse operand, made dense a block of rows at a time: columns of every start, out of order, a zero one."""
    S = grid_normal(3, n_x=11, n_y=13)
    factor = block_cholesky(S)
    n = S.shape[0]
    rng = np.random.default_rng(3)
    X = rng.normal(size=(n, 7)) * (rng.uniform(size=(n, 7)) < 0.1)
    for j, start in enumerate([n // 2, 0, n - 3, factor.block + 1, n // 3, 2 * factor.block]):
        X[:start, j] = 0  # first non-zero rows out of order
    X[:, -1] = 0
    inv = np.linalg.inv(S.toarray())
    got = factor.backward(factor.forward(csr_matrix(X)), overwrite=True)
    # condition ~1e3: round-off ~1e-14 relative to the largest entry; a block started late is off by O(1)
    np.testing.assert_allclose(got, inv @ X, rtol=0, atol=1e-12 * np.abs(inv @ X).max())
    assert not np.any(got[:, -1])
