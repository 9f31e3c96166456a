"""Precision of the published estimates: cofactors scaled by the a posteriori σ0, and the
r.m.s. of the GP standard errors (seed 003 §4.4). Shared by Sim and the sequential
estimators (docs/algorithm.md)."""

from __future__ import annotations

import numpy as np

from seqat.types import FloatArray


def sigma_scale(sigma0: float, redundancy: int) -> float:
    """Factor applied to cofactors' square roots: the a posteriori sigma0 (1 without redundancy)."""
    return sigma0 if redundancy > 0 and np.isfinite(sigma0) else 1.0


def rms_point_sigma(variances_m2: FloatArray) -> tuple[float, float, float]:
    """r.m.s. of the GP standard errors per coordinate (seed 003 §4.4).

    Parameters
    ----------
    variances_m2 : (m, 3) float
        Variances of X, Y, Z of each point.

    Returns
    -------
    tuple of 3 float
        Metres, over the points whose three variances are > 0 (:func:`deviations`: the
        others have no sigma; an unconverged initial block of 8 images, its second INS
        45 deg off, had 126 of its points' 261 variances <= 0 and took the root of a
        negative mean); NaN without such points.
    """
    var = np.asarray(variances_m2, dtype=np.float64).reshape(-1, 3)
    var = var[np.all(np.isfinite(deviations(var)), axis=1)]
    if var.shape[0] == 0:
        return (float("nan"),) * 3  # type: ignore[return-value]
    rms = np.sqrt(np.mean(var, axis=0))
    return (float(rms[0]), float(rms[1]), float(rms[2]))


def deviations(variances: FloatArray) -> FloatArray:
    """Standard deviations of ``variances``; NaN for a variance <= 0: a block the data do not
    determine to rounding (a second image 60 deg off: reduced system of condition 1e14; an
    image of a least-squares block gone astray), no sigma rather than the root of a
    negative number."""
    return np.sqrt(np.where(variances > 0, variances, np.nan))
