"""The information engine's factorisation (seqat.information) against dense linear algebra."""

from __future__ import annotations

import numpy as np
import pytest

from seqat.factor_views import AugmentedFactor, MarginalFactor
from seqat.information import InformationFactor, RankDeficiency
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight


def _window_like(rng: np.random.Generator, n_e: int = 4, n_p: int = 12,
                 coupled: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """An SPD matrix laid out as a window: EOPs first, then GPs; the first ``coupled`` GPs
    share a dense prior, the others touch only the EOPs and their own 3x3 block."""
    ne, n = 6 * n_e, 6 * n_e + 3 * n_p
    A = rng.standard_normal((4 * n, n)) * (rng.random((4 * n, n)) < 0.2)
    for j in range(coupled, n_p):  # rows of an uncoupled GP touch EOPs and itself only
        o = ne + 3 * j
        others = np.r_[ne:o, o + 3:n]
        A[np.any(A[:, o:o + 3] != 0, axis=1)[:, None] & np.isin(np.arange(n), others)[None]] = 0
    L = A.T @ A + np.eye(n)
    gp = ne + 3 * np.arange(coupled, n_p)
    for j in range(coupled, n_p):  # enforce exact zeros GP-GP
        o = ne + 3 * j
        for k in range(coupled, n_p):
            if k != j:
                L[o:o + 3, ne + 3 * k:ne + 3 * k + 3] = 0.0
    return L, gp


@pytest.mark.parametrize("sparse", [False, True])
def test_factor_solve_columns_and_marginals_equal_the_dense_inverse(
        sparse: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    import seqat.information as information

    monkeypatch.setattr(information, "SPARSE_FROM", 0 if sparse else 10**12)
    rng = np.random.default_rng(3)
    L, gp = _window_like(rng)
    Q = np.linalg.inv(L)
    f = InformationFactor(L, gp)
    b = rng.standard_normal(L.shape[0])
    np.testing.assert_allclose(f.solve(b), Q @ b, rtol=1e-9, atol=1e-12)
    idx = np.array([0, 5, 30, 31, 40])
    np.testing.assert_allclose(f.solve(b, idx[::-1]), (Q @ b)[idx[::-1]], rtol=1e-9,
                               atol=1e-12)
    np.testing.assert_allclose(f.columns(idx), Q[:, idx], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.diagonal(), np.diagonal(Q), rtol=1e-9)
    np.testing.assert_allclose(f.block(idx), Q[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.dense(), Q, rtol=1e-8, atol=1e-12)
    eops = np.arange(24)  # kept entries: Q_RR, without the eliminated points
    np.testing.assert_allclose(f.entries(eops, idx[:2]), Q[np.ix_(eops, idx[:2])],
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.entries(idx, idx), Q[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)


def test_marginal_factor_answers_for_the_schur_complement() -> None:
    """After a departure the update reads ``Q[keep, keep]`` from the factorisation the leaving
    parameters left (MarginalFactor): the inverse of the Schur complement the window keeps."""
    rng = np.random.default_rng(5)
    L, gp = _window_like(rng)
    n = L.shape[0]
    leave = np.r_[0:6, 42:45]  # an image and an eliminated point
    keep = np.setdiff1d(np.arange(n), leave)
    Lkk = L[np.ix_(keep, keep)] - L[np.ix_(keep, leave)] @ np.linalg.solve(
        L[np.ix_(leave, leave)], L[np.ix_(leave, keep)])
    Qm = np.linalg.inv(Lkk)
    m = MarginalFactor.of(MarginalFactor.of(InformationFactor(L, gp), np.arange(n)), keep)
    b = rng.standard_normal(keep.size)
    np.testing.assert_allclose(m.solve(b), Qm @ b, rtol=1e-9, atol=1e-12)
    idx = np.array([0, 3, 25, 26, 34])
    np.testing.assert_allclose(m.columns(idx), Qm[:, idx], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m.block(idx), Qm[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m.entries(idx[:2], idx), Qm[np.ix_(idx[:2], idx)], rtol=1e-9,
                               atol=1e-12)


@pytest.mark.parametrize("marginal_first", [False, True])
def test_augmented_factor_answers_for_the_reopened_window(marginal_first: bool) -> None:
    """After a re-opening the update reads ``Q'`` from the factorisation the window had
    (AugmentedFactor): the inverse of ``L`` with the prior ``x_R = J x_W + e``,
    ``e ~ (0, C)``, of the parameters appended at its end; also on a marginal's view, twice
    (two re-openings in one update), and through a departure after it."""
    rng = np.random.default_rng(8)
    L, gp = _window_like(rng)
    base: InformationFactor | MarginalFactor = InformationFactor(L, gp)
    if marginal_first:
        keep = np.setdiff1d(np.arange(L.shape[0]), np.r_[6:12, 45:48])
        L = np.linalg.inv(np.linalg.inv(L)[np.ix_(keep, keep)])
        base = MarginalFactor.of(base, keep)
    aug: InformationFactor | MarginalFactor | AugmentedFactor = base
    for m in (9, 6):  # two re-openings: three points, then an image
        n = L.shape[0]
        J = rng.standard_normal((m, n)) * (rng.random((m, n)) < 0.1)
        A = rng.standard_normal((m, m))
        C = A @ A.T + m * np.eye(m)
        Ci = np.linalg.inv(C)
        Js = np.hstack([-J, np.eye(m)])  # x_R - J x_W
        L = np.pad(L, ((0, m), (0, m))) + Js.T @ Ci @ Js
        aug = AugmentedFactor(aug, J, C)
    Q = np.linalg.inv(L)
    n = L.shape[0]
    assert aug.n == n
    b = rng.standard_normal((n, 2))
    np.testing.assert_allclose(aug.solve(b), Q @ b, rtol=1e-9, atol=1e-12)
    idx = np.array([0, 5, 30, 31, 40, n - 14, n - 12, n - 1])  # old and re-opened, both times
    for rows in (idx, idx[:5], idx[5:]):  # some rows of the solution: the same rows
        np.testing.assert_allclose(aug.solve(b, rows), (Q @ b)[rows], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(aug.columns(idx), Q[:, idx], rtol=1e-9, atol=1e-12)
    got = aug.block(idx)
    np.testing.assert_allclose(got, Q[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)
    assert np.array_equal(got, got.T)
    for rows, cols in ((idx[:3], idx[3:]), (idx[4:], idx[:5]), (idx[5:6], idx[6:])):
        np.testing.assert_allclose(aug.entries(rows, cols), Q[np.ix_(rows, cols)], rtol=1e-9,
                                   atol=1e-12)
    keys = np.r_[0:6, 36:39, n - 15:n - 12, n - 6:n]  # an image, a point, re-opened ones
    blocks = aug.diagonal_blocks(keys, np.array([6, 3, 3, 6]))
    for blk, sub in zip(blocks, (keys[:6], keys[6:9], keys[9:12], keys[12:]), strict=True):
        np.testing.assert_allclose(blk, Q[np.ix_(sub, sub)], rtol=1e-9, atol=1e-12)
    keep = np.setdiff1d(np.arange(n), np.r_[0:6, n - 3:n])  # then a departure
    np.testing.assert_allclose(MarginalFactor.of(aug, keep).block(idx[1:5] - 6),
                               Q[np.ix_(keep, keep)][np.ix_(idx[1:5] - 6, idx[1:5] - 6)],
                               rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("sparse", [False, True])
def test_diagonal_blocks_equal_the_dense_inverse(sparse: bool,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A departure keeps each leaving key's own marginal block (an image's 6 x 6, a point's
    3 x 3, kept or eliminated): the diagonal blocks of ``Q`` without forming the blocks
    between them; also through a MarginalFactor, and with the memory chunking forced."""
    import seqat.information as information

    monkeypatch.setattr(information, "SPARSE_FROM", 0 if sparse else 10**12)
    rng = np.random.default_rng(7)
    L, gp = _window_like(rng, n_e=4, n_p=12, coupled=2)
    n = L.shape[0]
    Q = np.linalg.inv(L)
    f = InformationFactor(L, gp)
    # image 1, a coupled (kept) point, two eliminated points, image 3
    groups = [np.arange(6, 12), np.arange(27, 30), np.arange(36, 39), np.arange(57, 60),
              np.arange(18, 24)]
    idx = np.concatenate(groups)
    sizes = np.array([g.size for g in groups])
    got = f.diagonal_blocks(idx, sizes)
    for g, b in zip(groups, got, strict=True):
        np.testing.assert_allclose(b, Q[np.ix_(g, g)], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(b, b.T)
    monkeypatch.setattr(np, "array_split", lambda a, k: [a[:1], a[1:]])  # two chunks
    for g, b in zip(groups, f.diagonal_blocks(idx, sizes), strict=True):
        np.testing.assert_allclose(b, Q[np.ix_(g, g)], rtol=1e-9, atol=1e-12)
    keep = np.setdiff1d(np.arange(n), np.arange(0, 6))  # image 0 left: indices shift by 6
    m = MarginalFactor.of(f, keep)
    for g, b in zip(groups, m.diagonal_blocks(idx - 6, sizes), strict=True):
        np.testing.assert_allclose(b, Q[np.ix_(g, g)], rtol=1e-9, atol=1e-12)


def test_point_marginals_read_per_point_blocks_even_when_its_columns_differ(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The eliminated points' variances are ``D^-1 + B_p^T Q_RR B_p`` read point by point
    from ``Q_RR``: equal to the dense formula, also for a point whose three columns of ``B``
    have different rows."""
    import scipy.sparse

    import seqat.information as information

    monkeypatch.setattr(information, "SPARSE_FROM", 0)
    rng = np.random.default_rng(11)
    L, gp = _window_like(rng, n_e=5, n_p=30, coupled=3)
    f = InformationFactor(L, gp)
    B = f.B.toarray()
    B[np.flatnonzero(B[:, 3])[0], 3] = 0.0  # point 1: its first column loses a row
    f.B = scipy.sparse.csr_array(B)
    f.B.eliminate_zeros()
    Qrr = np.linalg.inv(np.linalg.inv(L)[np.ix_(f.r_idx, f.r_idx)])  # S
    Qrr = np.linalg.inv(Qrr)
    want = np.einsum("ij,ij->j", B, Qrr @ B).reshape(-1, 3)
    np.testing.assert_allclose(f._point_extra(), want, rtol=1e-9, atol=1e-15)
    # a departure's 3 x 3 blocks (diagonal_blocks) by the same per-point reads, point 1 too
    pts = np.array([0, 1, 5, 20])
    Bp = B.reshape(B.shape[0], -1, 3)
    got = f.diagonal_blocks(f.p_idx[pts].ravel(), np.full(pts.size, 3))
    for j, blk in zip(pts, got, strict=True):
        want_b = f.Dinv[j] + Bp[:, j].T @ Qrr @ Bp[:, j]
        np.testing.assert_allclose(blk, want_b, rtol=1e-9, atol=1e-15)
        np.testing.assert_array_equal(blk, blk.T)


@pytest.mark.parametrize(("sparse_l", "n_e", "coupled"),
                         [(False, 5, 3), (True, 5, 3), (True, 2, 8)])
def test_sparse_window_factor_equals_the_dense_inverse(
        sparse_l: bool, n_e: int, coupled: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """A large window (``L`` sparse, or dense with a large ``L_RP``): the Schur product and
    the points' marginals point by point (seqat.kernels) give the dense inverse; with more
    coupled (kept) GPs than EOPs, the points read ``Q_RR`` on the EOPs' rows only."""
    import scipy.sparse

    import seqat.information as information

    monkeypatch.setattr(information, "SPARSE_FROM", 0)
    rng = np.random.default_rng(17)
    L, gp = _window_like(rng, n_e=n_e, n_p=30, coupled=coupled)
    Q = np.linalg.inv(L)
    f = InformationFactor(scipy.sparse.csr_array(L) if sparse_l else L, gp)
    assert scipy.sparse.issparse(f.B)
    # a touched block: eliminated points, EOPs and a kept GP, in any order; by solves on the
    # rows of Q_RR it reads, then (the sigmas formed V = U^-1) by V's rows
    pts = gp[[4, 11, 20]]
    idx = np.concatenate([pts[:2] + 2, [7, 1], pts[2] + np.arange(3), [6 * n_e + 1], [29]])
    blocks = [f.block(idx)]
    assert f._V is None
    np.testing.assert_allclose(f.diagonal(), np.diagonal(Q), rtol=1e-9)
    blocks.append(f.block(idx))
    for got in blocks:
        np.testing.assert_allclose(got, Q[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(got, got.T)
    # the EOPs' rows of Q_RR alone (not all of it) when the coupled GPs are most of R
    assert (f._Qrr is None) == (3 * coupled > 6 * n_e)
    b = rng.standard_normal(L.shape[0])
    np.testing.assert_allclose(f.solve(b), Q @ b, rtol=1e-9, atol=1e-12)
    groups = [np.arange(6, 12), np.arange(int(gp[0]), int(gp[0]) + 3),
              np.arange(int(gp[7]), int(gp[7]) + 3), np.arange(int(gp[20]), int(gp[20]) + 3)]
    got = f.diagonal_blocks(np.concatenate(groups), np.array([g.size for g in groups]))
    for g, blk in zip(groups, got, strict=True):
        np.testing.assert_allclose(blk, Q[np.ix_(g, g)], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(blk, blk.T)


def test_singular_point_block_is_named_not_a_nan() -> None:
    rng = np.random.default_rng(4)
    L, gp = _window_like(rng)
    o = int(gp[3])
    L[o:o + 3, :] = 0.0  # a GP no observation fixes
    L[:, o:o + 3] = 0.0
    with pytest.raises(RankDeficiency) as err:
        InformationFactor(L, gp)
    assert err.value.gp_blocks.tolist() == [o]


def test_singular_reduced_system_is_named() -> None:
    rng = np.random.default_rng(5)
    L, gp = _window_like(rng)
    L[:, 2] = 0.0  # one EOP component the data do not determine
    L[2, :] = 0.0
    with pytest.raises(RankDeficiency) as err:
        InformationFactor(L, gp)
    assert 2 in err.value.indices.tolist()


@pytest.mark.parametrize("threshold", [None, 0.1])
def test_engines_agree_and_sigmas_stay_positive_after_every_update(
    short_strip: SimulatedFlight, threshold: float | None
) -> None:
    """Information and inverse engines: the same estimates and sigmas after every update
    (the inverse update is exact algebra, the factorisation recomputes it); every sigma finite
    and positive, sigma0 finite."""
    _engines_agree(short_strip, threshold)


def test_the_large_window_path_agrees_with_the_inverse_update(
        short_strip: SimulatedFlight, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every window as a large one: ``L`` sparse, the update's ``Q[touched, touched]`` solved
    from the factor (InformationFactor.block, not from a dense ``Q_RR``) and the window's
    correction as one solve (Window.q_apply)."""
    import seqat.information as information

    monkeypatch.setattr(information, "DENSE_UP_TO", 0)
    _engines_agree(short_strip, 0.1)


def _engines_agree(short_strip: SimulatedFlight, threshold: float | None) -> None:
    runs = {e: SequentialAT(short_strip.camera, SequentialOptions(
        correlation_threshold=threshold, engine=e)) for e in ("information", "inverse")}
    for fr in short_strip.frames():
        ups = {e: at.add_frame(fr) for e, at in runs.items()}
        for up in ups.values():
            assert np.all(np.isfinite(up.eop.sigma)) and np.all(up.eop.sigma > 0)
        if ups["information"].stage == "sequential":
            assert np.isfinite(ups["information"].sigma0)
            np.testing.assert_allclose(ups["information"].eop.eop, ups["inverse"].eop.eop,
                                       rtol=0, atol=1e-6)
            np.testing.assert_allclose(ups["information"].eop.sigma, ups["inverse"].eop.sigma,
                                       rtol=1e-5)
    sols = {e: at.solution() for e, at in runs.items()}
    for e, sol in sols.items():
        sig = np.concatenate([p.sigma_m for p in sol.points])
        assert np.all(np.isfinite(sig)) and np.all(sig > 0), e


@pytest.mark.parametrize("ce", [6, 13])
def test_factor_parts_summed_per_image_equal_the_block_scatter(ce: int) -> None:
    """add_factor_parts (image-block parts summed per image) == add_block_parts of every
    factor's full block, with eliminated and kept (coupled) GPs and a shared camera block."""
    from seqat.assembly import add_block_parts, add_factor_parts
    from seqat.information import gather_parts, split_indices
    from seqat.rows import factor_blocks

    rng = np.random.default_rng(4)
    n_img, n_pts, k = 5, 12, 40
    cam = ce - 6
    n = 6 * n_img + cam + 3 * n_pts
    img = rng.integers(0, n_img, k)
    pt = rng.integers(0, n_pts, k)
    e_cols = np.concatenate([6 * img[:, None] + np.arange(6),
                             np.broadcast_to(6 * n_img + np.arange(cam), (k, cam))], axis=1)
    p_cols = 6 * n_img + cam + 3 * pt[:, None] + np.arange(3)
    cols = np.concatenate([e_cols, p_cols], axis=1)
    Je, Jp = rng.normal(size=(k, 2, ce)), rng.normal(size=(k, 2, 3))
    w = rng.uniform(0.5, 2.0, k)
    A = rng.normal(size=(n, n))
    L = A @ A.T
    gp = 6 * n_img + cam + 3 * np.arange(2, n_pts)  # points 0 and 1 kept (coupled)
    r_idx, p_idx = split_indices(n, gp)
    base = gather_parts(L, r_idx, p_idx)
    ref = add_block_parts(base, factor_blocks(Je, Jp, w), cols, r_idx, p_idx, n)
    got = add_factor_parts(base, Je, Jp, w, img, cols, r_idx, p_idx, n)
    for x, y in zip(got, ref, strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-10)


def test_marginals_from_the_inverse_factor_equal_the_dense_inverse_of_the_reduced_system(
        ) -> None:
    """A small window's marginals come from ``V = U^-1`` (rows of V, ``V^T B``), not from a
    dense ``Q_RR``: equal to ``inv(S)`` of the reduced system formed here independently, on a
    window-sized system (25 images, 13 coupled GPs: r = 189 as on the paper strip) with
    EOP parameters in units eight decades apart; every variance positive, every block
    exactly symmetric."""
    rng = np.random.default_rng(21)
    L, gp = _window_like(rng, n_e=25, n_p=40, coupled=13)
    n = L.shape[0]
    units = np.ones(n)
    units[:150] = 10.0 ** rng.uniform(-4, 4, 150)
    L = L * units[:, None] * units[None, :]
    f = InformationFactor(L, gp)
    r_idx, p = f.r_idx, f.p_idx.ravel()
    assert r_idx.size == 189 and isinstance(f.B, np.ndarray)  # the small window's path
    S = L[np.ix_(r_idx, r_idx)] - L[np.ix_(r_idx, p)] @ np.linalg.solve(
        L[np.ix_(p, p)], L[np.ix_(p, r_idx)])
    Qrr = np.linalg.inv(S)
    Q = np.linalg.inv(L)
    V = f._v()
    np.testing.assert_array_equal(np.tril(V, -1), 0.0)
    np.testing.assert_allclose(f.reduced_diagonal(), np.diagonal(Qrr), rtol=1e-8)
    np.testing.assert_allclose(f._q_rr(), Qrr, rtol=1e-7, atol=1e-9 * np.abs(Qrr).max())
    d = f.diagonal()
    assert np.all(d > 0)
    np.testing.assert_allclose(d, np.diagonal(Q), rtol=1e-8)
    # an update's touched block: a kept point, two images, eliminated points, in any order
    idx = np.r_[p[9:12], 6:12, 150 + np.arange(3), 54:60, p[30:33], 0]
    got = f.block(idx)
    np.testing.assert_array_equal(got, got.T)
    want = Q[np.ix_(idx, idx)]
    np.testing.assert_allclose(got, want, rtol=1e-7,
                               atol=1e-9 * np.sqrt(np.outer(np.diagonal(want),
                                                            np.diagonal(want))).max())
    eops = np.arange(150)
    np.testing.assert_allclose(f.entries(eops, np.arange(144, 150)),
                               Q[np.ix_(eops, np.arange(144, 150))], rtol=1e-7,
                               atol=1e-9 * np.abs(Q[:150, :150]).max())
    groups = [np.arange(6, 12), 150 + np.arange(3), p[:3], p[-3:]]
    got_blocks = f.diagonal_blocks(np.concatenate(groups), np.array([6, 3, 3, 3]))
    for g, b in zip(groups, got_blocks, strict=True):
        np.testing.assert_array_equal(b, b.T)
        np.testing.assert_allclose(b, Q[np.ix_(g, g)], rtol=1e-7)
