"""The iterations of one sequential update: Gauss-Newton on the new rows, with its guards.

Mixed into :class:`seqat.sequential.SequentialAT` (its state lives there). Each iterate
linearises the update's rows (:class:`seqat.rows.RowBuilder`) at the last iterate and solves
Eq. 13-14 (:func:`seqat.update.solve_update`) until the rows describe the image points at the
new estimate (docs/algorithm.md, *Diverged updates* and *A poor start*).

A start far from the solution (an INS 20 deg off at a turn, no resection for lack of known
points) can send the first, least-squares iterate out of the models' domain: on Seneca's
every third image, IMG_0507's first iterate moved the self-calibrated focal length by
-2709 px to a negative value, and the flight stopped (exit 2, "camera f_px must be a
positive number": blamed on the input). And the robust loss, on from the second iterate,
can keep a wrong minimum near such a start: every ray is then beyond its core, so it
down-weights them all. An iterate outside the domain (not finite, a camera with a focal
length <= 0, a failed solve), a converged estimate that most of the new image's rays to
known points lie far beyond the loss's core of (seqat.robust.unsupported_images), and an
estimate left short of convergence that most of those rays lie beyond the core of, or so
far from a prior that the update would diverge the image (a GNSS fault at a start resected
from it) are not kept: the update starts again from
its start values with the window held (its cofactor taken as zero: a least-squares
resection of the new image with the birth of its points), then iterates jointly from
there; a second time the held phase starts from the attitude of the window's last image.
The third time, the image is diverged (its GPS/INS alone carries it, named).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from seqat.births import degenerate_points
from seqat.errors import EstimationError
from seqat.geometry import wrap_angle
from seqat.rows import RowBuilder
from seqat.types import EOP_SIZE, FloatArray
from seqat.update import LinearRows, UpdateSolution, solve_update
from seqat.window import Key

#: The held phase starts a last time at the window's last image's attitude when that lies
#: this far from the image's start (degrees; closer, it is the same start).
NEIGHBOUR_START_DEG = 5.0


@dataclass(frozen=True)
class Iterated:
    """What the iterations of one update ended with.

    ``sol`` is the solve of ``rows`` (``None`` when it met a degenerate birth);
    ``degenerate`` the born points (index in the update) to hold back; ``wild`` is True when
    the update failed again after the window was held, an iterate outside the models'
    domain or an estimate most of the image's rays reject (the image diverges).
    """

    rows: LinearRows
    sol: UpdateSolution | None
    d1t: FloatArray
    d2: FloatArray
    iterations: int
    degenerate: list[int] = field(default_factory=list)
    wild: bool = False


class IterationMixin:
    """:meth:`_iterate_update` for :class:`seqat.sequential.SequentialAT`."""

    def _in_domain(self, x1t: FloatArray, d1t: FloatArray, d2: FloatArray,
                   col_of: dict[Key, int]) -> bool:
        """The iterate is finite and its camera a camera (focal length > 0). Far moves inside
        the domain are left to the iterations (Gauss-Newton from a poor start comes back)
        and to the final test, :meth:`_diverged`."""
        if not (np.all(np.isfinite(d1t)) and np.all(np.isfinite(d2))):
            return False
        cam_key = self._cam_key  # type: ignore[attr-defined]
        if cam_key is None:
            return True
        c, size = col_of[cam_key], self._cam.size  # type: ignore[attr-defined]
        return self._cam.admissible(x1t[c:c + size] + d1t[c:c + size])  # type: ignore[attr-defined]

    def _iterate_update(self, builder: RowBuilder, Qtt: FloatArray, touched: np.ndarray,
                        terms: bool, x1t: FloatArray, x2_0: FloatArray, born: list[int],
                        born_xyz: FloatArray,
                        y12: list[tuple[int, int, FloatArray, float]],
                        y22: list[tuple[int, FloatArray, float]],
                        col_of: dict[Key, int], image: int) -> Iterated:
        """Iterate the update (the window's block ``Qtt``, rows from ``builder``) until its
        rows describe the image points at the estimate, at most ``max_update_iterations`` per
        phase (held window, joint).

        The first iterate of a phase is least squares, the robust losses (rays, GPS/INS)
        from the second on: a bad start is no outlier."""
        opts = self.options  # type: ignore[attr-defined]
        d1t, d2 = np.zeros(touched.size), np.zeros(x2_0.size)
        zero = np.zeros_like(Qtt)
        held = 0  # held phases started (_held_start)
        hold: bool | None = None  # None: the window not held (yet); True: held; False: after
        start = iterations = 0  # the iterations before this phase
        while True:
            iterations += 1
            builder.robust = iterations - start > 1 and not hold
            rows = builder.rows(x1t, x2_0, d1t, d2)
            try:
                step = solve_update(zero if hold else Qtt, touched, rows, block=True,
                                    terms=terms)
            except EstimationError:
                # a point being born that its rays no longer fix (an iterate sent it far
                # off): it waits for more rays; else the iterate left the models' domain
                degenerate = degenerate_points(rows, len(born))
                if degenerate:
                    return Iterated(rows, None, d1t, d2, iterations, degenerate)
                step = None
            if step is not None:
                d1t, d2 = step.delta1_touched, step.delta2
                degenerate = self._unstable_births(  # type: ignore[attr-defined]
                    born, born_xyz, y12, y22, x1t + d1t, x2_0 + d2, col_of)
                if degenerate:
                    return Iterated(rows, step, d1t, d2, iterations, degenerate)
            if step is not None and self._in_domain(x1t, d1t, d2, col_of):
                # Converged when the rows, linearised where they were, still describe the
                # image points at the new estimate: re-linearising would move it by less. The
                # first iterate is least squares: it is the robust one too when every image
                # point there lies within the loss's core (weight 1; clean data).
                lin = builder.linearisation_error(x1t, x2_0, d1t, d2)
                last = iterations - start >= opts.max_update_iterations
                if hold:  # the resection, least squares: then the window too, from there
                    if last or lin < opts.iteration_tolerance_px:
                        hold, start = False, iterations
                        # a GPS/INS group far from the resection its rays hold is wrong (a
                        # GNSS jump of 100 m): its loss on from the next iterate
                        builder.nav_loss_at(x1t, x2_0 + d2, image, born)
                    continue
                converged = lin < opts.iteration_tolerance_px and builder.settled()
                if not (last or converged):
                    continue
                # a converged estimate most of the image's rays reject as outliers (far
                # beyond the loss's core): the robust loss may have kept a poor start. One
                # the iterations left short of convergence, already when most of its rays lie
                # beyond the core (which those far beyond are too), or so far from a prior
                # that the update would diverge the image (a GNSS fault at a start resected
                # from it: the rays and the GPS/INS pull apart, ten iterates crawl between
                # them, or a tilt compensates the position over flat ground)
                if converged:
                    rejected = builder.unsupported(image, born)
                else:
                    diverged = self._diverged  # type: ignore[attr-defined]
                    rejected = builder.unsupported(image, born, 1.0) or diverged(
                        builder.nav, builder.nav_sigma, x2_0, d2, Qtt, d1t,
                        builder.rays_hold(image, born))
                if not rejected:
                    return Iterated(rows, step, d1t, d2, iterations)
            # out of the models' domain, or rejected by the image's rays: started again with
            # the window held (_held_start); with no start left, the image diverges (named;
            # its GPS/INS carries it)
            again = self._held_start(held, x2_0)
            if again is None:
                return Iterated(rows, step, d1t, d2, iterations, wild=True)
            held, hold, start, d2 = held + 1, True, iterations, again
            d1t = np.zeros(touched.size)
            builder.resect_without_far_nav(x2_0 + d2)

    def _held_start(self, held: int, x2_0: FloatArray) -> FloatArray | None:
        """The step ``d2`` the update's next held phase starts from, after ``held`` of them:
        the start values, then the attitude of the window's last image
        (:meth:`_neighbour_start`); None: no start left (the image diverges)."""
        if held == 0:
            return np.zeros(x2_0.size)
        return self._neighbour_start(x2_0) if held == 1 else None

    def _neighbour_start(self, x2_0: FloatArray) -> FloatArray | None:
        """The step ``d2`` that starts the new image at the attitude of the window's last
        image (a flight's consecutive images fly alike), if that lies more than
        :data:`NEIGHBOUR_START_DEG` from its start; else None. Gauss-Newton from an INS
        150 deg off in heading found no resection with the window held, from the previous
        image's attitude it did."""
        w, images = self._w, self._window_images  # type: ignore[attr-defined]
        if not images or ("e", images[-1]) not in w.offset:
            return None
        d2 = np.zeros(x2_0.size)
        d2[3:EOP_SIZE] = wrap_angle(w.x[w.index(("e", images[-1]))][3:] - x2_0[3:EOP_SIZE])
        return d2 if np.degrees(np.abs(d2[3:EOP_SIZE])).max() > NEIGHBOUR_START_DEG else None
