"""The final check of a sequential run: the whole flight adjusted once more, from its GPS/INS
(``run.json`` ``robustness.final_check``; docs/algorithm.md, *A wrong minimum*).

A sequential estimator — Seq-R, or Sim refitting after every image — starts each solve where
the last one stopped. When a later image ties a part of the flight that its own images
determined poorly to the rest (the take-off images of the real block flight, tied to a
return strip by a dozen points over flat fields), the solve that follows can stop in a
wrong minimum of the robust cost: on the real flight started at its 6th image, its first
four images ended 7-14 m and 7 deg from where the whole flight puts them, 16 times the
sigma of the flight adjusted at once, in both Seq-R and the sequential Sim
(docs/benchmarks.md, *A wrong minimum*). Gauss-Newton from there stays there; adjusting the
flight once, started from its GPS/INS, does not.

So when the run is finished, the flight is adjusted once by Sim from the GPS/INS ("cold").
Where every image agrees with the run within :data:`MOVED_SIGMA` of the cold sigmas, nothing
changes (the run's own solution is published). Otherwise the run's EOPs are adjusted by the
same Sim ("warm": the run's minimum, at the cost Sim measures) and the cold solution replaces
the run's when it fits the data better by :data:`MIN_GAIN` (in units of the variance of unit
weight) without leaving out an image the warm one keeps. When the warm adjustment itself
leaves the run's EOPs (an image beyond :data:`MOVED_SIGMA` of its sigmas), the run is no
minimum of Sim's cost at all (an image it carried by a wrong INS, its rays left out, which
Sim places by its rays): the better fitting of the two adjustments is published, on the
same condition. Its cost is one Sim adjustment of the flight (6.6 s for 70 images of the
real flight, 3.2 s for the 384 of the paper's strip), two when images moved.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.run.accuracy import eop_differences
from seqat.errors import SeqatError
from seqat.sequential import SequentialAT
from seqat.simultaneous import SimOptions, SimultaneousAT
from seqat.types import EOP_SIZE, ControlPoint, Frame, PinholeCamera, Solution

#: A check's adjustment that fails this way leaves the run's solution standing (a check must
#: not end a run that succeeded; a cold start from a GPS/INS far off can leave the camera's
#: domain, which the camera's own checks report as a bad camera).
_FAILURES = (SeqatError, np.linalg.LinAlgError)
#: An image whose EOP differs between the run and the cold adjustment by more than this many
#: of the cold adjustment's sigmas (in any component) has moved.
MOVED_SIGMA = 3.0
#: The cold adjustment replaces the run's when its cost is lower than the warm one's, at the
#: warm one's redundancy, by this many variances of unit weight (twice a log-likelihood
#: ratio: e^12.5). Two solves of one minimum differ by a few (the robust weights of a few
#: rays; up to 17 on the real flight's subsets); two minima of the real flight by 150.
MIN_GAIN = 25.0


@dataclass(frozen=True, kw_only=True)
class FinalCheck:
    """``run.json`` ``robustness.final_check``.

    Attributes
    ----------
    seconds : float
        Time the check took (its one or two adjustments).
    max_moved_sigma : float or None
        Largest difference of an EOP component between the run and the cold adjustment, in
        the cold adjustment's sigmas (``None``: the cold adjustment failed).
    moved_images : tuple[str, ...]
        Images beyond :data:`MOVED_SIGMA`.
    sigma0_warm, sigma0_cold : float or None
        Variance-of-unit-weight roots of the warm and cold adjustments (warm: only when
        images moved).
    gain : float or None
        ``r_warm (sigma0_warm^2 / sigma0_cold^2 - 1)``: how much better the cold solution
        fits, in variances of unit weight (only when images moved).
    warm_moved_images : tuple[str, ...]
        Images the warm adjustment moved beyond :data:`MOVED_SIGMA` of its sigmas from the
        run's EOPs it started at (the run is no minimum of Sim's cost there).
    adopted : bool
        An adjustment of the check was published instead of the run's solution: the cold
        one with a gain above :data:`MIN_GAIN`, or, when the warm one left the run's EOPs,
        the better fitting of the two; either only when it diverges no image the other
        keeps and every sigma is finite.
    published : str
        ``"run"``, ``"cold"`` or ``"warm"``: whose solution the run's files hold.
    failed : str
        Why the cold (or warm) adjustment gave no solution; empty otherwise.
    """

    seconds: float
    max_moved_sigma: float | None
    moved_images: tuple[str, ...] = ()
    sigma0_warm: float | None = None
    sigma0_cold: float | None = None
    gain: float | None = None
    warm_moved_images: tuple[str, ...] = ()
    adopted: bool = False
    published: str = "run"
    failed: str = ""


class FinalChecker:
    """The check of one run: the estimator's camera, Sim options and ground control, taken
    when the run starts (before a finished run narrows its robust loss)."""

    def __init__(self, camera: PinholeCamera, options: SimOptions,
                 control: Sequence[ControlPoint]) -> None:
        self.camera = camera
        self.options = options
        self.control = tuple(control)

    @classmethod
    def of(cls, estimator: object) -> FinalChecker | None:
        """The check of a run by ``estimator`` (``None``: a Sim adjusting once at the end is
        already the cold adjustment; an estimator of another kind is not checked)."""
        if isinstance(estimator, SimultaneousAT):
            if not estimator.refit_every_frame:
                return None
            opts = estimator.options
        elif isinstance(estimator, SequentialAT):
            opts = estimator.options.sim_options()
        else:
            return None
        return cls(estimator.camera, opts, tuple(estimator.control.values()))

    def _adjust(self, frames: Sequence[Frame], start: dict[str, np.ndarray] | None,
                ) -> tuple[SimultaneousAT, Solution]:
        """Sim, adjusting once, of ``frames`` started at ``start`` (image id -> EOP) or at
        their GPS/INS (``None``; not at the run's resections, made from its estimates, but
        for a GNSS dropout's, which has no GPS/INS to start from)."""
        sim = SimultaneousAT(self.camera, self.options, refit_every_frame=False,
                             control=self.control)
        for f in frames:
            if start is not None:
                init = start.get(f.image_id)
            else:  # a GNSS dropout has no GPS/INS to start from: its resection stays
                init = None if np.all(np.isfinite(f.nav_sigma)) else f.initial_eop
            sim.add_frame(dataclasses.replace(f, initial_eop=init))
        return sim, sim.solution()

    def run(self, frames: Sequence[Frame], solution: Solution,
            ) -> tuple[FinalCheck, SimultaneousAT | None, Solution]:
        """Check the run's ``solution`` of ``frames``.

        Returns
        -------
        (FinalCheck, SimultaneousAT or None, Solution)
            The record; the published adjustment's estimator and solution when one is
            adopted, else ``None`` and ``solution``.
        """
        t0 = time.perf_counter()
        try:
            cold, sol_c = self._adjust(frames, None)
        except _FAILURES as err:
            return FinalCheck(seconds=time.perf_counter() - t0, max_moved_sigma=None,
                              failed=f"cold: {err}"), None, solution
        moved, worst = moved_images(solution, sol_c)
        if not moved:
            return FinalCheck(seconds=time.perf_counter() - t0, max_moved_sigma=worst,
                              sigma0_cold=sol_c.sigma0), None, solution
        try:
            warm, sol_w = self._adjust(frames, {e.image_id: e.eop for e in solution.eops})
        except _FAILURES as err:
            return FinalCheck(seconds=time.perf_counter() - t0, max_moved_sigma=worst,
                              moved_images=moved, sigma0_cold=sol_c.sigma0,
                              failed=f"warm: {err}"), None, solution
        gain = fit_gain(sol_w, sol_c)
        left = moved_images(solution, sol_w)[0]
        pick: tuple[str, SimultaneousAT, Solution, SimultaneousAT] | None = None
        if gain > (0.0 if left else MIN_GAIN):
            pick = ("cold", cold, sol_c, warm)
        elif left:  # the run is no minimum: Sim from its own EOPs fits better
            pick = ("warm", warm, sol_w, cold)
        adopted = pick is not None and set(pick[1].diverged) <= set(pick[3].diverged) and all(
            np.all(np.isfinite(e.sigma) & (e.sigma > 0)) for e in pick[2].eops)
        check = FinalCheck(seconds=time.perf_counter() - t0, max_moved_sigma=worst,
                           moved_images=moved, sigma0_warm=sol_w.sigma0,
                           sigma0_cold=sol_c.sigma0, gain=gain, warm_moved_images=left,
                           adopted=adopted, published=pick[0] if adopted and pick else "run")
        return (check, pick[1], pick[2]) if adopted and pick else (check, None, solution)


def moved_images(run: Solution, cold: Solution) -> tuple[tuple[str, ...], float]:
    """The images of ``run`` whose EOP differs from ``cold``'s by more than
    :data:`MOVED_SIGMA` of ``cold``'s sigmas in some component (angles wrapped), in flight
    order, and the largest such ratio (0 when none is finite)."""
    rows, d_pos, d_att = eop_differences(
        tuple(e.image_id for e in cold.eops), np.array([e.eop for e in cold.eops]),
        tuple(e.image_id for e in run.eops), np.array([e.eop for e in run.eops]))
    sigma = np.array([cold.eops[r].sigma for r in rows], dtype=np.float64).reshape(-1, EOP_SIZE)
    sigma[:, 3:] = np.degrees(sigma[:, 3:])  # eop_differences gives degrees
    d = np.abs(np.concatenate([d_pos, d_att], axis=1))
    ok = np.isfinite(sigma) & (sigma > 0)
    z = np.max(np.where(ok, d / np.where(ok, sigma, 1.0), 0.0), axis=1, initial=0.0)
    moved = tuple(cold.eops[r].image_id for r in rows[z > MOVED_SIGMA])
    return moved, float(z.max(initial=0.0))


def fit_gain(warm: Solution, cold: Solution) -> float:
    """How much better ``cold`` fits than ``warm``: ``r_w (s_w^2 / s_c^2 - 1)``, the cost
    difference at the warm redundancy ``r_w`` in variances of unit weight (NaN-safe: -inf
    when either is not finite)."""
    s_w, s_c, r_w = float(warm.sigma0), float(cold.sigma0), int(warm.redundancy)
    if not (np.isfinite(s_w) and np.isfinite(s_c) and s_c > 0):
        return float("-inf")
    return r_w * (s_w**2 / s_c**2 - 1.0)


def check_warnings(check: FinalCheck | None) -> list[str]:
    """The warning of a check that replaced the run's solution."""
    if check is None or not check.adopted:
        return []
    n = len(check.moved_images)
    names = ", ".join(check.moved_images[:5]) + (f" and {n - 5} more" if n > 5 else "")
    if check.published == "warm":
        how = (f"the run's estimates adjusted again, which Sim moves from them (sigma0 "
               f"{check.sigma0_warm:.4f}; from the GPS/INS {check.sigma0_cold:.4f})")
    else:
        how = (f"the flight adjusted from its GPS/INS, which fits the data better (sigma0 "
               f"{check.sigma0_warm:.4f} -> {check.sigma0_cold:.4f})")
    return [f"final check: the sequential solution was in a wrong minimum ({n} image(s) up "
            f"to {check.max_moved_sigma:.0f} sigma away: {names}); published {how}"]
