"""The robust loss (seqat.robust): its weights, and one gross blunder in Sim and Seq-R."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.robust import ROBUST_SCALE, cauchy_cost, cauchy_weight
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight
from seqat.simultaneous import SimOptions, SimultaneousAT


def test_weights_are_the_derivative_of_the_cost_and_one_inside_the_core() -> None:
    sigma = np.full(5, 0.5)
    res = np.array([[0.3, 0.4], [1.0, 1.0], [3.0, 0.0], [10.0, -5.0], [200.0, 0.0]])
    w = cauchy_weight(res, sigma, ROBUST_SCALE)
    assert np.all(w[:2] == 1.0) and np.all(np.diff(w[1:]) < 0) and w[-1] < 1e-3
    # w = d rho / d u^2, by central differences on the cost of each point
    u2 = np.sum(res**2, axis=1) / sigma**2
    for q in range(res.shape[0]):
        h = 1e-6 * max(u2[q], 1.0)
        scale = np.sqrt((u2[q] + h) / u2[q]), np.sqrt((u2[q] - h) / u2[q])
        up = cauchy_cost(res[q : q + 1] * scale[0], sigma[:1], ROBUST_SCALE)
        dn = cauchy_cost(res[q : q + 1] * scale[1], sigma[:1], ROBUST_SCALE)
        assert (up - dn) / (2 * h) == pytest.approx(w[q], rel=1e-5)
    assert cauchy_cost(res, sigma, None) == pytest.approx(float(np.sum(u2)))
    np.testing.assert_array_equal(cauchy_weight(res, sigma, None), np.ones(5))


def _blunder(f: SimulatedFlight, px: float) -> SimulatedFlight:
    """One observation 300 px off in the middle of the strip (an in-image wrong match)."""
    uv = f.obs_uv.copy()
    k = int(np.flatnonzero(f.obs_image == len(f.image_ids) // 2)[3])
    uv[k, 0] += px
    return dataclasses.replace(f, obs_uv=uv)


def _rmse(eops: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((eops[:, :3] - truth[:, :3]) ** 2, axis=1))))


@pytest.mark.parametrize("method", ["sim", "seq-r"])
def test_one_gross_blunder_does_not_move_the_robust_solution(short_strip: SimulatedFlight,
                                                             method: str) -> None:
    """Least squares: a 300 px blunder moves the cameras; with the robust loss the EOP RMSE
    stays within 10 % of the clean run's."""

    def run(f: SimulatedFlight, robust: float | None) -> np.ndarray:
        if method == "sim":
            est = SimultaneousAT(f.camera, SimOptions(robust_scale=robust),
                                 refit_every_frame=False)
        else:
            est = SequentialAT(f.camera, SequentialOptions(robust_scale=robust))
        for fr in f.frames():
            est.add_frame(fr)
        if method != "sim":
            est.finish()
        return np.array([e.eop for e in est.solution().eops])

    bad = _blunder(short_strip, 300.0)
    truth = short_strip.truth_eop
    clean = _rmse(run(short_strip, ROBUST_SCALE), truth)
    robust = _rmse(run(bad, ROBUST_SCALE), truth)
    plain = _rmse(run(bad, None), truth)
    assert robust <= 1.10 * clean
    assert plain > robust
