"""Births of tie points in the sequential update: intersection, screening, guards.

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there). A tie point
becomes a GP once it has ``min_rays`` rays in window images with a usable intersection angle
(docs/algorithm.md, *When a tie point becomes a GP*).
"""

from __future__ import annotations

import numpy as np

from seqat.assembly import factor_information
from seqat.geometry import depth, intersect_rays, project, viewing_axes, wrap_angle
from seqat.information import RankDeficiency, padded, window_matrix
from seqat.robust import cauchy_weight
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray
from seqat.update import LinearRows
from seqat.window import Key

#: A tie point whose rays would otherwise leave the window is born with at least this spread.
MIN_FORCED_RAY_ANGLE_DEG = 1.0
#: Data snooping at birth: a ray farther than this many critical sigmas from the others'
#: intersection is screened out (SequentialAT._screen_rays), in at most this many rounds.
SCREEN_SIGMAS = 2.0
MAX_SCREEN_ROUNDS = 5
#: A point being born whose update iterate lies this many times farther from a camera than
#: its birth intersection (or behind it) is held back (SequentialAT._unstable_births).
BIRTH_DEPTH_FACTOR = 100.0


#: An update that moves the new image or a window parameter by more than this many of its
#: prior sigmas diverged (SequentialAT._diverged): the image is carried by its GPS/INS.
DIVERGED_SIGMAS = 100.0


class BirthMixin:
    """Point births of :class:`SequentialAT`, and the guard of an update's result."""

    @staticmethod
    def _diverged(nav: FloatArray, nav_sigma: FloatArray, x2_0: FloatArray, d2: FloatArray,
                  Q_tt: FloatArray, d1t: FloatArray, rays_hold: bool = False) -> bool:
        """The update moved the new image or a touched window parameter by more than
        :data:`DIVERGED_SIGMAS` of its prior sigma (GPS/INS; window cofactor, unscaled).
        ``rays_hold``: the new image's own rays fix its estimate (at least
        :data:`seqat.robust.RAYS_OVER_NAV` of them to known points within the loss's core, most
        of them): then its distance from the GPS/INS is the GPS/INS's error, not the
        update's (an INS 150 deg off with a sigma of 0.1 deg named an image the tracker's
        resection had placed on 161 rays)."""
        dev = x2_0[:EOP_SIZE] + d2[:EOP_SIZE] - nav
        dev[3:] = wrap_angle(dev[3:])
        if rays_hold:
            dev[:] = 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            z_new = np.abs(dev) / nav_sigma
            z_old = np.abs(d1t) / np.sqrt(np.diagonal(Q_tt)) if d1t.size else np.zeros(0)
        worst = max(float(np.nanmax(z_new, initial=0.0)), float(np.nanmax(z_old, initial=0.0)))
        return not worst <= DIVERGED_SIGMAS

    def _unstable_births(self, born: list[int], born_xyz: FloatArray,
                         y12: list[tuple[int, int, FloatArray, float]],
                         y22: list[tuple[int, FloatArray, float]], x1t: FloatArray,
                         x2: FloatArray, col_of: dict[Key, int]) -> list[int]:
        """Points being born (index in the update) that an iterate of the update sent where
        their rays no longer fix them: behind a camera, or more than
        :data:`BIRTH_DEPTH_FACTOR` times farther than at birth (seen on a real flight: 1e8 m
        after a turn, with a singular 3x3 block). They wait for more rays instead of being
        born into a singular, far-off solution."""
        if not born:
            return []
        # one gather of the y12 rays' EOPs (a birth's few dozen rays; called per iterate)
        cols = np.fromiter((col_of[("e", j)] for j, _, _, _ in y12), dtype=np.int64,
                           count=len(y12))
        E_a = np.concatenate([x1t[cols[:, None] + np.arange(EOP_SIZE)],
                              np.broadcast_to(x2[:EOP_SIZE], (len(y22), EOP_SIZE))])
        I_a = np.fromiter([b for _, b, _, _ in y12] + [b for b, _, _ in y22], dtype=np.int64,
                          count=len(y12) + len(y22))
        X = x2[EOP_SIZE:].reshape(-1, GP_SIZE)
        with np.errstate(all="ignore"):
            axis = viewing_axes(E_a)  # one rotation for both depths
            d = np.einsum("nj,nj->n", axis, E_a[:, :3] - X[I_a])
            d0 = np.einsum("nj,nj->n", axis, E_a[:, :3] - born_xyz[I_a])
        bad_ray = ~((d > 0) & (d < BIRTH_DEPTH_FACTOR * np.maximum(d0, 0.0)))
        bad = np.zeros(len(born), dtype=bool)
        np.logical_or.at(bad, I_a, bad_ray)
        bad |= ~np.all(np.isfinite(X), axis=1)
        return [int(b) for b in np.flatnonzero(bad)]

    def _birth(
        self, candidates: list[int], i: int, nav: FloatArray, *, use_new: bool = True
    ) -> tuple[list[int], FloatArray]:
        """Intersect candidate tie points; return those with a usable geometry and their XYZ.

        ``use_new=False`` leaves the new image's rays out of the intersection (its EOP start
        value is unknown: a GNSS dropout); the point then needs two other rays.
        """
        if not candidates:
            return [], np.zeros((0, GP_SIZE))
        if self.options.snooping_critical is not None:
            self._screen_rays(candidates, i)
            ok = [p for p in candidates if p in self._pending
                  and len(self._pending[p]) >= self._min_rays(p)]
            if len(ok) < len(candidates):
                return self._birth(ok, i, nav, use_new=use_new)
        rays = [(c, j, uv) for c, p in enumerate(candidates) for j, uv, _ in self._pending[p]
                if use_new or j != i]
        if not rays:
            return [], np.zeros((0, GP_SIZE))
        I = np.fromiter((r[0] for r in rays), dtype=np.int64, count=len(rays))
        J = np.fromiter((r[1] for r in rays), dtype=np.int64, count=len(rays))
        UV = np.array([r[2] for r in rays], dtype=np.float64).reshape(-1, 2)
        E = self._eop_values(J, i, nav)
        X, spread = intersect_rays(E, UV, I, len(candidates), self._camera_now())
        min_angle = np.radians(
            [
                MIN_FORCED_RAY_ANGLE_DEG if p in self._forced else self.options.min_ray_angle_deg
                for p in candidates
            ]
        )
        for c, p in enumerate(candidates):  # ground control: at its surveyed coordinates
            ctrl = self._control_of(p)
            if ctrl is not None:
                X[c], spread[c] = ctrl[0], np.inf
        ok = np.all(np.isfinite(X), axis=1) & (spread >= min_angle)
        front = np.ones(len(candidates), dtype=bool)
        if np.any(ok):
            d = depth(E, np.nan_to_num(X)[I])
            np.logical_and.at(front, I, d > 0)
        ok &= front
        sel = np.flatnonzero(ok)
        return [candidates[c] for c in sel], X[sel]

    def _birth_at_finish(self) -> int:
        """finish(): the tie points still pending with ``min_rays`` rays in window images (after
        the final re-opening: every image that may re-enter) are born at the current
        estimates, admitted as Sim admits them (``options.sim.min_ray_angle_deg``, default any
        intersection; in front of every camera), so the final re-linearisation adjusts the
        same tie points as Sim. During the flight a point waits for ``min_ray_angle_deg`` of
        ray spread (its start values there are the GPS/INS); a return over the same spot
        (Seneca without 11 of its images: 23 points seen 48 images apart from 3.3 m, 2.4 deg)
        never reaches it, and without them Seq-R ended 0.5 m / 0.3 deg from Sim
        (docs/algorithm.md, *When a tie point becomes a GP*).

        The points enter as an update does: their rows' information is added to ``L`` and
        the window moves to the minimum of the augmented model (one solve), σ0's sum of
        squares and redundancy follow. Returns the number born."""
        w = self._w
        if w.L is None or self._inverse:
            return 0  # the paper's inverse engine: no finish-time births
        cand: list[tuple[int, list[tuple[int, FloatArray, float]]]] = []
        for p, obs in self._pending.items():
            rays = [o for o in obs if ("e", o[0]) in w.offset]
            if len(rays) >= max(self._min_rays(p), 2) and self._control_of(p) is None:
                cand.append((p, rays))
        if not cand:
            return 0
        I = np.concatenate([np.full(len(r), c) for c, (_, r) in enumerate(cand)])
        J = np.fromiter((j for _, r in cand for j, _, _ in r), dtype=np.int64, count=I.size)
        UV = np.array([uv for _, r in cand for _, uv, _ in r], dtype=np.float64).reshape(-1, 2)
        sig = np.fromiter((s for _, r in cand for _, _, s in r), dtype=np.float64,
                          count=I.size)
        e_cols = w.offsets_of("e", J)[:, None] + np.arange(EOP_SIZE)
        E = w.x[e_cols]
        X, spread = intersect_rays(E, UV, I, len(cand), self._camera_now())
        ok = np.all(np.isfinite(X), axis=1) & (
            spread >= np.radians(self.options.sim.min_ray_angle_deg))
        front = np.ones(len(cand), dtype=bool)
        np.logical_and.at(front, I, depth(E, np.nan_to_num(X)[I]) > 0)
        born = np.flatnonzero(ok & front)
        if not born.size:
            return 0
        use = np.isin(I, born)
        I, J, UV, sig, E, e_cols = I[use], J[use], UV[use], sig[use], E[use], e_cols[use]
        n0, cam_key = w.x.size, self._cam_key
        keys = w.keys + [("p", cand[c][0]) for c in born]
        col = np.full(len(cand), -1, dtype=np.int64)
        col[born] = n0 + GP_SIZE * np.arange(born.size)
        if cam_key is not None:  # self-calibration: the camera rides along with every image
            cam_cols = w.index(cam_key)
            e_cols = np.concatenate([e_cols, np.broadcast_to(cam_cols, (J.size, cam_cols.size))],
                                    axis=1)
        x = np.concatenate([w.x, X[born].ravel()])
        Xr = x[col[I][:, None] + np.arange(GP_SIZE)]
        proj, Je, Jp = self._cam.project_with_jacobians(x[e_cols], Xr)
        r = UV - proj
        wt = cauchy_weight(r, sig, self.options.robust_scale) / sig**2
        cols = np.concatenate([e_cols, col[I][:, None] + np.arange(GP_SIZE)], axis=1)
        n = x.size
        # the rows' gradient at x (J^T W r), by window key: a point the factorisation finds
        # undetermined leaves the window below, and the other keys' offsets move
        g = np.zeros(n)
        np.add.at(g, cols.ravel(), np.einsum("kri,kr->ki", np.concatenate([Je, Jp], axis=2),
                                             wt[:, None] * r).ravel())
        w.L = window_matrix(padded(w.L, n) + factor_information(Je, Jp, wt, J, cols, n))
        w.x = x
        w.relayout(keys)
        g_key = {k: g[w.index(k)] for k in keys}
        self._factors.add_linearised(J, np.repeat([cand[c][0] for c in born],
                                                  np.bincount(I, minlength=len(cand))[born]),
                                     UV, sig, x[e_cols], Xr, Je, Jp, r, robust=wt * sig**2)
        for c in born:
            p, rays = cand[c]
            del self._pending[p]
            self._forced.discard(p)
            self._undetermined.pop(p, None)  # taken out earlier, determined now
            self._gp_count[p] = self._gp_nobs[p] = len(rays)
            self._gp_order.append(p)
            self._n_points += 1
            for j, _, _ in rays:
                self._img_points.setdefault(j, []).append(p)
        try:
            w.settle()  # a point the rays do not determine leaves (on_singular)
        except RankDeficiency:
            return int(born.size)  # left to the final re-linearisation's retries
        b = np.zeros(w.x.size)
        for k, v in g_key.items():
            if k in w.offset:
                b[w.index(k)] = v
        dx = w.q_apply(np.arange(b.size), b)
        w.x = w.x + dx
        self._ssr = max(self._ssr + float(np.sum(wt[:, None] * r**2)) - float(b @ dx), 0.0)
        self._redundancy += 2 * int(np.count_nonzero(wt)) - GP_SIZE * int(born.size)
        return int(born.size)

    def _control_of(self, p: int) -> tuple[FloatArray, FloatArray] | None:
        """Surveyed coordinates (local) and their weights of point ``p`` when it is a
        control point, else None."""
        cp = self.control.get(self._point_ids[p]) if self.control else None
        if cp is None:
            return None
        return cp.xyz_m - self._origin, cp.weight

    def _min_rays(self, p: int) -> int:
        """Rays point ``p`` needs to be born: one for a control point (its surveyed
        coordinates fix it), ``min_rays`` for a tie point."""
        return 1 if self.control and self._point_ids[p] in self.control else (
            self.options.min_rays)

    def _control_rows(self, born: list[int], t: int) -> list[tuple[int, FloatArray,
                                                                    FloatArray]]:
        """The coordinate observations of the control points among ``born`` for the
        update's row builder: (column in ``z = [x1t, x2]``, surveyed xyz, weights)."""
        out = []
        for b, p in enumerate(born):
            ctrl = self._control_of(p)
            if ctrl is not None:
                out.append((t + EOP_SIZE + GP_SIZE * b, ctrl[0], ctrl[1]))
        return out

    def _eop_values(self, images: np.ndarray, i: int, nav: FloatArray) -> FloatArray:
        """EOP of each of ``images`` (k, 6): the window's estimate, the frozen value of a
        departed image, ``nav`` for the new image ``i``."""
        w = self._w
        offs = w.offsets_of("e", images)
        E = np.empty((images.size, EOP_SIZE))
        inside = offs >= 0
        E[inside] = w.x[offs[inside, None] + np.arange(EOP_SIZE)]
        for r in np.flatnonzero(~inside):
            E[r] = nav if images[r] == i else self._frozen_eop[int(images[r])][0]
        return E

    def _eop_value(self, j: int) -> FloatArray:
        w = self._w
        return w.x[w.index(("e", j))] if ("e", j) in w.offset else self._frozen_eop[j][0]

    def _screen_rays(self, candidates: list[int], i: int) -> None:
        """Data snooping at birth: the rays of estimated images (not the new one, whose EOP is
        still the nav) must meet in one point. The worst ray of a point whose rays miss it by
        more than ``SCREEN_SIGMAS * critical * sigma`` pixels is rejected while at least two
        remain; a blunder in a point's first rays would otherwise be intersected into a wrong
        point the update cannot leave (a local minimum that fits all its rays)."""
        crit = self.options.snooping_critical
        assert crit is not None
        rays = [(c, j, uv) for c, p in enumerate(candidates) for (j, uv, _) in self._pending[p]]
        I = np.asarray([r[0] for r in rays], dtype=np.int64)
        UV = np.asarray([r[2] for r in rays], dtype=np.float64).reshape(-1, 2)
        # the new image's rays take any EOP: they are not used here
        E = np.asarray([self._eop_value(j) if j != i else np.zeros(EOP_SIZE)
                        for (_, j, _) in rays]).reshape(-1, EOP_SIZE)
        old = np.asarray([j != i for (_, j, _) in rays], dtype=bool)
        sig = np.asarray([s for p in candidates for (_, _, s) in self._pending[p]])
        limit = SCREEN_SIGMAS * crit * sig
        alive = old.copy()
        cam = self._camera_now()
        for _ in range(MAX_SCREEN_ROUNDS):
            n_old = np.bincount(I[alive], minlength=len(candidates))
            if not np.any(n_old >= 3):
                break
            X, _ = intersect_rays(E[alive], UV[alive], I[alive], len(candidates), cam)
            res = np.full(I.size, -np.inf)
            sel = alive & (n_old[I] >= 3) & np.all(np.isfinite(X[I]), axis=1)
            if not np.any(sel):
                break
            res[sel] = (np.linalg.norm(UV[sel] - project(E[sel], X[I[sel]], cam),
                                       axis=1) - limit[sel])
            order = np.lexsort((-res, I))
            first = order[np.r_[True, I[order][1:] != I[order][:-1]]]
            worst = first[res[first] > 0]
            if worst.size == 0:
                break
            alive[worst] = False
            for r in worst:
                p = candidates[int(I[r])]
                rays = self._pending[p]
                k = int(r - np.flatnonzero(I == I[r])[0])
                j, _, s = rays[k]
                self.rejections.append((self._image_ids[j], self._point_ids[p],
                                        float(res[r] / s / crit + SCREEN_SIGMAS)))
        if not np.all(alive | ~old):
            for c, p in enumerate(candidates):
                rays = self._pending[p]
                gone = ~alive[I == c] & old[I == c]
                if gone.any():
                    for (j, _, _), g in zip(rays, gone, strict=True):
                        if g and j in self._img_points and p in self._img_points[j]:
                            self._img_points[j].remove(p)
                    self._pending[p] = [o for o, g in zip(rays, gone, strict=True) if not g]


def degenerate_points(rows: LinearRows, n_born: int) -> list[int]:
    """Points being born (index in the update) whose own 3x3 normal block is singular."""
    D = rows.A22.T @ (rows.w2[:, None] * rows.A22) + rows.A32.T @ (rows.w3[:, None] * rows.A32)
    out = []
    for b in range(n_born):
        sl = slice(EOP_SIZE + GP_SIZE * b, EOP_SIZE + GP_SIZE * (b + 1))
        ev = np.linalg.eigvalsh(D[sl, sl])
        if not ev[0] > 1e-9 * max(ev[-1], 1e-300):
            out.append(b)
    return out
