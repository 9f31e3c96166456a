"""Streaming tracker (pipeline/tracking/tracker.py) on synthetic nadir views of a textured flat
ground.

Each view is an exact homography of a 2000 x 2000 px ground texture (0.1 m per texel, Z = 0):
the four texture corners are projected with :func:`seqat.geometry.project` and
``cv2.getPerspectiveTransform`` gives the plane-induced homography, so every emitted pixel can be
mapped back to the ground through the true homography.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.common.strict_yaml import build_dataclass
from pipeline.flight.schema import CameraConfig
from pipeline.tracking.options import TrackerOptions
from pipeline.tracking.tracker import TrackedImage, Tracker, feature_sites, read_gray_image
from seqat.errors import ConfigError, InputDataError
from seqat.geometry import project
from seqat.types import Frame, PinholeCamera

SEED = 20260611
TEXTURE_PX = 2000
TEXEL_M = 0.1
WIDTH_PX, HEIGHT_PX, F_PX = 1200, 900, 1000.0
FLYING_HEIGHT_M = 100.0  # 0.1 m ground sample: one full-resolution pixel ~ one texel
STRIP_STEP_M = 20.0  # 83 % forward overlap of the 120 m footprints
#: A track's ground points (texels ~ full-resolution pixels) agree to within this.
TRACK_TOL_PX = 1.0
#: The same for ORB (integer-pixel corners at working resolution, s = 2).
ORB_TRACK_TOL_PX = 2.0
#: Fraction of tracks that must meet TRACK_TOL_PX with the fundamental matrix (epipolar
#: verification is 1D: a few wrong matches along epipolar lines survive it).
MIN_GOOD_TRACK_FRACTION_F = 0.99

CAMERA = CameraConfig(model="PINHOLE", width_px=WIDTH_PX, height_px=HEIGHT_PX, fx_px=F_PX,
                      fy_px=F_PX, cx_px=(WIDTH_PX - 1) / 2, cy_px=(HEIGHT_PX - 1) / 2)
PINHOLE = PinholeCamera(f_px=F_PX, cx_px=CAMERA.cx_px, cy_px=CAMERA.cy_px, width_px=WIDTH_PX,
                        height_px=HEIGHT_PX)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """Seeded multi-scale smooth noise, uint8."""
    rng = np.random.default_rng(SEED)
    tex = np.zeros((TEXTURE_PX, TEXTURE_PX), np.float32)
    for sigma_px, weight in ((1.5, 1.0), (4.0, 1.5), (12.0, 2.0)):
        noise = cv2.GaussianBlur(rng.standard_normal((TEXTURE_PX, TEXTURE_PX)).astype(np.float32),
                                 (0, 0), sigma_px)
        tex += weight * noise / noise.std()
    return np.clip(128 + 40 * tex, 0, 255).astype(np.uint8)


def H_img_from_texture(eop: np.ndarray) -> np.ndarray:
    """Exact homography texture pixel -> image pixel for a flat ground at Z = 0."""
    tex_px = np.array([[0, 0], [TEXTURE_PX - 1, 0], [TEXTURE_PX - 1, TEXTURE_PX - 1],
                       [0, TEXTURE_PX - 1]], dtype=np.float64)
    world = np.c_[tex_px[:, 0] * TEXEL_M, -tex_px[:, 1] * TEXEL_M, np.zeros(4)]
    img_px = project(np.tile(eop, (4, 1)), world, PINHOLE)
    return cv2.getPerspectiveTransform(tex_px.astype(np.float32), img_px.astype(np.float32))


def render(texture: np.ndarray, eop: np.ndarray) -> np.ndarray:
    return cv2.warpPerspective(texture, H_img_from_texture(eop), (WIDTH_PX, HEIGHT_PX),
                               flags=cv2.INTER_LINEAR)


def strip_eops(n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Nadir-ish views along the texture's east-west middle, small attitude noise."""
    return [np.array([60.0 + STRIP_STEP_M * k, -100.0 + rng.uniform(-2, 2), FLYING_HEIGHT_M,
                      *np.radians(rng.uniform(-2, 2, 2)), np.radians(rng.uniform(-5, 5))])
            for k in range(n)]


@dataclass
class StripRun:
    tracker: Tracker
    eops: list[np.ndarray]
    out: list[TrackedImage]


def run_strip(texture: np.ndarray, options: TrackerOptions, n: int = 5) -> StripRun:
    eops = strip_eops(n, np.random.default_rng(SEED))
    tracker = Tracker(options, CAMERA)
    out = [tracker.add_image(f"img{k}", render(texture, e), e, 0.0) for k, e in enumerate(eops)]
    return StripRun(tracker=tracker, eops=eops, out=out)


def track_spreads_px(run: StripRun) -> np.ndarray:
    """Largest distance of a track's ground points (texels) from their mean, per track >= 2."""
    ground: dict[str, list[np.ndarray]] = {}
    for e, img in zip(run.eops, run.out, strict=True):
        H_inv = np.linalg.inv(H_img_from_texture(e))
        g = cv2.perspectiveTransform(img.uv_px.reshape(-1, 1, 2), H_inv).reshape(-1, 2)
        for pid, gp in zip(img.point_ids, g, strict=True):
            ground.setdefault(pid, []).append(gp)
    spreads = [np.max(np.linalg.norm(np.array(g) - np.mean(g, axis=0), axis=1))
               for g in ground.values() if len(g) >= 2]
    return np.array(spreads)


@pytest.fixture(scope="module")
def sift_run(texture: np.ndarray) -> StripRun:
    return run_strip(texture, TrackerOptions(working_width_px=600, emit_per_image=None))


@pytest.fixture(scope="module")
def budget_run(texture: np.ndarray) -> StripRun:
    return run_strip(texture, TrackerOptions(working_width_px=600, emit_per_image=200,
                                             emit_grid=(4, 3)))


def test_tracks_found_between_overlapping_images(sift_run: StripRun) -> None:
    stats = [o.stats for o in sift_run.out]
    assert stats[0].candidates == () and stats[0].new_tracks == 0
    assert stats[1].candidates == ("img0",)
    assert stats[1].pairs_matched == 1 and stats[1].new_tracks > 500
    # best predicted overlap first: the previous image
    assert all(s.candidates[0] == f"img{k - 1}" for k, s in enumerate(stats) if k > 0)
    assert stats[4].extended_tracks > 500
    for s in stats:
        assert s.inliers <= s.matches and s.new_tracks + s.extended_tracks <= s.features


def test_track_observations_land_on_one_ground_point(sift_run: StripRun) -> None:
    spreads = track_spreads_px(sift_run)
    assert len(spreads) > 1000
    assert np.median(spreads) < 0.3 * TRACK_TOL_PX
    assert np.mean(spreads <= TRACK_TOL_PX) >= MIN_GOOD_TRACK_FRACTION_F


def test_homography_verification_tracks_are_all_exact(texture: np.ndarray) -> None:
    run = run_strip(texture, TrackerOptions(working_width_px=600, geometry="homography",
                                            emit_per_image=None), n=3)
    spreads = track_spreads_px(run)
    assert len(spreads) > 1000
    assert np.percentile(spreads, 99) <= TRACK_TOL_PX
    assert spreads.max() <= 2 * TRACK_TOL_PX


def test_every_feature_site_emitted_once_with_unique_ids(sift_run: StripRun) -> None:
    """Without a budget every feature is emitted, but one pixel once: SIFT's second
    orientation at a pixel is a second descriptor, not a second observation."""
    seen_in: dict[str, list[int]] = {}
    for k, img in enumerate(sift_run.out):
        sites = {(float(u), float(v)) for u, v in img.uv_px}
        assert len(img.point_ids) == len(set(img.point_ids)) == len(sites) == img.stats.emitted
        assert img.stats.emitted <= img.stats.features
        assert img.uv_px.shape == (img.stats.emitted, 2)
        Frame(image_id=img.image_id, nav_eop=sift_run.eops[k], nav_sigma=np.ones(6),
              point_ids=img.point_ids, uv_px=img.uv_px)  # the estimator accepts it
        for pid in img.point_ids:
            seen_in.setdefault(pid, []).append(k)
    # no track holds two features of one image, whatever conflicts arose
    assert all(len(ks) == len(set(ks)) for ks in seen_in.values())
    assert all(pid[0] == "t" and pid[1:].isdigit() for pid in seen_in)


def test_emission_budget_keeps_tracks_and_spreads_new_points(budget_run: StripRun) -> None:
    """Every continuation is emitted; new points fill the grid cells evenly."""
    emitted_before: set[str] = set()
    for k, img in enumerate(budget_run.out):
        s = img.stats
        assert s.features > 1000 and len(img.point_ids) == s.emitted
        continuing = [p for p in img.point_ids if p in emitted_before]
        # only emitted tracks grow, and fresh ones that a late observation of a held image
        # joined (their second image)
        fresh_late = set(img.late_point_ids) - emitted_before
        assert len(continuing) + len(fresh_late) == s.new_tracks + s.extended_tracks
        assert s.emitted == max(200, len(continuing))
        fresh = np.array([uv for p, uv in zip(img.point_ids, img.uv_px, strict=True)
                          if p not in emitted_before])
        cells = np.bincount((fresh[:, 0] * 4 // WIDTH_PX).astype(int)
                            + 4 * (fresh[:, 1] * 3 // HEIGHT_PX).astype(int), minlength=12)
        if k == 0:  # 200 over 12 cells: 16 or 17 each (+-1 for points on a cell border,
            # as cells are cut at working resolution)
            assert cells.min() >= 15 and cells.max() <= 18, cells
        emitted_before.update(img.point_ids)
        emitted_before.update(img.late_point_ids)
    assert budget_run.out[-1].stats.extended_tracks > 20  # tracks still grow to 3+ images
    # every orientation at an emitted pixel carries its track (a later image may match the
    # other descriptor); a pixel without an emitted feature carries none
    for held in budget_run.tracker.state().held:
        site = feature_sites(held.kp_work)
        for s_ in np.unique(site):
            assert len(set(held.point_nums[site == s_].tolist())) == 1
        # 200 emitted with the image, more later as late observations (capped per pair)
        late_sites = np.unique(site[held.late[:, 0]]).size if len(held.late) else 0
        assert np.unique(held.point_nums[held.point_nums >= 0]).size <= 200 + late_sites


def test_conflicting_links_are_split_not_merged() -> None:
    tracker = Tracker(TrackerOptions(), CAMERA)
    tracker._tracks = {7: [2, 2], 9: [1, 1]}
    tracker._next_point = 10
    # feature 0: track 7 via two images, track 9 via one -> 7 (support), a conflict;
    # feature 1 also claims 7 with a larger distance -> loses, fresh id, a conflict;
    # feature 2: track 9 alone; feature 3: unmatched
    links = {0: [(7, 0, 100.0), (7, 1, 120.0), (9, 2, 50.0)], 1: [(7, 0, 150.0)],
             2: [(9, 1, 80.0)]}
    nums, n_new, n_ext, conflicts = tracker._assign(4, links)
    assert nums.tolist() == [7, -1, 9, -1]  # -1: numbered when emitted
    assert (n_new, n_ext, conflicts) == (1, 1, 2)
    assert tracker._tracks[7] == [3, 3] and tracker._tracks[9] == [2, 2]


def test_features_at_one_pixel_continue_one_track() -> None:
    """Features 0 and 1 share a pixel (two SIFT orientations): only the closer match
    continues its track, the other is a conflict and is not emitted as a new point."""
    tracker = Tracker(TrackerOptions(), CAMERA)
    tracker._tracks = {7: [1, 1], 9: [1, 1]}
    kp = np.array([[10.0, 20.0], [10.0, 20.0], [30.0, 40.0]], dtype=np.float32)
    site = feature_sites(kp)
    assert site[0] == site[1] != site[2]
    nums, n_new, n_ext, conflicts = tracker._assign(3, {0: [(7, 0, 90.0)], 1: [(9, 0, 60.0)]},
                                                    site)
    assert nums.tolist() == [-1, 9, -1] and conflicts == 1
    keep = tracker._emitted(kp, np.array([5.0, 1.0, 2.0]), nums, site)
    assert keep.tolist() == [1, 2]


def test_working_to_full_resolution_is_exact() -> None:
    tracker = Tracker(TrackerOptions(working_width_px=500), CAMERA)  # s = 1200/500 = 2.4
    assert tracker.working_size_px == (500, 375)
    assert tracker.scale_uv == (2.4, 2.4)
    uv = tracker.to_full_px(np.array([[-0.5, -0.5], [0.0, 0.0], [499.5, 374.5], [10.0, 20.0]]))
    # pixel edges map to pixel edges, the first working pixel centre to the middle of its block
    np.testing.assert_allclose(uv, [[-0.5, -0.5], [0.7, 0.7], [1199.5, 899.5], [24.7, 48.7]],
                               atol=1e-12)
    never_up = Tracker(TrackerOptions(working_width_px=5000), CAMERA)
    assert never_up.working_size_px == (WIDTH_PX, HEIGHT_PX)


@pytest.mark.parametrize("width", [600, 500])
def test_detected_blob_maps_to_its_full_resolution_centre(width: int) -> None:
    """A Gaussian blob rendered at a known full-resolution pixel is emitted there."""
    centre = np.array([523.3, 411.8])  # full-resolution OpenCV pixel
    v, u = np.mgrid[0:HEIGHT_PX, 0:WIDTH_PX].astype(np.float64)
    sigma_px = 12.0
    blob = np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma_px**2))
    image = np.round(60 + 150 * blob).astype(np.uint8)
    tracker = Tracker(TrackerOptions(working_width_px=width, max_features=50), CAMERA)
    out = tracker.add_image("blob", image, np.array([0, 0, 100.0, 0, 0, 0]), None)
    err = np.linalg.norm(out.uv_px - centre, axis=1).min()
    assert err < 0.5  # full-resolution pixels


def test_reduced_jpeg_decode_gives_the_same_full_resolution_pixels(
        texture: np.ndarray, sift_run: StripRun, tmp_path: Path) -> None:
    path = tmp_path / "view.jpg"
    assert cv2.imwrite(str(path), render(texture, sift_run.eops[0]),
                       [cv2.IMWRITE_JPEG_QUALITY, 95])
    tracker = Tracker(TrackerOptions(working_width_px=600), CAMERA)
    assert tracker.decode_factor == 2
    reduced = read_gray_image(path, tracker.decode_factor)
    assert reduced.shape == (HEIGHT_PX // 2, WIDTH_PX // 2)
    nav = sift_run.eops[0]
    uv_reduced = tracker.add_image("r", reduced, nav, 0.0).uv_px
    uv_full = Tracker(TrackerOptions(working_width_px=600), CAMERA).add_image(
        "f", read_gray_image(path), nav, 0.0).uv_px
    nearest = np.array([np.linalg.norm(uv_full - p, axis=1).min() for p in uv_reduced[:500]])
    assert np.median(nearest) < 0.05  # full-resolution pixels: no shift between decodes
    with pytest.raises(InputDataError, match="reduced by 2, 4, 8 to at least 600 x 450 px"):
        tracker.add_image("q", read_gray_image(path, 4), nav, 0.0)
    with pytest.raises(InputDataError, match="cannot read"):
        read_gray_image(tmp_path / "missing.jpg")


@pytest.mark.parametrize("min_overlap", [0.15, 0.0])
def test_images_apart_by_nav_are_never_matched(texture: np.ndarray, sift_run: StripRun,
                                               min_overlap: float) -> None:
    eops = sift_run.eops
    tracker = Tracker(TrackerOptions(working_width_px=600, min_overlap=min_overlap), CAMERA)
    first = tracker.add_image("a", render(texture, eops[0]), eops[0], 0.0)
    far = eops[0] + np.array([1000.0, 0, 0, 0, 0, 0])  # same pixels, footprint 1 km away
    out = tracker.add_image("b", render(texture, eops[0]), far, 0.0)
    assert out.stats.candidates == () and out.stats.pairs_matched == 0
    assert not set(out.point_ids) & set(first.point_ids)


def test_an_attitude_far_off_falls_back_to_the_recent_images_near_in_plan(
        texture: np.ndarray, sift_run: StripRun) -> None:
    """The third image's nav pitched 45 deg (an INS glitch): its predicted footprint lies
    ~100 m ahead and overlaps no held image, so it had no candidate and no tie point (the
    estimator kept it at its INS). Now the recent images whose nadir footprints would
    overlap are matched, and its tracks continue theirs; an image 1 km away is still not
    matched (above)."""
    eops = sift_run.eops
    tracker = Tracker(TrackerOptions(working_width_px=600), CAMERA)
    first = [tracker.add_image(f"img{k}", render(texture, eops[k]), eops[k], 0.0)
             for k in range(2)]
    glitch = eops[2] + np.array([0, 0, 0, 0, np.radians(45.0), 0])
    out = tracker.add_image("img2", render(texture, eops[2]), glitch, 0.0)
    assert out.stats.candidates == ("img1", "img0")
    assert out.stats.extended_tracks > 100  # of 200 emitted
    assert len(set(out.point_ids) & set(first[1].point_ids)) > 100


def test_horizon_falls_back_to_most_recent_images() -> None:
    cam = CameraConfig(model="PINHOLE", width_px=320, height_px=240, fx_px=300.0, fy_px=300.0,
                       cx_px=159.5, cy_px=119.5)
    rng = np.random.default_rng(SEED)
    tracker = Tracker(TrackerOptions(working_width_px=320, neighbours=2), cam)
    level = np.array([0, 0, 100.0, np.radians(90.0), 0, 0])  # looking at the horizon
    for k in range(4):
        out = tracker.add_image(f"h{k}", rng.integers(0, 255, (240, 320), dtype=np.uint8),
                                level + [k, 0, 0, 0, 0, 0], None)
    assert out.stats.candidates == ("h2", "h1")


def _noise_strip(options: TrackerOptions, step_m: float, n: int) -> list[int]:
    cam = CameraConfig(model="PINHOLE", width_px=320, height_px=240, fx_px=300.0, fy_px=300.0,
                       cx_px=159.5, cy_px=119.5)
    rng = np.random.default_rng(SEED)
    tracker = Tracker(options, cam)
    held = []
    for k in range(n):
        image = cv2.GaussianBlur(rng.integers(0, 255, (240, 320), dtype=np.uint8), (0, 0), 1.0)
        tracker.add_image(f"n{k}", image, np.array([step_m * k, 0, 100.0, 0, 0, 0]), 0.0)
        held.append(tracker.held_images)
        assert len(tracker._tracks) <= sum(len(h.point_nums) for h in tracker._held)
    return held


def test_held_images_bounded_over_a_long_strip() -> None:
    opts = TrackerOptions(working_width_px=320, max_features=200, neighbours=3,
                          max_held_images=6, stale_after_images=2)
    # footprint 107 m long along the strip, 40 m steps: each image overlaps the next two
    held = _noise_strip(opts, step_m=40.0, n=40)
    assert max(held) <= 4  # stale images leave before the cap binds
    # hovering: every image overlaps every other, so only the cap bounds the memory
    hover = _noise_strip(opts, step_m=0.0, n=12)
    assert max(hover) == opts.max_held_images == hover[-1]


def test_orb_option_tracks(texture: np.ndarray) -> None:
    run = run_strip(texture, TrackerOptions(detector="orb", working_width_px=600,
                                            max_features=2000), n=3)
    assert run.out[1].stats.new_tracks > 100
    spreads = track_spreads_px(run)
    # ORB corners are integer pixels of their pyramid level (no sub-pixel refinement): about
    # one working pixel (2 full-resolution pixels here) instead of SIFT's 0.1.
    assert np.median(spreads) < TRACK_TOL_PX
    assert np.mean(spreads <= ORB_TRACK_TOL_PX) >= 0.9  # coarser pyramid levels: coarser corners


@pytest.mark.parametrize(("field", "value"), [
    ("detector", "surf"), ("working_width_px", 10), ("max_features", 0), ("neighbours", 0),
    ("min_overlap", 1.0), ("ratio", 1.5), ("ransac_threshold_px", 0.0), ("min_inliers", 3),
    ("max_held_images", 2), ("stale_after_images", 0), ("default_height_above_ground_m", -5.0),
    ("opencv_threads", -1), ("sift_contrast_threshold", 0.0),
])
def test_bad_options_name_the_field(field: str, value: object) -> None:
    with pytest.raises(ConfigError, match=rf"^flight.yaml: tracking.{field}: expected"):
        build_dataclass(TrackerOptions, {field: value}, "flight.yaml", key="tracking")


def test_unknown_option_and_bad_image_are_rejected() -> None:
    with pytest.raises(ConfigError, match="tracking.ratio_test: unknown key"):
        build_dataclass(TrackerOptions, {"ratio_test": 0.7}, "flight.yaml", key="tracking")
    tracker = Tracker(TrackerOptions(), CAMERA)
    with pytest.raises(InputDataError, match="image 'x': expected a uint8 gray or BGR image"):
        tracker.add_image("x", np.zeros((10, 10), np.uint8), np.zeros(6), None)
    with pytest.raises(InputDataError, match="image 'y': nav_eop must be 6 finite numbers"):
        tracker.add_image("y", np.zeros((HEIGHT_PX, WIDTH_PX), np.uint8), np.zeros(5), None)


def test_the_budget_feature_dial_caps_the_next_images_features(texture: np.ndarray) -> None:
    eops = strip_eops(3, np.random.default_rng(SEED))
    tracker = Tracker(TrackerOptions(working_width_px=600, emit_per_image=None), CAMERA)
    first = tracker.add_image("img0", render(texture, eops[0]), eops[0], 0.0)
    assert first.stats.features > 300
    tracker.set_max_features(300)
    second = tracker.add_image("img1", render(texture, eops[1]), eops[1], 0.0)
    assert 0 < second.stats.features <= 300
    assert second.stats.pairs_matched == 1  # still matched with the held image's features
    tracker.set_max_features(first.stats.features + 1000)
    third = tracker.add_image("img2", render(texture, eops[2]), eops[2], 0.0)
    assert third.stats.features > 300
