"""The factorised conditional of a departure record (seqat.conditional) against dense algebra."""

from __future__ import annotations

import copy
import types

import numpy as np
import pytest

from seqat.conditional import Conditional
from seqat.departures import DepartureMixin
from seqat.information import InformationFactor
from tests.seqat.test_information import _window_like


def _split(C: np.ndarray, r: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense: ``K = C_mr C_rr^-1`` and ``C_mm - K C_rm`` (a record split on ``r``)."""
    K = np.linalg.solve(C[np.ix_(r, r)], C[np.ix_(r, m)]).T
    return K, C[np.ix_(m, m)] - K @ C[np.ix_(r, m)]


@pytest.mark.parametrize("factorised", [True, False])
def test_blocks_and_two_splits_equal_the_dense_conditional(factorised: bool) -> None:
    """Blocks, cross entries and two successive splits (re-opening keys of one record twice)
    equal the dense formulas on the dense inverse, for a factorised and a dense base."""
    rng = np.random.default_rng(11)
    L, gp = _window_like(rng, n_e=3, n_p=10)
    Q = np.linalg.inv(L)
    n = Q.shape[0]
    cond = Conditional(InformationFactor(L, gp) if factorised else Q)
    idx = np.array([1, 7, 20, 21, 22, 40, 41])
    np.testing.assert_allclose(cond.block(idx), Q[np.ix_(idx, idx)], rtol=1e-9, atol=1e-12)
    rest = np.setdiff1d(np.arange(n), idx[:2])
    np.testing.assert_allclose(cond.entries(idx[:2], rest), Q[np.ix_(idx[:2], rest)],
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cond.entries(rest, idx[:2]), Q[np.ix_(rest, idx[:2])],
                               rtol=1e-9, atol=1e-12)
    J = rng.standard_normal((2, rest.size))  # two re-opened entries' chain through rest
    np.testing.assert_allclose(cond.quadratic(rest, J), J @ Q[np.ix_(rest, rest)] @ J.T,
                               rtol=1e-9, atol=1e-12)

    dense, now = Q, cond
    for r in (np.array([0, 1, 2, 3, 4, 5]), np.array([3, 4, 5])):  # an image, then a point
        m = np.setdiff1d(np.arange(dense.shape[0]), r)
        C_rm = now.entries(r, m)
        K = np.linalg.solve(now.block(r), C_rm).T
        K_ref, dense = _split(dense, r, m)
        np.testing.assert_allclose(K, K_ref, rtol=1e-8, atol=1e-12)
        now = now.restricted(m, K, C_rm)
        assert now.size == m.size
        every = np.arange(m.size)
        np.testing.assert_allclose(now.block(every), dense, rtol=1e-8, atol=1e-12)
        Jm = rng.standard_normal((3, m.size))
        np.testing.assert_allclose(now.quadratic(every, Jm), Jm @ dense @ Jm.T,
                                   rtol=1e-8, atol=1e-12)
        sub = every[::3]
        np.testing.assert_allclose(now.entries(sub, every), dense[sub], rtol=1e-8, atol=1e-12)
        w = np.linalg.eigvalsh(now.block(every))
        assert w.min() > 0  # a conditional cofactor stays positive definite


@pytest.mark.parametrize("large", [False, True])
def test_a_sparse_leaving_block_gives_the_dense_ones_conditional_and_gain(
        large: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A large window's departure passes ``L_FF`` sparse (made dense, 40 images and their
    points cost 0.8 s of a 1 s update): conditional and RTS gain equal the dense inverse's,
    kept dense or factorised."""
    import scipy.sparse

    import seqat.departures as departures

    if large:
        monkeypatch.setattr(departures, "DENSE_CONDITIONAL_UP_TO", 0)
    rng = np.random.default_rng(5)
    L, gp = _window_like(rng, n_e=3, n_p=10)
    n = L.shape[0]
    f, s = np.arange(n - 9), np.arange(n - 9, n)  # the last three GPs stay
    keys = [("e", j) for j in range(3)] + [("p", j) for j in range(7)]
    coupled = {("p", 0), ("p", 1)}
    Q_ff = np.linalg.inv(L[np.ix_(f, f)])
    gain_ref = -Q_ff @ L[np.ix_(f, s)]
    for L_ff in (L[np.ix_(f, f)], scipy.sparse.csr_array(L[np.ix_(f, f)])):
        cond, gain = departures.leaving_conditional(L_ff, L[np.ix_(f, s)], keys, coupled)
        np.testing.assert_allclose(gain, gain_ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(cond.block(np.arange(f.size)), Q_ff, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("factorised", [True, False])
def test_a_records_gain_formed_on_request_equals_the_dense_one_after_two_splits(
        factorised: bool) -> None:
    """A departure record keeps ``L_FS`` (sparse) and its splits, not the RTS gain
    ``J = -L_FF^-1 L_FW``: the ``J`` it forms equals the dense formula at departure and,
    after two splits (keys of the record re-opened twice), the dense chain
    ``[J_M - K J_R, K]`` with ``K = C_MR C_RR^-1`` of the dense conditional."""
    import scipy.sparse

    from seqat.conditional import Departure

    rng = np.random.default_rng(19)
    L, gp = _window_like(rng, n_e=3, n_p=10)
    n = L.shape[0]
    f, w = np.arange(n - 12), np.arange(n - 12, n)  # the last four GPs stay (W)
    L_ff = L[np.ix_(f, f)]
    Q = np.linalg.inv(L_ff)
    support = np.flatnonzero(np.any(L[np.ix_(f, w)] != 0, axis=0))
    L_fs = L[np.ix_(f, w[support])]
    base = InformationFactor(L_ff, gp[gp < f.size]) if factorised else Q
    cond = Conditional(base)
    dep = Departure(leaving=(), staying=(), x_leaving=np.zeros(f.size),
                    x_staying=np.zeros(w.size), conditional=cond, at=0,
                    coupling=scipy.sparse.csr_array(L_fs), coupling_cols=support,
                    gain_width=w.size)
    J = np.zeros((f.size, w.size))
    J[:, support] = -Q @ L_fs
    np.testing.assert_allclose(dep.rts_gain(), J, rtol=1e-9, atol=1e-12)
    C = Q
    # the gain a re-opening reads, kept from one split to the next (each applied once)
    holder = types.SimpleNamespace(_gains={})
    np.testing.assert_allclose(DepartureMixin._record_gain(holder, 0, dep), J, rtol=1e-9,
                               atol=1e-12)
    seen = []
    for r in (np.array([0, 1, 2, 3, 4, 5]), np.array([2, 3, 4])):  # an image, then a GP
        m = np.setdiff1d(np.arange(C.shape[0]), r)
        K, C_next = _split(C, r, m)
        J_before = J
        J = np.hstack([J[m] - K @ J[r], K])
        dep = _split_record(dep, r, m, J.shape[1])
        C = C_next
        np.testing.assert_allclose(dep.rts_gain(), J, rtol=1e-8, atol=1e-11)
        # the gain as it stood before this split, carried through the new split alone
        np.testing.assert_allclose(dep.split(J_before, len(dep.splits) - 1), J, rtol=1e-12,
                                   atol=1e-14)
        np.testing.assert_allclose(DepartureMixin._record_gain(holder, 0, dep), J,
                                   rtol=1e-8, atol=1e-11)
        assert holder._gains[0][2] is dep.splits  # applied, kept
        seen.append((dep, J))
    # a second start's restored state: the same splits, copied (not the ones applied); the
    # record before its last split (a trial's split undone): formed again, not misread
    for old, J_old in (copy.deepcopy(seen[-1]), seen[0]):
        np.testing.assert_allclose(DepartureMixin._record_gain(holder, 0, old), J_old,
                                   rtol=1e-8, atol=1e-11)
    # ... and as many splits as the kept gain has, but not the same ones
    DepartureMixin._record_gain(holder, 0, seen[-1][0])
    r = np.array([6, 7, 8])
    other = _split_record(seen[0][0], r, np.setdiff1d(np.arange(seen[0][1].shape[0]), r),
                          seen[0][1].shape[1] + r.size)
    np.testing.assert_allclose(DepartureMixin._record_gain(holder, 0, other), other.rts_gain(),
                               rtol=1e-12, atol=1e-14)


def _split_record(dep, r: np.ndarray, m: np.ndarray, width: int):  # noqa: ANN001, ANN202
    """``dep`` split on its rows ``r`` (re-opened; ``m`` stay), as a re-opening splits it."""
    from seqat.conditional import Departure

    Kc = np.linalg.solve(dep.conditional.block(r), dep.conditional.entries(r, m)).T
    return Departure(leaving=(), staying=(), x_leaving=np.zeros(m.size),
                     x_staying=np.zeros(width),
                     conditional=dep.conditional.restricted(m, Kc,
                                                            dep.conditional.entries(r, m)),
                     at=0, coupling=dep.coupling, coupling_cols=dep.coupling_cols,
                     gain_width=dep.gain_width, splits=dep.splits + ((m, Kc, r),))
