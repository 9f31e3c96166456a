"""One run's per-image path, shared by ``seqat run`` and ``seqat watch``.

:class:`RunSession` takes one :class:`~pipeline.run.sources.PreparedFrame` at a time
(:meth:`RunSession.add`): the Seq-R threshold of the latency budget, the estimator's update,
the feedback to the source (initial values and terrain height for the next image), the
listeners (live ortho, ...), the budget's decision for the next image, and the journal
record, written last so that a kill at any moment loses at most the image in flight.
:meth:`RunSession.replay` feeds a journaled frame through the same path (``--resume``), and
:meth:`RunSession.finish` gives the final solution. The session also keeps what the run
folder needs: the update records, the observed pixels (``observations.csv``), per-image
tracking statistics and timings, the nav rows of the images adjusted.
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from pipeline.common.tables import NavTable
from pipeline.run.budget import BudgetEvent, LatencyBudget
from pipeline.run.final_check import FinalCheck, FinalChecker, check_warnings
from pipeline.run.journal import ImageRecord, Journal
from pipeline.run.sources import PreparedFrame
from pipeline.run.store import format_observation_lines
from pipeline.tracking.options import TrackerOptions
from pipeline.tracking.records import TrackerState
from seqat.surface import without_off_surface
from seqat.types import Frame, ImageUpdate, Solution


class Estimator(Protocol):
    """What a run needs from an estimator (SequentialAT, SimultaneousAT)."""

    def add_frame(self, frame: Frame) -> ImageUpdate: ...

    def solution(self) -> Solution: ...


class ImageListener(Protocol):
    """Something that follows a run image by image (live ortho, ...).

    ``on_image`` is called after each update with the frame, its update record and the
    estimator (query ``window_solution()`` there: O(window)) — replayed images of a resumed
    run included, so a listener's state is rebuilt; ``on_finish`` once after the final
    solution, before the run folder is published.
    """

    def on_image(self, frame: Frame, update: ImageUpdate, estimator: Estimator) -> None: ...

    def on_finish(self, solution: Solution) -> None: ...


class FrameFeedback(Protocol):
    """What the session needs from a frame source (:mod:`pipeline.run.sources`)."""

    tracking_options: TrackerOptions | None

    def replay(self, frame: Frame) -> None: ...

    def feedback(self, update: ImageUpdate, estimator: object) -> None: ...

    def tracker_state(self) -> TrackerState | None: ...

    def set_max_features(self, features: int) -> None: ...


@dataclass(frozen=True, kw_only=True)
class ImageLive:
    """Timings and counts of one image (``run.json`` ``images[].live``; the watch line).

    Attributes
    ----------
    image : str
    prep_ms : float
        Reading, tracking and resection.
    update_ms : float
        The estimator's update.
    processing_ms : float
        From the start of the update to the estimate, plus ``prep_ms`` (listeners included).
    latency_ms : float or None
        End to end: the image's input complete (file modification time) -> estimate (watch).
    threshold : float or None
        Seq-R correlation threshold the image was adjusted with.
    window_images : int
    sigma0 : float
    sigma_position_m : tuple[float, float, float]
        A posteriori σ of the new camera's X, Y, Z.
    observations_rejected : int
        Left out by the resection (contradicting the image's initial attitude).
    observations_skipped : int
        Not used by the estimator (pending rays of unborn points, ...).
    """

    image: str
    prep_ms: float
    update_ms: float
    processing_ms: float
    latency_ms: float | None
    threshold: float | None
    window_images: int
    sigma0: float
    sigma_position_m: tuple[float, float, float]
    observations_rejected: int
    observations_skipped: int


def _threshold(estimator: object) -> float | None:
    options = getattr(estimator, "options", None)
    value = getattr(options, "correlation_threshold", None)
    return None if value is None else float(value)


def _set_threshold(estimator: object, threshold: float | None) -> None:
    """Seq-R: the threshold of the next updates (options are frozen: replaced whole)."""
    if threshold is None or threshold == _threshold(estimator):
        return
    estimator.set_correlation_threshold(threshold)  # type: ignore[attr-defined]


#: Images without tie points named one warning each, then one summary line.
MAX_IMAGE_WARNINGS = 20


class RunSession:
    """Feed frames to an estimator one at a time; journal each; keep the run's records.

    Parameters
    ----------
    estimator : Estimator
    source : FrameFeedback
        Gets the estimator's state after each update.
    listeners : sequence of ImageListener
    journal : Journal or None
        Appended after every image.
    budget : LatencyBudget or None
        Adapts the Seq-R threshold between images.
    on_image : callable or None
        Called with each new image's :class:`ImageLive` (the watch display).
    final_check : bool
        When finished, adjust the flight once more from its GPS/INS and publish that if the
        run stopped in a wrong minimum (:mod:`pipeline.run.final_check`).
    """

    def __init__(self, *, estimator: Estimator, source: FrameFeedback,
                 listeners: Sequence[ImageListener] = (), journal: Journal | None = None,
                 budget: LatencyBudget | None = None,
                 on_image: Callable[[ImageLive, ImageUpdate], None] | None = None,
                 final_check: bool = True) -> None:
        self.estimator = estimator
        self._checker = FinalChecker.of(estimator) if final_check else None
        #: The final check's record (None: not run).
        self.final_check: FinalCheck | None = None
        #: The estimator the images went through (``estimator`` may become the final
        #: check's adjustment): its real-time records (second starts) stay the run's.
        self.flown = estimator
        self._frames: list[Frame] = []  # every frame the estimator took, for the check
        self.source = source
        self.listeners = tuple(listeners)
        self.journal = journal
        self.budget = budget
        self.on_image = on_image
        if budget is not None:
            _set_threshold(estimator, budget.threshold)
            opts = source.tracking_options
            budget.track_features(None if opts is None else opts.max_features)
        self.updates: list[ImageUpdate] = []
        self.live: list[ImageLive] = []
        self.tracking: list[Mapping[str, object]] = []
        self.journal_ms: list[float] = []  # time to journal each new image
        self.replayed = 0
        self.n_observations = 0
        self._lines: list[str] = []
        self._points: set[str] = set()
        #: image -> its point ids: its own observations, then late ones of later frames
        self._image_points: dict[str, list[str]] = {}
        self._late_points: dict[str, list[str]] = {}  # image -> late observations' points
        self.n_late = 0
        #: Tie points of the final solution off the surface of their neighbours, not
        #: published (:func:`seqat.surface.off_surface_points`).
        self.off_surface: tuple[str, ...] = ()
        self._nav_ids: list[str] = []
        self._nav_times: list[float] = []
        self._nav_eops: list[np.ndarray] = []

    # ----------------------------------------------------------------------------------------
    def add(self, prepared: PreparedFrame) -> ImageLive:
        """Adjust one new image, tell the source, listeners and budget, journal it."""
        t0 = time.perf_counter()
        frame = prepared.frame
        threshold = _threshold(self.estimator)
        update = self._update(frame)
        latency = (None if prepared.ready_s is None  # the image's estimate is out
                   else (time.time() - prepared.ready_s) * 1e3)
        update = self._refined(update)
        event: BudgetEvent | None = None
        if self.budget is not None:
            self.budget.arrived(prepared.ready_s)
            event = self.budget.after_image(frame.image_id, update.stage,
                                            # the refinement too: the next image waits
                                            prepared.prep_ms + update.processing_ms,
                                            tracking_ms=prepared.prep_ms, latency_ms=latency,
                                            window_images=update.window_images)
            if event is not None:
                self._apply(event)
        processing_ms = prepared.prep_ms + (time.perf_counter() - t0) * 1e3
        live = ImageLive(
            image=frame.image_id, prep_ms=prepared.prep_ms, update_ms=update.update_ms,
            processing_ms=processing_ms, latency_ms=latency, threshold=threshold,
            window_images=update.window_images, sigma0=update.sigma0,
            sigma_position_m=tuple(float(s) for s in update.eop.sigma[:3]),  # type: ignore[arg-type]
            observations_rejected=prepared.rejected,
            observations_skipped=update.observations_skipped)
        if self.journal is not None:
            t_journal = time.perf_counter()
            state = self.source.tracker_state()
            record = ImageRecord(seq=len(self.updates), frame=frame, time_s=prepared.time_s,
                                 observed_px=prepared.observed_px,
                                 late_observed_px=prepared.late_observed_px,
                                 threshold=threshold,
                                 live=dataclasses.asdict(live), tracking=prepared.tracking,
                                 budget_event=None if event is None else dataclasses.asdict(event),
                                 tracker_state=state is not None)
            self.journal.append_image(record, state)
            self.journal_ms.append((time.perf_counter() - t_journal) * 1e3)
        self._keep(update, live, prepared.tracking, prepared.time_s, prepared.observed_px, frame,
                   prepared.late_observed_px)
        if self.on_image is not None:
            self.on_image(live, update)
        return live

    def replay(self, record: ImageRecord) -> None:
        """Feed a journaled frame again (``--resume``): same threshold, same estimate."""
        frame = record.frame
        _set_threshold(self.estimator, record.threshold)
        self.source.replay(frame)
        update = dataclasses.replace(self._refined(self._update(frame)),
                                     update_ms=float(record.live["update_ms"]))  # type: ignore[arg-type]
        if self.budget is not None:
            self.budget.account(update.stage,
                                float(record.live["prep_ms"])  # type: ignore[arg-type]
                                + update.processing_ms)
            if record.budget_event is not None:
                event = BudgetEvent(**record.budget_event)  # type: ignore[arg-type]
                self.budget.apply(event)
                self._apply(event)
        live = ImageLive(**{**record.live,  # type: ignore[arg-type]
                            "sigma_position_m": tuple(record.live["sigma_position_m"])})  # type: ignore[call-overload]
        self._keep(update, live, record.tracking, record.time_s, record.observed_px, frame,
                   record.late_observed_px)
        self.replayed += 1

    def _apply(self, event: BudgetEvent) -> None:
        """The budget's new dials: the estimator's threshold and window cap, the tracker's
        features."""
        _set_threshold(self.estimator, event.new_threshold)
        options = getattr(self.estimator, "options", None)
        if getattr(options, "max_window_images", event.new_window_cap) != event.new_window_cap:
            self.estimator.set_max_window_images(event.new_window_cap)  # type: ignore[attr-defined]
        if event.new_features is not None and event.new_features != event.old_features:
            self.source.set_max_features(event.new_features)

    def _update(self, frame: Frame) -> ImageUpdate:
        """The estimator's update of ``frame``, given to the listeners (the live map): the
        image's estimate is out. The refinement it made due follows (:meth:`_refined`)."""
        if hasattr(self.estimator, "refined"):
            update = self.estimator.add_frame(frame, refine=False)  # type: ignore[call-arg]
        else:
            update = self.estimator.add_frame(frame)
        for listener in self.listeners:
            listener.on_image(frame, update, self.estimator)
        return update

    def _refined(self, update: ImageUpdate) -> ImageUpdate:
        """``update`` and the refinement it made due, run now (``SequentialAT.refined``: the
        re-linearisation, a second start, named in the update; its time is not the
        update's); then the tracker takes the refined window, the next image's start."""
        refined = getattr(self.estimator, "refined", None)
        update = update if refined is None else refined(update)
        self.source.feedback(update, self.estimator)
        return update

    def _keep(self, update: ImageUpdate, live: ImageLive, tracking: Mapping[str, object] | None,
              time_s: float, observed_px: np.ndarray, frame: Frame,
              late_observed_px: np.ndarray) -> None:
        self.updates.append(update)
        self.live.append(live)
        if tracking is not None:
            self.tracking.append(tracking)
        # the frame's late observations first (the estimator took them first)
        self._lines.append(format_observation_lines(
            frame.late_image_ids, frame.late_point_ids, late_observed_px, frame.image_id))
        self._lines.append(format_observation_lines(frame.image_id, frame.point_ids,
                                                    observed_px, frame.image_id))
        self._points.update(frame.point_ids)
        self._points.update(frame.late_point_ids)
        for image, point in zip(frame.late_image_ids, frame.late_point_ids, strict=True):
            self._image_points.setdefault(image, []).append(point)
            self._late_points.setdefault(image, []).append(point)
        self._image_points.setdefault(frame.image_id, []).extend(frame.point_ids)
        self.n_observations += len(frame.point_ids) + frame.n_late
        self.n_late += frame.n_late
        self._frames.append(frame)
        self._nav_ids.append(frame.image_id)
        self._nav_times.append(time_s)
        self._nav_eops.append(frame.nav_eop)

    # ----------------------------------------------------------------------------------------
    def finish(self) -> Solution:
        """Final solution (sequential: the window re-linearised; the flight adjusted from
        its GPS/INS instead when that found the run in a wrong minimum: :attr:`final_check`)
        without the tie points off the surface (:attr:`off_surface`); listeners'
        ``on_finish``."""
        finish = getattr(self.estimator, "finish", None)
        if finish is not None:
            finish()
        solution = self.estimator.solution()
        if self._checker is not None:
            self.final_check, adopted, solution = self._checker.run(self._frames, solution)
            if adopted is not None:  # its records (rejections, ...) are the run's now
                self.estimator = adopted
        solution = self._on_surface(solution)
        for listener in self.listeners:
            listener.on_finish(solution)
        return solution

    def _on_surface(self, solution: Solution) -> Solution:
        """``solution`` without its tie points off the surface (ground control exempt),
        named in :attr:`off_surface`."""
        solution, self.off_surface = without_off_surface(
            solution, getattr(self.estimator, "control", None) or ())
        return solution

    @property
    def images(self) -> int:
        return len(self.updates)

    def tie_point_warnings(self, solution: Solution) -> list[str]:
        """Warnings for images none of whose observations became a ground point of
        ``solution``, and for a flight without any ground point."""
        estimated = {p.point_id for p in solution.points}
        if not estimated:
            return [f"the flight has no tie points: no ground point was estimated from its "
                    f"{len(self._image_points)} images (no overlap, or images that all look "
                    "alike); its EOPs are the GPS/INS nav"]
        lonely = [image for image, points in self._image_points.items()
                  if not estimated.intersection(points)]
        warnings = [f"{image}: no tie points (none of its observations is a ground point of "
                    "the solution); its EOP rests on its GPS/INS nav"
                    for image in lonely[:MAX_IMAGE_WARNINGS]]
        if len(lonely) > MAX_IMAGE_WARNINGS:
            warnings.append(f"{len(lonely) - MAX_IMAGE_WARNINGS} more image(s) without tie "
                            f"points (of {len(self._image_points)})")
        return warnings

    def check_warnings(self) -> list[str]:
        """The final check's warning, when it replaced the run's solution."""
        return check_warnings(self.final_check)

    def late_summary(self, solution: Solution) -> dict[str, object]:
        """``run.json`` ``totals.late``: late observations received, the images that got
        some, and the images tied only thanks to them: every estimated ground point the image
        observes would have fewer than two rays without the late ones."""
        estimated = {p.point_id for p in solution.points}
        rays: Counter[str] = Counter(p for pts in self._image_points.values() for p in pts)
        late: Counter[str] = Counter(p for pts in self._late_points.values() for p in pts)
        late_only = []
        for image, points in self._image_points.items():
            tied = [p for p in points if p in estimated]
            if tied and all(rays[p] - late[p] < 2 for p in tied):
                late_only.append(image)
        order = {iid: k for k, iid in enumerate(self._nav_ids)}
        return {"observations": self.n_late, "images": len(self._late_points),
                "images_tied_only_by_late": sorted(late_only, key=order.__getitem__)}

    def observations_text(self) -> str:
        """Rows of the run's ``observations.csv`` (no header)."""
        return "".join(self._lines)

    def nav(self) -> NavTable:
        """The nav rows of the images adjusted, in order."""
        return NavTable(image_ids=tuple(self._nav_ids),
                        times_s=np.asarray(self._nav_times, dtype=np.float64),
                        eop=np.asarray(self._nav_eops, dtype=np.float64).reshape(-1, 6))
