"""The update's iterations from a poor GPS/INS start (seqat.iteration): an iterate outside
the models' domain and an estimate that most of the image's rays disagree with start again
with the window held; a second time the image is carried by its GPS/INS and named."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.calibration import FreeCamera, SelfCalibration
from seqat.geometry import project, resect, wrap_angle
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, StripSimConfig, simulate_strip
from seqat.types import Frame

#: A consumer INS: attitude sigma 10 deg, position 5 m (the start below is 5-15 sigma off).
NAV_SIGMA = np.array([5.0, 5.0, 5.0, *np.radians([10.0, 10.0, 10.0])])


def _poor_start(flight: SimulatedFlight, k: int, att_deg: tuple[float, float, float]
                ) -> list[Frame]:
    """The flight's frames, image ``k``'s nav attitude ``att_deg`` off (sigma NAV_SIGMA)."""
    frames = list(flight.frames())
    nav = frames[k].nav_eop.copy()
    nav[3:] += np.radians(att_deg)
    frames[k] = dataclasses.replace(frames[k], nav_eop=nav, nav_sigma=NAV_SIGMA)
    return frames


def _run(flight: SimulatedFlight, frames: list[Frame],
         calibration: SelfCalibration | None) -> tuple[SequentialAT, np.ndarray]:
    est = SequentialAT(flight.camera, SequentialOptions(calibration=calibration))
    for frame in frames:
        est.add_frame(frame)
    return est, np.array([e.eop for e in est.solution(smoothed=False).eops])


def _pos_rmse(eop: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.mean((eop[:, :3] - truth[:, :3]) ** 2)))


def _assert_recovered(flight: SimulatedFlight, eop: np.ndarray, k: int,
                      pos_m: float = 1.0) -> None:
    """Image ``k`` within ``pos_m`` and 0.5 deg of the truth on every axis."""
    err = eop[k] - flight.truth_eop[k]
    assert np.all(np.abs(err[:3]) < pos_m)
    assert np.all(np.degrees(np.abs(wrap_angle(err[3:]))) < 0.5)


def _assert_others_as_clean(flight: SimulatedFlight, eop: np.ndarray, k: int,
                            clean: np.ndarray) -> None:
    """The images but ``k`` within 5 % of the clean run's position RMSE."""
    others = np.arange(len(eop)) != k
    assert _pos_rmse(eop[others], flight.truth_eop[others]) <= 1.05 * _pos_rmse(
        clean[others], flight.truth_eop[others])


def test_an_iterate_outside_the_camera_domain_starts_again_with_the_window_held(
        short_strip: SimulatedFlight) -> None:
    """Self-calibration, image 25's INS 55 deg off on each axis: the first, least-squares
    iterate sends the focal length below zero (the flight stopped with "camera f_px must be
    a positive number", exit 2). Resected with the window held first, the image ends where
    its rays put it and the other images where the clean run has them."""
    f, k = short_strip, 25
    clean = _run(f, list(f.frames()), SelfCalibration())[1]
    est, eop = _run(f, _poor_start(f, k, (55.0, 55.0, 55.0)), SelfCalibration())
    assert est.diverged == []
    _assert_recovered(f, eop, k)
    _assert_others_as_clean(f, eop, k, clean)


@pytest.mark.parametrize(("k", "att_deg", "calibration"), [
    (30, (0.0, 0.0, 150.0), None), (30, (0.0, 0.0, 150.0), SelfCalibration()),
    (20, (50.0, 50.0, 50.0), SelfCalibration())],
    ids=["heading-150-fixed", "heading-150-self-cal", "50-each-axis-self-cal"])
def test_an_estimate_most_of_its_rays_reject_is_not_kept(
        short_strip: SimulatedFlight, k: int, att_deg: tuple[float, float, float],
        calibration: SelfCalibration | None) -> None:
    """An image of the sequential stage with its INS far off: the robust loss, on from the
    second iterate, down-weighted the image's rays as outliers of the poor start and kept a
    wrong minimum, silently (metres and tens of degrees off, not named). An estimate that
    most of the image's rays lie beyond the loss's core of is not kept: resected with the
    window held. From the INS that resection too ended where most rays disagree, and the
    image was carried by its GPS/INS and named; the held phase now starts a last time at
    the attitude of the window's last image, and the image ends where its rays put it. The
    other images keep the clean run's accuracy."""
    f = short_strip
    clean = _run(f, list(f.frames()), calibration)[1]
    est, eop = _run(f, _poor_start(f, k, att_deg), calibration)
    assert est.diverged == []
    _assert_recovered(f, eop, k, pos_m=2.0)  # its GPS sigma: 5 m
    _assert_others_as_clean(f, eop, k, clean)


def test_an_image_whose_rays_are_all_wrong_is_named_and_carried_by_its_gps_ins(
        short_strip: SimulatedFlight) -> None:
    """Image 30's image points replaced by random pixels (every match wrong): no start, the
    INS's nor the last image's attitude, gives an estimate its rays support. The image is
    carried by its GPS/INS (its sigma says so), named in ``diverged``, and the other
    images keep the clean run's accuracy."""
    f, k = short_strip, 30
    clean = _run(f, list(f.frames()), None)[1]
    frames = list(f.frames())
    rng = np.random.default_rng(5)
    size = np.array([f.camera.width_px, f.camera.height_px])
    frames[k] = dataclasses.replace(frames[k],
                                    uv_px=rng.uniform(0.0, 1.0, frames[k].uv_px.shape) * size)
    est, eop = _run(f, frames, None)
    assert est.diverged == [f"img_{k + 1:04d}"]
    nav, nav_sigma = frames[k].nav_eop, frames[k].nav_sigma
    np.testing.assert_allclose(eop[k, :3], nav[:3], atol=float(3 * nav_sigma[:3].max()))
    sigma = est.solution(smoothed=False).eops[k].sigma
    np.testing.assert_allclose(sigma, nav_sigma, rtol=0.5)
    _assert_others_as_clean(f, eop, k, clean)


def test_an_image_judged_on_too_few_rays_keeps_its_estimate(
        short_strip: SimulatedFlight) -> None:
    """Image 30 keeps three of its rays to points the earlier images determine, two of them
    wrong matches 60 σ off, and its rays to new points. Most of three rays cannot tell a
    poor start from two wrong matches (seqat.robust.MIN_JUDGED_RAYS): the estimate is kept,
    not rejected three times with the image then carried by its GPS/INS and its rays left
    out (Seneca's own tie points with a fifth of them wrong: 34 deg off). It ends where its
    good ray and its GPS/INS put it."""
    f, k = short_strip, 30
    frames = list(f.frames())
    seen = np.bincount(f.obs_point[f.obs_image < k], minlength=f.truth_xyz.shape[0])
    pids = np.array([f.point_ids.index(p) for p in frames[k].point_ids])
    known = np.flatnonzero(seen[pids] >= 2)
    keep = seen[pids] < 2
    keep[known[:3]] = True
    uv = frames[k].uv_px.copy()
    uv[known[:2]] += [[60.0 * f.sigma_px, 0.0], [0.0, -60.0 * f.sigma_px]]
    frames[k] = dataclasses.replace(frames[k], point_ids=tuple(np.array(
        frames[k].point_ids)[keep]), uv_px=uv[keep])
    est, eop = _run(f, frames, None)
    assert est.diverged == []
    _assert_recovered(f, eop, k)


def test_a_camera_iterate_is_admissible_only_with_a_positive_finite_focal_length(
        short_strip: SimulatedFlight) -> None:
    cam = FreeCamera(short_strip.camera, np.array([0, 3]))  # f_px and k1 free
    f = short_strip.camera.f_px
    assert cam.admissible(np.array([f, 0.1]))
    assert not cam.admissible(np.array([-f, 0.1]))
    assert not cam.admissible(np.array([0.0, 0.1]))
    assert not cam.admissible(np.array([f, np.nan]))
    assert FreeCamera(short_strip.camera, np.array([3])).admissible(np.array([0.2]))


@pytest.fixture(scope="module")
def clean_self_calibrated(short_strip: SimulatedFlight) -> np.ndarray:
    """The short strip's EOPs, self-calibrated, without a poor start."""
    return _run(short_strip, list(short_strip.frames()), SelfCalibration())[1]


@pytest.mark.parametrize(("k", "att_deg"), [
    (3, (0.0, 70.0, 0.0)), (3, (0.0, 0.0, 150.0)), (9, (0.0, 0.0, 150.0)),
    (1, (60.0, 0.0, 0.0)), (1, (0.0, 0.0, 150.0))],
    ids=["4th-pitch-70", "4th-heading-150", "10th-heading-150", "2nd-roll-60",
         "2nd-heading-150"])
def test_a_poor_start_in_the_initial_block_ends_where_its_rays_put_it(
        short_strip: SimulatedFlight, clean_self_calibrated: np.ndarray, k: int,
        att_deg: tuple[float, float, float]) -> None:
    """Self-calibration, an image of the initial Sim block with its INS far off. Before:
    the pitch 70 deg off stopped the flight ("camera f_px must be a positive number", exit
    2); the fourth image's heading 150 deg off ended that image 4.7 m and 1.3 deg off with
    every ray fitting (the free camera absorbed it: its focal length drifted from 4928 to
    5479 px) and the flight stopped with a singular window; the tenth's ended 88 m off.
    Now the initial block is solved with the camera held while its images arrive and
    freed when it is handed over, and an image the block does not converge with is
    started again at its resection: the image ends where its rays put it. The second
    image's heading 150 deg off has no resection in the block of two (no point seen by two
    others): it was left out, carried by its GPS/INS and named for the whole flight; now
    it is started again at its resection once the third image determines its points. The
    flight goes on as the clean one."""
    f = short_strip
    est, eop = _run(f, _poor_start(f, k, att_deg), SelfCalibration())
    assert est.diverged == []
    _assert_recovered(f, eop, k)
    _assert_others_as_clean(f, eop, k, clean_self_calibrated)


def test_an_earlier_image_whose_poor_start_fails_the_next_ones_is_started_again() -> None:
    """Seed 12, the second image's heading 150 deg off, fixed camera: in the block of two,
    where any relative orientation fits its two-ray points, the image ended 148 deg off,
    and its wrong points made each of the next eight images diverge in its place (named,
    carried by their GPS/INS). Now, before an image whose rays reject the block is left
    out, the earlier image that shares most of its points is tried as the culprit: the
    block without it fits the new image, and the culprit, started again at its resection
    on the others, fits too. No image diverges, the second ends where its rays put it."""
    f = simulate_strip(StripSimConfig(n_images=60, n_points=48), seed=12)
    k = 1
    clean = _run(f, list(f.frames()), None)[1]
    est, eop = _run(f, _poor_start(f, k, (0.0, 0.0, 150.0)), None)
    assert est.diverged == []
    _assert_recovered(f, eop, k, pos_m=1.5)
    _assert_others_as_clean(f, eop, k, clean)


@pytest.mark.parametrize(("att_deg", "calibration"), [
    ((0.0, 45.0, 0.0), SelfCalibration()), ((50.0, 50.0, 50.0), None)],
    ids=["pitch-45-self-cal", "50-each-axis-fixed"])
def test_an_earlier_image_whose_points_all_fit_two_places_is_started_again(
        att_deg: tuple[float, float, float], calibration: SelfCalibration | None) -> None:
    """Seed 12, the second image's INS far off: the block of two ended it 20-28 deg off;
    with the third image, every point the three share fitted two places (the pair of the
    good images at one, the wrong image's ray with either at another) and was held out.
    The block had no point left, and the second image stayed at its GPS/INS: at the end
    40 deg off with a sigma of 2 deg (pitch 45), or 50 deg off on each axis, neither
    named. Now an image most of whose points are held out that way makes the earlier images
    sharing them suspects, and the suspect is started again at its resection on the others
    (started also at its neighbours' attitude: from 50 deg off Gauss-Newton found none)."""
    f = simulate_strip(StripSimConfig(n_images=60, n_points=48), seed=12)
    k = 1
    clean = _run(f, list(f.frames()), calibration)[1]
    est, eop = _run(f, _poor_start(f, k, att_deg), calibration)
    assert est.diverged == []
    _assert_recovered(f, eop, k)
    _assert_others_as_clean(f, eop, k, clean)


def test_resection_recovers_a_pose_from_a_poor_start(short_strip: SimulatedFlight) -> None:
    """Noise-free rays to known points: Gauss-Newton from 20 deg and 30 m off returns the
    image's pose; fewer than 4 points, or points behind the camera, give none."""
    f = short_strip
    k = 20
    rays = np.flatnonzero(f.obs_image == k)
    X = f.truth_xyz[f.obs_point[rays]]
    uv = project(np.broadcast_to(f.truth_eop[k], (rays.size, 6)), X, f.camera)
    start = f.truth_eop[k] + np.array([30.0, -20.0, 10.0, *np.radians([20.0, -15.0, 20.0])])
    eop = resect(start, X, uv, np.full(rays.size, 0.5), f.camera)
    assert eop is not None
    np.testing.assert_allclose(eop[:3], f.truth_eop[k, :3], rtol=0, atol=1e-6)
    np.testing.assert_allclose(wrap_angle(eop[3:] - f.truth_eop[k, 3:]), 0.0, atol=1e-9)
    assert resect(start, X[:3], uv[:3], np.full(3, 0.5), f.camera) is None
    below = f.truth_eop[k].copy()
    below[2] = X[:, 2].min() - 100.0  # every point above the camera
    assert resect(below, X, uv, np.full(rays.size, 0.5), f.camera) is None
