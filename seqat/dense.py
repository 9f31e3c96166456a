"""Dense matrix gathers and scatters on index sets of a window's layout.

A window's dense information matrix is re-gathered on every update (a departure keeps all
but the leaving keys, a factorisation splits kept and eliminated parameters). Those index
sets are a few runs of consecutive indices; numpy's fancy indexing copies them element by
element, a copy by slices is several times faster (docs/benchmarks.md, *Paper strip*).
"""

from __future__ import annotations

import numpy as np

from seqat.types import FloatArray

#: :func:`take_columns` copies slice by slice up to this many runs of consecutive indices.
MAX_RUNS = 32


def square_take(M: FloatArray, idx: np.ndarray) -> FloatArray:
    """``M[np.ix_(idx, idx)]`` of a dense matrix, C-ordered. ``idx`` is mostly runs of
    consecutive indices (a window less the keys that left it): the rows are gathered whole,
    the columns run by run as slices (:func:`take_columns`)."""
    return take_columns(np.asarray(M).take(np.asarray(idx, dtype=np.int64), axis=0), idx)


def take_columns(rows: FloatArray, idx: np.ndarray) -> FloatArray:
    """``rows[:, idx]``, C-ordered, run by run of consecutive indices as slices: several
    times faster than numpy's element-by-element gather of columns (up to
    :data:`MAX_RUNS` runs; beyond, numpy's)."""
    idx = np.asarray(idx, dtype=np.int64)
    cut = np.flatnonzero(idx[1:] - idx[:-1] != 1) + 1
    if cut.size >= MAX_RUNS or idx.size == 0:
        return np.ascontiguousarray(rows[:, idx])
    out = np.empty((rows.shape[0], idx.size))
    a = 0
    for s, b in zip(idx[[0, *cut.tolist()]].tolist(), [*cut.tolist(), idx.size], strict=True):
        out[:, a:b] = rows[:, s:s + b - a]
        a = b
    return out


def add_square(M: FloatArray, idx: np.ndarray, B: FloatArray) -> None:
    """``M[np.ix_(idx, idx)] += B`` in place (``idx`` distinct; one flat scatter)."""
    n = M.shape[1]
    flat = (idx[:, None] * n + idx[None, :]).ravel()
    M.reshape(-1)[flat] += B.ravel()
