"""The one root-mean-square of the pipeline: per-axis RMSE of ``(k, 3)`` differences."""

from __future__ import annotations

import numpy as np

from seqat.types import FloatArray

Triple = tuple[float, float, float]
NAN3: Triple = (float("nan"), float("nan"), float("nan"))


def rmse(diff: FloatArray) -> Triple:
    """Per-column root-mean-square of ``(k, 3)`` differences (NaN triple when ``k == 0``)."""
    if diff.shape[0] == 0:
        return NAN3
    r = np.sqrt(np.mean(diff**2, axis=0))
    return (float(r[0]), float(r[1]), float(r[2]))
