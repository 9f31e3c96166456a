"""Frame sources of ``seqat run``: one :class:`~seqat.types.Frame` per image, in order.

* :class:`ObservationSource`: an observations flight (``observations.csv`` streamed by
  :class:`pipeline.flight.folder.FrameSource`, checked in a full pass first).
* :class:`ImageSource`: an image flight. Each image is read when its turn comes, handed to
  the streaming tracker (:class:`pipeline.tracking.tracker.Tracker`) with its nav EOP, and the
  tracker's observations of *that image only* become the frame (no look-ahead). After each
  update the estimator's state is fed back (:meth:`ImageSource.feedback`): its terrain
  height for the tracker's footprint prediction, its window points and EOPs for the
  :class:`Initialiser`, which resects the next image's initial attitude and leaves out the
  matches that contradict it.

Both hand out :class:`PreparedFrame` objects (the frame, its observed pixels for the run
folder's ``observations.csv``, the tracking statistics) one image at a time, from a flight
(:meth:`frames`) or, in watch mode, as each image's input completes (:meth:`prepare`).
After a resume, :meth:`replay` takes the journaled frames in place of new ones.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.flight.camera import PixelCorrector
from pipeline.flight.dropout import PoseResection, resect_from_known
from pipeline.flight.folder import Flight, ObservationStats
from pipeline.flight.inputs import SkippedImage
from pipeline.run.resection import Resection, resect_attitude
from pipeline.tracking.options import TrackerOptions
from pipeline.tracking.records import TrackerState
from pipeline.tracking.tracker import Tracker, read_gray_image
from seqat.errors import InputDataError
from seqat.geometry import rays_world
from seqat.types import FloatArray, Frame, ImageUpdate, PinholeCamera

#: A ray must point down by at least this (z of the unit vector) to meet the terrain plane.
MIN_RAY_DOWN = 0.2


class Initialiser:
    """Initial attitude of each new image from the estimator's current state.

    After every update (:meth:`feedback`) it keeps the estimator's current ground points and
    EOPs (Seq-R/Seq-F: the window's, O(window); Sim: all) and the median ground height; for
    each new frame (:meth:`resect`) it resects the attitude at the GPS position
    (:func:`pipeline.run.resection.resect_attitude`) on the known ground points plus the tie
    points seen once before, placed where that earlier image's ray meets the terrain plane
    ``Z = ground_z``: along a strip with 50-60 % overlap most tracks have two rays, so
    without them few images could be resected. Their relief errors (a degree or two) are
    within the RANSAC threshold; the result is an initial value only.

    Parameters
    ----------
    camera : PinholeCamera
        Ideal camera of the frames.
    threshold_deg : float
        RANSAC threshold of the resection.
    """

    def __init__(self, camera: PinholeCamera, threshold_deg: float) -> None:
        self.camera = camera
        self.threshold_deg = threshold_deg
        self.ground_z: float | None = None
        self._known: dict[str, FloatArray] = {}
        self._eops: dict[str, FloatArray] = {}
        self._last_obs: dict[str, tuple[str, FloatArray]] = {}  # point -> (image, frame uv)

    def resect(self, frame: Frame, *, reject: bool = True) -> tuple[Frame, Resection, int,
                                                                    np.ndarray]:
        """Resect a new frame (pixels of :attr:`camera`) and leave out the observations it
        rejects.

        ``reject=False`` keeps every observation (precomputed or replayed image points,
        already cleaned by the run that wrote them).

        :meth:`record` the frame once it goes to the estimator.

        Returns
        -------
        frame : Frame
            With ``initial_eop`` (or ``None``) and without the rejected observations.
        resection : Resection
        known : int
            Known ground points among the observations.
        keep : (k,) bool
            The observations kept (``False``: left out).
        """
        point_ids, uv = frame.point_ids, frame.uv_px
        known = [k for k, p in enumerate(point_ids) if p in self._known]
        xyz = [self._known[point_ids[k]] for k in known]
        used = list(known)
        if self.ground_z is not None:
            plane = [k for k, p in enumerate(point_ids)
                     if p not in self._known and p in self._last_obs]
            if plane:
                eops = np.array([self._eops[self._last_obs[point_ids[k]][0]] for k in plane])
                uvs = np.array([self._last_obs[point_ids[k]][1] for k in plane])
                rays = rays_world(eops, uvs, self.camera)
                down = rays[:, 2] < -MIN_RAY_DOWN
                t = (self.ground_z - eops[down, 2]) / rays[down, 2]
                xyz += list(eops[down, :3] + t[:, None] * rays[down])
                used += [k for k, d in zip(plane, down, strict=True) if d]
        res = resect_attitude(np.array(xyz).reshape(-1, 3), uv[used], self.camera,
                              frame.nav_eop, self.threshold_deg)
        keep = np.ones(len(point_ids), dtype=bool)
        if res.eop is not None and reject:
            # a plane point from a late ray never rejects the observation: the late ray's
            # image may be one without ties yet, its attitude the INS's (degrees off), and
            # the point is what would tie it (Seneca IMG_0455)
            late = {p for p in frame.late_point_ids if p not in self._known}
            out = [k for k in np.asarray(used, dtype=np.int64)[~res.inliers].tolist()
                   if point_ids[k] not in late]
            keep[np.asarray(out, dtype=np.int64)] = False
        frame = dataclasses.replace(frame, point_ids=tuple(np.asarray(point_ids)[keep]),
                                    uv_px=uv[keep], initial_eop=res.eop)
        return frame, res, len(known), keep

    def bridge(self, frame: Frame, *, reject: bool = True) -> tuple[Frame | None, PoseResection,
                                                                    np.ndarray]:
        """A GNSS dropout frame (``inf`` position σ): 6-DoF resection on the known ground
        points (:func:`pipeline.flight.dropout.resect_pose`) as its ``initial_eop``.

        ``reject`` leaves out the observations of known points that disagree with the pose.

        Returns
        -------
        frame : Frame or None
            ``None`` when the image cannot be resected (``resection.reason`` says why).
        resection : PoseResection
        keep : (k,) bool
            The observations kept.
        """
        res, used = resect_from_known(frame.point_ids, frame.uv_px, self._known, self.camera,
                                      sigma_px=frame.sigma_px, start_eop=frame.nav_eop)
        keep = np.ones(len(frame.point_ids), dtype=bool)
        if res.eop is None:
            return None, res, keep
        if reject:
            keep[used[~res.inliers]] = False
        frame = dataclasses.replace(frame, point_ids=tuple(np.asarray(frame.point_ids)[keep]),
                                    uv_px=frame.uv_px[keep], initial_eop=res.eop)
        return frame, res, keep

    def record_late(self, frame: Frame) -> None:
        """Keep the late rays a frame carries (of earlier images the estimator still
        holds), before the frame is resected: a new image's feature that joined a track
        only through a late observation then has that earlier ray as a plane point."""
        for iid, pid, uv in zip(frame.late_image_ids, frame.late_point_ids, frame.late_uv_px,
                                strict=True):
            if iid in self._eops and pid not in self._known:
                self._last_obs[pid] = (iid, uv)

    def record(self, frame: Frame) -> None:
        """Keep the rays of a frame sent to the estimator (plane points of later frames):
        its late rays (:meth:`record_late`, idempotent), then its own."""
        self.record_late(frame)
        for pid, uv in zip(frame.point_ids, frame.uv_px, strict=True):
            self._last_obs[pid] = (frame.image_id, uv)

    def feedback(self, update: ImageUpdate, estimator: object) -> None:
        """Take the estimator's current ground points and EOPs after an update."""
        if update.n_points_total == 0:
            return
        window = getattr(estimator, "window_solution", None)
        solution = window() if window is not None else estimator.solution()  # type: ignore[attr-defined]
        self._known = {p.point_id: p.xyz_m for p in solution.points}
        self._eops = {e.image_id: e.eop for e in solution.eops}
        self._last_obs = {p: o for p, o in self._last_obs.items() if o[0] in self._eops}
        if solution.points:
            self.ground_z = float(np.median([p.xyz_m[2] for p in solution.points]))


@dataclass(frozen=True, kw_only=True, eq=False)
class PreparedFrame:
    """A frame ready for the estimator, with what the run folder keeps of it.

    Attributes
    ----------
    frame : Frame
        Ideal pixels, initial EOP from the resection, observations it rejected left out.
    time_s : float
        Acquisition time (nav).
    observed_px : (k, 2) float
        Observed pixels of the frame's observations (``observations.csv`` of the run).
    late_observed_px : (m, 2) float
        Observed pixels of the frame's late observations (of earlier images).
    tracking : Mapping or None
        Tracker statistics and resection counts (image flights).
    rejected : int
        Observations left out because they contradict the resection.
    prep_ms : float
        Reading, tracking and resection, milliseconds.
    ready_s : float or None
        Wall-clock time (``time.time()``) at which the image's input was complete (watch
        mode: the file's modification time), for the end-to-end latency.
    """

    frame: Frame
    time_s: float
    observed_px: FloatArray
    tracking: Mapping[str, object] | None = None
    rejected: int = 0
    prep_ms: float = 0.0
    ready_s: float | None = None
    late_observed_px: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))


def with_control(flight: Flight, frame: Frame, observed_px: FloatArray) -> tuple[Frame,
                                                                               FloatArray]:
    """The frame with the flight's GCP observations of its image (``gcp:NAME``) appended; an
    observation of the same point already in the frame (a replayed ``observations.csv``) is
    replaced. Returns the frame and its observed pixels."""
    control = flight.control
    ids, uv = control.for_image(frame.image_id) if control is not None else ((), None)
    if not ids or uv is None:
        return frame, observed_px
    gcp = set(ids)
    keep = np.array([p not in gcp for p in frame.point_ids], dtype=bool)
    point_ids = tuple(p for p, k in zip(frame.point_ids, keep, strict=True) if k) + ids
    frame = dataclasses.replace(frame, point_ids=point_ids,
                                uv_px=np.vstack([frame.uv_px[keep], flight.frame_pixels(uv)]))
    return frame, np.vstack([np.asarray(observed_px).reshape(-1, 2)[keep], uv])


def _not_bridged(image_id: str, resection: PoseResection) -> SkippedImage:
    return SkippedImage(image=image_id, reason=f"{image_id}: GNSS dropout not bridged: "
                                               f"{resection.reason}")


class _InitialisedSource:
    """What both frame sources share: the :class:`Initialiser` their frames go through."""

    _init: Initialiser

    def replay(self, frame: Frame) -> None:
        """A journaled frame goes to the estimator again (:meth:`Initialiser.record`)."""
        self._init.record(frame)

    def feedback(self, update: ImageUpdate, estimator: object) -> None:
        """Take the estimator's state after an update (:meth:`Initialiser.feedback`)."""
        self._init.feedback(update, estimator)

    def tracker_state(self) -> TrackerState | None:
        """The tracker after the last image (``None``: no tracker)."""
        return None

    def set_max_features(self, features: int) -> None:
        """The latency budget's feature dial (:mod:`pipeline.run.budget`): no tracker here."""


class ObservationSource(_InitialisedSource):
    """Frames of an observations flight (validate in one streaming pass first)."""

    tracking_options: TrackerOptions | None = None

    def __init__(self, flight: Flight) -> None:
        self._flight = flight
        self._init = Initialiser(flight.camera, flight.config.tracking.resection_threshold_deg)
        #: GNSS dropout images left out (no resection) and bridged so far.
        self.skipped: list[SkippedImage] = []
        self.bridged: list[str] = []

    def validate(self) -> ObservationStats:
        """Read the whole observations file once, raising on the first problem."""
        return self._flight.frames().validate()

    def frames(self, start: int = 0) -> Iterator[PreparedFrame | SkippedImage]:
        """The flight's frames from nav row ``start`` on (earlier rows are read, not used);
        a GNSS dropout that cannot be bridged comes as its :class:`SkippedImage`."""
        times = self._flight.nav.times_s
        for k, (frame, observed, late) in enumerate(self._flight.frames().with_observed()):
            if k >= start:
                yield self.prepare(frame, observed, float(times[k]),
                                   dropout=self._flight.is_dropout(k), late_observed_px=late)

    def prepare(self, frame: Frame, observed_px: FloatArray, time_s: float,
                ready_s: float | None = None, *, dropout: bool = False,
                late_observed_px: FloatArray | None = None) -> PreparedFrame | SkippedImage:
        """Give a frame of precomputed observations its initial EOP (nothing is rejected); a
        dropout (``dropout``) is resected in 6 DoF on the known points, or skipped.
        ``late_observed_px``: observed pixels of the frame's late observations."""
        t0 = time.perf_counter()
        self._init.record_late(frame)
        frame, observed_px = with_control(self._flight, frame, observed_px)
        if dropout:
            bridged, res, _ = self._init.bridge(frame, reject=False)
            if bridged is None:
                skip = _not_bridged(frame.image_id, res)
                self.skipped.append(skip)
                return skip
            frame = bridged
            self.bridged.append(frame.image_id)
        else:
            frame, _, _, _ = self._init.resect(frame, reject=False)
        self._init.record(frame)
        late = np.zeros((0, 2)) if late_observed_px is None else late_observed_px
        return PreparedFrame(frame=frame, time_s=time_s, observed_px=observed_px,
                             prep_ms=(time.perf_counter() - t0) * 1e3, ready_s=ready_s,
                             late_observed_px=np.asarray(late, dtype=np.float64).reshape(-1, 2))


def read_tracker_image(path: Path, tracker: Tracker, width_px: int, height_px: int) -> np.ndarray:
    """An image as 8-bit gray for the tracker: reduced JPEG decode, camera size / factor.

    An image of another size (same aspect ratio, checked by
    :func:`pipeline.flight.folder.read_flight`) is resampled to the size the tracker expects.
    """
    factor = tracker.decode_factor
    image = read_gray_image(path, factor)
    want = (height_px // factor, width_px // factor)
    if image.shape != want:
        full = read_gray_image(path, 1)
        image = cv2.resize(full, (want[1], want[0]), interpolation=cv2.INTER_AREA)
    return image


class ImageSource(_InitialisedSource):
    """Frames of an image flight: read, track, emit the image's observations.

    Parameters
    ----------
    flight : Flight
        An image flight (:attr:`Flight.kind` ``"images"``); its camera, corrector and sigmas
        are used (its nav only by :meth:`frames`).
    options : TrackerOptions
    """

    def __init__(self, flight: Flight, options: TrackerOptions) -> None:
        self._flight = flight
        self.tracking_options = options
        camera = flight.camera_config
        self._tracker = Tracker(options, camera, ideal_pixels=(
            PixelCorrector(camera=camera).ideal_pixels if camera.has_distortion else None))
        self._init = Initialiser(flight.camera, options.resection_threshold_deg)
        #: GNSS dropout images left out (no resection) and bridged so far.
        self.skipped: list[SkippedImage] = []
        self.bridged: list[str] = []

    def frames(self, start: int = 0) -> Iterator[PreparedFrame | SkippedImage]:
        """The flight's images from nav row ``start`` on, one tracked frame each (a GNSS
        dropout that cannot be bridged: its :class:`SkippedImage`)."""
        nav = self._flight.nav
        for row in range(start, len(nav)):
            nav_eop, nav_sigma = self._flight.frame_nav(row)
            yield self.prepare(nav.image_ids[row], self._flight.image_paths[row], nav_eop,
                               float(nav.times_s[row]), nav_sigma=nav_sigma,
                               dropout=self._flight.is_dropout(row))

    def prepare(self, image_id: str, path: Path, nav_eop: FloatArray, time_s: float,
                ready_s: float | None = None, *, nav_sigma: FloatArray | None = None,
                dropout: bool = False) -> PreparedFrame | SkippedImage:
        """Read and track one image; resect its attitude and drop what contradicts it. A
        dropout (``dropout``; ``nav_sigma`` inf where the nav is missing) is resected in
        6 DoF on the known points instead, or skipped."""
        flight = self._flight
        cam = flight.camera_config
        t0 = time.perf_counter()
        try:
            gray = read_tracker_image(path, self._tracker, cam.width_px, cam.height_px)
        except InputDataError as err:  # corrupt image data: this image only is left out
            skip = SkippedImage(image=image_id, reason=str(err))
            self.skipped.append(skip)
            return skip
        read_ms = (time.perf_counter() - t0) * 1e3
        if nav_sigma is None:
            nav_sigma = flight.nav_sigma
        tracked = self._tracker.add_image(image_id, gray, nav_eop, self._init.ground_z)
        observed: FloatArray = np.asarray(tracked.uv_px, dtype=np.float64).reshape(-1, 2)
        late_observed = np.asarray(tracked.late_uv_px, dtype=np.float64).reshape(-1, 2)
        frame = Frame(image_id=image_id, nav_eop=nav_eop, nav_sigma=nav_sigma,
                      point_ids=tracked.point_ids, uv_px=flight.frame_pixels(observed),
                      sigma_px=flight.config.sigma_image_px,
                      late_image_ids=tracked.late_image_ids,
                      late_point_ids=tracked.late_point_ids,
                      late_uv_px=flight.frame_pixels(late_observed))
        # the late rays of earlier images: plane points of this image's resection
        self._init.record_late(frame)
        stats: dict[str, object] = {**dataclasses.asdict(tracked.stats), "read_ms": read_ms}
        if dropout:
            cleaned, pose, keep = self._init.bridge(frame)
            stats.update({"dropout": True, "resection_points": pose.n_points,
                          "resection_inliers": pose.n_inliers,
                          "resection_used": cleaned is not None,
                          "observations_rejected": int((~keep).sum())})
            if cleaned is None:
                skip = _not_bridged(image_id, pose)
                self.skipped.append(skip)
                return skip
            cleaned, observed_kept = with_control(flight, cleaned, observed[keep])
            bridged, _, _ = self._init.bridge(cleaned, reject=False)  # as a replay does
            frame = cleaned if bridged is None else bridged
            self.bridged.append(image_id)
        else:
            cleaned, first, known, keep = self._init.resect(frame)
            # the surveyed GCP observations are never rejected by the resection
            cleaned, observed_kept = with_control(flight, cleaned, observed[keep])
            # the initial value from the kept observations only, as a replay of them
            # (--observations) computes it: the sequential result depends on it
            frame, res, _, _ = self._init.resect(cleaned, reject=False)
            stats.update({"resection_points": first.n_points, "resection_known_points": known,
                          "resection_inliers": first.n_inliers,
                          "resection_used": res.eop is not None,
                          "observations_rejected": int((~keep).sum())})
        self._init.record(frame)
        rejected = int((~keep).sum())
        return PreparedFrame(frame=frame, time_s=time_s, observed_px=observed_kept,
                             tracking=stats, rejected=rejected,
                             prep_ms=(time.perf_counter() - t0) * 1e3, ready_s=ready_s,
                             late_observed_px=late_observed)

    def tracker_state(self) -> TrackerState | None:
        """The tracker after the last image (journaled after every image)."""
        return self._tracker.state()

    def set_max_features(self, features: int) -> None:
        """Detect at most ``features`` per image from the next image on (the latency
        budget's feature dial, :mod:`pipeline.run.budget`)."""
        self._tracker.set_max_features(features)

    def restore_tracker(self, state: TrackerState) -> None:
        """Continue tracking from a journaled state (``--resume``)."""
        self._tracker.restore(state)
