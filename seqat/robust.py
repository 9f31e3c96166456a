"""Robust weighting of image points: a least-squares core with a Cauchy tail, by iteratively
re-weighted least squares (IRLS).

One wrong tie point (a repeated texture matched to the wrong field corner) must not move the
solution (docs/algorithm.md, *Robust by default*). Each image point's squared normalised
residual ``u² = |v|² / σ²`` (both coordinates) enters the cost through

    ρ(u²) = u²                              for u² ≤ k²,
    ρ(u²) = k² + k² ln(1 + (u² − k²) / k²)   beyond,

with ``k`` the scale in σ (``robust_scale``; :data:`ROBUST_SCALE` = 3 recommended; the
options' default None is least squares, the paper's estimator). The IRLS weight is ``ρ'(u²)``: 1
for every point within ``k`` σ (98.9 % of Gaussian 2D errors: clean data are adjusted by
least squares, unchanged), then ``k² / u²``-like: a point 40σ off keeps 0.6 % of its weight
and pulls on the solution by less than ``k`` σ. Sim re-weights every Gauss-Newton iteration;
Seq-F / Seq-R weight each new image's rows in every update iteration (the first one least
squares: its start values may be 20° off) and the window re-linearisation keeps those
weights. GPS/INS rows stay least squares (their faults are the data snooping's,
docs/algorithm.md, *Blunders*). Why it is not the default yet: docs/algorithm.md.
"""

from __future__ import annotations

import numpy as np

from seqat.types import FloatArray

#: Recommended robust scale (sigmas): ``robust_scale: 3`` in an options file.
ROBUST_SCALE = 3.0


def _u2(res_px: FloatArray, sigma_px: FloatArray) -> FloatArray:
    res = np.asarray(res_px, dtype=np.float64).reshape(-1, 2)
    return np.sum(res**2, axis=1) / np.asarray(sigma_px, dtype=np.float64).reshape(-1) ** 2


def cauchy_weight(res_px: FloatArray, sigma_px: FloatArray, scale: float | None) -> FloatArray:
    """IRLS weight factor in (0, 1] of each image point (k,) from its residual (k, 2)."""
    u2 = _u2(res_px, sigma_px)
    if scale is None:
        return np.ones(u2.size)
    k2 = scale**2
    return 1.0 / (1.0 + np.maximum(u2 - k2, 0.0) / k2)


def cauchy_cost(res_px: FloatArray, sigma_px: FloatArray, scale: float | None) -> float:
    """``Σ ρ(u²)`` of the image points (``Σ u²`` without a scale: least squares)."""
    u2 = _u2(res_px, sigma_px)
    if scale is None:
        return float(np.sum(u2))
    k2 = scale**2
    tail = u2 > k2
    return float(np.sum(u2[~tail]) + np.sum(k2 + k2 * np.log1p((u2[tail] - k2) / k2)))
