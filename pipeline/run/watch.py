"""``seqat watch FLIGHT --out OUT``: georeference a flight folder while it is being written.

``FLIGHT/flight.yaml`` exists from the start; images arrive in the images folder, nav rows in
a growing ``nav.csv`` or in each image's EXIF/XMP, and, for an observations flight, image
points in a growing ``observations.csv``. Every poll (:class:`GrowingFlight`) finds the
inputs completed since the last one (docs/formats.md, *Watched flights*):

* an image is complete once its name is final (writers use ``name.jpg.part`` or a hidden
  name and rename) and it holds the JPEG end-of-image marker after its image data;
* a CSV line counts once it ends with a newline;
* an observations flight's image is complete once its nav row is (its rows come before).

Images are adjusted in acquisition order (nav-file order; for nav in EXIF, the order in
which they complete) through the same :class:`~pipeline.run.session.RunSession` as ``seqat run``,
with its journal, latency budget and listeners. An image waits for its nav row (and a nav row
for its image) up to ``wait_timeout_s``, then it is skipped with a reason. Each image prints
one line (:func:`live_line`). New input is read after every image (a backlog's rows each keep
the time of the poll that found them). Ctrl-C (or SIGTERM) or ``idle_timeout_s`` without new
input stops the watch cleanly: the results so far are published as by ``seqat run``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import numpy as np
import pyproj
from rich.console import Console
from rich.text import Text

from pipeline.common.columns import FLIGHT_YAML, NAV_GEODETIC_COLUMNS, OBS_FRAME_COLUMN
from pipeline.common.csvio import CsvRow, CsvTail
from pipeline.common.outdir import claim_output_folder, output_errors, release_output_folder
from pipeline.common.paths import file_problem
from pipeline.common.strict_yaml import build_dataclass
from pipeline.common.tables import NavTable
from pipeline.flight.camera import frame_camera
from pipeline.flight.folder import (
    Flight,
    camera_from_exif,
    check_image_size,
    geodetic_nav_eop,
    read_truth,
    resampling_warnings,
)
from pipeline.flight.gcp import ODM_GCP_FILE
from pipeline.flight.image_metadata import (
    ImageMetadata,
    check_jpeg_complete,
    found_tags,
    read_image_metadata,
    require_position,
)
from pipeline.flight.inputs import SkippedImage
from pipeline.flight.nav_files import (
    NAV_PROJECTED_COLUMNS,
    OBSERVATION_COLUMNS,
    NavRowChecker,
    check_lat_lon,
)
from pipeline.flight.navigation import (
    IMAGE_SUFFIXES,
    MIN_IMAGES,
    geodetic_to_eop,
    resolve_projected_crs,
    resolve_working_crs,
)
from pipeline.flight.observation_rows import (
    FrameRows,
    ObservationGroup,
    outside_tolerance_px,
    row_image_frame,
)
from pipeline.flight.schema import CameraConfig, FlightConfig, load_flight_config
from pipeline.run.live_view import LiveEstimates
from pipeline.run.runner import (
    KEEP_UP,
    EstimatorConfig,
    Method,
    RunSummary,
    estimator_options,
    load_estimator_config,
    load_journal,
    make_budget,
    make_estimator,
    publish_run,
    replay_journal,
    run_fingerprint,
    start_journal,
    with_calibration,
)
from pipeline.run.session import ImageListener, ImageLive, RunSession
from pipeline.run.sources import ImageSource, ObservationSource, PreparedFrame
from pipeline.run.store import to_jsonable
from seqat.errors import ConfigError, InputDataError
from seqat.types import FloatArray, Frame, ImageUpdate

#: Seconds between polls of the flight folder.
DEFAULT_POLL_S = 0.05
#: Seconds an image waits for its nav row, a nav row for its image, an image file to complete.
DEFAULT_WAIT_TIMEOUT_S = 10.0


@dataclass(frozen=True, kw_only=True)
class WatchOptions:
    """Options of ``seqat watch``.

    Attributes
    ----------
    idle_timeout_s : float or None
        Stop after this long without new input (None: until Ctrl-C).
    wait_timeout_s : float
        How long an image waits for its nav row (and a nav row for its image, a file for its
        end-of-image marker) before it is skipped.
    poll_s : float
        Seconds between polls.
    """

    idle_timeout_s: float | None = None
    wait_timeout_s: float = DEFAULT_WAIT_TIMEOUT_S
    poll_s: float = DEFAULT_POLL_S

    def __post_init__(self) -> None:
        for name in ("idle_timeout_s", "wait_timeout_s", "poll_s"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ConfigError(f"--{name.replace('_', '-')}: expected a positive number, "
                                  f"got {value!r}")


@dataclass(frozen=True, kw_only=True, eq=False)
class Arrival:
    """One image whose input is complete, ready for its source's ``prepare``.

    ``path`` for image flights; ``observed_px`` and ``point_ids`` for observations flights,
    and the late observations of earlier images that arrived with the image (``frame``
    column, docs/formats.md): ``late_image_ids``, ``late_point_ids``, ``late_observed_px``.
    ``ready_s`` is the wall-clock time the last of its inputs was complete.
    """

    image: str
    time_s: float
    nav_eop: FloatArray
    ready_s: float
    path: Path | None = None
    point_ids: tuple[str, ...] = ()
    observed_px: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))
    late_image_ids: tuple[str, ...] = ()
    late_point_ids: tuple[str, ...] = ()
    late_observed_px: FloatArray = dataclasses.field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True, kw_only=True)
class _NavRow:
    image: str
    time_s: float
    eop: FloatArray
    ready_s: float
    first_seen: float  # monotonic


class ImageWatcher:
    """Complete JPEGs of a folder that is being written to (module docstring)."""

    def __init__(self, folder: Path, done: set[str], wait_timeout_s: float) -> None:
        self.folder = folder
        self._done = done
        self._wait = wait_timeout_s
        self._incomplete: dict[str, tuple[tuple[int, int], float, str]] = {}

    def poll(self, now: float) -> tuple[list[tuple[str, Path, float]], list[SkippedImage]]:
        """``(image, path, ready wall time)`` of newly complete images; files given up on."""
        ready: list[tuple[str, Path, float]] = []
        given_up: list[SkippedImage] = []
        try:
            entries = sorted(os.scandir(self.folder), key=lambda e: e.name)
        except OSError as err:
            raise InputDataError(f"{self.folder}: cannot list the image folder: "
                                 f"{err.strerror or err}") from err
        for entry in entries:
            name = entry.name
            stem, suffix = os.path.splitext(name)
            if name.startswith(".") or suffix.lower() not in IMAGE_SUFFIXES or stem in self._done:
                continue
            path = Path(entry.path)
            try:
                st = path.stat()
                key = (st.st_size, st.st_mtime_ns)
                known = self._incomplete.get(stem)
                if known is not None and known[0] == key:  # unchanged and still incomplete
                    if now - known[1] > self._wait:
                        self._done.add(stem)
                        given_up.append(SkippedImage(image=stem, reason=f"{known[2]} after "
                                                     f"{self._wait:g} s"))
                    continue
                check_jpeg_complete(path)
                after = path.stat()
            except FileNotFoundError:
                continue  # renamed or removed meanwhile
            except InputDataError as err:
                first = now if known is None else known[1]
                self._incomplete[stem] = (key, first, str(err))
                continue
            if (after.st_size, after.st_mtime_ns) != key:
                continue  # still being written
            self._incomplete.pop(stem, None)
            self._done.add(stem)
            ready.append((stem, path, max(after.st_ctime, after.st_mtime)))
        return ready, given_up

    def pending(self) -> list[SkippedImage]:
        """Files still incomplete (when the watch stops)."""
        return [SkippedImage(image=stem, reason=f"{reason} when the watch stopped")
                for stem, (_, _, reason) in self._incomplete.items() if stem not in self._done]


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return time.time()


def _late_before_nav(row: CsvRow, image: str, frame: str) -> InputDataError:
    return row.error(f"field 'image': late observation of image {image!r} in frame {frame!r}, "
                     "whose nav row has not arrived before (a row's frame is its image or a "
                     "later one)")


class GrowingFlight:
    """The inputs of a flight folder that is being written, as complete images (:meth:`poll`).

    The working CRS and the camera are fixed by the first image (or come from ``setup``, a
    resumed journal's); :attr:`flight` exists from then on.

    Parameters
    ----------
    folder : Path
    config : FlightConfig
    done : set[str]
        Images already adjusted or skipped (a resumed journal's); their inputs are ignored.
    wait_timeout_s : float
    setup : Mapping or None
        ``crs`` (WKT), ``camera``, ``camera_approximate`` of a resumed journal.
    """

    def __init__(self, folder: Path, config: FlightConfig, done: set[str],
                 wait_timeout_s: float, setup: dict[str, object] | None = None) -> None:
        self.folder, self.config = folder, config
        source = str(folder / FLIGHT_YAML)
        self._source = source
        self._done = done
        self._journaled = frozenset(done)  # their rows are read again, and ignored
        self._wait = wait_timeout_s
        self.warnings: list[str] = []
        self.resampled: list[ImageMetadata] = []  # images of another size: warned at the end
        self.images_dir = folder / config.images if config.images is not None else None
        if self.images_dir is not None and not self.images_dir.is_dir():
            raise InputDataError(f"{self.images_dir}: no such image folder (images in {source})")
        self.kind = ("observations" if config.observations is not None
                     else "images" if config.nav.source == "file" else "exif")
        if config.observations is None and config.images is None:
            raise ConfigError(f"{source}: give observations: (image points) or images: (a "
                              "folder of images to track)")
        if self.kind == "observations" and config.camera is None:
            raise ConfigError(f"{source}: camera: required for an observations flight")
        self.crs: pyproj.CRS | None = None
        self.camera: CameraConfig | None = config.camera
        self.camera_approximate = False
        if setup is not None:
            self.crs = pyproj.CRS.from_wkt(str(setup["crs"]))
            self.camera = build_dataclass(CameraConfig, setup["camera"], source, key="camera")
            self.camera_approximate = bool(setup["camera_approximate"])
        elif config.nav.source == "file" and config.nav.frame == "projected":
            self.crs = resolve_projected_crs(config.crs, source)
        self.nav_path = folder / config.nav.file
        self._nav = (CsvTail(self.nav_path, NAV_PROJECTED_COLUMNS if config.nav.frame ==
                             "projected" else NAV_GEODETIC_COLUMNS)
                     if config.nav.source == "file" else None)
        self._nav_checker = NavRowChecker(NAV_PROJECTED_COLUMNS if config.nav.frame ==
                                          "projected" else NAV_GEODETIC_COLUMNS)
        self._rows: list[_NavRow] = []
        self._obs = (CsvTail(folder / config.observations, OBSERVATION_COLUMNS,
                             (OBS_FRAME_COLUMN,))
                     if config.observations is not None else None)
        # the same reader of the rows as seqat run's; a frame's group is complete at its
        # nav row (closed then, or earlier by a row of the next frame: kept in _closed)
        self._frame_rows = (FrameRows(self.camera, outside_tolerance_px(config.sigma_image_px),
                                      open_frame=lambda row, frame, image: -1,
                                      check_late=self._check_late,
                                      on_outside=lambda err: self.warnings.append(
                                          f"{err}; left out"))
                            if self.camera is not None else None)
        self._closed: dict[str, ObservationGroup] = {}
        self._unchecked_late: list[tuple[CsvRow, str, str]] = []  # :meth:`_check_late`
        self._images = (ImageWatcher(self.images_dir, set(done), wait_timeout_s)
                        if self.images_dir is not None and self.kind != "observations" else None)
        self._ready: dict[str, tuple[Path, float, float]] = {}  # image -> path, ready, seen
        self._last_time = -np.inf
        self.flight: Flight | None = None
        self._make_flight()

    # ----------------------------------------------------------------------------------------
    def setup(self) -> dict[str, object]:
        """CRS and camera for the journal (``kind: setup``)."""
        assert self.crs is not None and self.camera is not None
        return {"crs": self.crs.to_wkt(), "camera": to_jsonable(self.camera),
                "camera_approximate": self.camera_approximate}

    def _make_flight(self) -> None:
        if self.flight is not None or self.crs is None or self.camera is None:
            return
        cam = self.camera
        empty = NavTable(image_ids=(), times_s=np.zeros(0), eop=np.zeros((0, 6)))
        obs = self.folder / self.config.observations if self.config.observations else None
        calibration, camera, corrector = frame_camera(cam, self.config.self_calibration,
                                                      self.camera_approximate)
        self.flight = Flight(path=self.folder, config=self.config, crs=self.crs,
                             camera_config=cam, camera_approximate=self.camera_approximate,
                             camera=camera, corrector=corrector, calibration=calibration,
                             nav=empty, nav_sigma=self.config.nav.sigma_eop,
                             observations_path=obs, images_dir=self.images_dir)

    # ----------------------------------------------------------------------------------------
    def poll(self, now: float) -> tuple[list[Arrival | SkippedImage], bool]:
        """Images complete since the last poll, in order, and images given up on.

        Returns
        -------
        items : list of Arrival or SkippedImage
        activity : bool
            Something new arrived (a line, a file), complete or not.
        """
        items: list[Arrival | SkippedImage] = []
        activity = self._poll_nav(now)
        self._check_unchecked_late()
        if self._obs is not None:
            activity |= self._poll_observations()
        if self._images is not None:
            ready, given_up = self._images.poll(now)
            items += given_up
            activity |= bool(ready or given_up)
            for image, path, ready_s in ready:
                self._ready[image] = (path, ready_s, now)
        if self.kind == "exif":
            items += self._exif_arrivals()
        else:
            items += self._ordered_arrivals(now)
        return items, activity

    def _poll_nav(self, now: float) -> bool:
        if self._nav is None:
            return False
        rows = self._nav.poll()
        if not rows:
            return False
        ready_s = _mtime(self.nav_path)
        geodetic = self.config.nav.frame == "geodetic"
        for row in rows:
            image, time_s, values = self._nav_checker.check(row)
            if image in self._done:
                continue
            v = np.asarray(values, dtype=np.float64)
            if geodetic:
                check_lat_lon(self.nav_path, (image,), v.reshape(1, 6))
                if self.crs is None:
                    self.crs = resolve_working_crs(self.config.crs, float(v[1]), float(v[0]),
                                                   source=self._source)
                    self._make_flight()  # an observations flight: its camera is known
                eop = geodetic_nav_eop(self.config, self.crs, v[None, :3], v[None, 3:])[0]
            else:
                eop = np.concatenate([v[:3], np.radians(v[3:])])
            self._rows.append(_NavRow(image=image, time_s=time_s, eop=eop, ready_s=ready_s,
                                      first_seen=now))
        return True

    def _poll_observations(self) -> bool:
        assert self._obs is not None and self._frame_rows is not None
        rows = self._obs.poll()
        for row in rows:
            image, frame = row_image_frame(row)
            if frame in self._journaled:
                continue
            if frame in self._done:
                raise row.error(f"rows of {'image' if frame == image else 'frame'} {frame!r} "
                                "are not contiguous or arrive after its nav row (a frame's "
                                "observation rows, its late observations of earlier images "
                                "included, are appended together, before its nav row)")
            group = self._frame_rows.add(row)
            if group is not None:
                self._closed[group.image_id] = group
        return bool(rows)

    def _check_late(self, row: CsvRow, image: str, frame: str, nav_row: int) -> None:
        """A late row's image must have come before its frame (docs/formats.md, *Watched
        flights*): unknown, the row waits for the next reading of nav.csv, before its frame
        can arrive; with the frame's nav row read, the image's would be too: an error now."""
        if self._known(image):
            return
        if self._known(frame):
            raise _late_before_nav(row, image, frame)
        self._unchecked_late.append((row, image, frame))

    def _known(self, image: str) -> bool:
        return image in self._done or any(r.image == image for r in self._rows)

    def _check_unchecked_late(self) -> None:
        """Late rows read before this reading of nav.csv: their images are in now, or error."""
        for row, image, frame in self._unchecked_late:
            if not self._known(image):
                raise _late_before_nav(row, image, frame)
        self._unchecked_late.clear()

    def _ordered_arrivals(self, now: float) -> list[Arrival | SkippedImage]:
        """Nav-file order: each row's image (or observations), waiting for what is missing."""
        items: list[Arrival | SkippedImage] = []
        while self._rows:
            row = self._rows[0]
            if self.kind == "observations":
                items.append(self._observations_arrival(row))
            elif row.image in self._ready:
                path, ready_s, _ = self._ready.pop(row.image)
                items.append(self._image_arrival(row.image, path, max(ready_s, row.ready_s),
                                                 row.time_s, row.eop))
            elif now - row.first_seen > self._wait:
                items.append(SkippedImage(image=row.image, reason=(
                    f"{row.image}: listed in {self.config.nav.file} but no complete image in "
                    f"{self.images_dir} after {self._wait:g} s")))
            else:
                break
            self._done.add(row.image)
            self._rows.pop(0)
        listed = {r.image for r in self._rows}
        for image, (path, _, seen) in list(self._ready.items()):
            if image not in listed and now - seen > self._wait:
                del self._ready[image]
                self._done.add(image)
                items.append(SkippedImage(image=image, reason=(
                    f"{path.name}: no row in {self.config.nav.file} after {self._wait:g} s")))
        return items

    def _observations_arrival(self, row: _NavRow) -> Arrival:
        """The image of nav row ``row`` with its frame's observation rows (none: no rows)."""
        rows = self._frame_rows
        assert rows is not None
        group = rows.close() if rows.current == row.image else self._closed.pop(row.image, None)
        if group is None:
            return Arrival(image=row.image, time_s=row.time_s, nav_eop=row.eop,
                           ready_s=row.ready_s)
        return Arrival(image=row.image, time_s=row.time_s, nav_eop=row.eop,
                       ready_s=row.ready_s, point_ids=group.point_ids, observed_px=group.uv_px,
                       late_image_ids=group.late_image_ids,
                       late_point_ids=group.late_point_ids, late_observed_px=group.late_uv_px)

    def _exif_arrivals(self) -> list[Arrival | SkippedImage]:
        """Nav in EXIF/XMP: each complete image in the order they completed."""
        items: list[Arrival | SkippedImage] = []
        for image, (path, ready_s, _) in sorted(self._ready.items(), key=lambda kv: kv[1][1]):
            del self._ready[image]
            self._done.add(image)
            try:
                meta = read_image_metadata(path)
                require_position(meta)
                if meta.time_s is None or not meta.has_attitude or meta.attitude_frame is None:
                    missing = "acquisition time" if meta.time_s is None else "attitude in XMP"
                    raise InputDataError(f"{path.name}: no {missing} (found: {found_tags(meta)})")
            except InputDataError as err:
                items.append(SkippedImage(image=image, reason=str(err)))
                continue
            assert meta.lon_deg is not None and meta.lat_deg is not None and meta.h_m is not None
            if self.crs is None:
                self.crs = resolve_working_crs(self.config.crs, meta.lon_deg, meta.lat_deg)
            eop = geodetic_to_eop(
                np.array([meta.lon_deg]), np.array([meta.lat_deg]), np.array([meta.h_m]),
                np.array([[meta.roll_deg, meta.pitch_deg, meta.yaw_deg]], dtype=np.float64),
                [meta.attitude_frame], [meta.height_kind], self.crs, self.config.nav.boresight,
                np.asarray(self.config.nav.lever_arm_m))[0]
            if meta.time_s <= self._last_time:
                self.warnings.append(f"{path.name}: time {meta.time_s!r} s is not after the "
                                     "previous image's")
            self._last_time = max(self._last_time, meta.time_s)
            items.append(self._image_arrival(image, path, ready_s, meta.time_s, eop, meta))
        return items

    def _image_arrival(self, image: str, path: Path, ready_s: float, time_s: float,
                       eop: FloatArray, meta: ImageMetadata | None = None) -> (
            Arrival | SkippedImage):
        """An image with its nav; the camera from its EXIF if it is the first; size checked."""
        try:
            meta = meta or read_image_metadata(path)
        except InputDataError as err:
            return SkippedImage(image=image, reason=str(err))
        if self.camera is None:
            self.camera, self.camera_approximate = camera_from_exif(meta), True
        self._make_flight()
        skip, warning = check_image_size(meta, self.camera)
        self.resampled += [meta] if warning is not None else []
        if skip is not None:
            return SkippedImage(image=image, reason=skip)
        return Arrival(image=image, time_s=time_s, nav_eop=eop, ready_s=ready_s, path=path)

    def pending(self) -> list[SkippedImage]:
        """What is still waiting when the watch stops, as skipped images."""
        nav = self.config.nav.file
        items = [SkippedImage(image=r.image, reason=f"{r.image}: listed in {nav}; no complete "
                              "image when the watch stopped") for r in self._rows]
        items += [SkippedImage(image=i, reason=f"{p.name}: no row in {nav} when the watch "
                               "stopped") for i, (p, _, _) in self._ready.items()]
        if self._images is not None:
            items += self._images.pending()
        return items


# --------------------------------------------------------------------------------------------
# The watch loop
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT / SIGTERM set ``stop`` (the image in flight finishes); a second one raises."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def live_line(live: ImageLive, budget_ms: float | None) -> Text:
    """The line ``seqat watch`` prints per image."""
    text = Text()
    text.append(f"{live.image:<14}", style="bold")
    if live.latency_ms is not None:
        late = budget_ms is not None and live.latency_ms > budget_ms
        text.append(f" latency {live.latency_ms:6.0f} ms", style="red" if late else "green")
    text.append(f"  (track {live.prep_ms:4.0f} + AT {live.update_ms:4.0f} ms)")
    sxyz = " ".join(f"{s:.3f}" for s in live.sigma_position_m)
    text.append(f"  window {live.window_images:3d}  σ0 {live.sigma0:5.2f}  σXYZ {sxyz} m")
    text.append(f"  rejected {live.observations_rejected}  skipped {live.observations_skipped}")
    if live.threshold is not None:
        text.append(f"  ρ≥{live.threshold:g}")
    return text


class ImagePaths(dict[str, Path]):
    """Image id -> file of the arrived images; ``get`` of another id looks in the folder."""

    def __init__(self, folder: Path | None) -> None:
        super().__init__()
        self.folder = folder

    def get(self, key: str, default: Path | None = None) -> Path | None:  # type: ignore[override]
        if key in self:
            return self[key]
        if self.folder is not None:
            for suffix in IMAGE_SUFFIXES:
                for name in (key + suffix, key + suffix.upper()):
                    if (self.folder / name).is_file():
                        self[key] = self.folder / name
                        return self[key]
        return default


#: Makes a watch's listeners once the first image fixes CRS and camera: (flight, image files).
ListenerFactory = Callable[[Flight, Mapping[str, Path]], Sequence[ImageListener]]


def watch_flight(flight_dir: Path | str, out_dir: Path | str, *,
                 method: Method = Method.SEQ_R, options_path: Path | str | None = None,
                 threshold: float | None = None, initial_images: int | None = None,
                 budget_ms: float | str | None = KEEP_UP, resume: bool = False,
                 watch: WatchOptions = WatchOptions(), listeners: Sequence[ImageListener] = (),
                 console: Console | None = None, stop: threading.Event | None = None,
                 on_image: Callable[[ImageLive, ImageUpdate], None] | None = None,
                 make_listeners: ListenerFactory | None = None,
                 stop_sigma_m: float | None = None,
                 on_claimed: Callable[[Path], None] | None = None) -> RunSummary:
    """Adjust a flight folder's images as they appear; publish the run folder when stopped.

    Parameters
    ----------
    flight_dir : Path or str
        Flight folder with ``flight.yaml`` (module docstring).
    out_dir : Path or str
        Run folder, as ``seqat run`` writes it (``OUT/journal/`` after every image).
    method, options_path, threshold, initial_images, resume, listeners
        As :func:`pipeline.run.runner.run_flight`.
    budget_ms : float, ``"keep-up"`` or None
        The latency budget (:mod:`pipeline.run.budget`): N ms per image, keep up with the
        arrivals (the default), or none.
    watch : WatchOptions
    console : Console or None
        Where the per-image lines go (default: stderr).
    stop : threading.Event or None
        Set it to stop the watch (Ctrl-C and SIGTERM set it too).
    on_image : callable or None
        Called after each image (default: print :func:`live_line`).
    make_listeners : callable or None
        More listeners (the live ortho), made when the first image fixes CRS and camera.
    stop_sigma_m : float or None
        The user's stop criterion (every ground point σ ≤ this), for ``OUT/live/``.
    on_claimed : callable or None
        Called with OUT once it is claimed and journaled (``--serve`` starts its server).

    Returns
    -------
    RunSummary
        ``stopped``: ``idle`` or ``interrupted``.

    Raises
    ------
    ConfigError, InputDataError
        Bad options, ``flight.yaml`` or input row (the journal is kept: fix the input and
        watch again with ``--resume``); fewer than two images adjusted.
    """
    t_start = time.perf_counter()
    method = Method(method)
    out = Path(out_dir)
    config = load_estimator_config(options_path) if options_path is not None else EstimatorConfig()
    options = estimator_options(method, config, threshold=threshold,
                                initial_images=initial_images)
    budget = make_budget(budget_ms, method, options)
    folder = Path(flight_dir)
    if not folder.is_dir():
        raise InputDataError(f"{folder}: no such flight folder")
    yaml_path = folder / FLIGHT_YAML
    if not yaml_path.is_file():
        raise InputDataError(f"{yaml_path}: {file_problem(yaml_path)} (seqat watch needs "
                             "flight.yaml from the start)")
    if out.exists() and not out.is_dir():
        raise InputDataError(f"{out}: exists and is not a folder")
    flight_config = load_flight_config(yaml_path)
    console = console or Console(stderr=True, soft_wrap=True)
    if flight_config.gcp is not None or (folder / ODM_GCP_FILE).is_file():
        console.print(f"seqat: warning: {folder}: seqat watch does not use ground control "
                      "points yet (gcp: / gcp_list.txt); seqat run or seqat process on the "
                      "finished flight does", highlight=False, markup=False)
    fingerprint = run_fingerprint(folder, method, options, False, None)
    # everything is checked before OUT is touched: a config error never replaces the journal
    contents = load_journal(out, fingerprint, resume, console)
    skipped = list(contents.skips) if contents is not None else []
    done = {s.image for s in skipped}
    if contents is not None:
        done |= {r.frame.image_id for r in contents.images}
    grow = GrowingFlight(folder, flight_config, done, watch.wait_timeout_s,
                         dict(contents.setup) if contents and contents.setup else None)
    inputs_read = [folder, grow.images_dir, options_path,
                   None if flight_config.observations is None
                   else folder / flight_config.observations,
                   folder / flight_config.nav.file if flight_config.nav.source == "file"
                   else None]
    created = claim_output_folder(out, inputs_read)
    try:
        with output_errors(out):
            journal = start_journal(out, fingerprint, contents)
    except BaseException:
        release_output_folder(out, created)
        raise
    stop = stop or threading.Event()
    stopped = "interrupted"
    paths = ImagePaths(grow.images_dir)
    made: list[ImageListener] = []
    estimates: list[LiveEstimates] = []
    try:
        if on_claimed is not None:
            on_claimed(out)
        session: RunSession | None = None
        source: ObservationSource | ImageSource | None = None
        show = on_image or (lambda live, _: console.print(
            live_line(live, None if budget is None else budget.limit_ms), soft_wrap=True))

        def printer(live: ImageLive, update: ImageUpdate) -> None:
            for e in estimates:
                e.on_live(live)
            show(live, update)

        def start() -> tuple[RunSession, ObservationSource | ImageSource]:
            flight = grow.flight
            assert flight is not None
            if contents is None or contents.setup is None:
                journal.append_setup(grow.setup())
            src: ObservationSource | ImageSource = (
                ObservationSource(flight) if grow.kind == "observations"
                else ImageSource(flight, flight_config.tracking))
            if make_listeners is not None:
                made.extend(make_listeners(flight, paths))
            estimates.append(LiveEstimates(
                out, crs_wkt=flight.crs.to_wkt(), camera=flight.camera,
                stop_sigma_m=stop_sigma_m,
                images=paths if grow.kind != "observations" else None))
            s = RunSession(estimator=make_estimator(
                method, flight.camera, with_calibration(options, flight.calibration)), source=src,
                           listeners=(*listeners, *made, *estimates), journal=journal,
                           budget=budget, on_image=printer)
            replay_journal(s, src, journal, contents)
            if s.replayed:
                console.print(f"seqat: resumed after {s.replayed} images from the journal",
                              highlight=False, markup=False)
            return s, src

        if grow.flight is not None and contents is not None and contents.images:
            session, source = start()
        last_activity = time.monotonic()
        with _stop_on_signals(stop):
            while not stop.is_set():
                now = time.monotonic()
                items, activity = grow.poll(now)
                if activity:
                    last_activity = now
                queue = deque(items)
                while queue:
                    item = queue.popleft()
                    if stop.is_set():
                        break  # not adjusted, not skipped: a resumed watch takes them
                    if isinstance(item, SkippedImage):
                        journal.append_skip(item)
                        skipped.append(item)
                        console.print(f"seqat: skipped: {item.reason}", highlight=False,
                                      markup=False)
                        continue
                    if session is None:
                        session, source = start()
                    assert source is not None
                    if item.path is not None:
                        paths[item.image] = item.path
                    prepared = _prepare(source, item, grow)
                    if isinstance(prepared, SkippedImage):  # unreadable image data
                        journal.append_skip(prepared)
                        skipped.append(prepared)
                        console.print(f"seqat: skipped: {prepared.reason}", highlight=False,
                                      markup=False)
                        continue
                    session.add(prepared)
                    last_activity = time.monotonic()
                    queue.extend(grow.poll(last_activity)[0])  # each row at its own time
                if (watch.idle_timeout_s is not None
                        and time.monotonic() - last_activity > watch.idle_timeout_s):
                    stopped = "idle"
                    break
                stop.wait(watch.poll_s)
        for item in grow.pending():  # not journaled: a resumed watch waits for them again
            skipped.append(item)
            console.print(f"seqat: skipped: {item.reason}", highlight=False, markup=False)
        n = 0 if session is None else session.images
        if session is None or n < MIN_IMAGES:
            raise InputDataError(f"{folder}: {n} image(s) adjusted when the watch stopped; at "
                                 f"least {MIN_IMAGES} are needed (the journal in {out} is kept: "
                                 "watch again with --resume)")
        solution = session.finish()
    finally:
        journal.close()
        for listener in (*made, *estimates):
            close = getattr(listener, "close", None)
            if close is not None:
                close()
    flight = grow.flight
    assert flight is not None and source is not None
    inputs = dataclasses.replace(flight, nav=session.nav(), skipped=tuple(skipped), warnings=(
        *grow.warnings, *resampling_warnings(grow.resampled, flight.camera_config))).inputs()
    return publish_run(out, session, solution, method=method, flight=str(folder), inputs=inputs,
                       options=with_calibration(options, flight.calibration), final_only=False,
                       tracking_options=source.tracking_options, truth=read_truth(folder),
                       t_start=t_start, mode="watch", stopped=stopped)


def _prepare(source: ObservationSource | ImageSource, item: Arrival,
             grow: GrowingFlight) -> PreparedFrame | SkippedImage:
    flight = grow.flight
    assert flight is not None
    if isinstance(source, ObservationSource):
        frame = Frame(image_id=item.image, nav_eop=item.nav_eop, nav_sigma=flight.nav_sigma,
                      point_ids=item.point_ids,
                      uv_px=flight.frame_pixels(item.observed_px),
                      sigma_px=flight.config.sigma_image_px,
                      late_image_ids=item.late_image_ids, late_point_ids=item.late_point_ids,
                      late_uv_px=flight.frame_pixels(item.late_observed_px))
        return source.prepare(frame, item.observed_px, item.time_s, item.ready_s,
                              late_observed_px=item.late_observed_px)
    assert item.path is not None
    return source.prepare(item.image, item.path, item.nav_eop, item.time_s, item.ready_s)
