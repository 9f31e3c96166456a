"""Ground control points: ODM ``gcp_list.txt`` and Metashape marker exports (docs/formats.md,
*Ground control*).

A ground control point (GCP) is a surveyed ground point whose image observations the user
measured. The estimators adjust it like a tie point, with its surveyed coordinates as a prior
(``seqat.types.ControlPoint``); its observations go into the frames under the point id
``gcp:NAME`` (tracker ids are ``t0000001``, observation ids the flight's own).

Readers:

* **ODM** ``gcp_list.txt`` (OpenDroneMap, OpenSfM): a CRS line (PROJ string, ``EPSG:nnnn``,
  ``WGS84 UTM 32N``, or ``WGS84`` = longitude latitude height), then
  ``geo_x geo_y geo_z im_x im_y image_name [gcp_name] [extra...]`` separated by spaces or
  tabs; blank lines and lines starting with ``#`` are skipped (as OpenSfM does). Pixels are
  of the full-resolution image, origin top-left, integers at pixel centres (OpenSfM's
  ``normalized_image_coordinates`` adds 0.5): OpenCV pixels, used as they are. ``geo_z`` may be
  ``NaN`` (no height: the vertical is unconstrained). Without ``gcp_name`` the points are told
  apart by their coordinates, as OpenSfM does (``unnamed-1``, ...).
* **Metashape** markers export (*File > Export > Export Markers*, XML): markers with their
  reference coordinates (``<reference x y z enabled [sx sy sz]>``), the chunk's CRS as WKT and
  each marker's projections (``<location camera_id pinned x y>``). Only *pinned* projections
  (placed by the user) are used; the others are Metashape's own predictions. Disabled markers
  are Metashape's check points and are left out. Metashape's pixel coordinates put the
  centre of the top-left pixel at (0.5, 0.5): ``u = x - 0.5``. A reference CSV (*Reference
  pane > Export*; ``label, X, Y, Z`` and optionally one accuracy or three, ``#`` lines
  skipped) may give the coordinates instead of the XML's.

Coordinates go to the run's working CRS with pyproj (``always_xy``: x = easting or
longitude); pixels of an image file of another size than the camera's (same aspect ratio,
resampled when read) are scaled to the camera's pixels. Bad input is one line naming the
file, the line and the field (:class:`~seqat.errors.InputDataError`, exit 2).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyproj
from pyproj.exceptions import CRSError, ProjError

from pipeline.common.csvio import ID_PATTERN, NUMBER_PATTERN, decode_line
from pipeline.common.paths import file_problem
from pipeline.flight.image_metadata import read_image_metadata
from pipeline.flight.navigation import checked_transform, has_vertical_datum, to_3d
from pipeline.flight.schema import (
    DEFAULT_GCP_SIGMA_HORIZONTAL_M,
    DEFAULT_GCP_SIGMA_VERTICAL_M,
    GcpConfig,
)
from seqat.errors import InputDataError
from seqat.types import FloatArray

#: Point id prefix of a ground control point (cannot collide with tracker or file ids).
GCP_PREFIX = "gcp:"
#: ODM's default file name, auto-detected in the flight folder.
ODM_GCP_FILE = "gcp_list.txt"
#: Metashape pixel coordinates minus OpenCV's (centre of the top-left pixel 0.5 vs 0).
METASHAPE_PIXEL_OFFSET = 0.5
#: A GCP pixel farther than this many pixels outside its image is an error of the file.
OUTSIDE_TOLERANCE_PX = 2.0
#: Plausible magnitudes (as csvio.magnitude_limit): coordinates, heights, pixels.
MAX_COORDINATE = 1e8
MAX_HEIGHT_M = 1e5


@dataclass(frozen=True, kw_only=True, eq=False)
class GroundControlPoint:
    """One GCP in the working CRS.

    ``name`` as in the file; ``point_id`` = ``gcp:`` + name (whitespace as ``_``); ``sigma_m``
    (3,) > 0, ``inf`` for a component without a value (ODM ``NaN`` height).
    """

    name: str
    point_id: str
    xyz_m: FloatArray
    sigma_m: FloatArray


@dataclass(frozen=True, kw_only=True, eq=False)
class GroundControl:
    """The ground control of a flight.

    Attributes
    ----------
    path : Path
        The file read (ODM list or Metashape XML).
    points : tuple[GroundControlPoint, ...]
        Points with at least one observation in an image of the flight.
    observations : Mapping[str, tuple[tuple[str, ...], FloatArray]]
        Image id -> (point ids, observed camera pixels (k, 2), OpenCV convention).
    warnings : tuple[str, ...]
    """

    path: Path
    points: tuple[GroundControlPoint, ...]
    observations: Mapping[str, tuple[tuple[str, ...], FloatArray]]
    warnings: tuple[str, ...] = ()

    def for_image(self, image_id: str) -> tuple[tuple[str, ...], FloatArray]:
        """The GCP observations of one image (point ids, observed pixels)."""
        return self.observations.get(image_id, ((), np.zeros((0, 2))))

    @property
    def names(self) -> frozenset[str]:
        return frozenset(p.name for p in self.points)

    @property
    def n_observations(self) -> int:
        return sum(len(ids) for ids, _ in self.observations.values())


def point_id(name: str) -> str:
    """The frame point id of a GCP name (whitespace runs as ``_``)."""
    return GCP_PREFIX + re.sub(r"\s+", "_", name.strip())


def is_control_id(point: str) -> bool:
    return point.startswith(GCP_PREFIX)


# --------------------------------------------------------------------------------------------
# CRS
# --------------------------------------------------------------------------------------------


def odm_crs(text: str, where: str) -> pyproj.CRS:
    """The CRS of an ODM CRS line (OpenSfM's ``_parse_projection``, plus anything pyproj
    reads: WKT, ``EPSG:nnnn+vvvv``)."""
    line = text.strip()
    try:
        if line.upper() == "WGS84":
            return pyproj.CRS.from_epsg(4979)  # longitude, latitude, ellipsoidal height
        words = line.split()
        if line.upper().startswith("WGS84 UTM") and len(words) == 3:
            zone = words[2].upper()
            south = zone.endswith("S")
            number = int(zone[:-1] if zone[-1] in "NS" else zone)
            if not 1 <= number <= 60:
                raise ValueError(f"UTM zone {number}")
            return pyproj.CRS.from_epsg((32700 if south else 32600) + number)
        return pyproj.CRS.from_user_input(line)
    except (CRSError, ValueError) as err:
        raise InputDataError(f"{where}:1: CRS line: expected a PROJ string, EPSG:nnnn or "
                             f"'WGS84 UTM <zone>[N|S]', got {line!r} ({err})") from err


class ToWorld:
    """Coordinates of a GCP file's CRS -> the run's working CRS (pyproj, ``always_xy``).

    Heights follow each CRS's vertical reference (a 2D CRS: ellipsoidal, as the nav); a
    vertical datum change uses PROJ's best operation only (no "ballpark" that leaves heights
    unchanged; PROJ's network is off, as for the nav). The same CRS is the identity.
    """

    def __init__(self, source: pyproj.CRS, target: pyproj.CRS, where: str) -> None:
        pyproj.network.set_network_enabled(False)
        self.where = where
        self.identity = source.equals(target, ignore_axis_order=True)
        self.vertical_change = has_vertical_datum(source) != has_vertical_datum(target)
        self._tr: pyproj.Transformer | None = None
        if not self.identity:
            try:
                self._tr = pyproj.Transformer.from_crs(
                    to_3d(source), to_3d(target), always_xy=True,
                    only_best=self.vertical_change or None,
                    allow_ballpark=not self.vertical_change)
            except ProjError as err:
                raise InputDataError(f"{where}: cannot transform {source.name!r} to the run's "
                                     f"{target.name!r}: {err} (PROJ network access is off; "
                                     "install the grid)") from err

    def __call__(self, xyz: FloatArray) -> FloatArray:
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        if self._tr is None:
            return xyz.copy()
        z_in = np.nan_to_num(xyz[:, 2])
        out = checked_transform(self._tr, xyz[:, 0], xyz[:, 1], z_in,
                                vertical_change=self.vertical_change, where=self.where,
                                error=InputDataError)
        out[np.isnan(xyz[:, 2]), 2] = np.nan
        return out


# --------------------------------------------------------------------------------------------
# What both readers share
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class ImageFrame:
    """How the images of a flight are named and sized, for matching GCP observations.

    ``ids``: image ids in acquisition order; ``names``: file name -> id (image flights);
    ``camera_size``: the camera's (width, height) px; ``file_size``: image id -> the stored
    file's (width, height), read on demand (observations flights: the camera's).
    """

    ids: tuple[str, ...]
    names: Mapping[str, str]
    camera_size: tuple[int, int]
    file_size: Callable[[str], tuple[int, int]]

    def image_id(self, name: str) -> str | None:
        if name in self.names:
            return self.names[name]
        if name in self.ids:
            return name
        stem = Path(name).stem
        return stem if stem in self.ids else None


def image_frame(ids: Sequence[str], paths: Sequence[Path], camera_size: tuple[int, int]
                ) -> ImageFrame:
    """The :class:`ImageFrame` of a flight (``paths`` one per id, or empty)."""
    by_id = dict(zip(ids, paths, strict=False))
    sizes: dict[str, tuple[int, int]] = {}

    def file_size(image_id: str) -> tuple[int, int]:
        if image_id not in by_id:
            return camera_size
        if image_id not in sizes:
            meta = read_image_metadata(by_id[image_id])
            sizes[image_id] = (meta.width_px, meta.height_px)
        return sizes[image_id]

    return ImageFrame(ids=tuple(ids), names={p.name: i for i, p in by_id.items()},
                      camera_size=camera_size, file_size=file_size)


def _number(token: str, field: str, where: str, *, limit: float, allow_nan: bool = False
            ) -> float:
    if allow_nan and token.lower() == "nan":
        return math.nan
    value = float(token) if NUMBER_PATTERN.match(token) else math.inf
    if not math.isfinite(value):
        wanted = "a finite number or NaN" if allow_nan else "a finite number"
        raise InputDataError(f"{where}: field {field!r}: expected {wanted}, got {token!r}")
    if abs(value) > limit:
        raise InputDataError(f"{where}: field {field!r}: {token!r} is not plausible "
                             f"(magnitude above {limit:g})")
    return value


def _camera_pixel(u: float, v: float, image_id: str, frame: ImageFrame, where: str,
                  field: str) -> FloatArray:
    """A pixel of the stored image file -> the camera's pixel (checked inside the image)."""
    fw, fh = frame.file_size(image_id)
    cw, ch = frame.camera_size
    uv = np.array([(u + 0.5) * cw / fw - 0.5, (v + 0.5) * ch / fh - 0.5])
    tol = OUTSIDE_TOLERANCE_PX
    if not (-0.5 - tol <= u <= fw - 0.5 + tol and -0.5 - tol <= v <= fh - 0.5 + tol):
        raise InputDataError(f"{where}: field {field!r}: pixel ({u:g}, {v:g}) lies outside the "
                             f"{fw} x {fh} px image {image_id!r}")
    return uv


def _check_name(name: str, where: str, field: str) -> str:
    pid = point_id(name)
    if not ID_PATTERN.match(pid):
        raise InputDataError(f"{where}: field {field!r}: expected a name without commas or "
                             f"quotes, got {name!r}")
    return pid


@dataclass(kw_only=True)
class _Builder:
    """Points and observations as they are read."""

    where: str
    frame: ImageFrame
    names: dict[str, int] = field(default_factory=dict)  # point id -> row
    xyz: list[FloatArray] = field(default_factory=list)
    sigma: list[FloatArray] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    first_line: list[str] = field(default_factory=list)
    obs: dict[str, dict[str, tuple[FloatArray, str]]] = field(default_factory=dict)
    unknown: list[str] = field(default_factory=list)

    def point(self, name: str, xyz: FloatArray, sigma: FloatArray, where: str,
              field: str) -> str:
        pid = _check_name(name, where, field)
        row = self.names.get(pid)
        if row is None:
            self.names[pid] = len(self.xyz)
            self.xyz.append(xyz)
            self.sigma.append(sigma)
            self.labels.append(name)
            self.first_line.append(where)
        elif not np.allclose(np.nan_to_num(self.xyz[row], nan=1e300),
                             np.nan_to_num(xyz, nan=1e300), rtol=0, atol=1e-9):
            raise InputDataError(f"{where}: field {field!r}: GCP {name!r} has other "
                                 f"coordinates than at {self.first_line[row]}")
        return pid

    def observe(self, pid: str, image_name: str, u: float, v: float, where: str,
                pixel_field: str, offset: float = 0.0) -> None:
        image_id = self.frame.image_id(image_name)
        if image_id is None:
            self.unknown.append(f"{where}: {image_name!r}")
            return
        uv = _camera_pixel(u - offset, v - offset, image_id, self.frame, where, pixel_field)
        seen = self.obs.setdefault(image_id, {})
        if pid in seen:
            raise InputDataError(f"{where}: GCP {pid[len(GCP_PREFIX):]!r} is observed twice in "
                                 f"image {image_id!r} (first at {seen[pid][1]})")
        seen[pid] = (uv, where)

    def build(self, path: Path, to_world: ToWorld, warnings: list[str]) -> GroundControl:
        if self.unknown:
            warnings.append(f"{path}: {len(self.unknown)} GCP observation(s) of images not in "
                            f"the flight were left out (first: {self.unknown[0]})")
        if not self.obs:
            raise InputDataError(f"{path}: no GCP observation in an image of the flight")
        xyz = to_world(np.array(self.xyz).reshape(-1, 3))
        observed = {pid for per in self.obs.values() for pid in per}
        points = []
        for pid, row in self.names.items():
            if pid not in observed:
                warnings.append(f"{path}: GCP {self.labels[row]!r} is not observed in any image "
                                "of the flight; left out")
                continue
            sig = np.array(self.sigma[row], dtype=np.float64)
            p = xyz[row].copy()
            if np.isnan(p[2]):  # no height: unconstrained, a start value only
                sig[2] = np.inf
                finite = xyz[np.isfinite(xyz[:, 2]), 2]
                p[2] = float(np.median(finite)) if finite.size else 0.0
            points.append(GroundControlPoint(name=self.labels[row], point_id=pid, xyz_m=p,
                                             sigma_m=sig))
        order = {i: k for k, i in enumerate(self.frame.ids)}
        observations = {
            image: (tuple(per), np.array([uv for uv, _ in per.values()]).reshape(-1, 2))
            for image, per in sorted(self.obs.items(), key=lambda kv: order[kv[0]])}
        return GroundControl(path=path, points=tuple(points), observations=observations,
                             warnings=tuple(warnings))


def _default_sigma(h: float, v: float) -> FloatArray:
    return np.array([h, h, v], dtype=np.float64)


def _text_lines(path: Path) -> list[str]:
    try:
        raw = path.read_bytes().splitlines()
    except OSError as err:
        raise InputDataError(f"{path}: cannot read: {err.strerror}") from err
    return [decode_line(line, str(path), k) for k, line in enumerate(raw, start=1)]


# --------------------------------------------------------------------------------------------
# ODM gcp_list.txt
# --------------------------------------------------------------------------------------------

ODM_FIELDS = ("geo_x", "geo_y", "geo_z", "im_x", "im_y", "image_name")


def read_odm_gcp_list(path: Path | str, crs: pyproj.CRS, frame: ImageFrame, *,
                      sigma_horizontal_m: float = DEFAULT_GCP_SIGMA_HORIZONTAL_M,
                      sigma_vertical_m: float = DEFAULT_GCP_SIGMA_VERTICAL_M) -> GroundControl:
    """Read an ODM ``gcp_list.txt`` into the working CRS ``crs`` (module docstring)."""
    path = Path(path)
    lines = _text_lines(path)
    body = [(k, ln) for k, ln in enumerate(lines, start=1)
            if ln.strip() and not ln.strip().startswith("#")]
    if not body:
        raise InputDataError(f"{path}: empty (expected a CRS line, then GCP lines)")
    src = odm_crs(body[0][1], str(path))  # comment lines may precede it, as in OpenSfM
    to_world = ToWorld(src, crs, str(path))
    geographic = src.is_geographic
    b = _Builder(where=str(path), frame=frame)
    unnamed: dict[tuple[float, float, float], str] = {}
    sigma = _default_sigma(sigma_horizontal_m, sigma_vertical_m)
    for k, line in body[1:]:
        where = f"{path}:{k}"
        words = line.split()
        if len(words) < len(ODM_FIELDS):
            raise InputDataError(f"{where}: expected at least 6 fields ({' '.join(ODM_FIELDS)} "
                                 f"[gcp_name] [extra...]), got {len(words)}")
        xy_limit = 360.0 if geographic else MAX_COORDINATE
        x = _number(words[0], "geo_x", where, limit=xy_limit)
        y = _number(words[1], "geo_y", where, limit=xy_limit)
        z = _number(words[2], "geo_z", where, limit=MAX_HEIGHT_M, allow_nan=True)
        u = _number(words[3], "im_x", where, limit=MAX_COORDINATE)
        v = _number(words[4], "im_y", where, limit=MAX_COORDINATE)
        if len(words) > len(ODM_FIELDS):
            name = words[6]
        else:
            key = (x, y, z)
            name = unnamed.setdefault(key, f"unnamed-{len(unnamed) + 1}")
        pid = b.point(name, np.array([x, y, z]), sigma, where, "gcp_name")
        b.observe(pid, words[5], u, v, where, "im_x")
    return b.build(path, to_world, [])


# --------------------------------------------------------------------------------------------
# Metashape markers XML (+ reference CSV)
# --------------------------------------------------------------------------------------------


def _attr_number(el: ET.Element, name: str, where: str, *, limit: float) -> float | None:
    value = el.get(name)
    return None if value is None else _number(value.strip(), name, where, limit=limit)


def _read_reference_csv(path: Path, where_crs: str) -> dict[str, tuple[FloatArray,
                                                                      FloatArray | None, str]]:
    """Metashape reference CSV: ``label, X, Y, Z[, accuracy | acc_x, acc_y, acc_z]``."""
    out: dict[str, tuple[FloatArray, FloatArray | None, str]] = {}
    for k, line in enumerate(_text_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        where = f"{path}:{k}"
        sep = "\t" if "\t" in text else ("," if "," in text else None)
        words = [w.strip() for w in (text.split(sep) if sep else text.split())]
        if len(words) not in (4, 5, 7):
            raise InputDataError(f"{where}: expected label, X, Y, Z and optionally one accuracy "
                                 f"or three (X, Y, Z), got {len(words)} fields")
        label = words[0]
        xyz = np.array([_number(words[i], f, where, limit=MAX_COORDINATE)
                        for i, f in ((1, "X"), (2, "Y"), (3, "Z"))])
        acc = None
        if len(words) > 4:
            vals = [_number(w, "accuracy", where, limit=MAX_COORDINATE) for w in words[4:]]
            if any(a <= 0 for a in vals):
                raise InputDataError(f"{where}: field 'accuracy': expected > 0, got {vals}")
            acc = np.array(vals * 3 if len(vals) == 1 else vals, dtype=np.float64)
        if label in out:
            raise InputDataError(f"{where}: marker {label!r} listed twice (first at "
                                 f"{out[label][2]})")
        out[label] = (xyz, acc, where)
    if not out:
        raise InputDataError(f"{path}: no marker row ({where_crs})")
    return out


def read_metashape_markers(path: Path | str, crs: pyproj.CRS, frame: ImageFrame, *,
                           reference: Path | str | None = None, source_crs: str | None = None,
                           sigma_horizontal_m: float = DEFAULT_GCP_SIGMA_HORIZONTAL_M,
                           sigma_vertical_m: float = DEFAULT_GCP_SIGMA_VERTICAL_M
                           ) -> GroundControl:
    """Read a Metashape markers XML (and optionally a reference CSV) into ``crs``."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        line, col = err.position
        raise InputDataError(f"{path}:{line}: not a Metashape markers XML ({err.msg}, column "
                             f"{col})") from err
    except OSError as err:
        raise InputDataError(f"{path}: cannot read: {err.strerror}") from err
    chunk = root.find("chunk") if root.tag == "document" else None
    if chunk is None:
        raise InputDataError(f"{path}: not a Metashape markers XML (expected <document><chunk>,"
                             f" got <{root.tag}>)")
    ref_el = chunk.find("reference")
    crs_text = source_crs if source_crs is not None else (
        ref_el.text.strip() if ref_el is not None and ref_el.text else None)
    if crs_text is None:
        raise InputDataError(f"{path}: the export names no CRS (<reference>); give gcp.crs in "
                             "flight.yaml")
    try:
        src = pyproj.CRS.from_user_input(crs_text)
    except CRSError as err:
        raise InputDataError(f"{path}: <reference>: unknown CRS {crs_text[:60]!r}: {err}"
                             ) from err
    where_crs = str(path)
    to_world = ToWorld(src, crs, where_crs)
    sensors = {s.get("id"): s.find("resolution") for s in chunk.iter("sensor")}
    cameras: dict[str, tuple[str, tuple[int, int] | None]] = {}
    for cam in chunk.iter("camera"):
        res = sensors.get(cam.get("sensor_id"))
        size = None if res is None else (int(res.get("width", 0)), int(res.get("height", 0)))
        cameras[cam.get("id", "")] = (cam.get("label", ""), size)
    csv_refs = (_read_reference_csv(Path(reference), where_crs) if reference is not None
                else None)
    default = _default_sigma(sigma_horizontal_m, sigma_vertical_m)
    markers: dict[str, tuple[str, FloatArray, FloatArray]] = {}
    disabled: list[str] = []
    for m in chunk.iter("marker"):
        if m.get("label") is None:
            continue  # a <marker marker_id> of a frame
        label, mid = m.get("label", ""), m.get("id", "")
        where = f"{path}: marker {label!r}"
        ref = m.find("reference")
        if csv_refs is not None:
            if label not in csv_refs:
                continue
            xyz, acc, _ = csv_refs[label]
            sigma = default if acc is None else acc
        else:
            if ref is None:
                continue
            if ref.get("enabled", "true").lower() == "false":
                disabled.append(label)
                continue
            vals = [_attr_number(ref, a, where, limit=MAX_COORDINATE) for a in "xyz"]
            if any(v is None for v in vals):
                continue
            xyz = np.array(vals, dtype=np.float64)
            sig = [_attr_number(ref, a, where, limit=MAX_COORDINATE) for a in ("sx", "sy", "sz")]
            sigma = np.array([d if s is None else s for s, d in zip(sig, default, strict=True)])
        markers[mid] = (label, xyz, sigma)
    b = _Builder(where=str(path), frame=frame)
    for mk in chunk.iter("marker"):
        mid = mk.get("marker_id")
        if mid is None or mid not in markers:
            continue
        label, xyz, sigma = markers[mid]
        for loc in mk.iter("location"):
            if loc.get("pinned", "false").lower() != "true":
                continue
            where = f"{path}: marker {label!r}, camera_id {loc.get('camera_id')}"
            pid = b.point(label, xyz, sigma, f"{path}: marker {label!r}", "label")
            cam_label, size = cameras.get(loc.get("camera_id", ""), ("", None))
            u = _attr_number(loc, "x", where, limit=MAX_COORDINATE)
            v = _attr_number(loc, "y", where, limit=MAX_COORDINATE)
            if u is None or v is None or not cam_label:
                raise InputDataError(f"{where}: a <location> needs x, y and a known camera_id")
            if size is not None and all(size) and frame.image_id(cam_label) is not None:
                iid = frame.image_id(cam_label)
                fw, fh = frame.file_size(iid)  # type: ignore[arg-type]
                if (fw, fh) != size:  # pixels of the sensor's resolution; corner origin
                    u, v = u * fw / size[0], v * fh / size[1]
            b.observe(pid, cam_label, u, v, where, "x", offset=METASHAPE_PIXEL_OFFSET)
    warnings: list[str] = []
    if disabled:
        warnings.append(f"{path}: {len(disabled)} disabled marker(s) (Metashape check points) "
                        f"left out of the control: {', '.join(disabled)}")
    return b.build(path, to_world, warnings)


# --------------------------------------------------------------------------------------------
# Which file
# --------------------------------------------------------------------------------------------


def read_ground_control(path: Path | str, crs: pyproj.CRS, frame: ImageFrame,
                        config: GcpConfig | None = None, *,
                        sigma_m: tuple[float, float] | None = None,
                        folder: Path | None = None) -> GroundControl:
    """Read a GCP file of either kind (``.xml``: Metashape, else ODM).

    ``sigma_m`` (horizontal, vertical) overrides ``config``'s sigmas (``--gcp-sigma-m``).
    """
    path = Path(path)
    cfg = config if config is not None else GcpConfig()
    if file_problem(path) is not None:
        raise InputDataError(f"{path}: {file_problem(path)} (ground control points)")
    h, v = sigma_m if sigma_m is not None else (cfg.sigma_horizontal_m, cfg.sigma_vertical_m)
    if path.suffix.lower() == ".xml":
        ref = None
        if cfg.reference is not None:
            ref = Path(cfg.reference)
            ref = ref if ref.is_absolute() or folder is None else folder / ref
            if file_problem(ref) is not None:
                raise InputDataError(f"{ref}: {file_problem(ref)} (gcp.reference)")
        return read_metashape_markers(path, crs, frame, reference=ref, source_crs=cfg.crs,
                                      sigma_horizontal_m=h, sigma_vertical_m=v)
    return read_odm_gcp_list(path, crs, frame, sigma_horizontal_m=h, sigma_vertical_m=v)


def find_gcp_file(folder: Path, config: GcpConfig | None, source: str) -> Path | None:
    """The GCP file of a flight folder: ``gcp.file`` of ``flight.yaml`` (must exist), else
    ``gcp_list.txt`` in the folder when present (ODM's auto-detection), else None."""
    if config is not None:
        path = Path(config.file)
        path = path if path.is_absolute() else folder / path
        if file_problem(path) is not None:
            raise InputDataError(f"{path}: {file_problem(path)} (gcp.file in {source})")
        return path
    path = folder / ODM_GCP_FILE
    return path if path.is_file() else None
