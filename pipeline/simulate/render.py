"""Exact ray-cast rendering of a camera over a textured 2.5D surface (issue 6).

A :class:`Scene` is a height field (:class:`HeightField`, bilinear between cell centres, in the
working CRS, metres) and a texture (:class:`Texture`, an image with a map from working-CRS
coordinates to texture pixels). :class:`Renderer` renders the *observed* image of an OpenCV
camera: every observed pixel is undistorted once per camera (:class:`pipeline.flight.camera.
PixelCorrector`) into an ideal pinhole ray, the ray is rotated into
the world for each pose, marched down in steps of at most ``MARCH_STEP_CELLS`` cells until it
first passes below the surface (first hit = visibility), and the crossing is refined by
bisection on the bilinear surface. The march starts where the ray first meets a triangle mesh
lifted just above the surface (:class:`SurfaceMesh`: open3d's ``RaycastingScene``), on the step
grid of a march from above the highest terrain, so it finds the same crossing in a few steps
instead of ~50 (docs/benchmarks.md, *Occlusion and rendering with open3d*). The colour is
the texture sampled bilinearly at the hit point (``cv2.remap``). Mild vignetting and noise are
added by :func:`finish_image`.

Exactness (tests/pipeline/simulate/test_render.py): projecting a ground point with the true EOP
(``seqat.geometry.project`` + distortion) lands on the rendered feature within 0.5 px.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.flight.camera import PixelCorrector
from pipeline.flight.schema import CameraConfig
from seqat.geometry import rotation_matrix
from seqat.types import FloatArray

#: Largest horizontal step of the ray march, in height-field cells (a crossing inside a step is
#: found exactly; only features thinner than this could be stepped over).
MARCH_STEP_CELLS = 0.5
#: Bisection iterations refining a crossing (interval shrinks by 2^-n; 1 m -> 1e-9 m).
BISECTION_ITERATIONS = 30
#: Margin above the highest and below the lowest terrain where the march starts and ends, m.
HEIGHT_MARGIN_M = 1.0
#: Rays rendered per chunk (bounds memory to ~100 MB at the default march).
CHUNK_RAYS = 65536
#: Colour of rays that leave the height field or the texture.
BACKGROUND = 0
#: The march starts this far (metres along the ray) before the first hit of the lifted mesh.
MESH_START_MARGIN_M = 0.01


@dataclass(frozen=True, kw_only=True, eq=False)
class HeightField:
    """A north-up grid of heights, bilinear between cell centres (docs/conventions.md, *Rasters*).

    Attributes
    ----------
    heights_m : (rows, cols) float64
        Finite everywhere; cell ``(r, c)`` has its centre at
        ``(west_m + (c + 0.5) cell_m, north_m - (r + 0.5) cell_m)``.
    west_m, north_m, cell_m : float
        Outer corner of the top-left cell and the cell size (working CRS).
    """

    heights_m: np.ndarray
    west_m: float
    north_m: float
    cell_m: float

    def __post_init__(self) -> None:
        h = np.asarray(self.heights_m, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 2 or not np.all(np.isfinite(h)):
            raise ValueError("heights_m: expected a finite (rows >= 2, cols >= 2) grid")
        object.__setattr__(self, "heights_m", h)

    @property
    def z_range_m(self) -> tuple[float, float]:
        return float(self.heights_m.min()), float(self.heights_m.max())

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(west, south, east, north)`` of the cell centres (where bilinear is defined)."""
        rows, cols = self.heights_m.shape
        half = 0.5 * self.cell_m
        return (self.west_m + half, self.north_m - (rows - 0.5) * self.cell_m,
                self.west_m + (cols - 0.5) * self.cell_m, self.north_m - half)

    def sample(self, x_m: FloatArray, y_m: FloatArray) -> FloatArray:
        """Bilinear heights at ``(x_m, y_m)`` (any shape); clamped to the edge cells outside."""
        rows, cols = self.heights_m.shape
        c = np.clip((np.asarray(x_m) - self.west_m) / self.cell_m - 0.5, 0.0, cols - 1.0)
        r = np.clip((self.north_m - np.asarray(y_m)) / self.cell_m - 0.5, 0.0, rows - 1.0)
        c0 = np.minimum(np.floor(c).astype(np.int64), cols - 2)
        r0 = np.minimum(np.floor(r).astype(np.int64), rows - 2)
        fc, fr = c - c0, r - r0
        h = self.heights_m
        top = h[r0, c0] * (1.0 - fc) + h[r0, c0 + 1] * fc
        bottom = h[r0 + 1, c0] * (1.0 - fc) + h[r0 + 1, c0 + 1] * fc
        return top * (1.0 - fr) + bottom * fr


#: Maps working-CRS ``(x_m, y_m)`` arrays to texture pixel ``(col, row)`` arrays (pixel centres
#: at integers, OpenCV convention).
TextureMap = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True, kw_only=True, eq=False)
class Texture:
    """An image draped on the surface.

    Attributes
    ----------
    image : (h, w) or (h, w, 3) uint8
    to_pixel : TextureMap
        Working CRS -> texture pixel (col, row), e.g. a world file after a pyproj transform.
    """

    image: np.ndarray
    to_pixel: TextureMap


def affine_texture_map(x0_m: float, y0_m: float, pixel_x_m: float, pixel_y_m: float) -> (
        TextureMap):
    """The map of a north-up texture whose pixel ``(0, 0)`` is centred at ``(x0_m, y0_m)``.

    ``col = (x - x0) / pixel_x``, ``row = (y - y0) / pixel_y`` (``pixel_y`` negative for a
    north-up image), as a world file (whose C, F are the centre of the top-left pixel).
    """

    def to_pixel(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (x - x0_m) / pixel_x_m, (y - y0_m) / pixel_y_m

    return to_pixel


@dataclass(frozen=True, kw_only=True, eq=False)
class Scene:
    """Terrain and texture in the working CRS."""

    surface: HeightField
    texture: Texture


class SurfaceMesh:
    """Where to start marching: the bilinear surface's triangles *lifted above it*, in open3d's
    ``RaycastingScene`` (Embree BVH).

    Vertices at the cell centres; in a cell the two triangles (split along the 00-11 diagonal)
    differ from the bilinear patch by at most ``|h00 + h11 - h01 - h10| / 4``, so every vertex
    is raised by the largest such bound of its cells: the mesh then lies on or above the
    bilinear surface everywhere, and a ray's first hit of it comes no later than its first
    crossing of the surface. The march starts there (a few steps instead of ~50 from above the
    highest terrain) and finds the same crossing. Coordinates relative to the field's corner
    and mean height (open3d is float32).
    """

    def __init__(self, surface: HeightField) -> None:
        import open3d as o3d

        h = surface.heights_m
        rows, cols = h.shape
        q = np.abs(h[:-1, :-1] + h[1:, 1:] - h[:-1, 1:] - h[1:, :-1]) / 4.0
        lift = np.zeros_like(h)
        for dr in (0, 1):
            for dc in (0, 1):
                view = lift[dr:rows - 1 + dr, dc:cols - 1 + dc]
                np.maximum(view, q, out=view)
        self.origin = np.array([surface.west_m, surface.north_m, float(h.mean())])
        r, c = np.mgrid[0:rows, 0:cols]
        vertices = np.column_stack([(c.ravel() + 0.5) * surface.cell_m,
                                    -(r.ravel() + 0.5) * surface.cell_m,
                                    (h + lift).ravel() - self.origin[2]]).astype(np.float32)
        v = np.arange(rows * cols, dtype=np.uint32).reshape(rows, cols)
        a, b, c0, d = v[:-1, :-1].ravel(), v[:-1, 1:].ravel(), v[1:, :-1].ravel(), v[1:, 1:].ravel()
        triangles = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c0])])
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
        self._o3d = o3d

    def first_hit(self, origin_m: FloatArray, dirs: FloatArray) -> FloatArray:
        """Ray parameter ``t`` (in units of each direction's length) of the first hit of the
        lifted mesh; ``inf`` for rays that miss it."""
        norm = np.linalg.norm(dirs, axis=1)
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = np.asarray(origin_m, np.float64) - self.origin
        rays[:, 3:] = dirs / norm[:, None]
        t = self._o3d.core.Tensor(rays)
        return self.scene.cast_rays(t)["t_hit"].numpy().astype(np.float64) / norm


def cast_rays(surface: HeightField, origin_m: FloatArray, dirs: FloatArray,
              mesh: SurfaceMesh | None = None) -> FloatArray:
    """First intersection of rays with the bilinear surface.

    Parameters
    ----------
    surface : HeightField
    origin_m : (3,) float
        Common origin (the projection centre), above the surface.
    dirs : (n, 3) float
        Ray directions (any length), pointing downwards (``dz < 0``).
    mesh : SurfaceMesh, optional
        Start each ray's march at its first hit of the lifted mesh (minus 1 cm) instead of
        above the highest terrain; rays that miss it, or are already below the surface
        there, march from the top.

    Returns
    -------
    (n, 3) float
        Hit points; NaN for rays that do not point down or never meet the surface.
    """
    o = np.asarray(origin_m, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    z_lo, z_hi = surface.z_range_m
    z_top, z_bottom = min(o[2], z_hi + HEIGHT_MARGIN_M), z_lo - HEIGHT_MARGIN_M
    out = np.full(d.shape, np.nan)
    down = d[:, 2] < 0.0
    idx = np.flatnonzero(down)
    if idx.size == 0:
        return out
    dd = d[idx]
    t0 = (z_top - o[2]) / dd[:, 2]
    t1 = (z_bottom - o[2]) / dd[:, 2]

    def above(t: np.ndarray, rows: np.ndarray) -> np.ndarray:
        p = o + t[:, None] * dd[rows]
        return p[:, 2] - surface.sample(p[:, 0], p[:, 1])

    horizontal = np.hypot(dd[:, 0], dd[:, 1]) * (t1 - t0)
    n_steps = max(1, int(np.ceil(horizontal.max() / (MARCH_STEP_CELLS * surface.cell_m))))
    dt = (t1 - t0) / n_steps
    # First step to test per ray: 1, or (with the mesh) the first step after the start, on the
    # same step grid, so the crossing found is the one the full march finds.
    k_first = np.ones(idx.size, np.int64)
    if mesh is not None:
        start = mesh.first_hit(o, dd) - MESH_START_MARGIN_M / np.linalg.norm(dd, axis=1)
        k_start = np.floor((start - t0) / dt)
        usable = np.isfinite(k_start) & (k_start >= 1) & (k_start < n_steps)
        rows = np.flatnonzero(usable)
        t_grid = t0[rows] + k_start[rows] * dt[rows]
        usable[rows[above(t_grid, rows) <= 0.0]] = False  # already below: march from the top
        k_first[usable] = k_start[usable].astype(np.int64) + 1
    t_hit_lo = np.full(idx.size, np.nan)
    pending = np.arange(idx.size)
    for k in range(int(k_first.min()), n_steps + 1):
        active = pending[k_first[pending] <= k]
        if active.size == 0:
            continue
        t_k = t0[active] + k * dt[active]
        below = above(t_k, active) <= 0.0
        t_hit_lo[active[below]] = t_k[below] - dt[active[below]]
        if below.any():
            pending = np.setdiff1d(pending, active[below], assume_unique=True)
        if pending.size == 0:
            break
    found = np.flatnonzero(np.isfinite(t_hit_lo))
    lo, hi = t_hit_lo[found], t_hit_lo[found] + dt[found]
    for _ in range(BISECTION_ITERATIONS):
        mid = 0.5 * (lo + hi)
        is_above = above(mid, found) > 0.0
        lo = np.where(is_above, mid, lo)
        hi = np.where(is_above, hi, mid)
    t = 0.5 * (lo + hi)
    out[idx[found]] = o + t[:, None] * dd[found]
    return out


class Renderer:
    """Renders observed images of one camera over a :class:`Scene`.

    The ideal rays of all observed pixels are computed once (undistortion is per camera).
    """

    def __init__(self, scene: Scene, camera: CameraConfig, *, mesh_start: bool = True) -> None:
        self.scene = scene
        self.camera = camera
        #: open3d's first hits of the lifted mesh start the march (:class:`SurfaceMesh`);
        #: False: every ray marches from above the highest terrain (the same hits, slower).
        self.mesh = SurfaceMesh(scene.surface) if mesh_start else None
        w, h = camera.width_px, camera.height_px
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        ideal = PixelCorrector(camera=camera).ideal_pixels(np.column_stack([u.ravel(),
                                                                            v.ravel()]))
        #: (h*w, 3) ray directions in the camera frame (x right, y up, looking along -z).
        self.rays_cam = np.column_stack([ideal[:, 0] - camera.cx_px, camera.cy_px - ideal[:, 1],
                                         np.full(len(ideal), -camera.fx_px)])

    def hit_points(self, eop: FloatArray) -> FloatArray:
        """(h, w, 3) world points seen by each observed pixel (NaN where nothing is hit)."""
        e = np.asarray(eop, dtype=np.float64)
        R = rotation_matrix(e[3], e[4], e[5])
        out = np.empty_like(self.rays_cam)
        for start in range(0, len(self.rays_cam), CHUNK_RAYS):
            chunk = self.rays_cam[start:start + CHUNK_RAYS] @ R.T
            out[start:start + CHUNK_RAYS] = cast_rays(self.scene.surface, e[:3], chunk,
                                                      self.mesh)
        return out.reshape(self.camera.height_px, self.camera.width_px, 3)

    def render(self, eop: FloatArray) -> np.ndarray:
        """The noise-free observed image for ``eop`` ``[X, Y, Z, omega, phi, kappa]`` (m, rad).

        Returns
        -------
        (h, w) or (h, w, 3) uint8
            Same channels as the texture; ``BACKGROUND`` where no surface or texture is seen.
        """
        hits = self.hit_points(eop)
        x, y = hits[..., 0], hits[..., 1]
        miss = ~np.isfinite(x)
        col, row = self.scene.texture.to_pixel(np.where(miss, 0.0, x), np.where(miss, 0.0, y))
        col = np.where(miss, -1e6, col).astype(np.float32)
        row = np.where(miss, -1e6, row).astype(np.float32)
        return cv2.remap(self.scene.texture.image, col, row, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND)


def finish_image(image: np.ndarray, *, vignetting: float, noise_sigma_dn: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Mild radial vignetting ``1 - vignetting * (r / r_corner)^2`` and Gaussian noise (DN).

    Parameters
    ----------
    image : (h, w) or (h, w, 3) uint8
    vignetting : float
        Relative darkening at the corners (0 = none).
    noise_sigma_dn : float
        Standard deviation of additive noise, digital numbers.

    Returns
    -------
    uint8 array of the input shape.
    """
    h, w = image.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((u - (w - 1) / 2) ** 2 + (v - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2
                                                             + ((h - 1) / 2) ** 2)
    gain = 1.0 - vignetting * r2
    out = image.astype(np.float64) * (gain if image.ndim == 2 else gain[..., None])
    if noise_sigma_dn > 0:
        out += rng.normal(0.0, noise_sigma_dn, size=out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)
