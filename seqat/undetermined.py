"""Tie points the sequential window leaves out: GPs the data do not determine (singular
information), taken out with their rays, and those whose rays disagree at the final estimate.

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there;
docs/algorithm.md, *Robust loss (default) and undetermined points*).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from seqat.assembly import factor_information
from seqat.geometry import depth, intersect_rays
from seqat.information import RankDeficiency, window_matrix
from seqat.robust import (
    MAX_AMBIGUOUS_ROUNDS,
    core_u2,
    narrow_points,
    scale_in_force,
    uninformative_points,
    untrusted_two_ray_points,
    withheld_points,
)
from seqat.rows import FactorSet, gradient_from_factors
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray
from seqat.window import Key


class UndeterminedMixin:
    """Undetermined and disagreeing tie points of :class:`SequentialAT`."""

    def _drop_undetermined(self, keys: list[Key]) -> None:
        """GPs whose information became singular (every ray down-weighted by the robust loss,
        or rays that no longer intersect): out of the window and of the solution, named in
        :attr:`undetermined`. Their rays leave the window's information with them and wait
        again among the pending ones: more rays, or finish(), may determine them."""
        w = self._w
        for k in keys:  # departure records may refer to them: they are constants now
            self._dropped_value[k] = w.x[w.index(k)].copy()
        gone = {k[1] for k in keys if k[0] == "p"}
        pull = self._remove_rows_of(gone)
        w.drop(keys)
        self._factors.forget(gone)
        for p in gone:
            self._gp_count.pop(p, None)
            self._orphans.discard(p)
            self._undetermined[p] = None
        self._gp_order = [p for p in self._gp_order if p not in gone]
        self._n_points -= len(gone)
        if pull:  # the window to the minimum without those rows: one solve
            try:  # (may take out more undetermined GPs, each moved alike)
                factor = w.factor()
            except RankDeficiency:  # singular beyond GPs: as its caller would have met it
                return
            g = np.zeros(w.x.size)
            for k, v in pull.items():
                if k in w.offset:
                    g[w.index(k)] -= v
            delta = factor.solve(g)
            w.x = w.x + delta
            self._ssr = max(self._ssr - float(delta @ g), 0.0)

    @property
    def undetermined(self) -> list[str]:
        """GPs taken out as undetermined and not born again (out of the solution)."""
        return [self._point_ids[p] for p in self._undetermined]

    def _remove_rows_of(self, points: set[int]) -> dict[Key, FloatArray]:
        """Take the window rows of ``points`` out of ``L`` (their factors, as linearised:
        ``L`` minus them is exact), as Sim gives an undetermined point's rows no weight;
        their squared residuals leave σ0's sum, their rays return to the pending ones.
        Returns their pull on the other keys (``J^T W r`` at the estimate, by key): the
        estimate, the minimum with them, moves by ``L^-1`` of minus that.

        Deleting the point's rows and columns of ``L`` alone would condition the window on
        the point's value, which the data do not determine: its rays would hold the images
        like a control point at an arbitrary depth (Seneca's every second image: Seq-R's
        σZ 0.66 m against Sim's 0.85 m, and 0.6 m between them)."""
        w = self._w
        f = self._window_factors() if w.L is not None and points and not self._inverse else None
        sel = np.isin(f.pt, np.fromiter(points, dtype=np.int64)) if f is not None else None
        if f is None or sel is None or not sel.any():
            return {}
        for j, p, uv, w0 in zip(f.img[sel], f.pt[sel], f.uv[sel], f.w0[sel], strict=True):
            self._pending.setdefault(int(p), []).append((int(j), uv.copy(), float(w0**-0.5)))
        e_idx, p_idx = f.columns(w)
        cols = np.concatenate([e_idx, p_idx], axis=1)[sel]
        Je, Jp, wt = f.Je[sel], f.Jp[sel], f.w[sel]
        x = w.x
        r = f.predicted(x[e_idx], x[p_idx])[sel]  # the rows as linearised, at the estimate
        g = gradient_from_factors(Je, Jp, r, wt, cols, x.size)
        self._ssr = max(self._ssr - float(np.sum(wt[:, None] * r**2)), 0.0)
        self._redundancy -= 2 * int(np.count_nonzero(wt)) - GP_SIZE * len(set(f.pt[sel].tolist()))
        w.L = window_matrix(w.L - factor_information(Je, Jp, wt, f.img[sel], cols, x.size))
        w.changed()
        return {k: g[w.index(k)] for k in w.keys if k[0] != "p" or k[1] not in points}

    def _drop_ambiguous(self) -> None:
        """finish(), after the final re-linearisation: the window GPs whose rays disagree or
        fit another place as well (:func:`seqat.robust.uninformative_points`) leave with
        their rows (:meth:`_drop_undetermined`) and the window is re-adjusted without them,
        as Sim adjusts its block again without them: which ray or pair of rays the loss keeps
        depends on the start, and with it a weakly tied image's pose. Named in
        :attr:`disagreeing`. Information engine only (the inverse engine cannot take rows
        out)."""
        k = self.options.robust_scale
        for _ in range(MAX_AMBIGUOUS_ROUNDS):
            f = self._window_factors() if k is not None and not self._inverse else None
            if f is None:
                return
            xe, u2 = self._at_estimate(f)
            mine = self._whole_suspects(f, u2)
            found = [int(p) for p in uninformative_points(
                u2[mine], f.pt[mine], xe[mine, :EOP_SIZE], f.uv[mine],
                1.0 / np.sqrt(f.w0[mine]), self._camera_now(), k, self.sigma0)]
            if not found:
                return
            self._drop_undetermined([("p", p) for p in found])
            for p in found:
                self._undetermined.pop(p, None)
                self._ambiguous.add(p)
            self._final_relinearise()

    def _drop_untrusted_pairs(self) -> None:
        """finish(), before :meth:`_drop_ambiguous`: when the window's points of three rays or
        more show many wrong matches, every two-ray GP leaves with its rows, the image
        points' loss narrows its core (:func:`seqat.robust.scale_in_force`: ``options`` then
        carry the scale in force) and the window is re-adjusted from its points intersected
        anew, as Sim adjusts its block again (:func:`seqat.robust.untrusted_two_ray_points`;
        judged on the points all of whose rays are in the window's factors, ground control
        exempt). The contamination is :attr:`contamination`; the points, :attr:`untrusted`.
        Information engine only."""
        k = self.options.robust_scale
        f = self._window_factors() if k is not None and not self._inverse else None
        if f is None:
            return
        _, u2 = self._at_estimate(f)
        whole = self._whole(f, np.unique(f.pt))
        found, self.contamination = untrusted_two_ray_points(u2[whole], f.pt[whole],
                                                             f.img[whole], k, self.sigma0)
        scale = scale_in_force(k, self.contamination)
        if not found.size and scale == k:
            return
        self.options = dataclasses.replace(self.options, robust_scale=scale)
        self._drop_undetermined([("p", int(p)) for p in found])
        for p in found.tolist():
            self._undetermined.pop(p, None)
            self._untrusted.add(p)
        self._intersect_anew()
        self._final_relinearise()

    def _intersect_anew(self) -> None:
        """The window GPs (all rays among the factors, not control) intersected anew from
        their rays at the window's EOPs, where they meet in front of every camera: the
        start of the next re-linearisation (:attr:`_restart_points`; the window's model stays
        the estimate's), which must leave the robust minimum the points held
        (with wrong matches among them, re-weighting from there stays in it: the rendered
        block at 20 % blunders, EOPs 2.2 times the oracle's RMSE against 1.2)."""
        f = self._window_factors()
        if f is None:
            return
        whole = self._whole(f, np.unique(f.pt))
        pts, pos = np.unique(f.pt[whole], return_inverse=True)
        e = self._w.x[f.columns(self._w)[0][whole]][:, :EOP_SIZE]
        X, _ = intersect_rays(e, f.uv[whole], pos, pts.size, self._camera_now())
        ok = np.all(np.isfinite(X), axis=1)
        np.logical_and.at(ok, pos, depth(e, np.nan_to_num(X)[pos]) > 0)
        self._restart_points = dict(zip(pts[ok].tolist(), X[ok], strict=True))

    @property
    def untrusted(self) -> list[str]:
        """Two-ray tie points taken out at finish() (:meth:`_drop_untrusted_pairs`)."""
        return [self._point_ids[p] for p in sorted(self._untrusted)]

    def _at_estimate(self, f: FactorSet) -> tuple[FloatArray, FloatArray]:
        """The image blocks of the window's factors ``f`` at the estimate (k, 6 + c) and each
        factor's squared normalised residual there (k,)."""
        e_idx, p_idx = f.columns(self._w)
        xe = self._w.x[e_idx]
        return xe, np.sum(f.residuals(xe, self._w.x[p_idx], self._cam) ** 2, axis=1) * f.w0

    def _whole_suspects(self, f: FactorSet, u2: FloatArray) -> np.ndarray:
        """Mask of the factors of the window GPs with a ray beyond the core (at the squared
        normalised residuals ``u2``) all of whose rays are among the factors, not control."""
        k = self.options.robust_scale
        assert k is not None
        return self._whole(f, np.unique(f.pt[u2 > core_u2(k, self.sigma0)]))

    def _whole(self, f: FactorSet, points: np.ndarray) -> np.ndarray:
        """Mask of the factors of those window GPs among ``points`` (sorted, distinct) all of
        whose rays are among the factors ``f``, not control."""
        if points.size:
            rays = np.bincount(f.pt, minlength=int(points.max()) + 1)
            points = np.array([p for p in points.tolist()
                               if rays[p] == self._gp_nobs.get(p)
                               and self._control_of(p) is None], dtype=np.int64)
        return np.isin(f.pt, points)

    def _find_disagreeing(self) -> None:
        """finish(): the window GPs whose rays disagree at the final estimate, as Sim finds
        them (:meth:`_note_disagreeing`), or barely spread (:func:`seqat.robust.narrow_points`,
        whether or not the loss is on): left out of :meth:`solution` and named in
        :attr:`disagreeing`. Judged only with every ray of the point in the window's factors
        (after the final re-opening, all within ``reopen_max_age``)."""
        f = self._window_factors()
        if f is None:
            return
        xe, u2 = self._at_estimate(f)
        self._note_disagreeing(f, u2, xe)
        whole = self._whole(f, np.unique(f.pt))  # and the points whose rays barely spread
        self._disagreeing |= {int(p) for p in narrow_points(
            f.pt[whole], xe[whole, :EOP_SIZE], f.uv[whole], self._camera_now())}
        self.disagreeing = [self._point_ids[p]
                            for p in sorted(self._disagreeing | self._ambiguous)]

    def _note_disagreeing(self, f: FactorSet, u2: FloatArray, xe: FloatArray) -> None:
        """The window GPs whose rays disagree where the window's factors have the squared
        normalised residuals ``u2`` and their image blocks the values ``xe`` (k, 6 + c):
        fewer than two rays within the core, or the rays beyond it agreeing with as many
        elsewhere (:func:`seqat.robust.withheld_points`); at a drift check during the flight, at
        finish() in the end. Only GPs all of whose rays are among the factors, not ground
        control. Left out of :meth:`window_solution` until the next check. Only points with
        a ray beyond the core are looked at (clean data: none)."""
        k = self.options.robust_scale
        self._disagreeing = set()
        if k is None or f.pt.size == 0:
            return
        mine = self._whole_suspects(f, u2)
        if mine.any():
            self._disagreeing = {int(p) for p in withheld_points(
                u2[mine], f.pt[mine], xe[mine, :EOP_SIZE], f.uv[mine],
                1.0 / np.sqrt(f.w0[mine]), self._camera_now(), k, self.sigma0)}
