"""Dense gathers and scatters on a window's index sets (seqat/dense.py) against numpy's."""

import numpy as np
import pytest

from seqat.dense import MAX_RUNS, add_square, square_take
from seqat.window import keys_of


@pytest.mark.parametrize("runs", [1, 3, MAX_RUNS - 1, MAX_RUNS + 5])
def test_square_take_equals_outer_indexing(runs: int) -> None:
    rng = np.random.default_rng(runs)
    n = 4 * MAX_RUNS + 30
    M = rng.normal(size=(n, n))
    # single holes, none adjacent: each one more run
    holes = np.sort(rng.choice(np.arange(2, n - 1, 2), size=runs - 1, replace=False))
    idx = np.setdiff1d(np.arange(n), holes)
    assert np.count_nonzero(np.diff(idx) != 1) + 1 == runs
    out = square_take(M, idx)
    assert out.flags.c_contiguous
    np.testing.assert_array_equal(out, M[np.ix_(idx, idx)])


def test_square_take_of_any_order_and_of_nothing() -> None:
    M = np.arange(49.0).reshape(7, 7)
    idx = np.array([5, 6, 0, 1, 3])  # runs need not be sorted
    np.testing.assert_array_equal(square_take(M, idx), M[np.ix_(idx, idx)])
    assert square_take(M, np.zeros(0, dtype=np.int64)).shape == (0, 0)


def test_add_square_adds_in_place_on_the_outer_index_set() -> None:
    rng = np.random.default_rng(1)
    M = rng.normal(size=(12, 12))
    want = M.copy()
    idx = np.array([7, 2, 11, 3])
    B = rng.normal(size=(4, 4))
    want[np.ix_(idx, idx)] += B
    add_square(M, idx, B)
    np.testing.assert_array_equal(M, want)


def test_keys_of_names_each_key_once_in_layout_order() -> None:
    keys = [("e", 0), ("p", 4), ("e", 1), ("c", 2)]  # offsets 0, 6, 9, 15 (17 in all)
    assert keys_of(keys, np.array([16, 0, 5, 1, 10, 9])) == [("e", 0), ("e", 1), ("c", 2)]
    assert keys_of(keys, np.array([6, 8])) == [("p", 4)]
