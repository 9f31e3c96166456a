"""Frame sources of ``seqat run``: one :class:`~seqat.types.Frame` per image, in order.

* :class:`ObservationSource`: an observations flight (``observations.csv`` streamed by
  :class:`pipeline.flight.FrameSource`, checked in a full pass first).
* :class:`ImageSource`: an image flight. Each image is read when its turn comes, handed to
  the streaming tracker (:class:`pipeline.tracking.Tracker`) with its nav EOP, and the
  tracker's observations of *that image only* become the frame (no look-ahead). The
  estimator's current terrain height is fed back to the tracker after each update
  (:meth:`ImageSource.feedback`) for the footprint prediction of the next images.

Both keep the observed (distorted, full-resolution) pixels of every frame for the run
folder's ``observations.csv``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.flight import Flight, ObservationStats
from pipeline.store import format_observation_lines
from pipeline.tracking import Tracker, TrackerOptions, TrackStats
from seqat.errors import InputDataError
from seqat.types import FloatArray, Frame, ImageUpdate

#: Update the tracker's terrain height from the estimator every this many images.
GROUND_HEIGHT_EVERY = 5


@dataclass(frozen=True, kw_only=True)
class SourceStats:
    """Counts over a whole run (``run.json`` ``totals``)."""

    n_observations: int
    n_points: int
    n_images_observed: int


class ObservationSource:
    """Frames of an observations flight (validated in one streaming pass up front)."""

    tracking_options: TrackerOptions | None = None

    def __init__(self, flight: Flight) -> None:
        self._flight = flight
        self._frames = flight.frames()
        self._stats: ObservationStats = self._frames.validate()
        self._lines: list[str] = []
        self.tracking_stats: tuple[TrackStats, ...] = ()

    def __iter__(self) -> Iterator[Frame]:
        for frame, observed in self._frames.with_observed():
            self._lines.append(format_observation_lines(frame.image_id, frame.point_ids,
                                                        observed))
            yield frame

    def feedback(self, update: ImageUpdate, estimator: object) -> None:
        """Nothing to adapt for precomputed observations."""

    def stats(self) -> SourceStats:
        return SourceStats(n_observations=self._stats.n_observations,
                           n_points=self._stats.n_points,
                           n_images_observed=self._stats.n_images_observed)

    def observations_text(self) -> str:
        return "".join(self._lines)


def read_gray(path: Path, width_px: int, height_px: int) -> np.ndarray:
    """An image as 8-bit gray at the camera's size (resampled if it has another size).

    Raises
    ------
    InputDataError
        OpenCV cannot decode the file.
    """
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputDataError(f"{path}: OpenCV cannot decode the image")
    if image.shape != (height_px, width_px):
        image = cv2.resize(image, (width_px, height_px), interpolation=cv2.INTER_AREA)
    return image


class ImageSource:
    """Frames of an image flight: read, track, emit the image's observations.

    Parameters
    ----------
    flight : Flight
        An image flight (:attr:`Flight.kind` ``"images"``).
    options : TrackerOptions
    """

    def __init__(self, flight: Flight, options: TrackerOptions) -> None:
        self._flight = flight
        self.tracking_options = options
        self._tracker = Tracker(options, flight.camera_config)
        self._ground_z: float | None = None
        self._lines: list[str] = []
        self._stats: list[TrackStats] = []
        self._read_ms: list[float] = []
        self._points: set[str] = set()
        self._n_obs = 0
        self._count = 0

    @property
    def tracking_stats(self) -> tuple[TrackStats, ...]:
        return tuple(self._stats)

    @property
    def read_ms(self) -> tuple[float, ...]:
        """Image decoding time per image, milliseconds."""
        return tuple(self._read_ms)

    def __iter__(self) -> Iterator[Frame]:
        flight = self._flight
        cam = flight.camera_config
        for row, (image_id, path) in enumerate(zip(flight.nav.image_ids, flight.image_paths,
                                                   strict=True)):
            t0 = time.perf_counter()
            gray = read_gray(path, cam.width_px, cam.height_px)
            self._read_ms.append((time.perf_counter() - t0) * 1e3)
            tracked = self._tracker.add_image(image_id, gray, flight.nav.eop[row],
                                              self._ground_z)
            self._stats.append(tracked.stats)
            observed: FloatArray = np.asarray(tracked.uv_px, dtype=np.float64).reshape(-1, 2)
            self._lines.append(format_observation_lines(image_id, tracked.point_ids, observed))
            self._points.update(tracked.point_ids)
            self._n_obs += len(tracked.point_ids)
            yield Frame(image_id=image_id, nav_eop=flight.nav.eop[row],
                        nav_sigma=flight.nav_sigma, point_ids=tracked.point_ids,
                        uv_px=flight.corrector.ideal_pixels(observed),
                        sigma_px=flight.config.sigma_image_px)

    def feedback(self, update: ImageUpdate, estimator: object) -> None:
        """Refresh the terrain height the tracker predicts footprints with.

        Every :data:`GROUND_HEIGHT_EVERY` images, the median height of the ground points in
        the estimator's current window (or of all, for Sim).
        """
        self._count += 1
        if self._count % GROUND_HEIGHT_EVERY and self._ground_z is not None:
            return
        if update.n_points_total == 0:
            return
        window = getattr(estimator, "window_solution", None)
        solution = window() if window is not None else estimator.solution()  # type: ignore[attr-defined]
        if solution.points:
            self._ground_z = float(np.median([p.xyz_m[2] for p in solution.points]))

    def stats(self) -> SourceStats:
        observed = sum(1 for s in self._stats if s.features > 0)
        return SourceStats(n_observations=self._n_obs, n_points=len(self._points),
                           n_images_observed=observed)

    def observations_text(self) -> str:
        return "".join(self._lines)
