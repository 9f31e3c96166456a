"""Published precision: the r.m.s. GP sigma and the sigmas of positive variances only."""

from __future__ import annotations

import math

import numpy as np

from seqat.precision import deviations, rms_point_sigma


def test_rms_point_sigma_known_answers_and_points_without_a_sigma() -> None:
    """Known answer (1, 2, 3) m; a point with a variance <= 0 or NaN (a block the data do
    not determine to rounding) has no sigma and is left out, not rooted; none left: NaN."""
    good = np.array([[1.0, 4.0, 9.0], [1.0, 4.0, 9.0]])
    assert rms_point_sigma(good) == (1.0, 2.0, 3.0)
    bad = np.array([[-0.2, 4.0, 9.0], [1.0, np.nan, 9.0], [1.0, 4.0, 0.0]])
    assert rms_point_sigma(np.vstack([good, bad])) == (1.0, 2.0, 3.0)
    assert all(math.isnan(v) for v in rms_point_sigma(bad))
    assert all(math.isnan(v) for v in rms_point_sigma(np.zeros((0, 3))))
    np.testing.assert_array_equal(deviations(np.array([4.0, 0.0, -1.0]))[:1], [2.0])
    assert np.isnan(deviations(np.array([4.0, 0.0, -1.0]))[1:]).all()
