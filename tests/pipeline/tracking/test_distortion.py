"""A wide lens: the tracker verifies its pairs on keypoints with the distortion removed
(``Tracker(ideal_pixels=...)``), where the epipolar geometry holds."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from pipeline.flight.camera import PixelCorrector
from pipeline.tracking.options import TrackerOptions
from pipeline.tracking.tracker import Tracker
from seqat.geometry import project
from seqat.types import PinholeCamera
from tests.pipeline.tracking.test_tracking import (
    CAMERA,
    HEIGHT_PX,
    SEED,
    WIDTH_PX,
    render,
    strip_eops,
    texture,  # noqa: F401 - the module fixture
)

#: Barrel distortion of a wide lens: 80 px in the corners of the 1200 x 900 px image.
WIDE = dataclasses.replace(CAMERA, model="OPENCV", k1=-0.25, k2=0.06)
OPTIONS = TrackerOptions(working_width_px=600, emit_per_image=None)


@pytest.fixture(scope="module")
def wide_map() -> np.ndarray:
    """(H, W, 2) float32: the ideal pixel each observed pixel of :data:`WIDE` sees."""
    u, v = np.meshgrid(np.arange(WIDTH_PX, dtype=np.float64),
                       np.arange(HEIGHT_PX, dtype=np.float64))
    ideal = PixelCorrector(camera=WIDE).ideal_pixels(np.column_stack([u.ravel(), v.ravel()]))
    return ideal.reshape(HEIGHT_PX, WIDTH_PX, 2).astype(np.float32)


def _distorted(texture: np.ndarray, eop: np.ndarray, wide_map: np.ndarray) -> np.ndarray:  # noqa: F811
    """The pinhole view through :data:`WIDE`: each observed pixel reads the pinhole view at
    its ideal pixel."""
    return cv2.remap(render(texture, eop), wide_map[..., 0], wide_map[..., 1], cv2.INTER_LINEAR)


def test_geometric_keypoints_are_the_ideal_pixels_at_the_working_scale() -> None:
    corrector = PixelCorrector(camera=WIDE)
    tracker = Tracker(OPTIONS, WIDE, ideal_pixels=corrector.ideal_pixels)
    kp = np.array([[3.0, 4.0], [299.5, 224.5], [590.0, 440.0]], dtype=np.float32)
    geo = tracker.geometric_keypoints(kp)
    # back through the distortion at full resolution: the keypoints again
    back = corrector.observed_pixels(tracker.to_full_px(geo))
    np.testing.assert_allclose(back, tracker.to_full_px(kp), rtol=0, atol=2e-3)
    assert np.linalg.norm(geo[0] - kp[0]) > 10.0  # a corner moves (working pixels)
    plain = Tracker(OPTIONS, WIDE)
    assert plain.geometric_keypoints(kp) is kp


def test_a_wide_lens_keeps_its_matches_off_the_plane() -> None:
    """Correct matches of points with relief (±15 m at 100 m) between two views 30 m apart:
    on observed pixels the distortion bends them off their epipolar lines and the
    fundamental matrix (1 px) rejects 7 % of them; on ideal pixels it keeps them all."""
    rng = np.random.default_rng(5)
    cam = PinholeCamera(f_px=WIDE.fx_px, cx_px=WIDE.cx_px, cy_px=WIDE.cy_px, width_px=WIDTH_PX,
                        height_px=HEIGHT_PX, k1=WIDE.k1, k2=WIDE.k2)
    X = np.column_stack([rng.uniform(-100, 130, 3000), rng.uniform(-80, 80, 3000),
                         rng.uniform(-15, 15, 3000)])
    uv = [project(np.tile(e, (len(X), 1)), X, cam)
          for e in ([0.0, 0, 100, 0.01, -0.02, 0.0], [30.0, 1, 101, -0.015, 0.01, 0.03])]
    inside = np.all([(p >= 0) & (p <= [WIDTH_PX - 1, HEIGHT_PX - 1]) for p in uv], axis=(0, 2))
    tracker = Tracker(OPTIONS, WIDE, ideal_pixels=PixelCorrector(camera=WIDE).ideal_pixels)
    work = [((p[inside] + rng.normal(0, 0.2, (inside.sum(), 2)) + 0.5)
             / np.asarray(tracker.scale_uv) - 0.5).astype(np.float32) for p in uv]
    assert inside.sum() > 500
    observed = tracker._verify(*work)  # noqa: SLF001 - the verification alone
    ideal = tracker._verify(*(tracker.geometric_keypoints(w) for w in work))  # noqa: SLF001
    assert observed is not None and ideal is not None
    assert observed.mean() < 0.96 and ideal.mean() > 0.995


def test_a_restored_tracker_forms_the_geometric_keypoints_again(
        texture: np.ndarray, wide_map: np.ndarray) -> None:  # noqa: F811
    """The state files do not hold them: a restored tracker tracks as the original."""
    corrector = PixelCorrector(camera=WIDE)
    eops = strip_eops(3, np.random.default_rng(SEED))
    images = [_distorted(texture, e, wide_map) for e in eops]
    a = Tracker(OPTIONS, WIDE, ideal_pixels=corrector.ideal_pixels)
    a.add_image("img0", images[0], eops[0], 0.0)
    a.add_image("img1", images[1], eops[1], 0.0)
    state = dataclasses.replace(a.state(), held=tuple(
        dataclasses.replace(h, kp_geo=None) for h in a.state().held))
    b = Tracker(OPTIONS, WIDE, ideal_pixels=corrector.ideal_pixels)
    b.restore(state)
    out_a, out_b = (t.add_image("img2", images[2], eops[2], 0.0) for t in (a, b))
    assert out_a.point_ids == out_b.point_ids
    np.testing.assert_array_equal(out_a.uv_px, out_b.uv_px)
    assert out_a.stats.inliers == out_b.stats.inliers
