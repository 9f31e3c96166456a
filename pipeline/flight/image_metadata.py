"""Navigation metadata of one JPEG: EXIF GPS, time, focal length and the vendor's XMP attitude.

:func:`read_image_metadata` reads what an image flight folder needs (docs/formats.md, *Image
flight folder*) into a frozen :class:`ImageMetadata`; missing values are ``None``. Errors name
the file and what was found. Pillow reads EXIF; the XMP packet is parsed with
``xml.etree.ElementTree``. Converting positions and attitudes to the working CRS is
:mod:`pipeline.flight.navigation`.
"""

from __future__ import annotations

import datetime as dt
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from PIL import ExifTags, Image, UnidentifiedImageError

from seqat.errors import InputDataError

HeightKind = Literal["ellipsoidal", "orthometric", "unknown"]
#: Kinds of attitude: ``body`` = aircraft roll/pitch/yaw (camera fixed to the airframe through
#: the boresight mount), ``gimbal`` = absolute roll/pitch/yaw of a stabilised camera gimbal
#: (pitch -90 deg = nadir), ``camera`` = Pix4D ``Camera:`` angles of the camera itself
#: (0, 0, 0 = nadir, image top north).
AttitudeFrame = Literal["body", "gimbal", "camera"]

#: How far into the file the XMP packet is looked for (bytes).
XMP_SEARCH_BYTES = 256 * 1024
#: Marker bytes of a JPEG file.
JPEG_SOI = b"\xff\xd8"
JPEG_EOI = b"\xff\xd9"
JPEG_SOS = 0xDA
#: JPEG markers without a length field (TEM, RSTn) that may precede SOS.
_STANDALONE_MARKERS = {0x01, *range(0xD0, 0xD8)}

# EXIF tag numbers (Exif 2.32).
_IFD_EXIF = ExifTags.IFD.Exif
_IFD_GPS = ExifTags.IFD.GPSInfo
_TAG_MAKE = ExifTags.Base.Make
_TAG_MODEL = ExifTags.Base.Model
_TAG_DATETIME_ORIGINAL = ExifTags.Base.DateTimeOriginal
_TAG_SUBSEC_ORIGINAL = ExifTags.Base.SubsecTimeOriginal
_TAG_OFFSET_ORIGINAL = ExifTags.Base.OffsetTimeOriginal
_TAG_FOCAL = ExifTags.Base.FocalLength
_TAG_FOCAL_35 = ExifTags.Base.FocalLengthIn35mmFilm
_TAG_FP_XRES = ExifTags.Base.FocalPlaneXResolution
_TAG_FP_UNIT = ExifTags.Base.FocalPlaneResolutionUnit
_TAG_EXIF_WIDTH = ExifTags.Base.ExifImageWidth
#: Millimetres per unit of EXIF ``FocalPlaneResolutionUnit`` (2 inch, 3 cm, 4 mm, 5 um).
_FP_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
_GPS_LAT_REF, _GPS_LAT = ExifTags.GPS.GPSLatitudeRef, ExifTags.GPS.GPSLatitude
_GPS_LON_REF, _GPS_LON = ExifTags.GPS.GPSLongitudeRef, ExifTags.GPS.GPSLongitude
_GPS_ALT_REF, _GPS_ALT = ExifTags.GPS.GPSAltitudeRef, ExifTags.GPS.GPSAltitude
_GPS_TIME, _GPS_DATE = ExifTags.GPS.GPSTimeStamp, ExifTags.GPS.GPSDateStamp
#: GPSAltitudeRef value meaning "below the reference".
_GPS_ALT_BELOW = 1

#: XMP namespaces (matched by substring of the namespace URI, case-insensitive).
_NS_SENSEFLY = "sensefly.com"
_NS_DJI = "dji.com/drone-dji"
_NS_PIX4D_CAMERA = "pix4d.com/camera"


@dataclass(frozen=True, kw_only=True)
class ImageMetadata:
    """Navigation metadata of one image; ``None`` where the file does not say.

    Attributes
    ----------
    path : Path
    width_px, height_px : int
        Size of the stored image (not EXIF's ``ExifImageWidth``, which resized files keep).
    make, model : str or None
        EXIF camera make and model.
    lat_deg, lon_deg : float or None
        WGS 84 latitude (north positive) and longitude (east positive), degrees.
    h_m : float or None
        Height of the GPS fix, metres (sign from ``GPSAltitudeRef``); ``height_kind`` says
        which height it is.
    height_kind : {"ellipsoidal", "orthometric", "unknown"}
        Per vendor, docs/formats.md.
    time_s : float or None
        Acquisition time, seconds since 1970-01-01 (``time_source`` says which clock).
    time_source : str or None
        ``gps-utc`` (EXIF GPS date and time), ``xmp-utc`` (senseFly ``UTCTime``),
        ``camera-clock`` (``DateTimeOriginal``; local camera time read as UTC unless
        ``OffsetTimeOriginal`` is given).
    roll_deg, pitch_deg, yaw_deg : float or None
        Attitude in ``attitude_frame``; yaw from true north, clockwise.
    attitude_frame : {"body", "gimbal", "camera"} or None
    attitude_source : str or None
        Tags the attitude came from (``sensefly``, ``dji-gimbal``, ``dji-flight``,
        ``pix4d-camera``).
    focal_mm, focal_35mm : float or None
        EXIF ``FocalLength`` and ``FocalLengthIn35mmFilm``.
    focal_plane_px_per_mm : float or None
        EXIF ``FocalPlaneXResolution`` in pixels per millimetre (``FocalPlaneResolutionUnit``
        applied), for an image ``exif_width_px`` wide.
    exif_width_px : int or None
        EXIF ``ExifImageWidth``: the width the focal-plane resolution refers to (resized
        files keep the camera's original value).
    """

    path: Path
    width_px: int
    height_px: int
    make: str | None = None
    model: str | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    h_m: float | None = None
    height_kind: HeightKind = "unknown"
    time_s: float | None = None
    time_source: str | None = None
    roll_deg: float | None = None
    pitch_deg: float | None = None
    yaw_deg: float | None = None
    attitude_frame: AttitudeFrame | None = None
    attitude_source: str | None = None
    focal_mm: float | None = None
    focal_35mm: float | None = None
    focal_plane_px_per_mm: float | None = None
    exif_width_px: int | None = None

    @property
    def has_position(self) -> bool:
        return self.lat_deg is not None and self.lon_deg is not None and self.h_m is not None

    @property
    def has_attitude(self) -> bool:
        return self.roll_deg is not None and self.pitch_deg is not None \
            and self.yaw_deg is not None


def read_image_metadata(path: Path | str) -> ImageMetadata:
    """Read GPS, time, focal length and attitude of a JPEG.

    Parameters
    ----------
    path : Path or str

    Returns
    -------
    ImageMetadata
        Fields the file does not carry are ``None`` (a file without GPS is not an error here;
        :func:`require_position` makes it one).

    Raises
    ------
    InputDataError
        Missing or unreadable file, not a JPEG, truncated JPEG (no end-of-image marker after
        the scan), malformed EXIF GPS values or XMP packet.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            head = f.read(XMP_SEARCH_BYTES)
        check_jpeg_complete(path)
        with Image.open(path) as im:
            if im.format != "JPEG":
                raise InputDataError(f"{path.name}: not a JPEG (Pillow reads it as {im.format})")
            width_px, height_px = im.size
            exif = im.getexif()
            exif_ifd = exif.get_ifd(_IFD_EXIF)
            gps_ifd = exif.get_ifd(_IFD_GPS)
    except InputDataError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise InputDataError(f"{path}: cannot read image: {err}") from err
    xmp = _xmp_values(path, head)
    lat, lon, h = _gps_position(path, gps_ifd)
    make = _text(exif.get(_TAG_MAKE))
    height_kind = _height_kind(make, xmp)
    roll, pitch, yaw, frame, source = _attitude(path, xmp)
    time_s, time_source = _time(path, gps_ifd, exif_ifd, xmp)
    return ImageMetadata(
        path=path, width_px=width_px, height_px=height_px, make=make,
        model=_text(exif.get(_TAG_MODEL)), lat_deg=lat, lon_deg=lon, h_m=h,
        height_kind=height_kind, time_s=time_s, time_source=time_source, roll_deg=roll,
        pitch_deg=pitch, yaw_deg=yaw, attitude_frame=frame, attitude_source=source,
        focal_mm=_number(exif_ifd.get(_TAG_FOCAL)),
        focal_35mm=_number(exif_ifd.get(_TAG_FOCAL_35)),
        focal_plane_px_per_mm=_focal_plane_px_per_mm(exif_ifd),
        exif_width_px=_positive_int(exif_ifd.get(_TAG_EXIF_WIDTH)),
    )


#: Largest plausible EXIF GPS height and XMP angle (as nav.csv's, pipeline.common.csvio).
MAX_HEIGHT_M = 1e5
MAX_ANGLE_DEG = 1e4


def _positive_int(value: object) -> int | None:
    number = _number(value)
    return int(number) if number is not None and number >= 1 else None


def _focal_plane_px_per_mm(exif_ifd: dict[int, object]) -> float | None:
    res = _number(exif_ifd.get(_TAG_FP_XRES))
    unit = _number(exif_ifd.get(_TAG_FP_UNIT))
    unit_mm = _FP_UNIT_MM.get(int(unit) if unit is not None else 2)  # EXIF default: inch
    if res is None or unit_mm is None or not res > 0:
        return None
    return res / unit_mm


def found_tags(meta: ImageMetadata) -> str:
    """Short list of what an image carries, for error messages (``Make, Model, time``)."""
    names = [("Make", meta.make), ("Model", meta.model), ("time", meta.time_source),
             ("GPS", meta.lat_deg), ("attitude", meta.attitude_source),
             ("FocalLength", meta.focal_mm)]
    present = [name for name, value in names if value is not None]
    return ", ".join(present) if present else "nothing"


def require_position(meta: ImageMetadata) -> None:
    """Raise :class:`InputDataError` unless the image has latitude, longitude and height."""
    if not meta.has_position:
        raise InputDataError(f"{meta.path.name}: no GPS position in EXIF "
                             f"(found: {found_tags(meta)})")


# --------------------------------------------------------------------------------------------
# JPEG structure
# --------------------------------------------------------------------------------------------


def check_jpeg_complete(path: Path) -> None:
    """Walk the JPEG segments up to the first scan and require an end-of-image marker after it.

    Entropy-coded data cannot contain ``FF D9`` (``FF`` bytes are stuffed), so the EOI after
    the scan start marks a complete file; trailing bytes after it are allowed.
    """
    with path.open("rb") as f:
        if f.read(2) != JPEG_SOI:
            raise InputDataError(f"{path.name}: not a JPEG (no start-of-image marker)")
        while True:
            marker = f.read(2)
            if len(marker) < 2 or marker[0] != 0xFF:
                raise InputDataError(f"{path.name}: truncated or corrupt JPEG (segment headers "
                                     f"end at byte {f.tell()})")
            code = marker[1]
            if code == 0xFF:  # fill byte
                f.seek(-1, 1)
                continue
            if code in _STANDALONE_MARKERS:
                continue
            length_bytes = f.read(2)
            if len(length_bytes) < 2:
                raise InputDataError(f"{path.name}: truncated JPEG (in a segment header)")
            f.seek(int.from_bytes(length_bytes, "big") - 2, 1)
            if code == JPEG_SOS:
                break
        scan_start = f.tell()
        size = path.stat().st_size
        chunk = 1 << 16
        pos = size
        while pos > scan_start:  # search backwards: the EOI is normally the last two bytes
            start = max(scan_start, pos - chunk)
            f.seek(start)
            if JPEG_EOI in f.read(pos - start + 1):
                return
            pos = start
    raise InputDataError(f"{path.name}: truncated JPEG (no end-of-image marker after the image "
                         f"data; {size} bytes)")


# --------------------------------------------------------------------------------------------
# EXIF
# --------------------------------------------------------------------------------------------


def _text(value: object) -> str | None:
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    if not isinstance(value, str):
        return None
    value = value.strip("\x00 ")
    return value or None


def _number(value: object) -> float | None:
    try:
        x = float(value)  # type: ignore[arg-type]  # IFDRational, int, float, str
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _dms(path: Path, name: str, value: object) -> float:
    """Degrees from an EXIF (deg, min, sec) rational triple."""
    parts = value if isinstance(value, tuple | list) else (value,)
    numbers = [_number(p) for p in parts]
    if not 1 <= len(numbers) <= 3 or any(n is None for n in numbers):
        raise InputDataError(f"{path.name}: EXIF {name}: expected degrees, minutes, seconds, "
                             f"got {value!r}")
    total = 0.0
    for n, scale in zip(numbers, (1.0, 60.0, 3600.0), strict=False):
        total += float(n) / scale  # type: ignore[arg-type]
    return total


def _gps_position(path: Path, gps: dict[int, object]) -> tuple[float | None, float | None,
                                                                float | None]:
    """Latitude, longitude (degrees, signed by the refs) and height (metres) of EXIF GPS."""
    if _GPS_LAT not in gps or _GPS_LON not in gps:
        return None, None, None
    lat = _dms(path, "GPSLatitude", gps[_GPS_LAT])
    lon = _dms(path, "GPSLongitude", gps[_GPS_LON])
    lat_ref = (_text(gps.get(_GPS_LAT_REF)) or "N").upper()
    lon_ref = (_text(gps.get(_GPS_LON_REF)) or "E").upper()
    if lat_ref not in ("N", "S") or lon_ref not in ("E", "W"):
        raise InputDataError(f"{path.name}: EXIF GPSLatitudeRef/GPSLongitudeRef: expected N/S "
                             f"and E/W, got {lat_ref!r}, {lon_ref!r}")
    lat = -lat if lat_ref == "S" else lat
    lon = -lon if lon_ref == "W" else lon
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise InputDataError(f"{path.name}: EXIF GPS position out of range: latitude {lat!r}, "
                             f"longitude {lon!r}")
    h = _number(gps.get(_GPS_ALT))
    ref = gps.get(_GPS_ALT_REF)
    ref = ref[0] if isinstance(ref, bytes) and ref else ref  # a BYTE tag: b"\x01"
    if h is not None and _number(ref) == _GPS_ALT_BELOW:
        h = -h
    if h is not None and abs(h) > MAX_HEIGHT_M:
        raise InputDataError(f"{path.name}: EXIF GPSAltitude: {h!r} m is not a plausible "
                             f"height (magnitude above {MAX_HEIGHT_M:g} m)")
    return lat, lon, h


def _exif_datetime(text: str | None, path: Path, name: str) -> dt.datetime | None:
    if text is None:
        return None
    try:
        return dt.datetime.strptime(text.strip(), "%Y:%m:%d %H:%M:%S")
    except ValueError as err:
        raise InputDataError(f"{path.name}: EXIF {name}: expected 'YYYY:MM:DD HH:MM:SS', "
                             f"got {text!r}") from err


def _time(path: Path, gps: dict[int, object], exif_ifd: dict[int, object],
          xmp: dict[str, str]) -> tuple[float | None, str | None]:
    """Acquisition time: GPS UTC, else senseFly's XMP UTC, else the camera clock."""
    date = _text(gps.get(_GPS_DATE))
    hms = gps.get(_GPS_TIME)
    if date is not None and isinstance(hms, tuple) and len(hms) == 3:
        day = _exif_datetime(f"{date} 00:00:00", path, "GPSDateStamp")
        seconds = [_number(v) for v in hms]
        if day is not None and all(s is not None for s in seconds):
            h, m, s = (float(v) for v in seconds)  # type: ignore[arg-type]
            stamp = day.replace(tzinfo=dt.UTC).timestamp()
            return stamp + 3600.0 * h + 60.0 * m + s, "gps-utc"
    utc = xmp.get("sensefly:UTCTime")
    if utc is not None:
        try:
            when = dt.datetime.fromisoformat(utc.strip())
        except ValueError as err:
            raise InputDataError(f"{path.name}: XMP sensefly:UTCTime: expected an ISO 8601 "
                                 f"time, got {utc!r}") from err
        when = when if when.tzinfo else when.replace(tzinfo=dt.UTC)
        return when.timestamp(), "xmp-utc"
    when = _exif_datetime(_text(exif_ifd.get(_TAG_DATETIME_ORIGINAL)), path, "DateTimeOriginal")
    if when is None:
        return None, None
    offset = _text(exif_ifd.get(_TAG_OFFSET_ORIGINAL))
    tz = dt.UTC
    if offset is not None:
        try:
            tz = dt.datetime.strptime(offset, "%z").tzinfo or dt.UTC
        except ValueError:
            tz = dt.UTC
    stamp = when.replace(tzinfo=tz).timestamp()
    subsec = _text(exif_ifd.get(_TAG_SUBSEC_ORIGINAL))
    if subsec is not None and subsec.isdigit():
        stamp += int(subsec) / 10 ** len(subsec)
    return stamp, "camera-clock"


# --------------------------------------------------------------------------------------------
# XMP
# --------------------------------------------------------------------------------------------


def _xmp_values(path: Path, head: bytes) -> dict[str, str]:
    """Vendor XMP values as ``{"<vendor>:<LocalName>": text}`` (``sensefly``, ``dji``,
    ``pix4d``), from attributes and simple child elements of every ``rdf:Description``."""
    start = head.find(b"<x:xmpmeta")
    if start < 0:
        return {}
    end = head.find(b"</x:xmpmeta>", start)
    if end < 0:
        raise InputDataError(f"{path.name}: XMP packet not closed within the first "
                             f"{XMP_SEARCH_BYTES} bytes")
    packet = head[start:end + len(b"</x:xmpmeta>")]
    try:
        root = ET.fromstring(packet)
    except ET.ParseError as err:
        raise InputDataError(f"{path.name}: malformed XMP packet: {err}") from err
    values: dict[str, str] = {}

    def add(qualified: str, text: str | None) -> None:
        if text is None or not qualified.startswith("{"):
            return
        uri, _, local = qualified[1:].partition("}")
        vendor = _vendor(uri)
        if vendor is not None and text.strip():
            values.setdefault(f"{vendor}:{local}", text.strip())

    for element in root.iter():
        for name, text in element.attrib.items():
            add(name, text)
        if len(element) == 0:
            add(element.tag, element.text)
    return values


def _vendor(uri: str) -> str | None:
    uri = uri.lower()
    if _NS_SENSEFLY in uri:
        return "sensefly"
    if _NS_DJI in uri:
        return "dji"
    if _NS_PIX4D_CAMERA in uri:
        return "pix4d"
    return None


#: Attitude tags by priority: (source name, frame, roll tag, pitch tag, yaw tag).
_ATTITUDE_TAGS: tuple[tuple[str, AttitudeFrame, str, str, str], ...] = (
    ("sensefly", "body", "sensefly:RollAngle", "sensefly:PitchAngle", "sensefly:Heading"),
    ("dji-gimbal", "gimbal", "dji:GimbalRollDegree", "dji:GimbalPitchDegree",
     "dji:GimbalYawDegree"),
    ("dji-flight", "body", "dji:FlightRollDegree", "dji:FlightPitchDegree",
     "dji:FlightYawDegree"),
    ("pix4d-camera", "camera", "pix4d:Roll", "pix4d:Pitch", "pix4d:Yaw"),
)


def _attitude(path: Path, xmp: dict[str, str]) -> tuple[
        float | None, float | None, float | None, AttitudeFrame | None, str | None]:
    """Roll, pitch, yaw (degrees) from the first complete vendor tag set."""
    for source, frame, *tags in _ATTITUDE_TAGS:
        if not all(tag in xmp for tag in tags):
            continue
        angles = []
        for tag in tags:
            value = _number(xmp[tag])
            if value is None:
                raise InputDataError(f"{path.name}: XMP {tag}: expected a number, "
                                     f"got {xmp[tag]!r}")
            if abs(value) > MAX_ANGLE_DEG:
                raise InputDataError(f"{path.name}: XMP {tag}: {xmp[tag]!r} is not a plausible "
                                     f"angle (magnitude above {MAX_ANGLE_DEG:g} degrees)")
            angles.append(value)
        return angles[0], angles[1], angles[2], frame, source
    return None, None, None, None, None


def _height_kind(make: str | None, xmp: dict[str, str]) -> HeightKind:
    """Which height EXIF ``GPSAltitude`` is, per vendor (docs/formats.md)."""
    if any(key.startswith("sensefly:") for key in xmp):
        return "ellipsoidal"  # equals senseFly's AltitudeWGS84
    if any(key.startswith("dji:") for key in xmp) or (make or "").upper() == "DJI":
        return "orthometric"  # DJI: AbsoluteAltitude, EGM96 (approximate)
    return "unknown"
