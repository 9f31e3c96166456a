"""Seq-F update (seed 000 Eq. 10-14) == batch least squares of the same linear system."""

from __future__ import annotations

import numpy as np
import pytest

from seqat.update import LinearRows, solve_update, update_cofactor

#: Relative agreement required between sequential and batch solutions.
REL_TOL = 1e-9


def _random_rows(
    rng: np.random.Generator, n1: int, n2: int, m2: int, m3: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Dense designs on all existing columns, new columns, and weights."""
    A21_full = np.zeros((m2, n1))
    touched = np.sort(rng.choice(n1, size=min(n1, 7), replace=False))
    A21_full[:, touched] = rng.normal(size=(m2, touched.size))
    A22 = rng.normal(size=(m2, n2))
    A32 = rng.normal(size=(m3, n2))
    return A21_full, touched, A22, A32


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_chained_updates_equal_batch(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n1 = 12
    # Initial stage: a well-posed linear LS with normal matrix N0 and rhs c0.
    A0 = rng.normal(size=(40, n1))
    w0 = rng.uniform(0.5, 2.0, 40)
    y0 = rng.normal(size=40)
    N_batch = A0.T @ (w0[:, None] * A0)
    c_batch = A0.T @ (w0 * y0)
    Q = np.linalg.inv(N_batch)
    x = Q @ c_batch
    for _stage in range(4):
        n_old = x.size
        n2, m2, m3 = 5, 9, 8
        A21_full, touched, A22, A32 = _random_rows(rng, n_old, n2, m2, m3)
        w2, w3 = rng.uniform(0.5, 2.0, m2), rng.uniform(0.5, 2.0, m3)
        y2, y3 = rng.normal(size=m2), rng.normal(size=m3)
        x2_0 = rng.normal(size=n2)  # linearisation point of the new parameters
        # Reduced observations in corrections from (x, x2_0).
        l2 = y2 - A21_full @ x - A22 @ x2_0
        l3 = y3 - A32 @ x2_0
        rows = LinearRows(A21=A21_full[:, touched], A22=A22, w2=w2, l2=l2, A32=A32, w3=w3, l3=l3)
        sol = solve_update(Q, touched, rows)
        x_new = np.concatenate([x + sol.delta1(), x2_0 + sol.delta2])
        Q_new = update_cofactor(Q.copy(), touched, rows, sol)
        # Batch: grow the normal equations with the new rows and solve from scratch.
        N_batch = np.block(
            [[N_batch, np.zeros((n_old, n2))], [np.zeros((n2, n_old)), np.zeros((n2, n2))]]
        )
        c_batch = np.concatenate([c_batch, np.zeros(n2)])
        A2 = np.hstack([A21_full, A22])
        A3 = np.hstack([np.zeros((m3, n_old)), A32])
        N_batch += A2.T @ (w2[:, None] * A2) + A3.T @ (w3[:, None] * A3)
        c_batch += A2.T @ (w2 * y2) + A3.T @ (w3 * y3)
        x_batch = np.linalg.solve(N_batch, c_batch)
        Q_batch = np.linalg.inv(N_batch)
        assert _rel(x_new, x_batch) < REL_TOL
        assert _rel(Q_new, Q_batch) < REL_TOL
        x, Q = x_new, Q_new


def test_ssr_increment_matches_batch_objective() -> None:
    rng = np.random.default_rng(7)
    n1, n2, m2, m3 = 6, 4, 7, 6
    A0 = rng.normal(size=(20, n1))
    y0 = rng.normal(size=20)
    N0 = A0.T @ A0
    x = np.linalg.solve(N0, A0.T @ y0)
    ssr0 = float(np.sum((y0 - A0 @ x) ** 2))
    A21_full, touched, A22, A32 = _random_rows(rng, n1, n2, m2, m3)
    y2, y3 = rng.normal(size=m2), rng.normal(size=m3)
    rows = LinearRows(
        A21=A21_full[:, touched],
        A22=A22,
        w2=np.ones(m2),
        l2=y2 - A21_full @ x,
        A32=A32,
        w3=np.ones(m3),
        l3=y3,
    )
    sol = solve_update(np.linalg.inv(N0), touched, rows)
    A = np.block([[A0, np.zeros((20, n2))], [A21_full, A22], [np.zeros((m3, n1)), A32]])
    y = np.concatenate([y0, y2, y3])
    xb = np.linalg.lstsq(A, y, rcond=None)[0]
    ssr_batch = float(np.sum((y - A @ xb) ** 2))
    assert ssr0 + sol.ssr_increment == pytest.approx(ssr_batch, rel=1e-10)


def test_undetermined_new_parameter_is_an_estimation_error() -> None:
    from seqat.errors import EstimationError

    rng = np.random.default_rng(3)
    n1, n2, m2 = 6, 3, 4
    Q = np.eye(n1)
    A22 = rng.normal(size=(m2, n2))
    A22[:, 2] = 0.0  # no observation touches the third new parameter
    rows = LinearRows(
        A21=rng.normal(size=(m2, 2)),
        A22=A22,
        w2=np.ones(m2),
        l2=rng.normal(size=m2),
        A32=np.zeros((0, n2)),
        w3=np.zeros(0),
        l3=np.zeros(0),
    )
    with pytest.raises(EstimationError, match=r"\(M22 \+ L22\) \(3x3\) is not positive definite"):
        solve_update(Q, np.array([0, 1]), rows)


def test_large_update_forms_its_products_sparse_with_the_same_numbers(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Rows that touch one point (3 columns) of the window and the new image (6 columns),
    as a real update's do: the sparse products give what the dense ones give."""
    import seqat.update as update

    rng = np.random.default_rng(7)
    t, n2, m2 = 60, 6 + 3 * 4, 80
    M = rng.standard_normal((2 * t, t))
    Q = np.linalg.inv(M.T @ M + np.eye(t))
    Q = 0.5 * (Q + Q.T)
    A21 = np.zeros((m2, t))
    A22 = np.zeros((m2, n2))
    for i in range(m2):
        p = rng.integers(t // 3)
        A21[i, 3 * p:3 * p + 3] = rng.standard_normal(3)
        A22[i, :6] = rng.standard_normal(6)
    rows = LinearRows(A21=A21, A22=A22, w2=rng.uniform(0.5, 2.0, m2), l2=rng.standard_normal(m2),
                      A32=np.eye(n2), w3=np.full(n2, 1e-2), l3=rng.standard_normal(n2))
    touched = np.arange(t)
    monkeypatch.setattr(update, "SPARSE_ROWS_FROM", 10**12)
    dense = solve_update(Q, touched, rows, block=True)
    monkeypatch.setattr(update, "SPARSE_ROWS_FROM", 0)
    sparse = solve_update(Q, touched, rows, block=True)
    for name in ("Gt", "H", "P2bar", "S", "kappa", "delta1_touched", "delta2"):
        np.testing.assert_allclose(getattr(sparse, name), getattr(dense, name),
                                   rtol=1e-9, atol=1e-12, err_msg=name)
    assert sparse.ssr_increment == pytest.approx(dense.ssr_increment, rel=1e-10)


def test_large_update_in_the_parameter_space_gives_the_same_corrections(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """More rows than touched parameters (many points born at once): solved as a t x t
    system (``terms=False``), the corrections, ``kappa1`` and the sum of squares are those of
    Eq. 13-14's m2 x m2 system."""
    import seqat.update as update

    rng = np.random.default_rng(11)
    t, n_new, m2 = 36, 20, 150
    n2 = 6 + 3 * n_new
    M = rng.standard_normal((2 * t, t))
    Q = np.linalg.inv(M.T @ M + np.eye(t))
    Q = 0.5 * (Q + Q.T)
    A21, A22 = np.zeros((m2, t)), np.zeros((m2, n2))
    for i in range(m2):
        if i % 2:  # a window point seen by the new image
            p = rng.integers(t // 3)
            A21[i, 3 * p:3 * p + 3] = rng.standard_normal(3)
            A22[i, :6] = rng.standard_normal(6)
        else:  # a new point seen by a window image (6 of the touched columns)
            e, p = rng.integers(t // 6), rng.integers(n_new)
            A21[i, 6 * e:6 * e + 6] = rng.standard_normal(6)
            A22[i, 6 + 3 * p:9 + 3 * p] = rng.standard_normal(3)
    rows = LinearRows(A21=A21, A22=A22, w2=rng.uniform(0.5, 2.0, m2), l2=rng.standard_normal(m2),
                      A32=np.eye(n2), w3=np.full(n2, 1e-2), l3=rng.standard_normal(n2))
    touched = np.arange(t)
    monkeypatch.setattr(update, "SPARSE_ROWS_FROM", 0)
    ref = solve_update(Q, touched, rows, block=True)
    fast = solve_update(Q, touched, rows, block=True, terms=False)
    assert fast.S is None and fast.kappa is None  # it did take the parameter space
    for name in ("kappa1", "delta1_touched", "delta2"):
        np.testing.assert_allclose(getattr(fast, name), getattr(ref, name),
                                   rtol=1e-9, atol=1e-12 * np.abs(getattr(ref, name)).max(),
                                   err_msg=name)
    assert fast.ssr_increment == pytest.approx(ref.ssr_increment, rel=1e-10)


def test_information_of_a_large_update_added_sparse_equals_the_dense_sum(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``add_information`` on a sparse window: the large update's ``A^T P A`` formed from its
    non-zeros equals the dense block added on the touched and new columns."""
    import scipy.sparse

    import seqat.rows as rows_mod
    from seqat.information import sparse_information

    rng = np.random.default_rng(3)
    n1, t, n2, m2 = 90, 30, 6 + 3 * 5, 60
    touched = np.sort(rng.choice(n1, t, replace=False))
    A21 = np.where(rng.random((m2, t)) < 0.1, rng.standard_normal((m2, t)), 0.0)
    A22 = np.where(rng.random((m2, n2)) < 0.2, rng.standard_normal((m2, n2)), 0.0)
    rows = LinearRows(A21=A21, A22=A22, w2=rng.uniform(0.5, 2.0, m2), l2=np.zeros(m2),
                      A32=np.eye(n2)[:6], w3=np.full(6, 4.0), l3=np.zeros(6))
    B = rng.standard_normal((n1, n1)) * (rng.random((n1, n1)) < 0.05)
    L = B @ B.T + np.eye(n1)
    cols = np.concatenate([touched, n1 + np.arange(n2)])
    A2 = np.hstack([A21, A22])
    want = np.zeros((n1 + n2, n1 + n2))
    want[:n1, :n1] = L
    want[np.ix_(cols, cols)] += A2.T @ (rows.w2[:, None] * A2)
    want[n1:n1 + 6, n1:n1 + 6] += 4.0 * np.eye(6)
    monkeypatch.setattr(rows_mod, "SPARSE_ROWS_FROM", 0)
    monkeypatch.setattr(rows_mod, "window_matrix", lambda M: M)  # keep what it built
    got = rows_mod.add_information(sparse_information(L), touched, rows)
    assert scipy.sparse.issparse(got)
    got = got.toarray()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    np.testing.assert_array_equal(got, got.T)


@pytest.mark.parametrize("n", [1, 7, 127, 128, 201])
def test_lower_inverse_by_halves_equals_the_dense_inverse(n: int) -> None:
    """The triangle's inverse by halves (trtri on each, trmm for the corner) from the split's
    order on, one trtri below it: equal to ``inv``, triangular, on a factor with rows ten
    decades apart; a singular triangle raises."""
    from seqat.errors import EstimationError
    from seqat.update import lower_inverse

    rng = np.random.default_rng(n)
    A = rng.standard_normal((2 * n, n))
    units = 10.0 ** rng.uniform(-5, 5, n)
    L = np.linalg.cholesky((A.T @ A + np.eye(n)) * units[:, None] * units[None, :])
    got = lower_inverse(np.asfortranarray(L))
    assert got.flags.f_contiguous
    np.testing.assert_array_equal(np.triu(got, 1), 0.0)
    want = np.linalg.inv(L)
    np.testing.assert_allclose(got @ L, np.eye(n), atol=1e-9)
    np.testing.assert_allclose(got, want, rtol=1e-8, atol=1e-10 * np.abs(want).max())
    L[n // 2, n // 2] = 0.0
    with pytest.raises(EstimationError):
        lower_inverse(np.asfortranarray(L))
