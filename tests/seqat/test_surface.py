"""Tie points off the surface their neighbours define (seqat.surface)."""

from __future__ import annotations

import numpy as np

from seqat.surface import SURFACE_NEIGHBOURS, SURFACE_SIGMAS, off_surface_points


def _ground(rng: np.random.Generator, slope: float = 0.0, rough_m: float = 0.05,
            n: int = 15) -> np.ndarray:
    """An n × n grid of points 5 m apart on a plane rising ``slope`` to the east, each
    ``rough_m`` (σ) off it."""
    x, y = np.meshgrid(np.arange(n) * 5.0, np.arange(n) * 5.0)
    z = 100.0 + slope * x + rng.normal(0.0, rough_m, x.shape)
    return np.column_stack([x.ravel(), y.ravel(), z.ravel()])


def test_a_point_alone_above_or_below_the_ground_is_off_the_surface() -> None:
    """A point 20 m below flat ground and one 15 m above it are off the surface; two points
    on one 15 m roof hold each other up; a point 3 m off is caught by its σ_z (0.1 m) and
    not with σ_z = 3 m; ground control is never flagged but still defines the surface."""
    rng = np.random.default_rng(3)
    ground = _ground(rng)
    extra = np.array([[31.0, 31.0, 80.0],    # 20 m below
                      [46.0, 21.0, 115.0],   # 15 m above, alone
                      [21.0, 51.0, 115.0],   # a roof of two
                      [22.0, 52.0, 115.1],
                      [51.0, 46.0, 103.0],   # 3 m above, σ_z 0.1 m: flagged
                      [56.0, 11.0, 120.0],   # 20 m above, σ_z 3 m: its own σ
                      [11.0, 56.0, 130.0]])  # 30 m above: ground control
    xyz = np.vstack([ground, extra])
    sz = np.full(len(xyz), 0.1)
    sz[-2] = 3.0
    exempt = np.zeros(len(xyz), dtype=bool)
    exempt[-1] = True
    g = len(ground)
    np.testing.assert_array_equal(off_surface_points(xyz, sz, exempt), [g, g + 1, g + 4])
    # the threshold: the 3 m point is 3 / hypot(s, 0.1) σ off; at twice its σ_z it is not
    sz[g + 4] = 3.0 / SURFACE_SIGMAS
    assert g + 4 not in off_surface_points(xyz, sz, exempt)
    # without the exemption the control point is off the surface too
    assert g + 6 in off_surface_points(xyz, sz)


def test_slopes_and_rough_ground_lose_no_point() -> None:
    """Ground rising 60 % (the grid's corners see their neighbours on one side only) and
    ground 5 m rough: no point is off its surface."""
    rng = np.random.default_rng(4)
    for slope, rough in ((0.6, 0.05), (0.0, 5.0), (0.3, 2.0)):
        xyz = _ground(rng, slope, rough)
        assert off_surface_points(xyz, np.full(len(xyz), 0.1)).size == 0


def test_the_test_is_the_same_in_utm_coordinates_and_survives_odd_input() -> None:
    """Shifted to a UTM position (northing 4.9e6 m) the same points are flagged; points
    that coincide in plan, non-finite rows and too few points do not break it."""
    rng = np.random.default_rng(5)
    xyz = np.vstack([_ground(rng), [[31.0, 31.0, 80.0]]])
    sz = np.full(len(xyz), 0.1)
    local = off_surface_points(xyz, sz)
    np.testing.assert_array_equal(local, [len(xyz) - 1])
    utm = xyz + [494_000.0, 4_877_000.0, 0.0]
    np.testing.assert_array_equal(off_surface_points(utm, sz), local)
    # a ground point twice (one with a NaN σ), a NaN row: the low point alone is flagged
    dup = np.vstack([xyz, xyz[[0]], [[np.nan, 0.0, 0.0]]])
    np.testing.assert_array_equal(off_surface_points(dup, np.append(sz, [np.nan, 0.1])), local)
    # the low point twice: each is the other's partner at its height (two rays that agree)
    assert off_surface_points(np.vstack([xyz, xyz[[-1]]]), np.append(sz, 0.1)).size == 0
    few = xyz[:SURFACE_NEIGHBOURS]
    assert off_surface_points(few, np.full(len(few), 0.1)).size == 0
