"""The DSM as a triangle mesh in open3d's ``RaycastingScene``: first hits of rays, for the
orthorectifier's ray-cast occlusion (``ortho.occlusion_method: raycast``, docs/formats.md).

The DSM as its raster says it is (pixel-is-area, docs/conventions.md): every cell with a
height a flat square at that height, and vertical walls between neighbouring cells of
different height, the 2.5D surface the z-buffer's facade samples approximate (a mesh through
the cell centres instead would slope every wall across a cell and shrink roofs by half a cell).
Nodata cells are holes rays pass. Coordinates relative to the outer corner of the top-left
cell and the mean height: open3d works in float32, which holds UTM coordinates only to half a
metre but local ones to 0.1 mm. The BVH is built once per DSM (up to 6 triangles per cell),
when the mesh is made.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from pipeline.ortho.dsm import Dsm


class DsmMesh:
    """A DSM triangulated for ray casting (open3d ``RaycastingScene``).

    Parameters
    ----------
    dsm : Dsm
    """

    def __init__(self, dsm: Dsm) -> None:
        h = dsm.heights_m
        rows, cols = h.shape
        cw, ch = dsm.cell_m
        finite = np.isfinite(h)
        z0 = float(np.nanmean(h)) if finite.any() else 0.0
        self.origin = np.array([dsm.transform.c, dsm.transform.f, z0])
        # Four corners per cell, k = 0 NW, 1 NE, 2 SW, 3 SE, at the cell's height.
        r, c = np.mgrid[0:rows, 0:cols]
        dx, dy = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
        x = (c[..., None] + dx) * cw
        y = -(r[..., None] + dy) * ch
        z = np.repeat(np.where(finite, h - z0, 0.0)[..., None], 4, axis=2)
        vertices = np.stack([x, y, z], axis=-1).reshape(-1, 3).astype(np.float32)
        v = np.arange(rows * cols * 4, dtype=np.uint32).reshape(rows, cols, 4)
        parts = [  # flat tops of the cells with a height
            np.column_stack([v[..., 0][finite], v[..., 2][finite], v[..., 1][finite]]),
            np.column_stack([v[..., 1][finite], v[..., 2][finite], v[..., 3][finite]])]
        # Vertical walls between neighbours of different height (east, then south).
        east = finite[:, :-1] & finite[:, 1:] & (h[:, :-1] != h[:, 1:])
        w, e = v[:, :-1][east], v[:, 1:][east]
        parts += [np.column_stack([w[:, 1], w[:, 3], e[:, 0]]),
                  np.column_stack([e[:, 0], w[:, 3], e[:, 2]])]
        south = finite[:-1] & finite[1:] & (h[:-1] != h[1:])
        n, s_ = v[:-1][south], v[1:][south]
        parts += [np.column_stack([n[:, 2], s_[:, 0], n[:, 3]]),
                  np.column_stack([n[:, 3], s_[:, 0], s_[:, 1]])]
        triangles = np.concatenate(parts).astype(np.uint32)
        self.triangles = len(triangles)
        self.scene = o3d.t.geometry.RaycastingScene()
        if self.triangles:
            self.scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
            # Embree builds its BVH at the first query (1.8 s for 0.7 M triangles on a busy
            # core): here, not inside the first image's occlusion time.
            self.scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 1e6, 0, 0, -1]], np.float32)))

    def first_hit_m(self, origin_m: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance along each ray to the first triangle it meets.

        Parameters
        ----------
        origin_m : (3,) float
            World coordinates of the common start of the rays (the camera).
        directions : (n, 3) float
            Unit directions.

        Returns
        -------
        (n,) float32
            ``inf`` where a ray meets nothing.
        """
        n = len(directions)
        if n == 0 or self.triangles == 0:
            return np.full(n, np.inf, np.float32)
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = np.asarray(origin_m, np.float64) - self.origin
        rays[:, 3:] = directions
        hits = self.scene.cast_rays(o3d.core.Tensor(rays))
        return hits["t_hit"].numpy()
