"""Newton's method on the tie points with a ray in the robust loss's tail, the EOPs held;
on every point, for a trial step of the block (embedded point iterations).

Gauss-Newton on the robust cost weighs each ray by ``ρ'(u²)`` (IRLS, :mod:`seqat.robust`),
as if the loss were a parabola of that curvature. In the Cauchy tail it is concave along
the residual: the cost's second derivative along the ray's residual is ``-ρ'`` where IRLS
takes ``+ρ'``. A point with one of three rays just beyond the core then converges
linearly, by ~0.65 per iteration (``2 ρ' / (K + ρ')``, ``K`` its other rays' stiffness);
the initial block of a rendered flight took 20-40 iterations per image to the 1 µm
tolerance, an initial block with self-calibration 5 s (docs/algorithm.md, *Tie points in
the loss's tail*).

Once the block is in its basin (a full Gauss-Newton step of
:func:`seqat.adjustment.adjust_block` lowered the cost by at most
:data:`TAIL_NEWTON_FROM`), after each step every such point takes Newton steps on its own
cost, its rays' ``ρ`` (and its ground control) with the images where
they are: the Hessian of the loss as it is, ``Jᵀ ρ' (I - 2 r̂ r̂ᵀ) J`` per tail ray (``r̂``
the residual's direction), where that keeps the point's 3x3 block positive definite, the
IRLS block otherwise; a step is halved until the point's cost falls, else not taken. The
points are separable with the images held, so each point's lower cost lowers the block's.
The block stops where it stopped before, at a stationary point of its cost, by a shorter
way; only a saddle of a point's own cost, where IRLS could stop, is left for lower cost.

The same Newton steps on every point make a trial step of the block whose points lag its
images (:func:`embedded_points`: "embedded point iterations", Jeong et al. 2012, *Pushing
the envelope of modern methods for bundle adjustment*). A two-ray point of little parallax
moves along its rays far from where Gauss-Newton's linear model put it when its images
turn: the full step of a self-calibrating initial block then raised the cost 80-fold and
the line search took a quarter of it, iteration after iteration; with each point moved by
a Newton step for its images, the full step was taken (docs/algorithm.md, *Sim's
iterations*).
"""

from __future__ import annotations

import numpy as np

from seqat.geometry import depth, project, project_with_jacobians
from seqat.normals import BlockData, definite_enough, tail_ray_curvature
from seqat.robust import ray_u2, robust_rho, robust_weight
from seqat.types import GP_SIZE, FloatArray, PinholeCamera

#: The points take their Newton steps after a full Gauss-Newton step of the block that
#: lowered its cost by at most this fraction: in the basin, where they creep. From the first
#: step on, moving the points to fit start values still far off, the real take-off block's
#: batch adjustment ended in a wrong minimum (σ0 0.793 instead of 0.717).
TAIL_NEWTON_FROM = 1e-3
#: Newton iterations per call, and the step fractions tried in each.
TAIL_NEWTON_ITERATIONS = 2
#: Newton iterations of the embedded points (:func:`embedded_points`) per trial step: one.
#: Three cost Seneca's self-calibrating hand-over 291 ms against 182 ms for one, in the same
#: 20 iterations: most trials are not taken, so their cost counts more than their depth.
EMBEDDED_ITERATIONS = 1
TAIL_STEP_FRACTIONS = (1.0, 0.5, 0.25)
#: A point whose IRLS block has a smallest eigenvalue below this fraction of its largest is
#: not determined by its rays (seqat.normals.linearise's rule) and is not moved.
UNDETERMINED_RATIO = 1e-12


def newton_on_tail_points(camera: PinholeCamera, data: BlockData, eop: FloatArray,
                          gp: FloatArray, scale: float | None, skip: np.ndarray
                          ) -> tuple[FloatArray, float]:
    """The points of ``gp`` (m, 3) with a ray beyond the loss's core moved by Newton's
    method on their own robust cost (module docstring); ``skip`` (m,) bool: points left as
    they are (the linearisation's undetermined ones). Returns the points (a new array when
    any moved, else ``gp``) and the largest coordinate change (m)."""
    if scale is None or data.n_points == 0:
        return gp, 0.0
    img, pt = data.obs_image, data.obs_point
    u2 = ray_u2(data.obs_uv - project(eop[img], gp[pt], camera), data.obs_sigma_px)
    pts = np.unique(pt[u2 > scale**2])
    return _newton_points(camera, data, eop, gp, scale, pts[~skip[pts]],
                          TAIL_NEWTON_ITERATIONS)


def embedded_points(camera: PinholeCamera, data: BlockData, eop: FloatArray, gp: FloatArray,
                    scale: float | None, skip: np.ndarray) -> tuple[FloatArray, float]:
    """Every point of ``gp`` but ``skip`` moved by :data:`EMBEDDED_ITERATIONS` step(s) of
    Newton's method on its own cost, the images (and camera) held where they are: a trial
    step of the block with its points moved toward their optimum for its images (module
    docstring). Returns the points and the largest coordinate change (m), as
    :func:`newton_on_tail_points`."""
    if data.n_points == 0:
        return gp, 0.0
    return _newton_points(camera, data, eop, gp, scale, np.flatnonzero(~skip),
                          EMBEDDED_ITERATIONS)


def _newton_points(camera: PinholeCamera, data: BlockData, eop: FloatArray, gp: FloatArray,
                   scale: float | None, pts: np.ndarray, iterations: int
                   ) -> tuple[FloatArray, float]:
    """Points ``pts`` of ``gp`` moved by ``iterations`` Newton steps on their own cost (the
    loss's own curvature where the point's block stays positive definite, IRLS's else),
    each halved until the point's cost falls, else not taken."""
    if pts.size == 0:
        return gp, 0.0
    k2 = scale**2 if scale is not None else np.inf
    img, pt = data.obs_image, data.obs_point
    q = pts.size
    local = np.full(data.n_points, -1)
    local[pts] = np.arange(q)
    rays = np.flatnonzero(local[pt] >= 0)
    r_eop, r_pt = eop[img[rays]], local[pt[rays]]
    uv_obs, sigma = data.obs_uv[rays], data.obs_sigma_px[rays]
    s2 = sigma**2
    controlled = local[data.control_point] >= 0
    c_pt = local[data.control_point[controlled]]
    c_w, c_xyz = data.control_weight[controlled], data.control_xyz[controlled]

    def costs(X: FloatArray) -> FloatArray:
        """Each point's cost: its rays' ρ and its control; inf behind a camera."""
        res = uv_obs - project(r_eop, X[r_pt], camera)
        c = np.bincount(r_pt, weights=robust_rho(ray_u2(res, sigma), scale), minlength=q)
        np.add.at(c, c_pt, np.sum(c_w * (X[c_pt] - c_xyz) ** 2, axis=1))
        behind = np.bincount(r_pt, weights=(depth(r_eop, X[r_pt]) <= 0.0).astype(np.float64),
                             minlength=q) > 0
        return np.where(behind | ~np.isfinite(c), np.inf, c)

    X = gp[pts].copy()
    cost = costs(X)
    diag = np.arange(GP_SIZE)
    for _ in range(iterations):
        uv, _, Jp = project_with_jacobians(r_eop, X[r_pt], camera)
        ell = uv_obs - uv
        uu = ray_u2(ell, sigma)
        w = robust_weight(uu, scale) / s2
        wJ = Jp * w[:, None, None]
        irls = np.zeros((q, GP_SIZE, GP_SIZE))
        np.add.at(irls, r_pt, np.einsum("kai,kaj->kij", wJ, Jp))
        g = np.zeros((q, GP_SIZE))
        np.add.at(g, r_pt, np.einsum("kai,ka->ki", wJ, ell))
        irls[c_pt[:, None], diag, diag] += c_w
        g[c_pt] += c_w * (c_xyz - X[c_pt])
        # per tail ray -2 ρ' (Jᵀ r̂)(Jᵀ r̂)ᵀ: the loss's curvature along r̂ is -ρ', not +ρ'
        tail = uu > k2
        _, corr = tail_ray_curvature(Jp[tail], ell[tail], uu[tail], sigma[tail], w[tail])
        exact = irls.copy()
        np.add.at(exact, r_pt[tail], corr)
        ev_irls = np.linalg.eigvalsh(irls)
        determined = ev_irls[:, 0] > UNDETERMINED_RATIO * np.abs(ev_irls[:, -1])
        use_exact = definite_enough(exact)
        H = np.where(use_exact[:, None, None], exact, irls)
        H[~determined] = np.eye(GP_SIZE)
        step = np.linalg.solve(H, np.where(determined[:, None], g, 0.0)[:, :, None])[:, :, 0]
        todo = determined.copy()
        for fraction in TAIL_STEP_FRACTIONS:
            trial = np.where(todo[:, None], X + fraction * step, X)
            c = costs(trial)
            better = todo & (c < cost)
            X[better], cost[better] = trial[better], c[better]
            todo &= ~better
            if not todo.any():
                break
    moved = float(np.max(np.abs(X - gp[pts])))
    if moved == 0.0:
        return gp, 0.0
    out = gp.copy()
    out[pts] = X
    return out, moved
