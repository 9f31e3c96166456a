"""Baarda's data snooping (seed 003 §3.1): w-tests from residuals and redundancy numbers.

For an observation with standard deviation ``sigma`` and residual ``v`` of an adjustment
whose parameters have cofactor ``Q``, the residual cofactor is ``q_vv = sigma^2 - a Q a^T``
(``a``: the observation's design row), the redundancy number ``r = q_vv / sigma^2`` (its
share of the redundancy, 0..1) and Baarda's test statistic ``w = |v| / sqrt(q_vv)``, standard
normal without a blunder (a priori sigma0 = 1). Used by the sequential update (the rows of one
image, seqat.sequential) and by the simultaneous adjustment (every observation,
seqat.simultaneous); docs/algorithm.md, "Blunders".
"""

from __future__ import annotations

import numpy as np
import scipy.stats

from seqat.types import FloatArray

#: Observations with a smaller redundancy number are not testable (a blunder is absorbed).
MIN_REDUNDANCY = 0.05
#: A GPS/INS group (position or attitude) failing the w-test gets its sigma multiplied so.
NAV_DOWNWEIGHT = 10.0


def point_w(J: FloatArray, Z: FloatArray, v: FloatArray, sigma: FloatArray) -> FloatArray:
    """Largest w of the two coordinates of each image point (0 where not testable).

    Parameters
    ----------
    J : (k, 2, p) float
        Design of each point's two rows on its ``p`` parameters.
    Z : (k, p, p) float
        Cofactor of those parameters after the adjustment.
    v : (k, 2) float
        Residuals, pixels.
    sigma : (k,) float
        Standard deviation of a coordinate, pixels.
    """
    aqa = np.einsum("kri,kij,krj->kr", J, Z, J)
    var = np.repeat(np.asarray(sigma, dtype=np.float64)[:, None] ** 2, 2, axis=1)
    qvv = var - aqa
    w = np.abs(v) / np.sqrt(np.maximum(qvv, 1e-30))
    w[qvv / var < MIN_REDUNDANCY] = 0.0
    return w.max(axis=1) if w.size else np.zeros(0)


def predicted_w(J: FloatArray, Z: FloatArray, v: FloatArray, sigma: FloatArray) -> FloatArray:
    """Largest |v| / sqrt(sigma^2 + a Q a^T) of the two coordinates of observations *not* in
    the adjustment (prediction residuals: re-admission of rejected observations)."""
    aqa = np.einsum("kri,kij,krj->kr", J, Z, J)
    var = np.asarray(sigma, dtype=np.float64)[:, None] ** 2 + aqa
    return (np.abs(v) / np.sqrt(var)).max(axis=1) if v.size else np.zeros(0)


def select(worst: FloatArray, critical: float, image: np.ndarray,
           point: np.ndarray) -> np.ndarray:
    """Observations rejected this round (none when every w is within ``critical``).

    Baarda's rule rejects only the largest w and re-adjusts: a blunder's residual spreads to
    the other observations of its point and image, so the second largest w may be innocent.
    Taking, largest first, every failing observation that shares neither point nor image
    with one already taken this round keeps that rule where it matters and needs a few
    rounds, not one per blunder.
    """
    order = np.argsort(-worst, kind="stable")
    taken: list[int] = []
    images: set[int] = set()
    points: set[int] = set()
    for q in order:
        if worst[q] <= critical:
            break
        i, p = int(image[q]), int(point[q])
        if i in images or p in points:
            continue
        taken.append(int(q))
        images.add(i)
        points.add(p)
    return np.asarray(taken, dtype=np.int64)


def nav_exceedance(v: FloatArray, sigma: FloatArray, q: FloatArray,
                   critical: float) -> list[tuple[str, float]]:
    """GPS/INS groups with their test statistic over its critical value, largest first.

    ``v`` residuals, ``sigma`` their standard deviations (inf: no constraint), ``q`` the
    diagonal of the EOP cofactor after the adjustment. Each group (position, attitude) is
    tested as a whole, ``T = sum w_i^2`` against the chi-square quantile of the same
    significance level as the w-test's ``critical`` (Baarda's idea of one level for tests of
    any dimension; 16.3 for 3 components at 3.29): a 5 m jump under a 0.3 m sigma gives
    T ~ 800. A value above 1 fails.
    """
    alpha = 2.0 * scipy.stats.norm.sf(critical)
    out = []
    for name, sl in (("position", slice(0, 3)), ("attitude", slice(3, 6))):
        s = np.asarray(sigma[sl], dtype=np.float64)
        ok = np.isfinite(s)
        if not np.any(ok):
            continue
        var = s[ok] ** 2
        qvv = var - q[sl][ok]
        testable = qvv / var >= MIN_REDUNDANCY
        if not np.any(testable):
            continue
        w2 = (v[sl][ok] ** 2 / np.maximum(qvv, 1e-30))[testable]
        out.append((name, float(w2.sum() / scipy.stats.chi2.isf(alpha, w2.size))))
    return sorted(out, key=lambda g: -g[1])


def nav_groups(v: FloatArray, sigma: FloatArray, q: FloatArray, critical: float) -> list[str]:
    """GPS/INS groups whose test fails (:func:`nav_exceedance` above 1)."""
    return [name for name, excess in nav_exceedance(v, sigma, q, critical) if excess > 1.0]
