"""Seq-R window selection by correlation (seed 000 §2.3, Fig. 2).

The correlation between two images is the largest absolute correlation coefficient in the
6x6 block of their EOPs taken from the cofactor matrix the sequential update already holds.
Images are scanned from the oldest; the first one whose correlation with the *last* image
reaches the threshold starts the window, and every later image stays in it ("first over
threshold"), whatever its own correlation.
"""

from __future__ import annotations

import numpy as np

from seqat.types import EOP_SIZE, FloatArray


def eop_correlations(Q: FloatArray, eop_offsets: np.ndarray, last_offset: int) -> FloatArray:
    """Max |rho| of each image's EOP block against the last image's EOP block.

    Parameters
    ----------
    Q : (n, n) float
        Cofactor of the window parameters.
    eop_offsets : (W,) int
        Offset in ``Q`` of the EOP block of each window image, oldest first.
    last_offset : int
        Offset of the last image's EOP block.

    Returns
    -------
    (W,) float
        In ``[0, 1]``; the last image's own value is 1.
    """
    last = last_offset + np.arange(EOP_SIZE)
    return correlations_from_columns(Q[:, last], np.diagonal(Q), eop_offsets, last_offset)


def correlations_from_columns(q_last: FloatArray, q_diag: FloatArray, eop_offsets: np.ndarray,
                              last_offset: int) -> FloatArray:
    """:func:`eop_correlations` from the last image's cofactor columns ``Q[:, last]`` (n, 6)
    and the diagonal of ``Q``: what a factorised engine recovers without forming ``Q``."""
    idx = (eop_offsets[:, None] + np.arange(EOP_SIZE)).ravel()
    last = last_offset + np.arange(EOP_SIZE)
    sd = np.sqrt(q_diag)
    rho = q_last[idx] / (sd[idx, None] * sd[None, last])
    return np.minimum(np.max(np.abs(rho).reshape(-1, EOP_SIZE * EOP_SIZE), axis=1), 1.0)


def first_over_threshold(correlations: FloatArray, threshold: float) -> int:
    """Index of the first image (oldest first) whose correlation reaches ``threshold``.

    The last image always qualifies (its correlation with itself is 1), so the result is in
    ``[0, W-1]``.
    """
    over = np.flatnonzero(correlations >= threshold)
    return int(over[0]) if over.size else len(correlations) - 1
