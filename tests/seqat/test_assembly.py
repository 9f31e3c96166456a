"""seqat.assembly: a re-linearisation step assembled on L's pattern equals the entry-by-entry
assembly (docs/algorithm.md, *Re-linearising the window*)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse

from seqat.assembly import WindowAssembly, add_factor_parts, factor_information
from seqat.information import gather_parts, split_indices, window_matrix
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight

N_IMG, N_PTS, K = 6, 30, 90


def _window(ce: int, seed: int = 4, camera_xy: bool = False):  # noqa: ANN202
    """A window's factors and its information ``L`` (sparse CSR): the factors' blocks plus
    a prior coupling the images and GPs 0 and 1 (kept), and a diagonal."""
    rng = np.random.default_rng(seed)
    cam = ce - 6
    n = 6 * N_IMG + cam + 3 * N_PTS
    img = np.repeat(np.arange(N_IMG), K // N_IMG)
    pt = np.concatenate([rng.choice(N_PTS, K // N_IMG, replace=False) for _ in range(N_IMG)])
    e_cols = np.concatenate([6 * img[:, None] + np.arange(6),
                             np.broadcast_to(6 * N_IMG + np.arange(cam), (K, cam))], axis=1)
    p_cols = 6 * N_IMG + cam + 3 * pt[:, None] + np.arange(3)
    cols = np.concatenate([e_cols, p_cols], axis=1)

    def jacobians() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Je, Jp = rng.normal(size=(K, 2, ce)), rng.normal(size=(K, 2, 3))
        if camera_xy:  # the principal point: (1, 0) and (0, 1), an exact zero between them
            Je[:, :, 6:8] = np.eye(2)
        return Je, Jp, rng.uniform(0.5, 2.0, K)

    old = jacobians()
    kept = np.concatenate([np.arange(6 * N_IMG), 6 * N_IMG + cam + np.arange(6)])
    A = rng.normal(size=(kept.size, kept.size))
    prior = np.zeros((n, n))
    prior[np.ix_(kept, kept)] = A @ A.T
    prior += np.diag(rng.uniform(1.0, 2.0, n))
    L = scipy.sparse.csr_array(prior) + factor_information(*old, img, cols, n)
    L = scipy.sparse.csr_array(0.5 * (L + L.T))
    L.eliminate_zeros()
    gp = 6 * N_IMG + cam + 3 * np.arange(2, N_PTS)  # points 0 and 1 kept (coupled)
    return L, img, cols, gp, old, jacobians


def _general(L, img, cols, gp, old, new):  # noqa: ANN001, ANN202
    n = L.shape[0]
    r_idx, p_idx = split_indices(n, gp)
    base = add_factor_parts(gather_parts(L, r_idx, p_idx), old[0], old[1], -old[2], img, cols,
                            r_idx, p_idx, n)
    parts = add_factor_parts(base, *new, img, cols, r_idx, p_idx, n)
    return parts, window_matrix(L + factor_information(*new, img, cols, n, minus=old))


def _dense(M):  # noqa: ANN001, ANN202
    return M.toarray() if scipy.sparse.issparse(M) else np.asarray(M)


def _assert_equal(asm: WindowAssembly, L, img, cols, gp, old, new) -> None:  # noqa: ANN001
    parts = asm.parts(*new)
    ref_parts, ref_H = _general(L, img, cols, gp, old, new)
    for got, ref in zip(parts, ref_parts, strict=True):
        np.testing.assert_allclose(_dense(got), _dense(ref), rtol=0, atol=1e-11)
    H = asm.matrix(*new)
    assert type(H) is type(ref_H)  # dense up to DENSE_UP_TO parameters, as the window keeps it
    np.testing.assert_allclose(_dense(H), _dense(ref_H), rtol=0, atol=1e-11)
    if asm.fast:  # exactly symmetric (a sparse sum of duplicates need not be)
        np.testing.assert_array_equal(_dense(H), _dense(H).T)


@pytest.mark.parametrize(("ce", "last_first"), [(6, False), (13, False), (13, True)])
def test_pattern_assembly_equals_the_entry_by_entry_one(ce: int, last_first: bool,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """``last_first``: the first factor's EOP block ends where the camera's begins."""
    import seqat.information as information

    monkeypatch.setattr(information, "DENSE_UP_TO", 0)  # L kept sparse, as a large window's
    L, img, cols, gp, old, jacobians = _window(ce)
    if last_first:
        order = np.argsort(-img, kind="stable")
        img, cols = img[order], cols[order]
        old = tuple(a[order] for a in old)
        L = scipy.sparse.csr_array(L.toarray())  # (the same L: its factors are a set)
    asm = WindowAssembly(L, img, cols, gp, old)
    assert asm.fast
    _assert_equal(asm, L, img, cols, gp, old, old)
    for _ in range(2):  # the steps of a re-linearisation
        Je, Jp, w = jacobians()
        _assert_equal(asm, L, img, cols, gp, old, (Je, Jp, w))
    assert asm.fast


def test_an_exact_zero_outside_the_pattern(monkeypatch: pytest.MonkeyPatch) -> None:
    """The principal point's x-y entry is an exact zero L does not hold: scattered nowhere
    while it stays zero; a step where it is not goes the entry-by-entry way."""
    import seqat.information as information

    monkeypatch.setattr(information, "DENSE_UP_TO", 0)
    L, img, cols, gp, old, jacobians = _window(10, camera_xy=True)
    cx, cy = 6 * N_IMG, 6 * N_IMG + 1
    assert L[[cx]][:, [cy]].nnz == 0
    asm = WindowAssembly(L, img, cols, gp, old)
    assert asm.fast and asm.outside.size
    _assert_equal(asm, L, img, cols, gp, old, jacobians())
    assert asm.fast
    Je, Jp, w = jacobians()
    Je[:, :, 6:8] += 0.1  # no longer the principal point's exact zero
    _assert_equal(asm, L, img, cols, gp, old, (Je, Jp, w))
    assert not asm.fast


def test_a_dense_window_goes_entry_by_entry() -> None:
    L, img, cols, gp, old, jacobians = _window(6)
    L = window_matrix(L)  # small: dense
    assert not scipy.sparse.issparse(L)
    asm = WindowAssembly(L, img, cols, gp, old)
    assert not asm.fast
    _assert_equal(asm, L, img, cols, gp, old, jacobians())


def test_a_large_window_re_linearises_on_its_pattern(short_strip: SimulatedFlight,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Every window a large (sparse) one, an INS 4 deg off: the re-linearisations take the
    pattern's way and end where the dense windows' entry-by-entry ones end."""
    import dataclasses

    import seqat.assembly as assembly
    import seqat.information as information

    rng = np.random.default_rng(5)
    nav = short_strip.nav_eop.copy()
    nav[:, 3:] += np.radians(4.0) * rng.standard_normal((len(nav), 3))
    loose = dataclasses.replace(short_strip, nav_eop=nav,
                                nav_sigma=np.array([0.3, 0.3, 0.3, 0.1, 0.1, 0.1]))

    def run() -> tuple[np.ndarray, SequentialAT]:
        seq = SequentialAT(short_strip.camera, SequentialOptions(correlation_threshold=0.1))
        for fr in loose.frames():
            seq.add_frame(fr)
        seq.finish()
        return np.array([e.eop for e in seq.solution().eops]), seq

    ways: list[bool] = []
    init = assembly.WindowAssembly.__init__

    def recorded(self: WindowAssembly, *args, **kwargs) -> None:  # noqa: ANN002, ANN003
        init(self, *args, **kwargs)
        ways.append(self.fast)

    monkeypatch.setattr(assembly.WindowAssembly, "__init__", recorded)
    dense, seq_dense = run()
    assert seq_dense.relinearisations > 0 and not any(ways)
    monkeypatch.setattr(information, "DENSE_UP_TO", 0)
    ways.clear()
    sparse, seq_sparse = run()
    assert seq_sparse.relinearisations == seq_dense.relinearisations
    assert ways and all(ways)
    np.testing.assert_allclose(sparse[:, :3], dense[:, :3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(sparse[:, 3:], dense[:, 3:], rtol=0, atol=1e-8)
    assert seq_sparse.sigma0 == pytest.approx(seq_dense.sigma0, rel=1e-8)
