"""Sim (seed 000 §2.1): known answers and agreement with truth on seeded strips."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.geometry import intersect_rays, nearest_branch, project, rotation_matrix, wrap_angle
from seqat.normals import full_normal, linearise, weighted_ssr
from seqat.simulate import SimulatedFlight
from seqat.simultaneous import BlockData, Covariance, SimOptions, SimultaneousAT, adjust_block

#: Noise-free data must be reproduced to this (metres / radians).
EXACT_TOL = 1e-6
#: Two computations of one cofactor agree to this, on the correlation scale.
CORRELATION_TOL = 1e-9


def _solve(flight: SimulatedFlight) -> SimultaneousAT:
    sim = SimultaneousAT(flight.camera, SimOptions(), refit_every_frame=False)
    for fr in flight.frames():
        sim.add_frame(fr)
    return sim


def test_noise_free_block_returns_truth(short_strip: SimulatedFlight) -> None:
    f = short_strip
    exact = project(f.truth_eop[f.obs_image], f.truth_xyz[f.obs_point], f.camera)
    clean = dataclasses.replace(f, obs_uv=exact, nav_eop=f.truth_eop.copy())
    sol = _solve(clean).solution()
    E = np.array([e.eop for e in sol.eops])
    np.testing.assert_allclose(E[:, :3], f.truth_eop[:, :3], rtol=0, atol=EXACT_TOL)
    np.testing.assert_allclose(E[:, 3:], f.truth_eop[:, 3:], atol=EXACT_TOL)
    assert sol.sigma0 < 1e-4


def test_sim_improves_on_direct_georeferencing(short_strip: SimulatedFlight) -> None:
    f = short_strip
    sol = _solve(f).solution()
    E = np.array([e.eop for e in sol.eops])
    err_att = np.sqrt(np.mean((E[:, 3:] - f.truth_eop[:, 3:]) ** 2))
    nav_att = np.sqrt(np.mean((f.nav_eop[:, 3:] - f.truth_eop[:, 3:]) ** 2))
    assert err_att < 0.8 * nav_att
    # GPs: far better than intersecting with the GPS/INS orientation.
    idx = {p: i for i, p in enumerate(f.point_ids)}
    P = np.array([p.xyz_m for p in sol.points])
    T = f.truth_xyz[[idx[p.point_id] for p in sol.points]]
    X_dir, _ = intersect_rays(
        f.nav_eop[f.obs_image], f.obs_uv, f.obs_point, len(f.point_ids), f.camera
    )
    rmse_dir = np.sqrt(np.mean((X_dir - f.truth_xyz) ** 2))
    assert np.sqrt(np.mean((P - T) ** 2)) < 0.5 * rmse_dir
    assert 0.8 < sol.sigma0 < 1.2


def test_sigmas_describe_the_errors(short_strip: SimulatedFlight) -> None:
    f = short_strip
    sol = _solve(f).solution()
    E = np.array([e.eop for e in sol.eops])
    S = np.array([e.sigma for e in sol.eops])
    z = (E - f.truth_eop) / S
    # Normalised errors of a consistent estimator have r.m.s. ~ 1 (loose: few, correlated samples).
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.6


def _local_block(f: SimulatedFlight) -> tuple[BlockData, np.ndarray, np.ndarray]:
    origin = np.array([f.nav_eop[0, 0], f.nav_eop[0, 1], 0.0])
    nav = f.nav_eop.copy()
    nav[:, :3] -= origin
    data = BlockData(
        nav_eop=nav,
        nav_sigma=np.tile(f.nav_sigma, (len(f.image_ids), 1)),
        obs_image=f.obs_image,
        obs_point=f.obs_point,
        obs_uv=f.obs_uv,
        obs_sigma_px=np.full(f.obs_image.size, f.sigma_px),
        n_points=len(f.point_ids),
    )
    return data, nav, f.truth_xyz - origin


def test_block_and_full_cofactors_agree(short_strip: SimulatedFlight) -> None:
    data, eop0, gp0 = _local_block(short_strip)
    full = adjust_block(short_strip.camera, data, eop0, gp0, covariance=Covariance.FULL)
    blocks = adjust_block(short_strip.camera, data, eop0, gp0, covariance=Covariance.BLOCKS)
    assert full.full_cofactor is not None and full.eop_cofactor is not None
    assert (
        blocks.eop_cofactor is not None
        and blocks.gp_cofactor is not None
        and full.gp_cofactor is not None
    )
    for a, b in ((blocks.eop_cofactor, full.eop_cofactor), (blocks.gp_cofactor, full.gp_cofactor)):
        sd = np.sqrt(np.diagonal(b, axis1=1, axis2=2))
        scale = sd[:, :, None] * sd[:, None, :]  # compare on the correlation scale
        np.testing.assert_allclose(a / scale, b / scale, rtol=0, atol=CORRELATION_TOL)
    Q = full.full_cofactor
    np.testing.assert_allclose(Q, Q.T, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(Q) > 0)


def test_an_unconverged_block_returns_the_normal_matrix_at_its_estimate(
        short_strip: SimulatedFlight) -> None:
    """Stopped by max_iterations, the block's normal matrix is the one at the estimate it
    returns, not one Gauss-Newton step before (the sequential stage takes it as its
    window's information and later takes the rays' rows out of it as linearised at the
    estimate: the difference was indefinite, a self-calibrated initial block stopped the
    flight)."""
    data, eop0, gp0 = _local_block(short_strip)
    eop0 = eop0 + np.array([2.0, -2.0, 1.0, 0.02, -0.02, 0.03])  # a few iterations away
    opts = SimOptions(max_iterations=2)
    res = adjust_block(short_strip.camera, data, eop0, gp0, opts, Covariance.FULL)
    assert not res.converged and res.full_normal is not None
    nrm, _, _ = linearise(short_strip.camera, data, res.eop, res.gp, 0.0, opts.robust_scale)
    expected = full_normal(nrm, data.n_images, data.n_points)
    scale = np.sqrt(np.outer(np.diagonal(expected), np.diagonal(expected)))
    np.testing.assert_allclose(res.full_normal / scale, expected / scale, rtol=0, atol=1e-12)


def test_the_normal_mode_returns_the_full_modes_normal_matrix_alone(
        short_strip: SimulatedFlight) -> None:
    """``Covariance.NORMAL`` (the sequential information engine's start) returns the very
    normal matrix ``FULL`` does, and no inverse of it."""
    data, eop0, gp0 = _local_block(short_strip)
    eop0 = eop0 + np.array([2.0, -2.0, 1.0, 0.02, -0.02, 0.03])
    for opts in (SimOptions(), SimOptions(max_iterations=2)):  # converged, and stopped short
        full = adjust_block(short_strip.camera, data, eop0, gp0, opts, Covariance.FULL)
        normal = adjust_block(short_strip.camera, data, eop0, gp0, opts, Covariance.NORMAL)
        assert normal.full_cofactor is None and normal.eop_cofactor is None
        assert full.full_normal is not None and normal.full_normal is not None
        np.testing.assert_array_equal(normal.full_normal, full.full_normal)
        np.testing.assert_array_equal(normal.eop, full.eop)
        if not full.converged:
            assert full.model_step is not None and normal.model_step is not None
            np.testing.assert_array_equal(normal.model_step, full.model_step)


@pytest.mark.parametrize("self_calibrating", [False, True])
def test_the_dense_and_the_sparse_reduced_systems_agree(
        short_strip: SimulatedFlight, self_calibrating: bool,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A small block's reduced system is formed dense (its points eliminated one by one)
    and a large one's sparse: the same step, normal matrix and cofactors either way, with
    the camera free and with damping."""
    import seqat.normals as normals
    from seqat.calibration import FreeCamera
    from seqat.normals import CameraBlock, back_substitute, full_cofactor

    data, eop0, gp0 = _local_block(short_strip)
    eop0 = eop0 + np.array([0.5, -0.5, 0.3, 0.004, -0.003, 0.005])  # a step from the minimum
    cam = short_strip.camera
    calib = None
    if self_calibrating:
        idx = np.array([0, 1, 2, 3])
        calib = CameraBlock(index=idx, prior=cam.intrinsics[idx],
                            sigma=np.array([5.0, 2.0, 2.0, 1e-3]))
        cam = FreeCamera(cam, idx).at(cam.intrinsics[idx] + np.array([3.0, -1.0, 1.0, 2e-4]))
    n, m = data.n_images, data.n_points
    got = {}
    small = normals.DENSE_REDUCED_MAX
    assert 6 * data.n_images + 4 <= small  # the block is formed dense by default
    for most in (small, 0):
        monkeypatch.setattr(normals, "DENSE_REDUCED_MAX", most)
        nrm, rhs, _ = linearise(cam, data, eop0, gp0, 1e-3, 3.0, calib)
        step = nrm.lu.solve(rhs)
        got[most] = (step, back_substitute(nrm, step), full_normal(nrm, n, m),
                     full_cofactor(nrm, n, m))
    r = 6 * n + (4 if calib else 0)
    assert got[0][0].size == r
    d = np.sqrt(np.diagonal(got[0][2]))  # each parameter on the scale of its information
    dense, sparse = got[small], got[0]
    for a, b, unit in [(dense[0], sparse[0], d[:r]), (dense[1].ravel(), sparse[1].ravel(), d[r:]),
                       (dense[2], sparse[2], 1.0 / np.outer(d, d)),
                       (dense[3], sparse[3], np.outer(d, d))]:
        np.testing.assert_allclose(a * unit, b * unit, rtol=0,
                                   atol=1e-11 * np.max(np.abs(b * unit)))


def test_adjust_block_rejects_non_finite_start(short_strip: SimulatedFlight) -> None:
    from seqat.errors import EstimationError

    data, eop0, gp0 = _local_block(short_strip)
    with pytest.raises(EstimationError, match="finite"):
        adjust_block(short_strip.camera, data, eop0, np.full_like(gp0, np.nan))


def test_a_step_is_taken_only_into_the_models_domain() -> None:
    # From a start of infinite cost (a point behind a camera) a step of infinite cost, such as
    # one whose focal length is <= 0, was taken (inf <= inf): the next camera raised an input
    # error in the middle of a solve (a least-squares Sim of the real flight's take-off).
    from seqat.adjustment import _accepted

    assert not _accepted(np.inf, np.inf)
    assert not _accepted(np.nan, 10.0)
    assert _accepted(1e6, np.inf)
    assert _accepted(10.0, 10.0) and not _accepted(11.0, 10.0)


def test_damped_steps_reach_the_minimum_from_far_away(short_strip: SimulatedFlight) -> None:
    """Real flights start far from the solution: attitudes 8 deg off, points 20 m off.

    Gauss-Newton from there overshoots; the damped (Levenberg-Marquardt) steps must still
    reach the minimum that a start at the truth finds, and the cost must never rise. σ0's
    sum ``Σ w v²`` is not stationary at the robust minimum: it agrees to first order in
    the 1 µm steps where both stop (1e-8), the robust cost to the last digits.
    """
    data, nav, truth_gp = _local_block(short_strip)
    rng = np.random.default_rng(7)
    loose = dataclasses.replace(data, nav_sigma=np.tile([5.0, 5.0, 5.0, 0.3, 0.3, 0.3],
                                                       (len(nav), 1)))
    truth_eop = short_strip.truth_eop.copy()
    truth_eop[:, :3] -= short_strip.nav_eop[0, :3] * np.array([1.0, 1.0, 0.0])
    far_eop = nav.copy()
    far_eop[:, 3:] += np.radians(8.0) * rng.choice([-1.0, 1.0], size=(len(nav), 3))
    far_gp = truth_gp + rng.normal(0.0, 20.0, truth_gp.shape)
    opts = SimOptions(max_iterations=60)
    ref = adjust_block(short_strip.camera, loose, truth_eop, truth_gp, opts, Covariance.NONE)
    got = adjust_block(short_strip.camera, loose, far_eop, far_gp, opts, Covariance.NONE)
    assert ref.converged and got.converged
    np.testing.assert_allclose(got.eop, ref.eop, rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.gp, ref.gp, atol=1e-6)
    assert got.weighted_ssr == pytest.approx(ref.weighted_ssr, rel=1e-8)
    assert weighted_ssr(short_strip.camera, loose, got.eop, got.gp, opts.robust_scale) == \
        pytest.approx(weighted_ssr(short_strip.camera, loose, ref.eop, ref.gp,
                                   opts.robust_scale), rel=1e-12)


def test_a_solution_before_any_point_is_adjusted(short_strip: SimulatedFlight) -> None:
    """One image: its observations are not yet points of the block; the solution has the
    image and no point (the rule on disagreeing rays has nothing to judge; it once indexed
    an empty selection)."""
    sim = SimultaneousAT(short_strip.camera, SimOptions())
    sim.add_frame(next(short_strip.frames()))
    sol = sim.solution()
    assert len(sol.eops) == 1 and sol.points == () and sim.disagreeing == []


def test_an_image_the_block_does_not_determine_has_no_sigma_not_a_negative_variance(
        short_strip: SimulatedFlight) -> None:
    """Two images, the second's INS 60 deg off in roll: the block's reduced system has
    condition 1e14 and the second image's height cofactor came out -0.9 (its sigma the
    root of a negative number: a RuntimeWarning, NaN). A variance <= 0 now gives no sigma
    (NaN, as before the first solution); the others stay positive."""
    frames = list(short_strip.frames())
    nav = frames[1].nav_eop.copy()
    nav[3] += np.radians(60.0)
    frames[1] = dataclasses.replace(frames[1], nav_eop=nav, nav_sigma=np.array(
        [5.0, 5.0, 5.0, *np.radians([10.0, 10.0, 10.0])]))
    sim = SimultaneousAT(short_strip.camera, SimOptions())
    for frame in frames[:2]:
        sigma = sim.add_frame(frame).eop.sigma  # (RuntimeWarnings are errors in the suite)
    assert np.all(np.isnan(sigma) | (sigma > 0))
    # the solution too (it took the root: a least-squares Sim of the real flight's take-off
    # printed the warning and wrote NaN); a point is published only with positive variances
    sol = sim.solution()
    for e in sol.eops:
        assert np.all(np.isnan(e.sigma) | (e.sigma > 0))
    assert all(np.all(p.sigma_m > 0) for p in sol.points)


def test_the_euler_branch_of_the_gps_ins(short_strip: SimulatedFlight) -> None:
    """``Rx(w + pi) Ry(pi - p) Rz(k + pi)`` is ``Rx(w) Ry(p) Rz(k)``. An adjustment can reach
    that branch (a turn of a rendered weak-GPS block ended at omega -182, phi 182, kappa 855
    degrees in Sim); there the GPS/INS prior, compared angle by angle, is ~180 degrees off:
    the robust loss dropped it and the angles were published as they were. Started there
    (and 4 pi further in kappa), Sim returns the solution of the usual start, its angles on
    the GPS/INS's branch, every GPS/INS group kept."""
    frames = list(short_strip.frames())

    def solve(first_start: np.ndarray | None) -> SimultaneousAT:
        sim = SimultaneousAT(short_strip.camera, SimOptions(), refit_every_frame=False)
        for k, fr in enumerate(frames):
            sim.add_frame(dataclasses.replace(fr, initial_eop=first_start) if k == 0 else fr)
        return sim

    ref = solve(None)
    other = frames[0].nav_eop.copy()
    other[3:] = other[3:] * np.array([1.0, -1.0, 1.0]) + np.array([np.pi, np.pi, 5 * np.pi])
    got = solve(other)
    a, b = ref.solution(), got.solution()
    np.testing.assert_allclose([e.eop for e in b.eops], [e.eop for e in a.eops], atol=1e-6)
    np.testing.assert_allclose([e.sigma for e in b.eops], [e.sigma for e in a.eops],
                               rtol=1e-6)
    angles = np.array([e.eop[3:] for e in b.eops])
    assert np.all((angles >= -np.pi) & (angles < np.pi))
    assert got.nav_robust == ref.nav_robust == []


def test_nearest_branch_is_the_same_rotation() -> None:
    rng = np.random.default_rng(7)
    ref = rng.uniform(-np.pi, np.pi, (200, 3))
    ref[:, 1] = rng.uniform(-1.4, 1.4, 200)
    other = ref * np.array([1.0, -1.0, 1.0]) + np.pi + 2 * np.pi * rng.integers(-2, 3, (200, 3))
    got = nearest_branch(other, ref)
    for g, o in zip(got, other, strict=True):
        np.testing.assert_allclose(rotation_matrix(*g), rotation_matrix(*o), atol=1e-12)
    np.testing.assert_allclose(wrap_angle(got - ref), 0.0, atol=1e-12)
    assert np.all((got >= -np.pi) & (got < np.pi))
    # no reference attitude: the branch with |phi| <= pi / 2
    level = nearest_branch(other, np.full((200, 3), np.nan))
    assert np.all(np.abs(level[:, 1]) <= np.pi / 2)
    np.testing.assert_allclose(wrap_angle(level - ref), 0.0, atol=1e-12)
