"""Descriptor matching of the tracker (``pipeline/tracking/matching.py``): exact nearest
neighbours by one BLAS product, the ratio test, one match per new feature, the matcher
choice."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.tracking import matching
from pipeline.tracking.matching import (
    NewImageMatcher,
    nearest_two_exact,
    nearest_two_knn,
    ratio_matches,
)
from pipeline.tracking.options import TrackerOptions
from seqat.errors import ConfigError


def descriptors(n: int, seed: int) -> np.ndarray:
    """uint8 descriptors up to 255 in every component (the exactness bound's worst case)."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (n, 128), dtype=np.uint8)


def test_exact_nearest_two_are_exact() -> None:
    """Distances equal the integer computation exactly; neighbours equal OpenCV's brute-force
    matcher's (NORM_L2 in float32)."""
    q, t = descriptors(700, 1), descriptors(900, 2)
    t[5] = q[3]  # a zero distance
    idx, d1, d2 = nearest_two_exact(q, t)
    sq = ((q[:, None, :].astype(np.int64) - t[None, :, :].astype(np.int64)) ** 2).sum(-1)
    order = np.argsort(sq, axis=1, kind="stable")
    np.testing.assert_array_equal(idx, order[:, 0])
    np.testing.assert_array_equal(d1, np.sqrt(np.take_along_axis(sq, order[:, :1], 1)[:, 0]))
    np.testing.assert_array_equal(d2, np.sqrt(np.take_along_axis(sq, order[:, 1:2], 1)[:, 0]))
    assert d1[3] == 0.0 and idx[3] == 5
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(q.astype(np.float32), t.astype(np.float32), k=2)
    bf_idx, bf_d1, bf_d2 = nearest_two_knn(knn)
    np.testing.assert_array_equal(idx, bf_idx)
    np.testing.assert_allclose(d1, bf_d1, rtol=1e-5)
    np.testing.assert_allclose(d2, bf_d2, rtol=1e-5)


def test_exact_in_chunks_equals_one_product(monkeypatch: pytest.MonkeyPatch) -> None:
    q, t = descriptors(301, 3), descriptors(257, 4)
    whole = nearest_two_exact(q, t)
    monkeypatch.setattr(matching, "CHUNK_ELEMENTS", 257 * 7)  # 7 rows at a time
    for a, b in zip(nearest_two_exact(q, t), whole, strict=True):
        np.testing.assert_array_equal(a, b)


def test_ratio_test_and_one_match_per_new_feature() -> None:
    idx = np.array([4, 4, 7, 2, 9, 4])
    d1 = np.array([1.0, 0.5, 3.0, 2.0, 1.0, 0.5])
    d2 = np.array([2.0, 2.0, 3.1, 10.0, np.nan, 2.0])
    new, old, dist = ratio_matches(idx, d1, d2, 0.8)
    # query 2 fails the ratio, query 4 has no second neighbour; feature 4: the closest
    # (queries 1 and 5 tie at 0.5: the first)
    np.testing.assert_array_equal(new, [2, 4])
    np.testing.assert_array_equal(old, [3, 1])
    np.testing.assert_array_equal(dist, [2.0, 0.5])
    empty = ratio_matches(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), 0.8)
    assert all(len(a) == 0 for a in empty)


def test_matcher_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    """auto: exact up to AUTO_EXACT_PAIRS descriptor pairs, FLANN above (approximate: random
    128-d descriptors are its worst case, so only the path is checked)."""
    q, t = descriptors(200, 5), descriptors(300, 6)
    exact = nearest_two_exact(q, t)
    auto = NewImageMatcher(t, "sift", "auto")
    np.testing.assert_array_equal(auto.nearest_two(q)[0], exact[0])
    assert auto._flann is None  # noqa: SLF001 - which path ran
    monkeypatch.setattr(matching, "AUTO_EXACT_PAIRS", 200 * 300 - 1)
    big = NewImageMatcher(t, "sift", "auto")
    idx, _, _ = big.nearest_two(q)
    assert big._flann is not None  # noqa: SLF001
    assert idx.shape == (200,) and np.all((idx >= 0) & (idx < 300))
    brute = NewImageMatcher(t, "sift", "brute_force")
    np.testing.assert_array_equal(brute.nearest_two(q)[0], exact[0])
    orb = NewImageMatcher(t[:, :32].copy(), "orb", "auto")
    assert len(orb.nearest_two(q[:, :32].copy())[0]) == 200
    assert TrackerOptions().matcher == "auto"
    with pytest.raises(ConfigError, match="matcher"):
        TrackerOptions(matcher="kdtree")  # type: ignore[arg-type]
