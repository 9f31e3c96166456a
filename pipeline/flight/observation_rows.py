"""Rows of an observations flight's ``observations.csv``, grouped by frame.

One reader for every way an observations file is read: ``seqat run`` (the whole file,
:class:`pipeline.flight.folder.FrameSource`), ``seqat watch`` (a growing file,
:class:`pipeline.run.watch.GrowingFlight`) and ``seqat feed`` (which copies each frame's rows
before the frame's nav row). A row's *frame* is the image it arrived with: its own image, or,
with the optional ``frame`` column, a later image that carries a late observation of an
earlier one (docs/formats.md). A frame's rows are contiguous; :class:`FrameRows` takes them
row by row and gives each frame's :class:`ObservationGroup` once the frame is complete. What
depends on the caller (is the frame known and in order, is a late row's image an earlier one)
is checked by the callables it is given, each raising a one-line error naming file, line and
field.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.common.columns import OBS_FRAME_COLUMN
from pipeline.common.csvio import CsvRow
from pipeline.flight.schema import CameraConfig
from seqat.errors import InputDataError
from seqat.types import FloatArray

#: Half a pixel: observed pixel centres lie in ``[-0.5, width - 0.5]`` (OpenCV convention).
HALF_PIXEL = 0.5
#: Observations up to this many sigma_image_px outside the image border are accepted.
OUTSIDE_TOLERANCE_SIGMAS = 5.0


@dataclass(frozen=True, kw_only=True, eq=False)
class ObservationGroup:
    """The contiguous observation rows of one frame: its image's, and the late observations
    of earlier images that arrived with it (``frame`` column)."""

    image_id: str  # the frame
    nav_row: int  # what ``open_frame`` of :class:`FrameRows` returned for the frame
    point_ids: tuple[str, ...]
    uv_px: FloatArray  # (k, 2) observed pixels
    late_image_ids: tuple[str, ...] = ()
    late_point_ids: tuple[str, ...] = ()
    late_uv_px: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


class PixelOutsideImage(InputDataError):
    """An observation further outside the image than the tolerance (:func:`observation_row`)."""


def row_image_frame(row: CsvRow) -> tuple[str, str]:
    """``(image, frame)`` of a row; without a ``frame`` column the frame is the image."""
    image = row.ident("image")
    return image, (row.ident(OBS_FRAME_COLUMN) if OBS_FRAME_COLUMN in row.values else image)


class FrameRows:
    """Rows of ``observations.csv`` -> one :class:`ObservationGroup` per frame.

    :meth:`add` each row in file order; it returns the previous frame's group when a row of
    another frame starts. :meth:`close` ends the current frame (at the end of the file, or
    in watch mode when the frame's nav row arrives). A frame whose rows were closed cannot
    have rows again (rows are grouped by frame); a point is observed at most once per image
    within a frame (the estimator refuses an observation repeated across frames).

    Parameters
    ----------
    camera : CameraConfig
        Size of the images (pixels outside it).
    tolerance_px : float
        :func:`outside_tolerance_px`.
    open_frame : callable
        ``open_frame(row, frame, image) -> nav_row``: checks a frame whose first row is
        ``row`` (known, in acquisition order) and gives the value kept as the group's
        ``nav_row``.
    check_late : callable
        ``check_late(row, image, frame, nav_row)``: checks a late row's image (an image
        acquired before its frame).
    on_outside : callable
        Called with the error of a row whose pixel lies outside the image (the row is left
        out).
    """

    def __init__(self, camera: CameraConfig, tolerance_px: float, *,
                 open_frame: Callable[[CsvRow, str, str], int],
                 check_late: Callable[[CsvRow, str, str, int], None],
                 on_outside: Callable[[PixelOutsideImage], None]) -> None:
        self._camera = camera
        self._tolerance = tolerance_px
        self._open_frame = open_frame
        self._check_late = check_late
        self._on_outside = on_outside
        #: The frame whose rows are being read (None: between frames).
        self.current: str | None = None
        self._nav_row = -1
        self._done: dict[str, int] = {}  # closed frame -> last line of its rows
        self._last_line = 0
        self._point_line: dict[str, int] = {}
        self._uvs: list[tuple[float, float]] = []
        self._late: list[tuple[str, str, float, float]] = []
        self._late_line: dict[str, dict[str, int]] = {}  # late image -> point -> line

    def add(self, row: CsvRow) -> ObservationGroup | None:
        """Take one row; returns the group of the frame it ends (a row of another frame)."""
        image, frame = row_image_frame(row)
        closed = None
        if frame != self.current:
            closed = self.close()
            if frame in self._done:
                raise row.error(f"rows of {'image' if frame == image else 'frame'} {frame!r} "
                                f"are not contiguous (its earlier rows end at line "
                                f"{self._done[frame]}); group rows by image (frame)")
            self._nav_row = self._open_frame(row, frame, image)
            self.current = frame
        self._last_line = row.line
        if image != frame:  # a late observation of an earlier image
            self._check_late(row, image, frame, self._nav_row)
        lines = self._point_line if image == frame else self._late_line.setdefault(image, {})
        try:
            point, u, v = observation_row(row, image, lines, self._camera, self._tolerance)
        except PixelOutsideImage as err:
            self._on_outside(err)
            return closed
        if image == frame:
            self._uvs.append((u, v))
        else:
            self._late.append((image, point, u, v))
        return closed

    def close(self) -> ObservationGroup | None:
        """End the current frame: its group (None between frames)."""
        if self.current is None:
            return None
        late = self._late
        group = ObservationGroup(
            image_id=self.current, nav_row=self._nav_row, point_ids=tuple(self._point_line),
            uv_px=np.asarray(self._uvs, dtype=np.float64).reshape(-1, 2),
            late_image_ids=tuple(r[0] for r in late), late_point_ids=tuple(r[1] for r in late),
            late_uv_px=np.asarray([r[2:] for r in late], dtype=np.float64).reshape(-1, 2))
        self._done[self.current] = self._last_line
        self.current = None
        self._point_line, self._uvs, self._late, self._late_line = {}, [], [], {}
        return group


def observation_row(row: CsvRow, image: str, point_line: dict[str, int],
                    camera: CameraConfig, tolerance_px: float = 0.0) -> tuple[str, float, float]:
    """Point id and pixel of an ``observations.csv`` row of ``image``, checked.

    ``point_line`` (point -> line) holds the image's earlier rows; the row is added to it.
    A pixel up to ``tolerance_px`` outside the image border is accepted as it is.

    Raises
    ------
    InputDataError
        A point observed twice in the image.
    PixelOutsideImage
        A pixel more than ``tolerance_px`` outside the image (the row is not added).
    """
    point = row.ident("point")
    if point in point_line:
        raise row.error(f"duplicate observation of point {point!r} in image {image!r} "
                        f"(first at line {point_line[point]})")
    u, v = row.number("x_px"), row.number("y_px")
    lo = -HALF_PIXEL - tolerance_px
    if not (lo <= u <= camera.width_px - lo and lo <= v <= camera.height_px - lo):
        raise PixelOutsideImage(f"{row.path}:{row.line}: pixel ({u!r}, {v!r}) of point "
                                f"{point!r} lies outside the {camera.width_px} x "
                                f"{camera.height_px} px image")
    point_line[point] = row.line
    return point, u, v


def outside_tolerance_px(sigma_image_px: float) -> float:
    """How far outside the image border an observation is still accepted (5 sigma)."""
    return OUTSIDE_TOLERANCE_SIGMAS * sigma_image_px


def outside_warning(path: object, dropped: int, total: int, first: str) -> str:
    """The warning of observations dropped for lying outside the image."""
    return (f"{path}: {dropped} of {total} observation(s) lie more than "
            f"{OUTSIDE_TOLERANCE_SIGMAS:g} sigma_image_px outside the image and were left out "
            f"(first: {first})")
