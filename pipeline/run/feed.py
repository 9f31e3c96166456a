"""``seqat feed SRC DST``: replay a flight into a folder at the camera's rate (for ``watch``).

The destination starts as a flight folder without images: ``flight.yaml`` (the source's, or
for a bare folder of JPEGs the defaults ``images: images``, ``nav: {source: images}``), the
header of ``nav.csv`` / ``observations.csv``, and the static files a report or the live
ortho uses (``truth/``, check points, the ``lidar:`` files inside the flight folder). Then,
image after image in acquisition order, every ``1 / rate_hz`` seconds, it writes what a
camera and its downlink would, with the
partial-file convention of docs/formats.md (*Watched flights*):

* the JPEG as ``images/<name>.part``, then renamed to ``images/<name>``;
* an observations flight's rows of the image's frame (its own observations, and the late
  observations of earlier images that arrived with it: ``frame`` column), then its
  ``nav.csv`` row, each appended as whole lines (the text of the source files, unchanged)
  and flushed.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pipeline.common.columns import (
    CHECKPOINT_OBS_FILE,
    CHECKPOINTS_FILE,
    FLIGHT_YAML,
    IMAGES_DIR,
    NAV_GEODETIC_COLUMNS,
    OBS_FRAME_COLUMN,
    TRUTH_DIR,
)
from pipeline.common.csvio import CsvRow, decode_line, read_csv
from pipeline.flight.folder import read_flight
from pipeline.flight.nav_files import NAV_PROJECTED_COLUMNS, OBSERVATION_COLUMNS
from pipeline.flight.observation_rows import row_image_frame
from seqat.errors import ConfigError, InputDataError

#: Images per second of ``seqat feed`` by default (the issue's real frame rate).
DEFAULT_RATE_HZ = 2.0
#: Suffix of a file being written; renamed away once complete.
PARTIAL_SUFFIX = ".part"
#: ``flight.yaml`` of a bare folder of JPEGs (read_flight's defaults).
BARE_FLIGHT_YAML = "images: images\nnav:\n  source: images\n"


@dataclass(frozen=True, kw_only=True)
class FeedSummary:
    """What :func:`feed_flight` wrote."""

    images: int
    duration_s: float
    late_s: float  # largest delay behind the schedule


def _image_key(row: CsvRow) -> str:
    return row.ident("image")


def _frame_key(row: CsvRow) -> str:
    return row_image_frame(row)[1]


def _lines_by(path: Path, columns: tuple[str, ...], optional: tuple[str, ...] = (),
              key: Callable[[CsvRow], str] = _image_key) -> tuple[str, dict[str, list[str]]]:
    """Header line and the data lines of each image (``key``: an observations file's rows go
    with their frame), text as in the file, newline-ended; rows read by :func:`read_csv`."""
    try:
        raw = path.read_bytes().splitlines(keepends=True)
    except OSError as err:
        raise InputDataError(f"{path}: cannot read: {err.strerror or err}") from err
    lines = [decode_line(r, str(path), k).rstrip("\r\n") + "\n"
             for k, r in enumerate(raw, start=1)]
    rows: dict[str, list[str]] = {}
    for row in read_csv(path, columns, optional):
        rows.setdefault(key(row), []).append(lines[row.line - 1])
    return lines[0], rows


def _append(path: Path, lines: list[str]) -> None:
    with path.open("a", encoding="utf-8", newline="") as handle:
        handle.write("".join(lines))
        handle.flush()


def feed_flight(src_dir: Path | str, dst_dir: Path | str, *, rate_hz: float = DEFAULT_RATE_HZ,
                limit: int | None = None, delay_s: float = 0.0,
                on_start: Callable[[], None] | None = None,
                on_image: Callable[[str], None] | None = None) -> FeedSummary:
    """Copy a flight into ``dst_dir`` image by image at ``rate_hz`` (module docstring).

    Parameters
    ----------
    src_dir : Path or str
        A flight folder ``seqat run`` reads (observations or images).
    dst_dir : Path or str
        Created; must not exist or be empty.
    rate_hz : float
        Images per second.
    limit : int or None
        Feed only the first ``limit`` images.
    delay_s : float
        Seconds between writing ``flight.yaml`` and the first image (time to start a watch).
    on_start : callable or None
        Called once ``flight.yaml`` is written (before the first image).
    on_image : callable or None
        Called with each image id once it is written.

    Raises
    ------
    ConfigError
        ``rate_hz`` not positive; ``dst_dir`` not empty.
    InputDataError
        The source flight cannot be read.
    """
    if not rate_hz > 0:
        raise ConfigError(f"--rate: expected a positive number of images per second, got "
                          f"{rate_hz!r}")
    src, dst = Path(src_dir), Path(dst_dir)
    flight = read_flight(src)
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        raise ConfigError(f"{dst}: exists and is not an empty folder")
    config = flight.config
    yaml_text = ((src / FLIGHT_YAML).read_text(encoding="utf-8")
                 if (src / FLIGHT_YAML).is_file() else BARE_FLIGHT_YAML)
    nav_rows: dict[str, list[str]] = {}
    obs_rows: dict[str, list[str]] = {}
    dst.mkdir(parents=True, exist_ok=True)
    nav_dst = dst / config.nav.file
    if config.nav.source == "file":
        columns = NAV_PROJECTED_COLUMNS if config.nav.frame == "projected" else \
            NAV_GEODETIC_COLUMNS
        header, nav_rows = _lines_by(src / config.nav.file, columns)
        nav_dst.parent.mkdir(parents=True, exist_ok=True)
        nav_dst.write_text(header, encoding="utf-8")
    obs_dst = None
    if flight.observations_path is not None:
        # a frame's rows (its late observations of earlier images with them) before its
        # nav row, as the camera's downlink sends them
        header, obs_rows = _lines_by(flight.observations_path, OBSERVATION_COLUMNS,
                                     (OBS_FRAME_COLUMN,), _frame_key)
        obs_dst = dst / (config.observations or "observations.csv")
        obs_dst.write_text(header, encoding="utf-8")
    images_dst = dst / (config.images or IMAGES_DIR)
    if flight.kind == "images":
        images_dst.mkdir(parents=True, exist_ok=True)
    for name in (TRUTH_DIR,):
        if (src / name).is_dir():
            shutil.copytree(src / name, dst / name)
    for name in (CHECKPOINTS_FILE, CHECKPOINT_OBS_FILE):
        if (src / name).is_file():
            shutil.copy2(src / name, dst / name)
    lidar = (config.lidar,) if isinstance(config.lidar, str) else (config.lidar or ())
    for name in lidar:  # flown before: there from the start (absolute paths stay as they are)
        if not Path(name).is_absolute() and (src / name).is_file():
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src / name, dst / name)
    (dst / FLIGHT_YAML).write_text(yaml_text, encoding="utf-8")
    if on_start is not None:
        on_start()

    ids = flight.nav.image_ids[:limit]
    paths = flight.image_paths[:limit] if flight.kind == "images" else (None,) * len(ids)
    t0 = time.monotonic() + delay_s
    late = 0.0
    for k, (image, path) in enumerate(zip(ids, paths, strict=True)):
        due = t0 + k / rate_hz
        wait = due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        late = max(late, -wait)
        if path is not None:
            part = images_dst / (path.name + PARTIAL_SUFFIX)
            shutil.copyfile(path, part)
            os.replace(part, images_dst / path.name)
        if obs_dst is not None:
            _append(obs_dst, obs_rows.get(image, []))
        if nav_rows:
            _append(nav_dst, nav_rows[image])
        if on_image is not None:
            on_image(image)
    return FeedSummary(images=len(ids), duration_s=time.monotonic() - t0, late_s=late)
