"""Descriptor matching of the tracker: two nearest neighbours, Lowe's ratio test, one match per
new feature.

Exact nearest neighbours of SIFT descriptors (:func:`nearest_two_exact`) are one BLAS matrix
product per pair of images: ``|q - t|² = |q|² + |t|² - 2 q·t``. SIFT's uint8 descriptors have
integer components ≤ 255 in 128 dimensions, so every dot product and squared norm is an integer
below 2²⁴ and float32 holds it exactly in any summation order: the distances are those of
OpenCV's brute-force matcher (``cv2.BFMatcher``, NORM_L2; equal to its float32 rounding), at
about a fifth of its cost, and
cheaper than FLANN's approximate kd-trees up to ~2500 features per image (whose misses either
lose a match or let an ambiguous one pass the ratio test: on the rendered Autzen sample FLANN
with 4 trees and 32 checks found 96 % of the exact ratio-test matches, plus 8 % others).
The cost grows with the product of the two feature counts, FLANN's with one of them: above
:data:`AUTO_EXACT_PAIRS` descriptor pairs ``matcher: auto`` (the default) uses FLANN;
``brute_force`` is always exact, ``flann`` always approximate.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from threadpoolctl import ThreadpoolController

from seqat.types import FloatArray

#: ``matcher: auto``: exact matching up to this many descriptor pairs (query x train) per
#: image pair, FLANN above (2500 x 2500: exact ~0.7x FLANN's CPU at 1500-2000 features per
#: image, 1.4x at 4000; docs/benchmarks.md).
AUTO_EXACT_PAIRS = 2500 * 2500
#: Rows of the distance matrix computed at once (bounds its memory to ~16 MB).
CHUNK_ELEMENTS = 1 << 22
#: BLAS threads of the products: one, as for the AT update (``seqat.sequential``): OpenBLAS's
#: threads spin while waiting, which costs more CPU than they save on 2 shared cores
#: (A/B on the Autzen sample at load ~6: tracking CPU 0.80x FLANN's with one thread, 1.04x
#: with two).
MATCH_BLAS_THREADS = 1
_BLAS = ThreadpoolController()


def nearest_two_exact(query: NDArray[np.uint8], train: NDArray[np.uint8],
                      train_sq: FloatArray | None = None,
                      ) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """Exact two nearest neighbours in ``train`` (L2) of every row of ``query``.

    Parameters
    ----------
    query : (m, d) uint8
    train : (n, d) uint8, n ≥ 2
    train_sq : (n,) float32, optional
        Squared norms of ``train`` (:func:`squared_norms`), when several queries share it.

    Returns
    -------
    idx : (m,) int64
        Index of the nearest train row (the first of equals).
    d1, d2 : (m,) float64
        Distances to the nearest and the second nearest train row.
    """
    q = np.asarray(query, dtype=np.float32)
    t = np.asarray(train, dtype=np.float32)
    if len(t) < 2:
        raise ValueError("nearest_two_exact needs at least two train descriptors")
    tt = squared_norms(t) if train_sq is None else train_sq
    qq = squared_norms(q)
    m, n = len(q), len(t)
    idx = np.empty(m, dtype=np.int64)
    sq1 = np.empty(m, dtype=np.float32)
    sq2 = np.empty(m, dtype=np.float32)
    step = max(1, CHUNK_ELEMENTS // n)
    tT = t.T
    for s in range(0, m, step):
        e = min(m, s + step)
        g = q[s:e] @ tT  # (rows, n): q·t, exact in float32 (module docstring)
        g *= -2.0
        g += tt  # |t|² - 2 q·t: the squared distance less |q|², same order along a row
        rows = np.arange(e - s)
        i1 = g.argmin(axis=1)
        sq1[s:e] = g[rows, i1]
        g[rows, i1] = np.inf
        sq2[s:e] = g.min(axis=1)
        idx[s:e] = i1
    d1 = np.sqrt(np.maximum(sq1.astype(np.float64) + qq, 0.0))
    d2 = np.sqrt(np.maximum(sq2.astype(np.float64) + qq, 0.0))
    return idx, d1, d2


def squared_norms(desc: NDArray[np.generic]) -> NDArray[np.float32]:
    """Squared L2 norm of every row, float32 (exact for uint8 SIFT descriptors)."""
    d = np.asarray(desc, dtype=np.float32)
    return np.einsum("ij,ij->i", d, d)


def nearest_two_knn(knn: list[list[cv2.DMatch]] | tuple[tuple[cv2.DMatch, ...], ...],
                    ) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
    """:func:`nearest_two_exact`'s arrays from OpenCV ``knnMatch(k=2)`` results (a query with
    fewer than two neighbours gets ``d2 = nan``, failing every ratio test)."""
    m = len(knn)
    idx = np.zeros(m, dtype=np.int64)
    d1 = np.full(m, np.nan)
    d2 = np.full(m, np.nan)
    for k, pair in enumerate(knn):
        if len(pair) >= 2:
            m0, m1 = pair[0], pair[1]
            idx[k], d1[k], d2[k] = m0.trainIdx, m0.distance, m1.distance
    return idx, d1, d2


def ratio_matches(idx: NDArray[np.int64], d1: FloatArray, d2: FloatArray, ratio: float,
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray]:
    """Lowe's ratio test, then one match per train feature (the smallest distance; equal
    distances: the first query).

    Returns
    -------
    idx_train, idx_query : (k,) int64
        Matched pairs, by increasing ``idx_train``.
    dist : (k,) float64
    """
    ok = d1 < ratio * d2  # nan (no second neighbour) fails
    q = np.flatnonzero(ok)
    t = idx[ok]
    d = d1[ok]
    order = np.lexsort((q, d, t))
    ts = t[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = ts[1:] != ts[:-1]
    pick = order[first]
    return t[pick], q[pick], d[pick]


#: FLANN kd-tree parameters for SIFT (4 randomised trees, 32 leaf checks).
FLANN_KDTREE = 1
FLANN_TREES = 4
FLANN_CHECKS = 32
#: Seed of OpenCV's RNG before each kd-tree build (deterministic matching).
FLANN_SEED = 1


class NewImageMatcher:
    """The new image's descriptors, matched by each candidate's (the query).

    Parameters
    ----------
    desc : (n, d) uint8
        The new image's descriptors (the train set).
    detector : {"sift", "orb"}
    matcher : {"auto", "brute_force", "flann"}
        SIFT: exact brute force (:func:`nearest_two_exact`), FLANN kd-trees (one index of the
        new image, built at the first query that needs it), or brute force up to
        :data:`AUTO_EXACT_PAIRS` descriptor pairs and FLANN above. ORB: brute-force Hamming.
    """

    def __init__(self, desc: NDArray[np.uint8], detector: str, matcher: str) -> None:
        self.desc = desc
        self.sift = detector == "sift"
        self.matcher = matcher
        self._sq: NDArray[np.float32] | None = None
        self._flann: cv2.FlannBasedMatcher | None = None

    def nearest_two(self, query: NDArray[np.uint8],
                    ) -> tuple[NDArray[np.int64], FloatArray, FloatArray]:
        """Nearest and second nearest new feature of every query row: ``(idx, d1, d2)``."""
        if not self.sift:
            bf = cv2.BFMatcher(cv2.NORM_HAMMING)
            return nearest_two_knn(bf.knnMatch(query, self.desc, k=2))
        exact = self.matcher == "brute_force" or (
            self.matcher == "auto" and len(query) * len(self.desc) <= AUTO_EXACT_PAIRS)
        if exact and len(self.desc) >= 2:
            if self._sq is None:
                self._sq = squared_norms(self.desc)
            with _BLAS.limit(limits=MATCH_BLAS_THREADS, user_api="blas"):
                return nearest_two_exact(query, self.desc, self._sq)
        if self._flann is None:
            # FLANN's randomised kd-trees draw from OpenCV's thread RNG: seed it so an image's
            # matches depend on its inputs only, not on what the process did before (a
            # resumed run must track like an uninterrupted one)
            cv2.setRNGSeed(FLANN_SEED)
            self._flann = cv2.FlannBasedMatcher(
                {"algorithm": FLANN_KDTREE, "trees": FLANN_TREES}, {"checks": FLANN_CHECKS})
            self._flann.add([self.desc.astype(np.float32)])
            self._flann.train()  # one index of the new image, queried by every candidate
        return nearest_two_knn(self._flann.knnMatch(query.astype(np.float32), k=2))
