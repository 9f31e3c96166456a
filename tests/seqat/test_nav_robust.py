"""The robust loss of the GPS/INS groups (seqat.robust): its weights, and one GNSS jump in
Sim and the sequential estimator (every default)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.errors import ConfigError
from seqat.robust import (
    NAV_ROBUST_SCALE,
    check_scale,
    nav_cost,
    nav_group_weight,
    nav_outside,
    nav_tail_curvature,
    nav_u2,
    nav_weight,
    nav_within_core,
)
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight
from seqat.simultaneous import SimOptions, SimultaneousAT

SIGMA = np.array([0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3])


def test_nav_weight_known_answers() -> None:
    """Core u² <= k² dof = 27 (k = 3, 3 DoF): weight 1; beyond, 1 / (1 + (u² - 27) / 27)."""
    u2 = np.array([0.0, 15.2, 27.0, 54.0, 270.0, 2700.0])
    np.testing.assert_allclose(nav_group_weight(u2, 3.0),
                               [1.0, 1.0, 1.0, 0.5, 0.1, 0.01], rtol=1e-12)
    np.testing.assert_array_equal(nav_group_weight(u2, None), np.ones(6))
    # a 5 m jump at 0.1 m: u² = 2500 -> 27 / 2500; the attitude group untouched
    res = np.array([[3.0, 4.0, 0.0, 1e-3, 0.0, 0.0]])
    np.testing.assert_allclose(nav_u2(res, SIGMA), [[2500.0, 1.0]])
    np.testing.assert_allclose(nav_weight(res, SIGMA, 3.0),
                               [[27 / 2500] * 3 + [1.0] * 3], rtol=1e-12)
    assert not nav_within_core(res, SIGMA, 3.0) and nav_within_core(res, SIGMA, 50.0)
    np.testing.assert_array_equal(nav_outside(res, SIGMA, 3.0), [[True, False]])
    # the loss on the attitude group alone (a sequential update turns them on one by one)
    np.testing.assert_array_equal(nav_weight(res, SIGMA, 3.0, np.array([False, True])),
                                  np.ones((1, 6)))
    assert nav_within_core(res, SIGMA, None)
    # the real flight's largest normalised position residual, 3.9 (u² = 15.2): full weight
    clean = np.array([[3.9 * 0.1 / np.sqrt(3)] * 3 + [0.0] * 3])
    assert nav_weight(clean, SIGMA, NAV_ROBUST_SCALE)[0, 0] == 1.0


def test_nav_weight_is_the_derivative_of_the_cost() -> None:
    rng = np.random.default_rng(1)
    for length in (0.05, 0.5, 0.6, 2.0, 50.0):
        d = rng.normal(size=6) * SIGMA
        d[:3] *= length / np.linalg.norm(d[:3])  # 0.05-50 m: core and tail
        u2 = nav_u2(d[None], SIGMA)[0, 0]
        h = 1e-6 * max(u2, 1.0)
        up, dn = (nav_cost(np.r_[d[:3] * np.sqrt((u2 + s) / u2), d[3:]][None], SIGMA, 3.0)
                  for s in (h, -h))
        w = nav_weight(d[None], SIGMA, 3.0)[0, 0]
        assert (up - dn) / (2 * h) == pytest.approx(w, rel=1e-5)
    assert nav_cost(d[None], SIGMA, None) == pytest.approx(float(np.sum((d / SIGMA) ** 2)))


def test_nav_tail_curvature_completes_the_hessian_of_the_cost() -> None:
    """IRLS's ``w / σ²`` plus nav_tail_curvature is half the Hessian of nav_cost (the
    normal matrix's scale), by central differences, for groups within the core (no
    correction) and in the tail (concave along the residual: its curvature there -ρ')."""
    rng = np.random.default_rng(2)
    for pos_m, att in ((0.2, 1e-3), (2.0, 1e-3), (0.2, 0.02), (5.0, 0.05)):
        d = rng.normal(size=6) * SIGMA
        d[:3] *= pos_m / np.linalg.norm(d[:3])
        d[3:] *= att / np.linalg.norm(d[3:])
        half = (np.diag(nav_weight(d[None], SIGMA, 3.0)[0] / SIGMA**2)
                + nav_tail_curvature(d[None], SIGMA, 3.0)[0])
        numeric = np.zeros((6, 6))
        for a in range(6):
            for b in range(6):
                ha, hb = 1e-3 * SIGMA[a], 1e-3 * SIGMA[b]

                def cost(sa: float, sb: float, a: int = a, b: int = b, ha: float = ha,
                         hb: float = hb, d: np.ndarray = d) -> float:
                    x = d.copy()
                    x[a] += sa * ha
                    x[b] += sb * hb
                    return nav_cost(x[None], SIGMA, 3.0)

                numeric[a, b] = (cost(1, 1) - cost(1, -1) - cost(-1, 1) + cost(-1, -1)) / (
                    8.0 * ha * hb)
        np.testing.assert_allclose(half, numeric, rtol=1e-4,
                                   atol=1e-6 * np.max(np.abs(numeric)))
        tail = nav_outside(d[None], SIGMA, 3.0)[0]
        for g, sl in enumerate((slice(0, 3), slice(3, 6))):
            block = nav_tail_curvature(d[None], SIGMA, 3.0)[0][sl, sl]
            assert np.any(block != 0.0) == tail[g]
    np.testing.assert_array_equal(nav_tail_curvature(d[None], SIGMA, None), np.zeros((1, 6, 6)))


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), float("inf"), "3"])
def test_nav_robust_scale_must_be_positive_or_null(value: object) -> None:
    for options in (SimOptions, SequentialOptions):
        with pytest.raises(ConfigError, match="nav_robust_scale"):
            options(nav_robust_scale=value)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="robust_scale"):
        check_scale("robust_scale", value)  # type: ignore[arg-type]
    SequentialOptions(nav_robust_scale=None)


def _jump(f: SimulatedFlight, image: int, seed: int) -> SimulatedFlight:
    """One nav.csv row's position 5 m off (random 3D direction)."""
    d = np.random.default_rng(seed).normal(size=3)
    nav = f.nav_eop.copy()
    nav[image, :3] += 5.0 * d / np.linalg.norm(d)
    return dataclasses.replace(f, nav_eop=nav)


def _run(f: SimulatedFlight, method: str, **kw: object) -> tuple[np.ndarray, object]:
    est: SimultaneousAT | SequentialAT
    if method == "sim":
        est = SimultaneousAT(f.camera, SimOptions(**kw), refit_every_frame=False)  # type: ignore[arg-type]
    else:
        est = SequentialAT(f.camera, SequentialOptions(**kw))  # type: ignore[arg-type]
    for fr in f.frames():
        est.add_frame(fr)
    if method != "sim":
        est.finish()  # type: ignore[union-attr]
    return np.array([e.eop for e in est.solution().eops]), est


def _rmse(eops: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((eops[:, :3] - truth[:, :3]) ** 2, axis=1))))


@pytest.mark.parametrize("method", ["sim", "seq-r"])
def test_one_gnss_jump_keeps_the_solution_near_the_clean_run(short_strip: SimulatedFlight,
                                                             method: str) -> None:
    """Every default: one 5 m GNSS position jump (in the initial Sim block, mid-strip, the
    last image) leaves the EOP RMSE within 10 % of the clean run's; the jump's group is the
    one reported down-weighted. Least-squares GPS/INS: 1.3-1.5 times the clean RMSE
    (measured), so the test can fail."""
    f = short_strip
    clean = _rmse(_run(f, method)[0], f.truth_eop)
    for image, seed in ((3, 1), (30, 2), (59, 3)):
        bad = _jump(f, image, seed)
        eop, est = _run(bad, method)
        assert _rmse(eop, f.truth_eop) <= 1.10 * clean, (image, _rmse(eop, f.truth_eop), clean)
        assert [(i, g) for i, g, _ in est.nav_robust] == [  # type: ignore[attr-defined]
            (f.image_ids[image], "position")]
        plain = _rmse(_run(bad, method, nav_robust_scale=None)[0], f.truth_eop)
        assert plain > 1.2 * clean


def test_sim_judges_the_gps_ins_once_least_squares_settles(short_strip: SimulatedFlight,
                                                             ) -> None:
    """The GPS/INS loss turns on once the least-squares cost stops falling, whether or not
    every step is below the tolerances: a point that converges linearly (a two-ray point
    under the rays' loss: 50 iterations on the rendered flight) must not keep a 5 m jump in
    least squares. Steps are made never small enough here (tolerance 0): the jump is still
    down-weighted and the RMSE stays within 10 % of the clean run (least squares: > 1.2x)."""
    f = short_strip
    clean = _rmse(_run(f, "sim")[0], f.truth_eop)
    bad = _jump(f, 30, 2)
    creeping = {"position_tolerance_m": 0.0, "angle_tolerance_rad": 0.0}
    eop, est = _run(bad, "sim", **creeping)
    assert not est._result.converged  # type: ignore[attr-defined]
    assert [(i, g) for i, g, _ in est.nav_robust] == [  # type: ignore[attr-defined]
        (f.image_ids[30], "position")]
    assert _rmse(eop, f.truth_eop) <= 1.10 * clean
    # the same estimate as the run whose steps do settle
    np.testing.assert_allclose(eop[:, :3], _run(bad, "sim")[0][:, :3], rtol=0, atol=1e-4)


def test_a_later_solve_of_the_block_keeps_its_gps_ins_outliers_judged(
        short_strip: SimulatedFlight, monkeypatch: pytest.MonkeyPatch) -> None:
    """Sim adjusts a block again within one solve (points taken out or let in) from the
    solution it has: the GPS/INS groups that solution found beyond the core stay judged
    from the first iteration (``nav_on``). A least-squares phase first pulled a 5 m jump
    back in, and on the rendered fault flight (seed 4) crept past ``max_iterations``
    without settling: Sim's jump image ended 2.35 m off (Seq-R 0.08 m)."""
    import seqat.simultaneous as sm

    bad = _jump(short_strip, 30, 2)
    sim = SimultaneousAT(short_strip.camera, SimOptions(), refit_every_frame=False)
    for fr in bad.frames():
        sim.add_frame(fr)
    sim.solution()
    res = sim._result  # type: ignore[attr-defined]
    assert res is not None and res.nav_weight[30, 0] < 0.2
    data = sim._block()[0]  # type: ignore[attr-defined]
    one = SimOptions(max_iterations=1)
    steps = {on: sm.adjust_block(short_strip.camera, data, res.eop, res.gp, one,
                                 sm.Covariance.NONE, nav_on=on) for on in (False, True)}
    moved = {on: float(np.linalg.norm(r.eop[30, :3] - res.eop[30, :3]))
             for on, r in steps.items()}
    assert moved[True] < 0.01 < 0.2 < moved[False]  # measured: 3e-8 and 1.77 m
    assert steps[True].nav_weight[30, 0] < 0.2  # type: ignore[index]
    # and a solve's second adjustment starts so (a point taken out after the first)
    seen: list[bool] = []
    orig = sm.adjust_block

    def spy(*args: object, **kw: object) -> object:
        seen.append(bool(args[7]) if len(args) > 7 else bool(kw.get("nav_on", False)))
        return orig(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(sm, "adjust_block", spy)
    once = iter([{0}])
    monkeypatch.setattr(SimultaneousAT, "_ambiguous_points",
                        lambda self, r, d, s: next(once, set()))
    sim._dirty = True  # type: ignore[attr-defined]
    sim.solution()
    assert seen == [False, True]


def test_finalised_images_keep_only_down_weighted_nav_groups(short_strip: SimulatedFlight,
                                                               ) -> None:
    """With ``smoothing_lag`` an image finalised long ago cannot re-enter the window: its
    GPS/INS rows are let go (memory flat along the flight), except the weights of a group the
    loss down-weighted, which the report still names, as without the lag."""
    f = _jump(short_strip, 3, 1)
    n = len(f.image_ids)
    _, est = _run(f, "seq-r", smoothing_lag=10)
    kept = est._nav_rows  # type: ignore[attr-defined]
    assert len(kept) < n - 20 and 3 not in kept
    assert [(i, g) for i, g, _ in est.nav_robust] == [  # type: ignore[attr-defined]
        (f.image_ids[3], "position")]
    _, whole = _run(f, "seq-r")
    assert len(whole._nav_rows) == n  # type: ignore[attr-defined]
    # the same group; its weight as it left, not re-weighted by finish() (0.11 / 0.12)
    assert [g[:2] for g in est.nav_robust] == [g[:2] for g in whole.nav_robust]  # type: ignore[attr-defined]


@pytest.mark.parametrize("method", ["sim", "seq-r"])
def test_clean_gps_ins_is_solved_as_least_squares(short_strip: SimulatedFlight,
                                                  method: str) -> None:
    """Without a jump every group lies in the core: the run equals the one with the GPS/INS
    loss off (measured: identical to the last bit) and nothing is reported."""
    on, est = _run(short_strip, method)
    off, _ = _run(short_strip, method, nav_robust_scale=None)
    assert np.max(np.abs(on - off)) <= 1e-12
    assert est.nav_robust == []  # type: ignore[attr-defined]


def test_finished_seq_f_reaches_sims_robust_minimum_with_a_jump(
        short_strip: SimulatedFlight) -> None:
    """finish() re-weights the window's GPS/INS rows until the weights settle: the finished
    Seq-F is Sim's robust minimum (the update-time weight of the jump image alone left it
    7 cm off), with the same σ0 and the same weight."""
    bad = _jump(short_strip, 30, 4)
    ref, sim = _run(bad, "sim", max_iterations=200)
    got, seq = _run(bad, "seq-f", correlation_threshold=None)
    np.testing.assert_allclose(got[:, :3], ref[:, :3], rtol=0, atol=5e-5)
    np.testing.assert_allclose(got[:, 3:], ref[:, 3:], atol=1e-6)
    assert seq.sigma0 == pytest.approx(sim.solution().sigma0, rel=1e-4)  # type: ignore[attr-defined]
    (i, g, w_seq), = seq.nav_robust  # type: ignore[attr-defined]
    (_, _, w_sim), = sim.nav_robust  # type: ignore[attr-defined]
    assert (i, g) == (short_strip.image_ids[30], "position")
    assert w_seq == pytest.approx(w_sim, abs=2e-4)
