"""The compiled point-by-point kernels (seqat.kernels) against dense products."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse

from seqat.kernels import point_quadratic, schur_product


def _columns(rng: np.random.Generator, r: int, npt: int) -> np.ndarray:
    """(r, 3 npt) with each point's columns on a few rows: a run of images, a return to
    earlier ones, a point with no row, columns of one point on different rows."""
    C = np.zeros((r, 3 * npt))
    for p in range(npt):
        a = int(rng.integers(0, r - 8))
        rows = np.r_[a:a + int(rng.integers(1, 9))]
        if p % 4 == 0:  # a return: rows far from the run, not in order
            rows = np.r_[rows, rng.permutation(r)[:3]]
        C[np.ix_(rows, np.arange(3 * p, 3 * p + 3))] = rng.standard_normal((rows.size, 3))
    C[:, 9:12] = 0.0  # point 3: no row
    C[C[:, 13] != 0, 13] = 0.0  # point 4: its second column has no row at all
    C[np.flatnonzero(C[:, 15])[0], 15] = 0.0  # point 5: its columns differ by a row
    C[rng.integers(0, r), 16] = 2.5  # ... and by a row only its last column has
    return C


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_schur_product_equals_the_dense_product_and_is_exactly_symmetric(seed: int) -> None:
    rng = np.random.default_rng(seed)
    r, npt = 45, 27
    C = _columns(rng, r, npt)
    M = rng.standard_normal((npt, 3, 3))
    Dinv = M @ np.swapaxes(M, 1, 2) + np.eye(3)
    want = C @ scipy.linalg.block_diag(*Dinv) @ C.T
    Cs = scipy.sparse.csc_array(C)  # int32 indices, as scipy keeps them
    got = schur_product(Cs.indptr, Cs.indices, Cs.data, Dinv, r)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(got, got.T)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_point_quadratic_equals_the_dense_product_and_is_exactly_symmetric(seed: int) -> None:
    rng = np.random.default_rng(seed)
    r, npt = 45, 27
    B = _columns(rng, r, npt)
    V = rng.standard_normal((r, r))
    Q = V @ V.T
    pts = np.array([0, 3, 4, 5, 16, 26, 5])  # any subset, in any order, repeats allowed
    Bp = B.reshape(r, npt, 3)
    want = np.stack([Bp[:, p].T @ Q @ Bp[:, p] for p in pts])
    Bs = scipy.sparse.csc_array(B)
    got = point_quadratic(Bs.indptr, Bs.indices, Bs.data, Q, pts)
    np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11)
    np.testing.assert_array_equal(got, np.swapaxes(got, 1, 2))
    np.testing.assert_array_equal(got[1], np.zeros((3, 3)))  # point 3 has no row
    np.testing.assert_array_equal(got[-1], got[3])


def test_kernels_take_empty_input() -> None:
    Cs = scipy.sparse.csc_array((4, 0))
    np.testing.assert_array_equal(
        schur_product(Cs.indptr, Cs.indices, Cs.data, np.zeros((0, 3, 3)), 4), np.zeros((4, 4)))
    assert point_quadratic(Cs.indptr, Cs.indices, Cs.data, np.eye(4),
                           np.zeros(0, dtype=np.int64)).shape == (0, 3, 3)
