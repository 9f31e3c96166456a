"""Late observations of the streaming tracker (pipeline/tracking/late.py): a held image's
feature that was not emitted is emitted when a new image matches it."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from pipeline.tracking.late import emit_late, late_candidates
from pipeline.tracking.options import TrackerOptions
from pipeline.tracking.tracker import TrackedImage, Tracker, feature_sites
from tests.pipeline.tracking.test_tracking import (
    CAMERA,
    SEED,
    TRACK_TOL_PX,
    H_img_from_texture,
    render,
    strip_eops,
    texture,  # noqa: F401 - the module fixture
)

#: Image 0 emits only a few features (one grid cell): most of what image 1 matches in it was
#: not emitted.
FEW = TrackerOptions(working_width_px=600, emit_per_image=40, emit_grid=(1, 1),
                     late_per_pair=60, late_untied_per_pair=80)


def _ground(uv: np.ndarray, eop: np.ndarray) -> np.ndarray:
    H_inv = np.linalg.inv(H_img_from_texture(eop))
    return cv2.perspectiveTransform(np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2),
                                    H_inv).reshape(-1, 2)


def _run(tracker: Tracker, images: list[np.ndarray], eops: list[np.ndarray],
         start: int = 0) -> list[TrackedImage]:
    return [tracker.add_image(f"img{k}", images[k], eops[k], 0.0)
            for k in range(start, len(images))]


@pytest.fixture(scope="module")
def views(texture: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:  # noqa: F811
    eops = strip_eops(4, np.random.default_rng(SEED))
    return [render(texture, e) for e in eops], eops


def test_late_observations_emitted_capped_and_on_their_tracks(
        views: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    images, eops = views
    tracker = Tracker(FEW, CAMERA)
    before = tracker.add_image("img0", images[0], eops[0], 0.0)
    snapshot = tracker.state()
    nums0 = snapshot.held[0].point_nums.copy()
    out = [before, *_run(tracker, images, eops, start=1)]
    first = out[1]
    assert first.stats.late == len(first.late_point_ids) > 0
    assert set(first.late_image_ids) == {"img0"}
    # capped per pair (ties topped up to late_per_pair, or the untied cap) and by the
    # emission budget of the new image
    ties = len(set(first.point_ids) & set(before.point_ids))
    assert len(first.late_point_ids) <= (FEW.late_per_pair - ties if ties
                                         else FEW.late_untied_per_pair)
    assert first.stats.emitted <= FEW.emit_per_image
    # every late observation is on the track of a feature of the new image, at the same
    # ground point
    own = dict(zip(first.point_ids, first.uv_px, strict=True))
    for pid, uv in zip(first.late_point_ids, first.late_uv_px, strict=True):
        assert pid in own
        g_old, g_new = _ground(uv, eops[0]), _ground(own[pid], eops[1])
        assert np.linalg.norm(g_old - g_new) < 2 * TRACK_TOL_PX
    # a track never holds two features of one image, late observations included
    per_image: dict[str, list[str]] = {}
    for img in out:
        per_image.setdefault(img.image_id, []).extend(img.point_ids)
        for iid, pid in zip(img.late_image_ids, img.late_point_ids, strict=True):
            per_image.setdefault(iid, []).append(pid)
    assert all(len(p) == len(set(p)) for p in per_image.values())
    # the held image's numbers: one per pixel, the late ones recorded apart; the snapshot
    # taken before kept its own arrays (copy on write)
    np.testing.assert_array_equal(snapshot.held[0].point_nums, nums0)
    held0 = next(h for h in tracker.state().held if h.image_id == "img0")
    assert len(held0.late) >= len(first.late_point_ids)
    np.testing.assert_array_equal(held0.point_nums[held0.late[:, 0]], held0.late[:, 1])
    site = feature_sites(held0.kp_work)
    for s_ in np.unique(site):
        assert len(set(held0.point_nums[site == s_].tolist())) == 1


def test_no_late_observations_when_switched_off(
        views: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    images, eops = views
    off = dataclasses.replace(FEW, late_per_pair=0, late_untied_per_pair=0)
    out = _run(Tracker(off, CAMERA), images, eops)
    assert all(o.stats.late == 0 and not o.late_point_ids for o in out)


def test_state_and_restore_are_exact_with_late_observations(
        views: tuple[list[np.ndarray], list[np.ndarray]]) -> None:
    images, eops = views
    a = Tracker(FEW, CAMERA)
    _run(a, images[:2], eops[:2])
    state = a.state()
    b = Tracker(FEW, CAMERA)
    b.restore(state)
    rest_a = _run(a, images, eops, start=2)
    rest_b = _run(b, images, eops, start=2)
    assert sum(o.stats.late for o in rest_a) > 0
    for x, y in zip(rest_a, rest_b, strict=True):
        assert x.point_ids == y.point_ids and x.late_point_ids == y.late_point_ids
        assert x.late_image_ids == y.late_image_ids
        np.testing.assert_array_equal(x.uv_px, y.uv_px)
        np.testing.assert_array_equal(x.late_uv_px, y.late_uv_px)
    # the state taken after image 1 is unchanged by what a did later
    c = Tracker(FEW, CAMERA)
    c.restore(state)
    rest_c = _run(c, images, eops, start=2)
    assert [o.late_point_ids for o in rest_c] == [o.late_point_ids for o in rest_a]


@dataclasses.dataclass
class _Held:
    image_id: str
    kp_work: np.ndarray
    point_nums: np.ndarray
    late: np.ndarray


def test_late_caps_sites_and_track_invariant() -> None:
    """Unit test of the rules: cap per pair (larger without a tie), one emission per held
    pixel (every feature at it takes the number), never a second feature of the held image
    on a track, copy on write of the held arrays."""
    kp = np.array([[1, 1], [2, 2], [2, 2], [3, 3], [4, 4], [5, 5]], dtype=np.float32)
    nums = np.array([-1, -1, -1, -1, 100, -1], dtype=np.int64)  # feature 4 emitted (track 100)
    held = _Held("h", kp, nums, np.zeros((0, 2), dtype=np.int64))
    # new features 0..4 with numbers (site of each): 0 -> 7, 1 -> 8, 2 -> 100 (the held image
    # has track 100 already), 3 -> 9, 4 -> -1 (not emitted)
    new_nums = np.array([7, 8, 100, 9, -1], dtype=np.int64)
    unlinked = [(0, 0, 1, 5.0), (0, 1, 2, 6.0), (0, 2, 3, 1.0), (0, 3, 0, 9.0), (0, 4, 5, 0.5)]
    for ties, cap in (({0: 3}, 1), ({}, 2)):  # 4 tops 3 ties up by 1; 2 without a tie
        late, preferred = late_candidates(unlinked, ties, 4, 2)
        assert late[0][0] == (4, 5) and preferred == [4, 2, 0, 1][:cap]  # by distance
        h = dataclasses.replace(held)
        tracks = {7: [1, 1], 8: [1, 1], 9: [1, 1], 100: [3, 2]}
        out = emit_late([h], late, ties, new_nums, tracks, 4, 2)
        # 4: not emitted; 2: track 100 is the held image's already; then 0 -> site of
        # features 1 and 2 (one pixel) takes 7; then 1 -> feature 2, its site emitted now
        assert [(o[0], o[1]) for o in out] == [("h", 7), ("h", 9)][:cap]
        assert h.point_nums is not nums and nums.tolist() == [-1, -1, -1, -1, 100, -1]
        assert h.point_nums[1] == h.point_nums[2] == 7 and tracks[7] == [2, 2]
        np.testing.assert_array_equal(h.point_nums[h.late[:, 0]], h.late[:, 1])
        if cap == 2:
            assert h.point_nums[0] == 9 and tracks[8] == [1, 1]
    late, preferred = late_candidates(unlinked, {}, 0, 0)
    assert late == {} and preferred == []
    late, preferred = late_candidates(unlinked, {0: 4}, 4, 8)  # tied enough: none
    assert preferred == [] and emit_late([dataclasses.replace(held)], late, {0: 4}, new_nums,
                                         {}, 4, 8) == []
