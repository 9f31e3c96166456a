"""A GPS/INS blunder: an image's INS attitude tens of degrees off with a sigma of 0.1 deg
(docs/algorithm.md, *A poor start*, *A wrong GPS/INS*). Its rays, not its GPS/INS, place the
image; the GPS/INS group is named (``nav_downweighted`` in the initial block, ``nav_robust``
in the sequential stage), and no other image pays for it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from seqat.calibration import SelfCalibration
from seqat.geometry import wrap_angle
from seqat.sequential import SequentialAT, SequentialOptions
from seqat.simulate import SimulatedFlight, StripSimConfig, simulate_strip
from seqat.types import Frame

#: A strip dense enough for an image's rays to outweigh a tight INS (~40 rays per image).
DENSE_STRIP = StripSimConfig(n_images=40, n_points=200)
#: A tactical-grade INS: the attitude sigma the blunder is measured against.
TIGHT_ATTITUDE_SIGMA = np.radians(0.1)


@pytest.fixture(scope="module")
def dense_strip() -> SimulatedFlight:
    return simulate_strip(DENSE_STRIP, seed=11)


@pytest.fixture(scope="module")
def clean(dense_strip: SimulatedFlight) -> np.ndarray:
    return _run(dense_strip, list(dense_strip.frames()))[1]


#: A resection start near the truth (m, rad), as the tracker's on known points gives it.
RESECTION_OFFSET = np.r_[0.2, -0.2, 0.1, np.radians([0.05, -0.05, 0.05])]


def _blunder(flight: SimulatedFlight, k: int, att_deg: tuple[float, float, float],
             resection: bool, start_offset: np.ndarray = RESECTION_OFFSET) -> list[Frame]:
    """The flight's frames, image ``k``'s INS attitude ``att_deg`` off with a sigma of
    0.1 deg; ``resection``: its start (``initial_eop``) ``start_offset`` from the truth."""
    frames = list(flight.frames())
    f = frames[k]
    nav = f.nav_eop.copy()
    nav[3:] += np.radians(att_deg)
    sigma = f.nav_sigma.copy()
    sigma[3:] = TIGHT_ATTITUDE_SIGMA
    start = flight.truth_eop[k] + start_offset if resection else None
    frames[k] = dataclasses.replace(f, nav_eop=nav, nav_sigma=sigma, initial_eop=start)
    return frames


def _run(flight: SimulatedFlight, frames: list[Frame]) -> tuple[SequentialAT, np.ndarray]:
    est = SequentialAT(flight.camera, SequentialOptions())
    for frame in frames:
        est.add_frame(frame)
    return est, np.array([e.eop for e in est.solution(smoothed=False).eops])


def _assert_near_truth(flight: SimulatedFlight, eop_k: np.ndarray, k: int) -> None:
    """Image ``k``'s EOP ``eop_k`` within 1 m and 0.2 deg of the truth."""
    err = eop_k - flight.truth_eop[k]
    assert np.all(np.abs(err[:3]) < 1.0)
    assert np.all(np.degrees(np.abs(wrap_angle(err[3:]))) < 0.2)


def _assert_named(est: SequentialAT, k: int, group: str) -> None:
    """Image ``k``'s GPS/INS ``group``, and it alone, reported in ``nav_robust`` with a
    weight under 0.01."""
    named = [(g, w) for image, g, w in est.nav_robust if image == f"img_{k + 1:04d}"]
    assert [g for g, _ in named] == [group] and named[0][1] < 0.01


def _assert_placed_by_its_rays(flight: SimulatedFlight, eop: np.ndarray, clean: np.ndarray,
                               k: int) -> None:
    """Image ``k`` within 1 m and 0.2 deg of the truth, the others within 5 % of the clean
    run's position r.m.s."""
    _assert_near_truth(flight, eop[k], k)
    others = np.arange(len(eop)) != k
    rms = [float(np.sqrt(np.mean((e[others, :3] - flight.truth_eop[others, :3]) ** 2)))
           for e in (eop, clean)]
    assert rms[0] <= 1.05 * rms[1]


@pytest.mark.parametrize(("k", "att_deg", "resection"), [
    (3, (0.0, 45.0, 0.0), False), (3, (0.0, 45.0, 0.0), True), (1, (0.0, 0.0, 150.0), False),
    (5, (0.0, 0.0, 90.0), False), (1, (0.0, 45.0, 0.0), False), (2, (40.0, 0.0, 0.0), False)],
    ids=["4th-pitch-45", "4th-pitch-45-resected", "2nd-heading-150", "6th-heading-90",
         "2nd-pitch-45", "3rd-roll-40"])
def test_a_wrong_gps_ins_in_the_initial_block_is_left_free_and_named(
        dense_strip: SimulatedFlight, clean: np.ndarray, k: int,
        att_deg: tuple[float, float, float], resection: bool) -> None:
    """Sim weighs the GPS/INS by least squares until the block converges. Before: the
    fourth image's INS 45 deg off kept the block from converging and the flight ended with
    18 images diverged, the image 44 deg off with a sigma of 0.3 deg (on a sparser strip:
    "adjustment diverges", the flight stopped); the second image's heading 150 deg off
    ended 150 deg off with a sigma of 0.1 deg, silently. Now a GPS/INS group far beyond
    the loss's core at the image's resection on points three other images determine (or,
    on two-ray points, the culprit's after the blame) is left free and named, and the
    image is placed by its rays. The second image's pitch 45 deg off and the third's roll
    40 deg off ended at their INS with all their rays rejected, unnamed (a block of two or
    three fits a tight INS): now the initial block, when handed over, starts again every
    image its rays reject."""
    f = dense_strip
    est, eop = _run(f, _blunder(f, k, att_deg, resection))
    image = f"img_{k + 1:04d}"
    assert est.diverged == []
    assert (image, "attitude") in est.nav_downweighted
    assert [n for n in est.nav_downweighted if n[0] != image] == []
    _assert_placed_by_its_rays(f, eop, clean, k)


def test_a_wrong_gps_ins_in_the_sequential_stage_gives_way_to_the_resection(
        dense_strip: SimulatedFlight, clean: np.ndarray) -> None:
    """Image 31's INS heading 150 deg off at 0.1 deg, its start the tracker's resection:
    the update's least-squares GPS/INS pull took the image from its resection to the INS as
    the ray loss down-weighted the rays, and the image was named and carried by the INS.
    Now the GPS/INS loss of a group far from a resection is on from the first robust
    iterate, and an image its own rays fix (at least 8, most of them) is not diverged for
    its distance from the GPS/INS: the image ends where its rays put it and the group is
    named with weight ~0."""
    f, k = dense_strip, 30
    est, eop = _run(f, _blunder(f, k, (0.0, 0.0, 150.0), resection=True))
    assert est.diverged == []
    _assert_named(est, k, "attitude")
    _assert_placed_by_its_rays(f, eop, clean, k)


@pytest.mark.parametrize(("k", "att_deg"), [(20, (0.0, 0.0, 90.0)), (30, (0.0, 0.0, 150.0)),
                                            (25, (30.0, 30.0, 30.0))],
                         ids=["21st-heading-90", "31st-heading-150", "26th-30-each-axis"])
def test_a_wrong_gps_ins_gives_way_to_the_resection_with_the_camera_free(
        dense_strip: SimulatedFlight, k: int, att_deg: tuple[float, float, float]) -> None:
    """Self-calibration, image ``k``'s INS far off at 0.1 deg, its start the tracker's
    resection: the GPS/INS loss came on from the first robust iterate only, so the
    least-squares iterate before it pulled the image towards its INS and the free camera
    with it (a flight folder's 21st image, 90 deg: 17 deg and the focal length -2800 px);
    ten iterates did not come back, and the image was diverged and carried by its INS, 90 or
    150 deg off with a sigma of 0.1 deg, until the final check. A group found wrong at a
    start the rays hold is now weighed by its loss from the first iterate: the update itself
    (the real-time estimate, not only the final one) places the image by its rays."""
    f = dense_strip
    est = SequentialAT(f.camera, SequentialOptions(calibration=SelfCalibration()))
    frames = _blunder(f, k, att_deg, resection=True)
    updates = [est.add_frame(frame) for frame in frames]
    assert est.diverged == []
    live = updates[k]  # the image's own update
    _assert_near_truth(f, live.eop.eop, k)
    assert live.observations_used >= 0.9 * len(frames[k].point_ids)
    _assert_named(est, k, "attitude")


@pytest.mark.parametrize("att_deg", [(0.0, 0.0, 90.0), (30.0, 30.0, 30.0)],
                         ids=["heading-90", "30-each-axis"])
def test_a_wrong_gps_ins_gives_way_to_a_resection_on_seven_rays(
        att_deg: tuple[float, float, float]) -> None:
    """A sparse strip (~10 rays per image), the 31st image's INS far off at 0.1 deg, its
    start an attitude resection 1 deg off (the tracker's, at the GPS position): seven rays
    to known points, 75-96 sigma off at that start, so the GPS/INS was not found wrong
    there, and the update's resection with the window held was a least-squares compromise
    with an INS 900 sigma away (10 deg from where the rays put it). The image was diverged
    and carried by its INS, with the INS's sigma. Now the held resection weighs a group far
    from its start by its loss, and six rays within the core (most of them) hold an image:
    the update places it by its rays, the group named."""
    f = simulate_strip(StripSimConfig(n_images=60, n_points=48), seed=11)
    k = 30
    frames = _blunder(f, k, att_deg, resection=True,
                      start_offset=np.r_[-0.3, 0.1, 0.0, np.radians([-0.1, 0.9, 0.5])])
    est = SequentialAT(f.camera, SequentialOptions())
    updates = [est.add_frame(frame) for frame in frames]
    assert est.diverged == []
    _assert_near_truth(f, updates[k].eop.eop, k)
    _assert_named(est, k, "attitude")


@pytest.mark.parametrize("jump_m", [20.0, 100.0])
def test_a_gnss_jump_far_beyond_every_sigma_gives_way_to_the_rays(
        dense_strip: SimulatedFlight, clean: np.ndarray, jump_m: float) -> None:
    """Image 21's GNSS position ``jump_m`` off (sigma 0.3 m), no resection start (the
    tracker resects the attitude at the GPS position, which fails there): 100 m sent the
    update beyond 100 sigma of the GPS/INS from every start, and the image was diverged,
    carried by the wrong position with its rays left out. Now the update's resection with
    the window held turns the loss of the GPS/INS group far from it on, and the rays place
    the image; the group is named with weight ~0."""
    f, k = dense_strip, 20
    frames = list(f.frames())
    nav = frames[k].nav_eop.copy()
    nav[:3] += jump_m * np.array([0.6, 0.8, 0.0])
    frames[k] = dataclasses.replace(frames[k], nav_eop=nav)
    est, eop = _run(f, frames)
    assert est.diverged == []
    _assert_named(est, k, "position")
    _assert_placed_by_its_rays(f, eop, clean, k)


@pytest.mark.parametrize(("sigma_m", "jump_m"), [(0.1, 30.0), (0.05, 30.0), (0.3, 30.0),
                                                 (0.1, 15.0)])
def test_a_gnss_fault_at_a_start_resected_from_it_gives_way_to_the_rays(
        dense_strip: SimulatedFlight, clean: np.ndarray, sigma_m: float,
        jump_m: float) -> None:
    """Image 21's GNSS position ``jump_m`` off (sigma ``sigma_m``), its start the tracker's
    attitude resection *at that position* (the rays' directions turned to the wrong centre:
    tilted several degrees): ten joint iterates crawled between the rays and the GPS/INS
    and stopped short, 25 of 30 m from it (sigma 0.1 m), which the update then took for
    divergence: the image was carried by the wrong position, its rays left out, its live
    sigma that of the GPS (seen on a rendered block at sigma 0.18 m, until the final
    check). At sigma 0.05 m they stopped 27 m from the truth, 3 m from the fix, a tilt
    compensating the position (the image's rays at a median 8.5 sigma): used, the live
    estimate 27 m off. An update stopped short that far from a prior, or that most of its
    rays lie beyond the loss's core of, now starts again with the window held, as an
    unsupported one does: the rays place the image, the group is named."""
    from pipeline.run.resection import resect_attitude

    f, k = dense_strip, 20
    frames = list(f.frames())
    nav = frames[k].nav_eop.copy()
    nav[:3] += jump_m * np.array([0.6, 0.8, 0.0])
    sigma = frames[k].nav_sigma.copy()
    sigma[:3] = sigma_m
    pts = np.array([f.point_ids.index(pid) for pid in frames[k].point_ids])
    start = resect_attitude(f.truth_xyz[pts], frames[k].uv_px, f.camera, nav, 5.0).eop
    assert start is not None and np.degrees(np.abs(wrap_angle(start[3:] - f.truth_eop[k, 3:]))
                                            ).max() > 2.0  # a tilted start
    frames[k] = dataclasses.replace(frames[k], nav_eop=nav, nav_sigma=sigma, initial_eop=start)
    est = SequentialAT(f.camera, SequentialOptions())
    updates = [est.add_frame(frame) for frame in frames]
    assert est.diverged == []
    _assert_near_truth(f, updates[k].eop.eop, k)  # the live estimate, not only the final
    assert updates[k].observations_used >= 0.9 * len(frames[k].point_ids)
    named = dict((g, w) for image, g, w in est.nav_robust if image == f"img_{k + 1:04d}")
    assert named["position"] < 0.05  # 50-100 sigma off; the INS kept (30 m: weight 0.75)
    assert named.get("attitude", 1.0) > 0.5
    _assert_placed_by_its_rays(f, np.array([e.eop for e in est.solution(smoothed=False).eops]),
                               clean, k)


@pytest.mark.parametrize(("k", "att_deg"), [(1, (0.0, 45.0, 0.0)), (2, (40.0, 0.0, 0.0)),
                                            (1, (0.0, 0.0, 90.0)), (20, (0.0, 0.0, 150.0))],
                         ids=["2nd-pitch-45", "3rd-roll-40", "2nd-heading-90",
                              "21st-heading-150"])
def test_sim_adjusting_once_starts_again_the_images_their_rays_reject(
        dense_strip: SimulatedFlight, clean: np.ndarray, k: int,
        att_deg: tuple[float, float, float]) -> None:
    """Sim adjusting the flight once, from its GPS/INS (``seqat run --method sim
    --final-only``, and the final check's cold adjustment): before, the image stayed at its
    wrong INS with all its rays rejected (44.8, 39.7 and 89.8 deg off, nothing named). Now
    each image most of whose rays reject the solution is started again at its resection
    and its GPS/INS group, far from it, is left free and named."""
    from seqat.simultaneous import SimOptions, SimultaneousAT

    f = dense_strip
    sim = SimultaneousAT(f.camera, SimOptions(), refit_every_frame=False)
    for frame in _blunder(f, k, att_deg, resection=False):
        sim.add_frame(frame)
    eop = np.array([e.eop for e in sim.solution().eops])
    assert sim.diverged == []
    assert sim.nav_downweighted == [(f"img_{k + 1:04d}", "attitude")]
    _assert_placed_by_its_rays(f, eop, clean, k)
