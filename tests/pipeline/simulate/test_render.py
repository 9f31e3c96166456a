"""Exactness of the ray-cast renderer on a synthetic textured terrain (issue 6)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pipeline.flight.camera import PixelCorrector, pinhole_camera
from pipeline.flight.schema import CameraConfig
from pipeline.simulate.render import (
    HeightField,
    Renderer,
    Scene,
    Texture,
    affine_texture_map,
    cast_rays,
)
from seqat.geometry import project

#: Rendered feature vs projected truth point: the issue's bound.
EXACT_PX = 0.5
#: Synthetic terrain: 1 m cells over 200 m, texture 0.05 m texels, dots sigma in metres.
CELL_M = 1.0
SIZE_M = 200.0
TEXEL_M = 0.05
DOT_SIGMA_M = 0.25
DOT_DN, BACKGROUND_DN = 200.0, 40.0
#: Half size of the centroid window, px.
WINDOW_PX = 8

CAMERA = CameraConfig(model="OPENCV", width_px=320, height_px=240, fx_px=300.0, fy_px=300.0,
                      cx_px=159.5, cy_px=119.5, k1=-0.12, k2=0.05, p1=3e-4, p2=-2e-4, k3=0.0)


def _hills(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 100.0 + 4.0 * np.sin(x / 17.0) * np.cos(y / 23.0) + 0.02 * x


def synthetic_scene(dots_xy_m: np.ndarray) -> Scene:
    n = int(SIZE_M / CELL_M)
    centres = (np.arange(n) + 0.5) * CELL_M
    X, Y = np.meshgrid(centres, SIZE_M - centres)
    surface = HeightField(heights_m=_hills(X, Y), west_m=0.0, north_m=SIZE_M, cell_m=CELL_M)
    m = int(SIZE_M / TEXEL_M)
    tc = np.arange(m) * TEXEL_M + TEXEL_M / 2
    tx, ty = tc[None, :], SIZE_M - tc[:, None]
    image = np.full((m, m), BACKGROUND_DN, dtype=np.float32)
    for x, y in dots_xy_m:
        c0, r0 = int(x / TEXEL_M), int((SIZE_M - y) / TEXEL_M)
        rs, cs = slice(max(r0 - 40, 0), r0 + 40), slice(max(c0 - 40, 0), c0 + 40)
        d2 = (tx[:, cs] - x) ** 2 + (ty[rs, :] - y) ** 2
        image[rs, cs] += (DOT_DN - BACKGROUND_DN) * np.exp(-0.5 * d2 / DOT_SIGMA_M**2)
    texture = Texture(image=np.clip(image, 0, 255).astype(np.uint8),
                      to_pixel=affine_texture_map(TEXEL_M / 2, SIZE_M - TEXEL_M / 2,
                                                  TEXEL_M, -TEXEL_M))
    return Scene(surface=surface, texture=texture)


def _centroid(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    u0, v0 = int(round(uv[0])), int(round(uv[1]))
    win = image[v0 - WINDOW_PX:v0 + WINDOW_PX + 1, u0 - WINDOW_PX:u0 + WINDOW_PX + 1]
    w = np.clip(win.astype(np.float64) - BACKGROUND_DN, 0.0, None)
    vv, uu = np.mgrid[v0 - WINDOW_PX:v0 + WINDOW_PX + 1, u0 - WINDOW_PX:u0 + WINDOW_PX + 1]
    return np.array([(w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()])


def test_rendered_dots_land_on_projected_truth() -> None:
    rng = np.random.default_rng(6)
    eop = np.array([100.0, 100.0, 130.0, *np.radians([4.0, -3.0, 25.0])])
    dots = np.array([[100 + dx, 100 + dy] for dx in (-12, -4, 4, 12) for dy in (-9, 0, 9)],
                    dtype=float)
    dots += rng.uniform(-1.0, 1.0, dots.shape)
    scene = synthetic_scene(dots)
    truth = np.column_stack([dots, scene.surface.sample(dots[:, 0], dots[:, 1])])
    start = time.perf_counter()
    image = Renderer(scene, CAMERA).render(eop)
    elapsed = time.perf_counter() - start
    ideal = project(eop, truth, pinhole_camera(CAMERA))
    observed = PixelCorrector(camera=CAMERA).observed_pixels(ideal)
    inside = ((observed[:, 0] > WINDOW_PX + 1) & (observed[:, 0] < CAMERA.width_px - WINDOW_PX - 2)
              & (observed[:, 1] > WINDOW_PX + 1)
              & (observed[:, 1] < CAMERA.height_px - WINDOW_PX - 2))
    assert inside.sum() >= 8
    found = np.array([_centroid(image, uv) for uv in observed[inside]])
    err = np.linalg.norm(found - observed[inside], axis=1)
    print(f"render {CAMERA.width_px}x{CAMERA.height_px}: {elapsed:.2f} s; "
          f"max error {err.max():.3f} px, rms {np.sqrt(np.mean(err**2)):.3f} px")
    assert err.max() <= EXACT_PX
    # distortion matters here: without it the dots would be off by more than the bound
    assert np.max(np.linalg.norm(observed - ideal, axis=1)) > 4 * EXACT_PX


def test_ray_cast_hits_the_bilinear_surface() -> None:
    scene = synthetic_scene(np.empty((0, 2)))
    rng = np.random.default_rng(1)
    dirs = np.column_stack([rng.uniform(-0.6, 0.6, (500, 2)), -np.ones(500)])
    hits = cast_rays(scene.surface, np.array([100.0, 100.0, 140.0]), dirs)
    assert np.all(np.isfinite(hits))
    assert np.max(np.abs(hits[:, 2] - scene.surface.sample(hits[:, 0], hits[:, 1]))) < 1e-6
    # hit points lie on the rays
    rel = hits - np.array([100.0, 100.0, 140.0])
    cross = np.cross(rel, dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    assert np.max(np.linalg.norm(cross, axis=1)) < 1e-6


def test_occlusion_first_hit() -> None:
    heights = np.zeros((40, 40))
    heights[18:22, 10:30] = 30.0  # a wall 30 m high, 4 m thick, east-west, y in [18, 22] m
    surface = HeightField(heights_m=heights, west_m=0.0, north_m=40.0, cell_m=1.0)
    origin = np.array([20.0, 0.0, 40.0])
    target = np.array([20.0, 35.0, 0.0])  # on the ground behind the wall, seen from the south
    hit = cast_rays(surface, origin, (target - origin)[None, :])[0]
    assert hit[1] < 22.0 and hit[2] > 5.0  # the ray stops on the wall's south face / top
    assert hit[2] == pytest.approx(surface.sample(hit[:1], hit[1:2])[0], abs=1e-6)
    # a ray that misses the wall reaches the ground target
    target2 = np.array([35.0, 35.0, 0.0])
    origin2 = np.array([35.0, 30.0, 40.0])
    hit2 = cast_rays(surface, origin2, (target2 - origin2)[None, :])[0]
    np.testing.assert_allclose(hit2, target2, atol=1e-6)


def test_mesh_start_finds_the_same_hits_as_the_full_march() -> None:
    """The open3d start (the first hit of the lifted mesh) skips only empty space: the hits
    are the full march's, bit for bit, on a smooth scene and over a wall."""
    from pipeline.simulate.render import SurfaceMesh

    rng = np.random.default_rng(3)
    scene = synthetic_scene(np.empty((0, 2)))
    dirs = np.column_stack([rng.uniform(-0.6, 0.6, (2000, 2)), -np.ones(2000)])
    origin = np.array([100.0, 100.0, 140.0])
    np.testing.assert_array_equal(cast_rays(scene.surface, origin, dirs,
                                            SurfaceMesh(scene.surface)),
                                  cast_rays(scene.surface, origin, dirs))
    heights = np.zeros((40, 40))
    heights[18:22, 10:30] = 30.0
    heights += rng.uniform(0.0, 2.0, heights.shape)  # rough: the lift matters
    wall = HeightField(heights_m=heights, west_m=0.0, north_m=40.0, cell_m=1.0)
    origin = np.array([20.0, 0.0, 40.0])
    targets = np.column_stack([rng.uniform(0, 40, 2000), rng.uniform(5, 40, 2000),
                               np.zeros(2000)])
    dirs = targets - origin
    with_mesh = cast_rays(wall, origin, dirs, SurfaceMesh(wall))
    np.testing.assert_array_equal(with_mesh, cast_rays(wall, origin, dirs))
    assert np.isfinite(with_mesh).all()
