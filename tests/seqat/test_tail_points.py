"""Newton on tie points with a ray in the robust loss's tail (seqat/tail_points.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

import seqat.normals as normals
import seqat.tail_points as tp
from seqat.geometry import project
from seqat.normals import BlockData
from seqat.robust import ROBUST_SCALE, ray_u2, robust_rho
from seqat.simulate import SimulatedFlight
from seqat.simultaneous import Covariance, SimOptions, adjust_block

#: Image points pushed just beyond the loss's core, in sigmas (the core ends at 3).
PUSH_SIGMA = 8.0


def _block(f: SimulatedFlight, pushed: int, seed: int) -> tuple[BlockData, np.ndarray,
                                                                 np.ndarray, np.ndarray]:
    """The strip in local coordinates, ``pushed`` points cut to three rays (their first)
    and one of them moved ``PUSH_SIGMA`` sigmas: those points' costs have a ray in the
    tail and two in the core (the strip's points have 10-22 rays, which hold a point
    whatever its tail ray's curvature)."""
    origin = np.array([f.nav_eop[0, 0], f.nav_eop[0, 1], 0.0])
    nav = f.nav_eop.copy()
    nav[:, :3] -= origin
    rng = np.random.default_rng(seed)
    points = rng.choice(len(f.point_ids), pushed, replace=False)
    keep = np.ones(f.obs_point.size, dtype=bool)
    uv = f.obs_uv.copy()
    for j in points:
        rays = np.flatnonzero(f.obs_point == j)
        keep[rays[3:]] = False
        angle = rng.uniform(0.0, 2.0 * np.pi)
        uv[rng.choice(rays[:3])] += PUSH_SIGMA * f.sigma_px * np.array([np.cos(angle),
                                                                        np.sin(angle)])
    data = BlockData(nav_eop=nav, nav_sigma=np.tile(f.nav_sigma, (len(f.image_ids), 1)),
                     obs_image=f.obs_image[keep], obs_point=f.obs_point[keep], obs_uv=uv[keep],
                     obs_sigma_px=np.full(int(keep.sum()), f.sigma_px),
                     n_points=len(f.point_ids))
    truth_eop = f.truth_eop.copy()
    truth_eop[:, :3] -= origin
    return data, truth_eop, f.truth_xyz - origin, points


def _point_cost(f: SimulatedFlight, data: BlockData, eop: np.ndarray, j: int,
                X: np.ndarray) -> float:
    sel = data.obs_point == j
    res = data.obs_uv[sel] - project(eop[data.obs_image[sel]], np.tile(X, (sel.sum(), 1)),
                                     f.camera)
    return float(np.sum(robust_rho(ray_u2(res, data.obs_sigma_px[sel]), ROBUST_SCALE)))


def _calls(f: SimulatedFlight, data: BlockData, eop: np.ndarray, gp: np.ndarray,
           skip: np.ndarray, limit: int = 60) -> tuple[np.ndarray, int]:
    """Calls until no point moves (at most ``limit``): the points and the calls."""
    for calls in range(1, limit + 1):
        gp, moved = tp.newton_on_tail_points(f.camera, data, eop, gp, ROBUST_SCALE, skip)
        if moved == 0.0:
            return gp, calls
    return gp, limit + 1


def test_tail_points_reach_their_minimum_in_a_few_steps(short_strip: SimulatedFlight,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The images held at the truth, each point with a ray 8 sigma off reaches the minimum
    of its own robust cost (a derivative-free minimiser's from the truth) to 1e-5 m, every
    call lowering its cost, in a few calls (two Newton steps each). With the IRLS curvature
    instead (the loss's own refused) it takes more than twice the calls (6 and 15): the
    curvature is what converges. Points without a tail ray, and skipped ones, are not
    moved."""
    f = short_strip
    data, eop, gp, points = _block(f, 6, seed=3)
    start = gp.copy()
    skip = np.zeros(data.n_points, dtype=bool)
    got, calls = _calls(f, data, eop, start, skip)
    np.testing.assert_array_equal(start, gp)  # input untouched
    u2 = ray_u2(data.obs_uv - project(eop[data.obs_image], gp[data.obs_point], f.camera),
                data.obs_sigma_px)
    clean = np.setdiff1d(np.arange(data.n_points), data.obs_point[u2 > ROBUST_SCALE**2])
    assert clean.size > 0 and not np.isin(points, clean).any()
    np.testing.assert_array_equal(got[clean], gp[clean])
    with monkeypatch.context() as patch:
        patch.setattr(normals, "MIN_EIGENVALUE_RATIO", np.inf)  # definite_enough refuses all
        _, irls_calls = _calls(f, data, eop, start, skip)
    assert 2 * calls < irls_calls, (calls, irls_calls)
    for j in points:
        best = minimize(lambda X, j=j: _point_cost(f, data, eop, j, X), gp[j],
                        method="Powell",
                        options={"xtol": 1e-10, "ftol": 1e-15})
        assert np.max(np.abs(got[j] - best.x)) < 1e-5
        assert _point_cost(f, data, eop, j, got[j]) <= best.fun + 1e-9
    once, _ = tp.newton_on_tail_points(f.camera, data, eop, gp, ROBUST_SCALE, skip)
    for j in points:
        assert _point_cost(f, data, eop, j, once[j]) <= _point_cost(f, data, eop, j, gp[j])
    skip[points] = True
    held, _ = tp.newton_on_tail_points(f.camera, data, eop, gp, ROBUST_SCALE, skip)
    np.testing.assert_array_equal(held[points], gp[points])


def test_a_block_with_tail_rays_converges_in_fewer_iterations_to_the_same_minimum(
        short_strip: SimulatedFlight, monkeypatch: pytest.MonkeyPatch) -> None:
    """Sim on the strip with 5 of its 48 points cut to three rays, one 8 sigma off: the
    same estimate with and without the points' Newton steps (1e-5 m: both stop at steps
    of 1 µm, converging linearly), in 16 iterations instead of 35. Not accelerated in
    either (``accelerate=False``: IRLS for the images; the block's own Newton steps are the
    next test's)."""
    f = short_strip
    data, _, gp, _ = _block(f, 5, seed=6)
    opts = SimOptions(max_iterations=200)
    fast = adjust_block(f.camera, data, data.nav_eop, gp, opts, Covariance.NONE,
                        accelerate=False)
    monkeypatch.setattr(tp, "TAIL_NEWTON_ITERATIONS", 0)
    slow = adjust_block(f.camera, data, data.nav_eop, gp, opts, Covariance.NONE,
                        accelerate=False)
    assert fast.converged and slow.converged
    np.testing.assert_allclose(fast.eop, slow.eop, rtol=0, atol=1e-5)
    np.testing.assert_allclose(fast.gp, slow.gp, rtol=0, atol=1e-5)
    assert fast.iterations <= 0.6 * slow.iterations, (fast.iterations, slow.iterations)


def test_embedded_points_are_each_points_optimum_for_the_held_images(
        short_strip: SimulatedFlight) -> None:
    """The images held at the truth and every point moved 2 m off: embedded_points brings
    each to the minimum of its own cost (least squares: the triangulation a derivative-free
    minimiser finds, to 1e-6 m) in at most four calls, each lowering every point's cost
    (Newton converges quadratically); skipped points stay where they are."""
    f = short_strip
    data, eop, gp, _ = _block(f, 0, seed=1)
    rng = np.random.default_rng(4)
    start = gp + rng.normal(0.0, 2.0, gp.shape)
    skip = np.zeros(data.n_points, dtype=bool)
    skip[:3] = True
    once, moved = tp.embedded_points(f.camera, data, eop, start, None, skip)
    assert moved > 1.0
    np.testing.assert_array_equal(once[skip], start[skip])
    got = once
    for _ in range(3):
        got, _ = tp.embedded_points(f.camera, data, eop, got, None, skip)

    def cost(j: int, X: np.ndarray) -> float:
        sel = data.obs_point == j
        res = data.obs_uv[sel] - project(eop[data.obs_image[sel]],
                                         np.tile(X, (int(sel.sum()), 1)), f.camera)
        return float(np.sum(ray_u2(res, data.obs_sigma_px[sel])))

    for j in np.flatnonzero(~skip)[:12]:
        assert cost(j, once[j]) < cost(j, start[j])
        best = minimize(lambda X, j=j: cost(j, X), gp[j], method="Powell",
                        options={"xtol": 1e-12, "ftol": 1e-16})
        assert np.max(np.abs(got[j] - best.x)) < 1e-6


def test_newton_in_the_basin_reaches_the_same_minimum_in_fewer_iterations(
        short_strip: SimulatedFlight) -> None:
    """Sim on the strip with 5 points cut to three rays, one 8 sigma off, and the sixth
    image's GPS 12 sigma off (a GNSS fault: its group in the loss's tail). Under IRLS alone
    the images creep toward the minimum; accelerated, with Newton's method on the robust
    cost once in the basin, the block reaches the same estimate (1e-5 m) in at most 60 % of
    the iterations (15 against 28). The normal matrix it exports is IRLS's at that
    estimate, never Newton's (which may be indefinite)."""
    f = short_strip
    data, _, gp, _ = _block(f, 5, seed=6)
    nav = data.nav_eop.copy()
    nav[5, 0] += 12.0 * data.nav_sigma[5, 0]
    data = BlockData(nav_eop=nav, nav_sigma=data.nav_sigma, obs_image=data.obs_image,
                     obs_point=data.obs_point, obs_uv=data.obs_uv,
                     obs_sigma_px=data.obs_sigma_px, n_points=data.n_points)
    opts = SimOptions(max_iterations=200)
    fast = adjust_block(f.camera, data, data.nav_eop, gp, opts, Covariance.NORMAL)
    slow = adjust_block(f.camera, data, data.nav_eop, gp, opts, Covariance.NORMAL,
                        accelerate=False)
    assert fast.converged and slow.converged
    assert fast.nav_weight is not None and fast.nav_weight[5, 0] < 0.5  # the fault judged
    np.testing.assert_allclose(fast.eop, slow.eop, rtol=0, atol=1e-5)
    np.testing.assert_allclose(fast.gp, slow.gp, rtol=0, atol=1e-5)
    assert fast.iterations <= 0.6 * slow.iterations, (fast.iterations, slow.iterations)
    assert fast.full_normal is not None and slow.full_normal is not None
    np.testing.assert_allclose(fast.full_normal, slow.full_normal, rtol=1e-6,
                               atol=1e-9 * np.max(np.abs(slow.full_normal)))
    assert np.linalg.eigvalsh(fast.full_normal)[0] > 0.0
