"""Robust weighting of image points: a least-squares core with a Cauchy tail, by iteratively
re-weighted least squares (IRLS).

One wrong tie point (a repeated texture matched to the wrong field corner) must not move the
solution (docs/algorithm.md, *Robust loss (default)*). Each image point's squared normalised
residual ``u² = |v|² / σ²`` (both coordinates) enters the cost through

    ρ(u²) = u²                              for u² ≤ k²,
    ρ(u²) = k² + k² ln(1 + (u² − k²) / k²)   beyond,

with ``k`` the scale in σ (``robust_scale``; the options' default :data:`ROBUST_SCALE` = 3;
None is least squares, the paper's estimator). The IRLS weight is ``ρ'(u²)``: 1
for every point within ``k`` σ (98.9 % of Gaussian 2D errors: clean data are adjusted by
least squares, unchanged), then ``k² / u²``-like: a point 40σ off keeps 0.6 % of its weight
and pulls on the solution by less than ``k`` σ. Sim re-weights every Gauss-Newton iteration;
Seq-F / Seq-R weight each new image's rows in every update iteration (the first one least
squares: its start values may be 20° off) and the window re-linearisation keeps those
weights. GPS/INS rows stay least squares (their faults are the data snooping's,
docs/algorithm.md, *Blunders*). Why it is the default: docs/algorithm.md.
"""

from __future__ import annotations

import numpy as np

from seqat.types import FloatArray

#: Default robust scale (sigmas) of SimOptions and SequentialOptions.
ROBUST_SCALE = 3.0


def _u2(res_px: FloatArray, sigma_px: FloatArray) -> FloatArray:
    res = np.asarray(res_px, dtype=np.float64).reshape(-1, 2)
    return np.sum(res**2, axis=1) / np.asarray(sigma_px, dtype=np.float64).reshape(-1) ** 2


def robust_weight(u2: FloatArray, scale: float | None) -> FloatArray:
    """``ρ'(u²)`` of squared normalised residuals ``u2`` (k,): the IRLS weight factor."""
    u2 = np.asarray(u2, dtype=np.float64)
    if scale is None:
        return np.ones(u2.size)
    k2 = scale**2
    return 1.0 / (1.0 + np.maximum(u2 - k2, 0.0) / k2)


def robust_cost(u2: FloatArray, scale: float | None) -> float:
    """``Σ ρ(u²)`` of squared normalised residuals ``u2`` (``Σ u²`` without a scale)."""
    u2 = np.asarray(u2, dtype=np.float64)
    if scale is None:
        return float(np.sum(u2))
    k2 = scale**2
    tail = u2 > k2
    return float(np.sum(u2[~tail]) + np.sum(k2 + k2 * np.log1p((u2[tail] - k2) / k2)))


def cauchy_weight(res_px: FloatArray, sigma_px: FloatArray, scale: float | None) -> FloatArray:
    """IRLS weight factor in (0, 1] of each image point (k,) from its residual (k, 2)."""
    return robust_weight(_u2(res_px, sigma_px), scale)


def cauchy_cost(res_px: FloatArray, sigma_px: FloatArray, scale: float | None) -> float:
    """``Σ ρ(u²)`` of the image points (``Σ u²`` without a scale: least squares)."""
    return robust_cost(_u2(res_px, sigma_px), scale)
