"""Result files: exact round trips, strict run.json, all-or-nothing writes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pyproj
import pytest

from pipeline.common import atomic
from pipeline.common.atomic import atomic_write_text, write_files_atomically
from pipeline.common.columns import EOP_COLUMNS
from pipeline.common.tables import NavTable
from pipeline.flight.inputs import RunInputs, SkippedImage
from pipeline.flight.schema import CameraConfig
from pipeline.run import store
from pipeline.run.store import (
    RunRecord,
    RunTotals,
    TimingStats,
    format_observation_lines,
    format_run_json,
    read_eop_csv,
    read_points_csv,
    read_run,
    write_eop_csv,
    write_points_csv,
    write_run_outputs,
)
from seqat.errors import InputDataError
from seqat.types import EopEstimate, ImageUpdate, PointEstimate, Solution

#: Round-trip tolerance of positions (metres) and of angles after degrees <-> radians (radians).
ROUND_TRIP_TOL = 1e-9


def random_eops(n: int, seed: int = 0) -> list[EopEstimate]:
    rng = np.random.default_rng(seed)
    eops = []
    for i in range(n):
        eop = np.concatenate([[500000.0, 4090000.0, 300.0] + rng.normal(0, 100, 3),
                              rng.uniform(-np.pi, np.pi, 3)])
        sigma = np.abs(rng.normal(0, [0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3]))
        if i == 1:
            sigma[:] = np.nan  # an estimator may give no precision
        eops.append(EopEstimate(image_id=f"img_{i:04d}", eop=eop, sigma=sigma))
    return eops


def random_points(m: int, seed: int = 1) -> list[PointEstimate]:
    rng = np.random.default_rng(seed)
    return [PointEstimate(point_id=f"p{j}", xyz_m=[500000.0, 4090000.0, 100.0]
                          + rng.normal(0, 50, 3), sigma_m=np.abs(rng.normal(0, 0.1, 3)),
                          n_obs=int(rng.integers(2, 30))) for j in range(m)]


def test_eop_csv_round_trip(tmp_path: Path) -> None:
    eops = random_eops(5)
    path = tmp_path / "eop.csv"
    write_eop_csv(path, eops)
    table = read_eop_csv(path)
    assert table.image_ids == tuple(e.image_id for e in eops)
    expected = np.array([e.eop for e in eops])
    np.testing.assert_array_equal(table.eop[:, :3], expected[:, :3])  # exact decimal repr
    np.testing.assert_allclose(table.eop[:, 3:], expected[:, 3:], rtol=0, atol=ROUND_TRIP_TOL)
    np.testing.assert_allclose(table.sigma, np.array([e.sigma for e in eops]), rtol=0,
                               atol=ROUND_TRIP_TOL)
    assert np.all(np.isnan(table.sigma[1]))
    assert path.read_text().splitlines()[0] == ",".join(EOP_COLUMNS)


def test_points_csv_round_trip(tmp_path: Path) -> None:
    points = random_points(7)
    path = tmp_path / "points.csv"
    write_points_csv(path, points)
    table = read_points_csv(path)
    assert table.point_ids == tuple(p.point_id for p in points)
    np.testing.assert_array_equal(table.xyz_m, np.array([p.xyz_m for p in points]))
    np.testing.assert_array_equal(table.sigma_m, np.array([p.sigma_m for p in points]))
    np.testing.assert_array_equal(table.n_obs, [p.n_obs for p in points])


def test_reading_bad_eop_csv_names_line(tmp_path: Path) -> None:
    path = tmp_path / "eop.csv"
    write_eop_csv(path, random_eops(3))
    lines = path.read_text().splitlines()
    lines[3] = lines[3].replace(lines[3].split(",")[1], "nan", 1)  # position must be finite
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputDataError, match=r"eop\.csv:4: field 'x_m': expected a finite "
                                             r"number, got 'nan'"):
        read_eop_csv(path)


def test_timing_stats_known_values() -> None:
    t = TimingStats.from_samples(np.arange(1.0, 101.0))
    assert (t.median_ms, t.max_ms, t.total_ms) == (50.5, 100.0, 5050.0)
    assert t.p95_ms == pytest.approx(95.05) and t.p99_ms == pytest.approx(99.01)
    empty = TimingStats.from_samples([])
    assert np.isnan(empty.median_ms) and empty.total_ms == 0.0


def update_for(eop: EopEstimate, index: int) -> ImageUpdate:
    return ImageUpdate(image_id=eop.image_id, index=index, stage="sequential", update_ms=2.5,
                       window_images=3, window_first_image="img_0000", window_params=30,
                       window_eop_params=18, window_gp_params=12, inverse_sizes=(8, 12),
                       sim_reduced_size=0, sigma0=float("nan"), redundancy=4,
                       rms_gp_sigma_m=(0.1, 0.2, float("nan")), n_points_total=4, new_points=1,
                       observations_used=8, observations_skipped=0, iterations=2, eop=eop)


def sample_record(eops: list[EopEstimate]) -> RunRecord:
    totals = RunTotals(images=len(eops), points=2, observations=16,
                       update_ms=TimingStats.from_samples([2.5] * len(eops)),
                       sequential_update_ms=TimingStats.from_samples([2.5] * (len(eops) - 1)),
                       wall_s=0.1,
                       sigma0=1.02, redundancy=7)
    nav = NavTable(image_ids=tuple(e.image_id for e in eops),
                   times_s=np.arange(len(eops), dtype=np.float64),
                   eop=np.array([e.eop for e in eops]))
    camera = CameraConfig(model="OPENCV", width_px=640, height_px=480, fx_px=800.0,
                          fy_px=801.0, cx_px=319.5, cy_px=239.5, k1=-0.1)
    inputs = RunInputs(crs=pyproj.CRS.from_epsg(32652), camera=camera, camera_approximate=True,
                       nav=nav, nav_sigma=np.array([1.0, 2.0, 3.0, 0.01, 0.02, 0.03]),
                       sigma_image_px=0.7, images_dir=Path("/data/images"),
                       skipped=(SkippedImage(image="img_9", reason="img_9.jpg: truncated"),),
                       warnings=("a warning",))
    return RunRecord(method="seq-r", flight="flight", inputs=inputs,
                     options=TimingStats.from_samples([1.0]), final_only=False,
                     images=tuple(update_for(e, i) for i, e in enumerate(eops)), totals=totals)


def test_run_json_is_strict_json_with_file_units(tmp_path: Path) -> None:
    eops = random_eops(2)
    text = format_run_json(sample_record(eops))

    def no_constants(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    doc = json.loads(text, parse_constant=no_constants)
    assert doc["version"] == store.RUN_JSON_VERSION and doc["method"] == "seq-r"
    first = doc["images"][0]
    assert first["sigma0"] is None and first["rms_gp_sigma_m"] == [0.1, 0.2, None]
    assert first["inverse_sizes"] == [8, 12]
    assert first["eop"]["omega_deg"] == pytest.approx(np.degrees(eops[0].eop[3]), abs=1e-12)
    assert first["eop"]["x_m"] == eops[0].eop[0]
    assert doc["totals"]["update_ms"]["median_ms"] == 2.5
    assert doc["totals"]["accuracy"] is None


def test_run_outputs_are_published_together(tmp_path: Path) -> None:
    eops, points = random_eops(2), random_points(2)
    solution = Solution(eops=tuple(eops), points=tuple(points), sigma0=1.0, redundancy=3)
    out = tmp_path / "a" / "run"
    record = sample_record(eops)
    obs = format_observation_lines("img_0000", ("p1", "p2"), np.array([[1.5, 2.25], [3.0, 4.0]]),
                                   "img_0000")
    files = write_run_outputs(out, solution, record, obs)
    names = ["eop.csv", "points.csv", "run.json", "nav.csv", "observations.csv",
             "shots.geojson", "cameras_opk.csv", "cameras_opk.prj", "tie_points.laz"]
    assert [p.name for p in files] == names
    assert sorted(p.name for p in out.iterdir()) == sorted(names)
    assert read_eop_csv(out / "eop.csv").image_ids == ("img_0000", "img_0001")
    # the run folder reads back as the inputs it was written from
    run = read_run(out)
    assert run.method == "seq-r" and run.flight_dir == Path("flight")
    assert run.crs.to_epsg() == 32652
    assert run.camera == record.inputs.camera and run.inputs.camera_approximate
    np.testing.assert_allclose(run.nav_sigma, record.inputs.nav_sigma, rtol=1e-14)
    np.testing.assert_allclose(run.nav.eop, record.inputs.nav.eop, rtol=1e-14, atol=1e-14)
    assert run.nav.image_ids == record.inputs.nav.image_ids
    assert run.sigma_image_px == 0.7 and run.images_dir == Path("/data/images")
    assert run.inputs.skipped == record.inputs.skipped
    assert run.inputs.warnings == ("a warning",)
    assert run.observations_path.read_text().splitlines() == [
        "image,point,x_px,y_px,frame", "img_0000,p1,1.5,2.25,img_0000",
        "img_0000,p2,3.0,4.0,img_0000"]
    np.testing.assert_array_equal(run.points.xyz_m, np.array([p.xyz_m for p in points]))


def test_read_run_names_what_is_missing(tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="no such run folder"):
        read_run(tmp_path / "nowhere")
    with pytest.raises(InputDataError, match=r"run\.json: no such file"):
        read_run(tmp_path)
    (tmp_path / "run.json").write_text('{"method": "seq-r"}')
    with pytest.raises(InputDataError, match=r"run\.json: missing key 'crs'"):
        read_run(tmp_path)


def test_failed_publish_leaves_no_folder_and_no_temp_files(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {"n": 0}
    real_replace = os.replace

    def failing_replace(src: str, dst: str) -> None:
        calls["n"] += 1
        if calls["n"] == 1:
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    with pytest.raises(OSError, match="No space left"):
        write_files_atomically(tmp_path / "new" / "run", {"a.csv": "x\n", "b.csv": "y\n"})
    assert list(tmp_path.iterdir()) == []  # the folders it created are gone again


def test_bytes_are_published_with_the_text_files(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The run's binary export (tie_points.laz) goes through the same publish: temporary
    file, fsync, rename; a failure leaves no temporary file and no partial LAZ."""
    files = {"a.csv": "x\n", "b.laz": bytes(range(256))}
    written = write_files_atomically(tmp_path / "ok", files)
    assert written[1].read_bytes() == bytes(range(256)) and written[0].read_text() == "x\n"
    real_replace = atomic.os.replace

    def failing_last(src: str, dst: str) -> None:
        if str(dst).endswith("b.laz"):
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", failing_last)
    with pytest.raises(OSError, match="No space left"):
        write_files_atomically(tmp_path / "new", files)
    assert not (tmp_path / "new" / "b.laz").exists()
    assert not list((tmp_path / "new").glob(".*"))  # no temporary file left


def test_failed_write_keeps_previous_file(tmp_path: Path) -> None:
    path = tmp_path / "eop.csv"
    path.write_text("previous\n")
    with pytest.raises(UnicodeEncodeError):
        atomic_write_text(path, "half\udc80written")  # not encodable: fails mid-write
    assert path.read_text() == "previous\n"
    assert [p.name for p in tmp_path.iterdir()] == ["eop.csv"]  # no temp file left


def test_publish_refuses_a_file_as_folder(tmp_path: Path) -> None:
    (tmp_path / "run").write_text("")
    with pytest.raises(InputDataError, match="exists and is not a folder"):
        write_files_atomically(tmp_path / "run", {"a.csv": "x\n"})
