"""Whole-flight checks of an image flight's inputs (docs/formats.md, *Bad images*):

* the same photo twice under two names (identical files, or the same GPS position and time):
  the later one is skipped, naming both;
* the camera changing mid-flight (EXIF make, model or focal length): refused, naming the
  first image of the other camera (one camera per flight);
* the working CRS: a flight whose centre lies outside the CRS's area of use is warned about.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from collections.abc import Mapping, Sequence

import numpy as np
import pyproj

from pipeline.common.tables import NavTable
from pipeline.flight.image_metadata import ImageMetadata
from pipeline.flight.inputs import SkippedImage
from seqat.errors import InputDataError


def _digest(meta: ImageMetadata) -> str:
    h = hashlib.sha256()
    with meta.path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def duplicate_images(image_ids: Sequence[str], metas: Mapping[str, ImageMetadata]) -> (
        list[SkippedImage]):
    """The images (nav order) that repeat an earlier one: identical files (only files of
    equal size are hashed) or the same GPS position and time (a zero baseline)."""
    ids = [i for i in image_ids if i in metas]
    by_size: dict[int, list[str]] = defaultdict(list)
    for image in ids:
        by_size[metas[image].path.stat().st_size].append(image)
    first_of: dict[str, tuple[str, str]] = {}  # duplicate -> (original, how)
    for group in by_size.values():
        if len(group) < 2:
            continue
        seen: dict[str, str] = {}
        for image in group:
            digest = _digest(metas[image])
            if digest in seen:
                first_of[image] = (seen[digest], "an identical file")
            else:
                seen[digest] = image
    seen_fix: dict[tuple[float, ...], str] = {}
    for image in ids:
        m = metas[image]
        if image in first_of or not m.has_position or m.time_s is None:
            continue
        key = (m.time_s, m.lat_deg, m.lon_deg, m.h_m)  # type: ignore[assignment]
        if key in seen_fix:
            first_of[image] = (seen_fix[key], "the same GPS position and time")
        else:
            seen_fix[key] = image  # type: ignore[index]
    return [SkippedImage(image=image, reason=(
        f"{metas[image].path.name}: a duplicate of {metas[first_of[image][0]].path.name} "
        f"({first_of[image][1]}); left out"))
        for image in ids if image in first_of]


def _camera_of(meta: ImageMetadata) -> tuple[str | None, str | None, float | None]:
    return meta.make, meta.model, meta.focal_mm


def _describe(camera: tuple[str | None, str | None, float | None]) -> str:
    make, model, focal = camera
    if make and model and model.lower().startswith(make.lower()):
        make = None  # "Canon" + "Canon PowerShot ...": the model names the make already
    name = " ".join(part for part in (make, model) if part) or "unknown camera"
    return f"{name}, {focal:g} mm" if focal is not None else name


def check_one_camera(image_ids: Sequence[str], metas: Mapping[str, ImageMetadata]) -> None:
    """Refuse a flight whose EXIF camera (make, model, focal length) changes.

    Raises
    ------
    InputDataError
        Naming the first image of another camera and the first image's camera.
    """
    first: ImageMetadata | None = None
    for image in image_ids:
        meta = metas.get(image)
        if meta is None:
            continue
        if first is None:
            first = meta
            continue
        a, b = _camera_of(first), _camera_of(meta)
        if any(x is not None and y is not None and x != y for x, y in zip(a, b, strict=True)):
            raise InputDataError(
                f"{meta.path.name}: taken with another camera ({_describe(b)}) than "
                f"{first.path.name} ({_describe(a)}); one camera per flight is supported "
                "(split the flight by camera)")


def crs_area_warning(crs: pyproj.CRS, nav: NavTable, source: str) -> str | None:
    """A warning when the flight's centre lies outside the working CRS's area of use."""
    area = crs.area_of_use
    xy = nav.eop[:, :2]
    xy = xy[np.isfinite(xy).all(axis=1)]
    if area is None or len(xy) == 0:
        return None
    x, y = np.median(xy, axis=0)
    try:
        to_geo = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        lon, lat = to_geo.transform(float(x), float(y))
    except pyproj.exceptions.ProjError:
        return None
    if not (np.isfinite(lon) and np.isfinite(lat)):
        return None
    if area.west <= area.east:
        inside_lon = area.west <= lon <= area.east
    else:  # the area crosses the antimeridian
        inside_lon = lon >= area.west or lon <= area.east
    if inside_lon and area.south <= lat <= area.north:
        return None
    return (f"{source}: crs: the flight's centre ({lat:.4f} N, {lon:.4f} E) lies outside the "
            f"area of use of {crs.name!r} ({area.west:g} to {area.east:g} E, {area.south:g} "
            f"to {area.north:g} N); check crs:")
