"""The compiled point-by-point kernels (seqat.kernels) against dense products."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse

from seqat.kernels import (
    eliminate_points,
    point_quadratic,
    ray_products,
    scatter_add,
    schur_product,
)


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


@pytest.mark.parametrize(("seed", "c"), [(1, 0), (2, 3)])
def test_eliminate_points_equals_the_dense_schur_complement(seed: int, c: int) -> None:
    """Rays in any order, a point seen twice from one image (their rows add), a point with
    no ray, the camera's rows shared by every ray: ``N - M D^-1 M^T`` and ``rhs - M D^-1
    b_p`` of the dense ``M`` (r, 3 m) the rays' blocks make, exactly symmetric."""
    rng = np.random.default_rng(seed)
    n, m, k = 7, 12, 40
    r = 6 * n + c
    img = rng.integers(0, n, k)
    pt = rng.integers(0, m - 1, k)  # the last point has no ray
    img[1], pt[1] = img[0], pt[0]  # a second ray of one point from the same image
    blocks = rng.standard_normal((k, 6 + c, 3))
    rows = np.concatenate([6 * img[:, None] + np.arange(6),
                           np.broadcast_to(6 * n + np.arange(c), (k, c))], axis=1)
    M = np.zeros((r, 3 * m))
    for o in range(k):
        np.add.at(M, (rows[o][:, None], 3 * pt[o] + np.arange(3)[None, :]), blocks[o])
    A = rng.standard_normal((m, 3, 3))
    Dinv = A @ np.swapaxes(A, 1, 2) + np.eye(3)
    b_p = rng.standard_normal((m, 3))
    V = rng.standard_normal((r, r))
    N0, rhs0 = V @ V.T, rng.standard_normal(r)
    D = scipy.linalg.block_diag(*Dinv)
    N, rhs = N0.copy(), rhs0.copy()
    eliminate_points(pt, img, blocks, Dinv, b_p, c, N, rhs)
    np.testing.assert_allclose(N, N0 - M @ D @ M.T, rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(rhs, rhs0 - M @ D @ b_p.ravel(), rtol=1e-12, atol=1e-11)
    np.testing.assert_array_equal(N, N.T)


def test_scatter_add_sums_as_numpy_add_at_does() -> None:
    rng = np.random.default_rng(4)
    idx = rng.integers(0, 5, 200)
    vals = rng.standard_normal((200, 3, 2))
    want = np.zeros((5, 3, 2))
    np.add.at(want, idx, vals)
    got = np.zeros((5, 3, 2))
    scatter_add(got, idx, vals)
    np.testing.assert_array_equal(got, want)  # the same sums in the same order
    scatter_add(got, idx[:0], vals[:0])  # nothing to add
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("c", [0, 4])
def test_ray_products_sum_each_rays_weighted_products(c: int) -> None:
    """Per image, over the camera and per point, the sums of ``w A^T A`` and ``w A^T ell``
    of each ray's rows ``A = [JR | Jp]``, and each ray's ``w JR^T Jp``: against numpy's
    products, a ray of weight 0 left out, an image and a point without rays."""
    rng = np.random.default_rng(5 + c)
    n, m, k = 6, 9, 50
    img, pt = rng.integers(0, n - 1, k), rng.integers(0, m - 1, k)
    JR, Jp = rng.standard_normal((k, 2, 6 + c)), rng.standard_normal((k, 2, 3))
    w, ell = rng.uniform(0.1, 2.0, k), rng.standard_normal((k, 2))
    w[3] = 0.0
    Nee, be, Nce, Ncc, bc, bp, NRp = ray_products(img, pt, JR, Jp, w, ell, n, m)
    wA = np.concatenate([JR, Jp], axis=2) * w[:, None, None]
    A = np.concatenate([JR, Jp], axis=2)
    per_ray = np.einsum("kri,krj->kij", wA, A)  # (k, 9 + c, 9 + c)
    grad = np.einsum("kri,kr->ki", wA, ell)
    want_ee, want_be = np.zeros((n, 6, 6)), np.zeros((n, 6))
    want_ce, want_bp = np.zeros((n, c, 6)), np.zeros((m, 3))
    np.add.at(want_ee, img, per_ray[:, :6, :6])
    np.add.at(want_be, img, grad[:, :6])
    np.add.at(want_ce, img, per_ray[:, 6:6 + c, :6])
    np.add.at(want_bp, pt, grad[:, 6 + c:])
    for got, want in [(Nee, want_ee), (be, want_be), (Nce, want_ce),
                      (Ncc, per_ray[:, 6:6 + c, 6:6 + c].sum(axis=0)),
                      (bc, grad[:, 6:6 + c].sum(axis=0)), (bp, want_bp),
                      (NRp, per_ray[:, :6 + c, 6 + c:])]:
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert not Nee[n - 1].any() and not bp[m - 1].any()  # no ray: nothing
