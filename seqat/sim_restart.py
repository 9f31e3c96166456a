"""The refit of :class:`seqat.simultaneous.SimultaneousAT` as an image is added, and images
most of whose rays reject the solution, or whose points all fit two places: started again at
a resection, an earlier image blamed, their GPS/INS left free when a resection shows it
wrong, or named and carried by their GPS/INS until the others determine their points
(docs/algorithm.md, *A poor start*, *A wrong GPS/INS*)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from seqat import robust as rloss
from seqat.catalogue import FREE_NAV_SIGMA, free_nav_sigma
from seqat.errors import EstimationError
from seqat.geometry import project, resect
from seqat.normals import eop_residual
from seqat.types import EOP_SIZE, GP_SIZE, FloatArray, Frame

if TYPE_CHECKING:
    from seqat.simultaneous import Covariance, SimResult


#: An earlier image is tried as the culprit of a rejected one if it shares this many of its
#: points (:meth:`RestartMixin._blame_earlier`) ...
MIN_SHARED_POINTS = 3
#: ... and at most this many earlier images are tried (each costs a solve of the block).
MAX_BLAMED = 2
#: A diverged image is started again once the others determine this many of its points.
MIN_READMIT_POINTS = 6
#: A trial that needs the block to converge solves again from where a solve stopped this
#: many times (the other images, pulled by a wrong GPS/INS, took 37 iterations to come back).
TRIAL_MORE_SOLVES = 2
#: A resection is started also at the attitude of this many images sharing most points.
RESECTION_NEIGHBOURS = 2
#: The key of the catalogue's GPS/INS sigmas in a state (RestartMixin._state).
_CAT_NAV_SIGMA = "catalogue nav_sigma"


class RestartMixin:
    """Unsupported images of :class:`seqat.simultaneous.SimultaneousAT` (its state lives
    there)."""

    def _refit(self, i: int, cov: Covariance) -> int:
        """Solve the block with image ``i`` just added; returns the solves' iterations.

        An image whose start makes the block fail is left out; one most of whose rays
        reject the solution, or that the block converged without and does not converge
        with (its rays may fit a wrong minimum), is started again (:meth:`_start_again`)."""
        was_converged = self._result is None or self._result.converged
        try:
            res = self._solve(cov)
        except EstimationError:
            # the block solved before this image: its start made it fail (a GPS/INS far
            # off; docs/algorithm.md, *A poor start*). It is carried by its GPS/INS.
            if i == 0:
                raise
            self._leave_out([i])
            res = self._solve(cov)
        iterations = res.iterations
        if i > 0 and self._rejected_by_rays(i):
            iterations += self._start_again(i, cov)
        elif i > 0 and was_converged and not res.converged and i not in self._diverged:
            iterations += self._start_again(i, cov, rejected=False)
        elif i > 0 and self._lost_to_ambiguity(i):
            # each of i's points fits two places: an earlier image's poor start may be
            # the other place; if none is, the points stay out (the image untied)
            iterations += self._blame_earlier(i, cov) or 0
        if self._diverged:
            iterations += self._readmit_diverged(cov)
        return iterations

    def _solve_on(self, cov: Covariance, res: SimResult, times: int) -> tuple[SimResult, int]:
        """While ``res``, the last solution, has not converged, the block solved again from
        where it stopped, at most ``times`` times; the last solution and the iterations the
        further solves took."""
        iterations = 0
        for _ in range(times):
            if res.converged:
                break
            res = self._solve(cov)
            iterations += res.iterations
        return res, iterations

    def _readmit_diverged(self, cov: Covariance) -> int:
        """Images left out (:attr:`diverged`) are started again at their resection once
        the other images determine more of their points (at least
        :data:`MIN_READMIT_POINTS`) than when last tried, and kept if their rays fit. The
        second image's heading 150 deg off could not be resected in the block of two (no
        point seen by two others) and stayed out, carried by its GPS/INS, for the whole
        flight; with the third image its points are determined. Returns the solves'
        iterations."""
        cat = self._cat
        oi, op = cat.rays()
        out = np.fromiter(self._diverged, dtype=np.int64)
        others = np.bincount(op[~np.isin(oi, out)], minlength=len(cat.point_ids))
        iterations = 0
        for j in sorted(self._diverged):
            mine = op[oi == j]
            n = int(np.count_nonzero((others[mine] >= 2) & np.isin(mine, self._point_sel)))
            if n < MIN_READMIT_POINTS or self._readmit_tried.get(j, 0) >= n:
                continue
            before = self._state()
            self._diverged.discard(j)
            self.diverged.remove(cat.image_ids[j])
            try:
                iterations += self._start_again(j, cov, blame=False)
                if j not in self._diverged and self._result is not None:
                    iterations += self._solve_on(cov, self._result, TRIAL_MORE_SOLVES)[1]
            except EstimationError:  # the block fails with it: as it was
                self._leave_out([j])
            if j in self._diverged or self._result is None or not self._result.converged:
                self._restore(before)
            self._readmit_tried[j] = n
        return iterations

    def _start_nav_sigma(self, frame: Frame, nav: FloatArray) -> FloatArray:
        """The GPS/INS sigma the block takes for ``frame`` (``nav``: local): its own (the
        free components weak, :func:`seqat.catalogue.free_nav_sigma`), but a group far
        beyond the loss's core at the start the image's rays gave (the tracker's resection,
        ``initial_eop``) is left free (:meth:`_wrong_nav`)."""
        sigma = free_nav_sigma(np.asarray(frame.nav_sigma, dtype=np.float64))
        if frame.initial_eop is not None:
            start = np.asarray(frame.initial_eop, dtype=np.float64).copy()
            start[:3] -= self._origin
            if self._rays_hold(frame, start):
                sigma = self._wrong_nav(frame.image_id, nav, sigma, start)
        return sigma

    def _rays_hold(self, frame: Frame, eop: FloatArray) -> bool:
        """``frame``'s rays to points of the block hold ``eop`` (local) within
        :data:`seqat.robust.POOR_START_BEYOND` times the loss's core
        (:func:`seqat.robust.rays_hold`): a start its rays hold (a resection), not one merely
        given (6 deg off, the GPS/INS right)."""
        k = self.options.robust_scale
        at = {int(j): n for n, j in enumerate(self._point_sel)}
        idx = self._cat.point_index
        mine = [(at[idx[p]], n) for n, p in enumerate(frame.point_ids)
                if p in idx and idx[p] in at]
        if k is None or len(mine) < rloss.RAYS_OVER_NAV:
            return False
        pos, obs = (np.array(v, dtype=np.int64) for v in zip(*mine, strict=True))
        r = np.asarray(frame.uv_px, dtype=np.float64)[obs] - project(
            np.broadcast_to(eop, (obs.size, EOP_SIZE)), self._gp_est[pos], self.camera_now)
        u2 = rloss.ray_u2(r, np.full(obs.size, frame.sigma_px))
        return rloss.rays_hold(u2, k, rloss.POOR_START_BEYOND)

    def _wrong_nav(self, image_id: str, nav: FloatArray, sigma: FloatArray,
                   start: FloatArray) -> FloatArray:
        """``sigma`` with the GPS/INS groups far beyond the loss's core at ``start`` (a start
        the image's rays gave: a resection; :func:`seqat.robust.nav_far_beyond`) left free,
        and those groups named in :attr:`nav_downweighted`: that GPS/INS is wrong. Sim weighs
        the GPS/INS by least squares until the block converges, and that pull (an INS 45 deg
        off at a sigma of 0.1 deg) took an image from its resection back to the INS, the
        block left it out, and started again at its resection it kept the block from
        converging."""
        far = self._far_nav(nav, sigma, start)
        if not far.any():
            return sigma
        sigma = sigma.copy()
        for (group, sl), out in zip(rloss.NAV_GROUPS, far, strict=True):
            if out:
                sigma[sl] = FREE_NAV_SIGMA[sl]
                self.nav_downweighted.append((image_id, group))
        return sigma

    def _lost_to_ambiguity(self, i: int) -> bool:
        """Most of image ``i``'s points that could be tested (three rays or more), and at
        least :data:`MIN_SHARED_POINTS`, were held out of the last solution as fitting two
        places (:func:`seqat.robust.ambiguous_points`). Wrong matches make such points one
        by one; most of an image's at once are the mark of a poor start in an image they
        share: the block of images 1, 2 (45 deg off) and 3 took every point out, leaving
        image 2 at its GPS/INS for the rest of the flight (docs/algorithm.md, *A poor
        start*)."""
        if not self._ambiguous:
            return False
        cat = self._cat
        oi, op = cat.rays()
        rays = np.bincount(op, minlength=len(cat.point_ids))
        mine = np.unique(op[oi == i])
        mine = mine[rays[mine] >= 3]
        held = np.isin(mine, np.fromiter(self._ambiguous, dtype=np.int64))
        n = int(np.count_nonzero(held))
        return n >= MIN_SHARED_POINTS and 2 * n > mine.size

    def _unfit(self, i: int) -> bool:
        """Image ``i``'s rays reject the block, or its points were held out as fitting
        two places."""
        return self._rejected_by_rays(i) or self._lost_to_ambiguity(i)

    def _rejected_by_rays(self, i: int) -> bool:
        """Most of image ``i``'s rays in the last solution's block lie far beyond the loss's
        core (:func:`seqat.robust.unsupported_images`): the loss kept a poor GPS/INS start,
        or most of the rays are wrong matches (docs/algorithm.md, *A poor start*)."""
        sel = self._point_sel
        if sel.size == 0:
            return False
        _, oi, op, uv, sg = self._observations()
        pos = np.minimum(np.searchsorted(sel, op), sel.size - 1)  # sel is sorted
        mine = (oi == i) & (sel[pos] == op)
        n = int(np.count_nonzero(mine))
        u2 = rloss.ray_u2(uv[mine] - project(np.broadcast_to(self._eop_est[i], (n, EOP_SIZE)),
                                             self._gp_est[pos[mine]], self.camera_now),
                          sg[mine])
        return rloss.unsupported_images(u2, oi[mine], self.options.robust_scale).size > 0

    def _rejected_images(self) -> list[int]:
        """The images (catalogue indices, in flight order) most of whose rays in the last
        solution's block lie far beyond the loss's core (:meth:`_rejected_by_rays`, for every
        image at once), those left out (diverged) aside."""
        sel = self._point_sel
        if sel.size == 0:
            return []
        _, oi, op, uv, sg = self._observations()
        pos = np.minimum(np.searchsorted(sel, op), sel.size - 1)  # sel is sorted
        inb = sel[pos] == op
        oi, pos = oi[inb], pos[inb]
        u2 = rloss.ray_u2(uv[inb] - project(self._eop_est[oi], self._gp_est[pos],
                                            self.camera_now), sg[inb])
        bad = rloss.unsupported_images(u2, oi, self.options.robust_scale)
        return [int(i) for i in bad if int(i) not in self._diverged]

    def _start_rejected_again(self, cov: Covariance) -> None:
        """After the last solve (:meth:`export_state`; :meth:`solution` of a Sim adjusting
        once): each image whose rays reject the solution is started again
        (:meth:`_start_again`), once, in flight order. A refit tests only the image just
        added, an adjustment at the end none: a tight INS 45 deg off (sigma 0.1 deg) on the
        second image of a strip, where a block of two fits it, kept that image at its INS to
        the end with all its 73 rays rejected, sigma 0.1 deg, and nothing named
        (docs/algorithm.md, *A poor start*). Not after each refit: in a block of two, where
        any relative orientation fits, the image with the right INS looked rejected, was
        left out, and every later image with it."""
        tried: set[int] = set()
        while todo := [i for i in self._rejected_images() if i not in tried]:
            tried.add(todo[0])
            self._start_again(todo[0], cov)

    def _start_again(self, i: int, cov: Covariance, *, rejected: bool = True,
                     blame: bool = True) -> int:
        """Image ``i``, just added, is one most of whose rays reject the solution: the
        block is solved again with ``i`` started at its least-squares resection on the
        points the other images determine (:meth:`_resect`), as a sequential
        update starts again with the window held (:mod:`seqat.iteration`). If most rays
        reject that solution too, or no resection exists, ``i`` is carried by its GPS/INS
        (:meth:`_leave_out`). ``rejected`` False: not its rays but the block's failing to
        converge with ``i`` sent it here; without a resection the block stays as solved.
        Before ``i`` is left out, an earlier image may take the blame (``blame``:
        :meth:`_blame_earlier`). Returns the iterations of the solves."""
        cat = self._cat
        oi, op = cat.rays()
        at = {int(j): k for k, j in enumerate(self._point_sel)}
        others = np.bincount(op[oi != i], minlength=len(cat.point_ids))
        mine = np.flatnonzero((oi == i) & (others[op] >= 2)
                              & np.isin(op, self._point_sel))
        if self._rejected:
            mine = np.setdiff1d(mine, np.fromiter(self._rejected, dtype=np.int64))
        X = self._gp_est[[at[int(j)] for j in op[mine]]].reshape(-1, GP_SIZE)
        uv = np.asarray(cat.obs_uv, dtype=np.float64).reshape(-1, 2)[mine]
        sigma = np.asarray(cat.obs_sigma, dtype=np.float64)[mine]
        eop = self._resect(i, X, uv, sigma)
        if eop is None and not rejected:  # (a block that did not converge): as it is
            return 0
        wrong = np.zeros(len(rloss.NAV_GROUPS), dtype=bool)
        if eop is not None:
            wrong = self._far_nav(cat.nav_eop[i], cat.nav_sigma[i], eop)
            kept = self._try_start(i, eop, cov, need_convergence=bool(wrong.any()))
            if kept is not None:
                return kept
        # The image's own GPS/INS far from its resection (an INS 45 deg off at a sigma of
        # 0.1 deg kept the block from converging, its wrong points made later images
        # diverge): wrong, if the resection stands on points three other images or more
        # determine; on two-ray points (a block of two fits any relative orientation) an
        # earlier image is the likelier culprit, and the GPS/INS is suspected last.
        firm = int(np.count_nonzero(others[op[mine]] >= 3)) >= MIN_READMIT_POINTS
        for own in (firm, not firm):
            if own and eop is not None and wrong.any():
                kept = self._without_nav(i, eop, cov)
                if kept is not None:
                    return kept
            elif not own and blame:
                more = self._blame_earlier(i, cov)
                if more is not None:
                    return more
        self._leave_out([i])
        return self._solve(cov).iterations

    def _without_nav(self, i: int, eop: FloatArray, cov: Covariance) -> int | None:
        """:meth:`_try_start` at ``eop`` with image ``i``'s GPS/INS groups far from it left
        free (:meth:`_wrong_nav`), needing the block to converge; None: as it was."""
        cat = self._cat
        before = self._state()
        cat.nav_sigma[i] = self._wrong_nav(cat.image_ids[i], cat.nav_eop[i], cat.nav_sigma[i],
                                           eop)
        kept = self._try_start(i, eop, cov, need_convergence=True)
        if kept is None:
            self._restore(before)  # the sigma and its name in nav_downweighted
        return kept

    def _far_nav(self, nav: FloatArray, sigma: FloatArray, start: FloatArray) -> np.ndarray:
        """(g,) bool: the GPS/INS groups (``nav``, ``sigma``) far beyond the loss's core at
        ``start`` (:func:`seqat.robust.nav_far_beyond`)."""
        res = eop_residual(np.asarray(nav, dtype=np.float64)[None], np.asarray(start)[None])
        return rloss.nav_far_beyond(res, sigma, self.options.nav_robust_scale)[0]

    def _try_start(self, i: int, eop: FloatArray, cov: Covariance, *,
                   need_convergence: bool) -> int | None:
        """The block solved with image ``i`` started at ``eop`` (a resection), kept if ``i``'s
        rays fit (and the block converged, ``need_convergence``): the solve's iterations; else
        the state as it was and None."""
        before = self._state()
        self._eop_est[i] = eop
        self._dirty = True
        if need_convergence:  # its points intersected again: not where its GPS/INS put them
            cat = self._cat
            oi, op = cat.rays()
            seen = op[oi == i]
            keep = ~np.isin(self._point_sel, seen)
            self._point_sel, self._gp_est = self._point_sel[keep], self._gp_est[keep]
        try:
            first = self._solve(cov)
            res, more = self._solve_on(cov, first, TRIAL_MORE_SOLVES if need_convergence else 0)
            if not self._rejected_by_rays(i) and (res.converged or not need_convergence):
                return first.iterations + more
        except EstimationError:  # the block fails from there too (a trial: not the end)
            pass
        self._restore(before)
        return None

    def _resect(self, i: int, X: FloatArray, uv: FloatArray, sigma: FloatArray
                ) -> FloatArray | None:
        """Image ``i``'s least-squares resection on the points ``X`` (its rays ``uv``,
        ``sigma``) with the lowest cost, started at its estimate and at the attitude of each
        of the :data:`RESECTION_NEIGHBOURS` images sharing most of its points (a flight's
        neighbours fly level alike; Gauss-Newton from 50 deg off on each axis ends at a
        wrong minimum or behind the points); None if no start converges."""
        cat = self._cat
        oi, op = cat.rays()
        shared = np.bincount(oi[np.isin(op, op[oi == i])], minlength=len(cat.image_ids))
        shared[i] = 0
        if self._diverged:
            shared[np.fromiter(self._diverged, dtype=np.int64)] = 0
        starts = [self._eop_est[i]]
        for j in np.argsort(-shared, kind="stable")[:RESECTION_NEIGHBOURS]:
            if shared[j] > 0:
                starts.append(np.concatenate([self._eop_est[i, :3], self._eop_est[j, 3:]]))
        best, best_cost = None, np.inf
        for start in starts:
            eop = resect(start, X, uv, sigma, self.camera_now)
            if eop is None:
                continue
            n = X.shape[0]
            r = uv - project(np.broadcast_to(eop, (n, EOP_SIZE)), X, self.camera_now)
            c = float(np.sum(rloss.ray_u2(r, sigma)))
            if c < best_cost:
                best, best_cost = eop, c
        return best

    def _blame_earlier(self, i: int, cov: Covariance) -> int | None:
        """Image ``i``'s rays reject the block even from a resection, or most of its points
        fit two places (:meth:`_lost_to_ambiguity`): is an earlier image's poor start to
        blame? The earlier images sharing most of ``i``'s points (at least
        :data:`MIN_SHARED_POINTS`, at most :data:`MAX_BLAMED` of them) are tried in turn:
        the block solved without it (``i`` from its GPS/INS, the points it saw intersected
        again); if ``i`` then fits (:meth:`_unfit`), that image is started again at its
        resection on the block without it, and the block is kept if both fit. Returns the
        solves' iterations, or None (nothing kept: ``i`` is to blame).

        A second image 150 deg off in heading, in a block of two where any relative
        orientation fits its two-ray points, ended 148 deg off, and its wrong points made
        each of the next eight images diverge in its place (the 60-image strip, seed 12)."""
        cat = self._cat
        oi, op = cat.rays()
        seen = np.isin(op, op[oi == i])
        shared = np.bincount(oi[seen], minlength=i + 1)[:i]
        order = [int(j) for j in np.argsort(-shared, kind="stable")
                 if shared[j] >= MIN_SHARED_POINTS and int(j) not in self._diverged]
        before = self._state()
        for j in order[:MAX_BLAMED]:
            try:
                kept = self._blame(i, j, cov)
            except EstimationError:  # a solve of the trial failed: not the culprit
                kept = None
            if kept is not None:
                return kept
            self._restore(before)
        return None

    def _blame(self, i: int, j: int, cov: Covariance) -> int | None:
        """One trial of :meth:`_blame_earlier`: ``j`` left out, then started again at its
        resection; the solves' iterations if ``i`` and ``j`` fit, else None."""
        cat = self._cat
        oi, op = cat.rays()
        self._leave_out([j])
        # i from its GPS/INS, j's points intersected again from the other rays: not where
        # j's poor start put them
        self._eop_est[i] = np.asarray(cat.nav_eop)[i]
        keep = ~np.isin(self._point_sel, op[oi == j])
        self._point_sel, self._gp_est = self._point_sel[keep], self._gp_est[keep]
        self._ambiguous = set()  # tested again without j
        iterations = self._solve(cov).iterations
        if self._unfit(i):
            return None
        self._diverged.discard(j)  # back, from its resection on the others
        self.diverged.remove(cat.image_ids[j])
        iterations += self._start_again(j, cov, blame=False)
        return iterations if j not in self._diverged and not self._unfit(i) else None

    def _state(self) -> dict[str, object]:
        """The solver's state, copied: the catalogue aside (solves only read it) but for its
        GPS/INS sigmas (a trial may leave a group free: :meth:`_without_nav`)."""
        state = _copied({k: v for k, v in vars(self).items() if k != "_cat"})
        state[_CAT_NAV_SIGMA] = list(self._cat.nav_sigma)
        return state

    def _restore(self, state: dict[str, object]) -> None:
        """Back to ``state`` (:meth:`_state`), which stays as it was."""
        vars(self).update(_copied({k: v for k, v in state.items() if k != _CAT_NAV_SIGMA}))
        self._cat.nav_sigma[:] = state[_CAT_NAV_SIGMA]  # type: ignore[index]

    def _leave_out(self, images: list[int]) -> None:
        """The ``images`` (catalogue indices) diverged: their rays left out, started again
        at their GPS/INS, named in :attr:`diverged`."""
        self._diverged |= set(images)
        self.diverged += [self._cat.image_ids[j] for j in images]
        self._eop_est[images] = np.asarray(self._cat.nav_eop)[images]
        self._dirty = True


def _copied(state: dict[str, object]) -> dict[str, object]:
    """``state`` with its arrays and containers copied (the solves change them in place)."""
    return {k: (v.copy() if isinstance(v, (np.ndarray, list, set, dict)) else v)
            for k, v in state.items()}
