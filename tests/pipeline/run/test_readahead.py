"""The watch's read-ahead (pipeline.run.readahead): the same features as detecting in turn,
and an unreadable image skipped as without it."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from pipeline.flight.folder import read_flight
from pipeline.flight.inputs import SkippedImage
from pipeline.run.readahead import ReadAhead
from pipeline.run.sources import ImageSource, PreparedFrame

from ..sample_runs import AUTZEN


def _source(folder: Path) -> tuple[ImageSource, object]:
    flight = read_flight(folder)
    return ImageSource(flight, flight.config.tracking), flight


def test_frames_read_ahead_equal_frames_read_in_turn(tmp_path: Path) -> None:
    plain, flight = _source(AUTZEN)
    ahead_src, _ = _source(AUTZEN)
    ahead = ReadAhead(ahead_src)
    paths = list(flight.image_paths)[:4]  # type: ignore[attr-defined]
    nav = flight.nav  # type: ignore[attr-defined]
    try:
        for k, path in enumerate(paths):
            ahead.schedule(paths[k:])
            eop, _ = flight.frame_nav(k)  # type: ignore[attr-defined]
            args = (nav.image_ids[k], path, eop, float(nav.times_s[k]))
            a = plain.prepare(*args)
            read = ahead.take(path)
            assert read is not None and read.features is not None
            b = ahead_src.prepare(*args, ahead=read)
            assert isinstance(a, PreparedFrame) and isinstance(b, PreparedFrame)
            assert a.frame.point_ids == b.frame.point_ids
            np.testing.assert_array_equal(a.frame.uv_px, b.frame.uv_px)
            np.testing.assert_array_equal(a.frame.late_uv_px, b.frame.late_uv_px)
            assert b.tracking["detect_ms"] == read.features.detect_ms
        assert ahead.take(paths[0]) is None  # taken once
    finally:
        ahead.close()


def test_an_unreadable_image_read_ahead_is_skipped(tmp_path: Path) -> None:
    src, flight = _source(AUTZEN)
    bad = tmp_path / "broken.jpg"
    good = Path(flight.image_paths[0])  # type: ignore[attr-defined]
    bad.write_bytes(good.read_bytes()[:200])
    shutil.copy(good, tmp_path / "good.jpg")
    ahead = ReadAhead(src)
    try:
        ahead.schedule([bad, tmp_path / "good.jpg"])
        eop, _ = flight.frame_nav(0)  # type: ignore[attr-defined]
        out = src.prepare("broken", bad, eop, 0.0, ahead=ahead.take(bad))
        assert isinstance(out, SkippedImage) and out.image == "broken" and out.reason
    finally:
        ahead.close()
