"""Dense matrix gathers and scatters on index sets of a window's layout.

A window's dense information matrix is re-gathered on every update (a departure keeps all
but the leaving keys, a factorisation splits kept and eliminated parameters). Those index
sets are a few runs of consecutive indices; numpy's fancy indexing copies them element by
element, a copy by slices is several times faster (docs/benchmarks.md, *Paper strip*).
"""

from __future__ import annotations

import numpy as np

from seqat.types import FloatArray

#: :func:`square_take` copies block by block up to this many runs of consecutive indices.
MAX_RUNS = 32


def square_take(M: FloatArray, idx: np.ndarray) -> FloatArray:
    """``M[np.ix_(idx, idx)]`` of a dense matrix, C-ordered. ``idx`` is mostly runs of
    consecutive indices (a window less the keys that left it): the rows are gathered whole,
    the columns run by run as slices, several times faster than numpy's element-by-element
    gather of the columns."""
    idx = np.asarray(idx, dtype=np.int64)
    cut = np.flatnonzero(idx[1:] - idx[:-1] != 1) + 1
    if cut.size >= MAX_RUNS or idx.size == 0:
        return M[np.ix_(idx, idx)]
    rows = M.take(idx, axis=0)
    out = np.empty((idx.size, idx.size))
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
