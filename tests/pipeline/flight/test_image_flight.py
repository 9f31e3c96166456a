"""Image flights end to end: sample_data/seneca_mini (real images), bad input, nav sources."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.common.text import first_few
from pipeline.flight.folder import read_flight
from pipeline.flight.navigation import geodetic_to_eop, read_image_folder_nav
from pipeline.run.resection import resect_attitude
from pipeline.run.runner import Method, run_flight
from pipeline.run.store import read_eop_csv, read_run
from seqat.calibration import DEFAULT_FREE
from seqat.errors import InputDataError
from seqat.geometry import project, rotation_matrix
from seqat.types import PinholeCamera

from ..sample_runs import MINI, MINI_ORTHO_PIXEL_M, copy_run_files, resize_images

#: EXIF of the Seneca images: 4.3 mm, 16393.44 px/inch at ExifImageWidth 4000 px.
MINI_F_PX = 4.3 * 16393.44262295082 / 25.4 * 1000 / 4000


@pytest.fixture(scope="module")
def mini_run(mini_chain: Path) -> Path:
    """The session's Seq-R run of the sample (``seqat run --ortho --report``, read-only)."""
    return mini_chain


def test_bare_image_folder_reads_nav_and_camera_from_exif() -> None:
    flight = read_flight(MINI)
    assert flight.kind == "images" and flight.camera_approximate
    assert flight.crs.to_epsg() == 32617  # auto: UTM 17N of the first fix
    cam = flight.camera_config
    assert (cam.width_px, cam.height_px) == (1000, 750)
    assert cam.fx_px == pytest.approx(MINI_F_PX, rel=1e-9)
    assert len(flight.nav) == len(flight.image_paths) == 18 and not flight.skipped
    assert np.all(np.diff(flight.nav.times_s) > 0)


def test_seneca_mini_runs_and_georeferences_every_image(mini_run: Path) -> None:
    run = read_run(mini_run)
    assert run.eop.image_ids == run.nav.image_ids and len(run.eop) == 18
    record = run.record
    totals = record["totals"]
    # default sigmas fit the Seneca nav; the matches fit to ~0.4-0.9 px (0.48-0.86 over FLANN
    # seeds; 0.38-0.40 since one observation per pixel left SIFT's orientation twins out)
    assert 0.3 < totals["sigma0"] < 2.0
    images = record["images"]
    assert all("tracking" in im for im in images)
    matched = [im["tracking"]["pairs_matched"] > 0 for im in images[1:]]
    assert sum(matched) >= 15  # all but the odd turn image find a verified pair
    # the adjusted EOPs differ from the nav, inside the nav's a priori sigmas
    d = run.eop.eop - run.nav.eop
    assert np.all(np.abs(d[:, :3]) < 3 * np.asarray(record["nav_sigma"]["position_m"]))
    assert len(run.points) > 200
    # after every image of a real flight: sigma0 finite, every published sigma finite and > 0
    for im in images:
        if im["stage"] == "sequential":
            assert np.isfinite(im["sigma0"]) and im["sigma0"] > 0
        sig = np.asarray(im["live"]["sigma_position_m"], dtype=float)
        assert np.all(np.isfinite(sig)) and np.all(sig > 0), im["image_id"]
    assert np.all(np.isfinite(run.eop.sigma)) and np.all(run.eop.sigma > 0)
    assert np.all(np.isfinite(run.points.sigma_m)) and np.all(run.points.sigma_m > 0)


def test_replay_of_the_tie_points_gives_the_same_result(mini_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "replay"
    run_flight(MINI, out, method=Method.SEQ_R, observations=mini_run / "observations.csv",
               progress=False)
    assert (out / "observations.csv").read_text() == (mini_run / "observations.csv").read_text()
    a, b = read_eop_csv(mini_run / "eop.csv"), read_eop_csv(out / "eop.csv")
    # the same observations and the same initial values (resected from the kept
    # observations in both runs): the same sequential result, to round-off
    np.testing.assert_allclose(a.eop, b.eop, rtol=0, atol=1e-9)


# --------------------------------------------------------------------------------------------
# Bad input: the run goes on without the unusable images and says why
# --------------------------------------------------------------------------------------------


def _copy_images(dst: Path, n: int) -> list[Path]:
    (dst / "images").mkdir(parents=True)
    paths = sorted((MINI / "images").glob("*.jpg"))[:n]
    return [Path(shutil.copy(p, dst / "images" / p.name)) for p in paths]


def test_unusable_images_are_skipped_with_the_reason(tmp_path: Path) -> None:
    paths = _copy_images(tmp_path, 5)
    data = paths[1].read_bytes()
    paths[1].write_bytes(data[: len(data) // 2])  # truncated
    with Image.open(paths[2]) as im:  # no EXIF: no GPS
        im.save(paths[2].with_name("nogps.jpg"), "JPEG")
    paths[2].unlink()
    flight = read_flight(tmp_path)
    reasons = {s.image: s.reason for s in flight.skipped}
    assert set(reasons) == {paths[1].stem, "nogps"}
    assert "truncated JPEG" in reasons[paths[1].stem]
    assert "no GPS position" in reasons["nogps"]
    assert flight.nav.image_ids == tuple(p.stem for p in (paths[0], paths[3], paths[4]))
    out = tmp_path.with_name(tmp_path.name + "-out")  # never inside the flight folder
    run_flight(tmp_path, out, progress=False)
    doc = json.loads((out / "run.json").read_text())
    assert {s["image"] for s in doc["skipped"]} == set(reasons)


def _geodetic_nav(folder: Path, rows: list[str], extra: str = "") -> None:
    (folder / "nav.csv").write_text(
        "image,time_s,lat_deg,lon_deg,h_m,roll_deg,pitch_deg,yaw_deg\n" + "".join(rows))
    (folder / "flight.yaml").write_text(
        "crs: auto\nimages: images\nnav:\n  frame: geodetic\n" + extra)


def _rows_from_exif(paths: list[Path]) -> list[str]:
    nav = read_image_folder_nav(paths[0].parent)
    rows = []
    for r in nav.records:
        m = r.metadata
        rows.append(f"{r.image},{m.time_s},{m.lat_deg},{m.lon_deg},{m.h_m},{m.roll_deg},"
                    f"{m.pitch_deg},{m.yaw_deg}\n")
    return rows


def test_geodetic_nav_csv_equals_the_image_metadata(tmp_path: Path) -> None:
    paths = _copy_images(tmp_path, 4)
    from_exif = read_flight(tmp_path)  # bare folder: nav from the images
    _geodetic_nav(tmp_path, _rows_from_exif(paths))
    from_csv = read_flight(tmp_path)
    assert from_csv.nav.image_ids == from_exif.nav.image_ids
    np.testing.assert_allclose(from_csv.nav.eop, from_exif.nav.eop, rtol=0, atol=1e-9)


def test_nav_rows_without_images_and_images_without_rows_are_skipped(tmp_path: Path) -> None:
    paths = _copy_images(tmp_path, 4)
    rows = _rows_from_exif(paths)
    _geodetic_nav(tmp_path, rows[:3] + [rows[3].replace(paths[3].stem, "IMG_9999")],
                  "  dropout: skip\n")  # bridge (default): tests/pipeline/flight/test_dropout.py
    flight = read_flight(tmp_path)
    reasons = {s.image: s.reason for s in flight.skipped}
    assert "listed in nav.csv but no IMG_9999.jpg" in reasons["IMG_9999"]
    assert reasons[paths[3].stem].endswith("no row in nav.csv")
    assert len(flight.nav) == 3


@pytest.mark.parametrize(("edit", "message"), [
    (lambda rows: rows[:2] + [rows[1]] + rows[2:], "duplicate nav row for image"),
    (lambda rows: [rows[1], rows[0]] + rows[2:], "nav out of time order"),
])
def test_nav_rows_out_of_order_or_duplicated_are_errors(tmp_path: Path, edit: object,
                                                        message: str) -> None:
    paths = _copy_images(tmp_path, 4)
    _geodetic_nav(tmp_path, edit(_rows_from_exif(paths)))  # type: ignore[operator]
    with pytest.raises(InputDataError, match=message):
        read_flight(tmp_path)
    result = CliRunner().invoke(app, ["run", str(tmp_path), "--out", str(tmp_path / "o"),
                                      "--no-progress"])
    assert result.exit_code == 2 and message in result.stderr
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------------------------
# Navigation and resection known answers
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("yaw_deg", "east", "north"), [(0.0, 0.0, 1.0), (90.0, 1.0, 0.0)])
def test_lever_arm_is_applied_in_the_body_frame(yaw_deg: float, east: float,
                                                north: float) -> None:
    """A camera 1 m ahead of the antenna lies 1 m along the heading (on the meridian)."""
    import pyproj

    crs = pyproj.CRS.from_epsg(32617)  # central meridian -81
    args = ([-81.0], [41.0], [300.0], [[0.0, 0.0, yaw_deg]], ["body"], ["ellipsoidal"], crs)
    from pipeline.flight.navigation import BoresightConfig

    base = geodetic_to_eop(*args, BoresightConfig())
    moved = geodetic_to_eop(*args, BoresightConfig(), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(moved[0, :3] - base[0, :3], [east, north, 0.0], atol=1e-9)
    np.testing.assert_allclose(moved[0, 3:], base[0, 3:], atol=0)


@pytest.mark.parametrize("distortion", [{}, {"k1": -0.25, "k2": 0.06, "p1": 0.002}])
def test_resection_recovers_the_rotation_despite_outliers(distortion: dict[str, float]) -> None:
    """Also through a strongly distorted camera (the frames' pixels are observed ones)."""
    rng = np.random.default_rng(3)
    cam = PinholeCamera(f_px=500.0, cx_px=499.5, cy_px=374.5, width_px=1000, height_px=750,
                        **distortion)
    truth = np.array([100.0, 200.0, 80.0, 0.12, -0.08, 1.3])
    xyz = np.column_stack([rng.uniform(40, 160, 60), rng.uniform(160, 240, 60),
                           rng.uniform(-2, 2, 60)])
    uv = project(np.tile(truth, (60, 1)), xyz, cam) + rng.normal(0, 0.5, (60, 2))
    uv[:15] += rng.uniform(60, 200, (15, 2)) * rng.choice([-1, 1], (15, 2))  # 25 % wrong
    nav = truth.copy()
    nav[3:] += np.radians([8.0, -6.0, 15.0])  # the INS: far off
    res = resect_attitude(xyz, uv, cam, nav, threshold_deg=1.0)
    assert res.eop is not None
    R_err = rotation_matrix(*res.eop[3:]).T @ rotation_matrix(*truth[3:])
    angle = math.degrees(math.acos(np.clip((np.trace(R_err) - 1) / 2, -1, 1)))
    assert angle < 0.05
    assert not np.any(res.inliers[:15]) and np.all(res.inliers[15:])


def test_flight_bench_compares_methods_on_the_same_tie_points(
        mini_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.bench import flight as bench_flight

    tracking_runs: list[Path] = []

    def run_flight_in_bench(flight: Path, out: Path, **kwargs: object) -> object:
        if kwargs == {"method": Method.SEQ_R, "progress": True}:
            # The bench's own tracking run is the session's Seq-R run of the same flight with
            # the same options (tracking and results are deterministic): its files, not a
            # fourth tracking of the 18 images in the suite.
            assert Path(flight) == MINI
            tracking_runs.append(copy_run_files(mini_run, Path(out)))
            return None
        assert kwargs.get("observations") is not None, kwargs  # the others replay its points
        return run_flight(flight, out, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(bench_flight, "run_flight", run_flight_in_bench)
    b = bench_flight.run_flight_bench(MINI, tmp_path)
    assert tracking_runs == [tmp_path / "seq-r"]
    doc = json.loads((tmp_path / "bench_flight.json").read_text())
    assert doc["images"] == 18 and (tmp_path / "latency.png").stat().st_size > 0
    # every run read the same observations
    texts = {(tmp_path / m / "observations.csv").read_text() for m in ("seq-r", "sim", "seq-f")}
    assert len(texts) == 1
    assert sum(b.track_length_histogram.values()) == b.tracks > 100
    assert b.track_length_median >= 2
    # sigma_image_px is 1 px; the matches fit to ~0.4-0.9 px (as above)
    assert 0.3 < b.sigma0["sim"] < 2.0 and b.rms_residual_px["sim"] < 2.0
    assert b.latency_ms.median >= b.at_ms.median > 0
    # a camera from EXIF is self-calibrated by default; the bench reruns it fixed
    # (an 18-image strip does not determine f against the heights: held at the prior)
    for m in ("seq-r", "sim", "seq-f"):
        est = b.camera_estimate[m]
        assert isinstance(est, dict) and "k1" in est["free"]
        assert set(est["free"]) | set(est["held"]) == set(DEFAULT_FREE)
    assert b.other_camera["self_calibration"] is False
    fixed = b.other_camera["sigma0"]
    assert fixed["sim"] > 0.95 * b.sigma0["sim"]  # type: ignore[index]
    # the COLMAP reference of the same tie points, with the run's (robust) loss, near Sim
    assert b.colmap.get("loss") == "huber" and b.colmap.get("converged") is True, b.colmap
    assert b.colmap_minus_sim is not None and b.seq_r_minus_colmap is not None
    assert max(b.colmap_minus_sim.pos_rms_m) < 0.5
    assert doc["at_ms"]["p99"] >= doc["at_ms"]["p95"]


def test_run_with_ortho_and_report_writes_the_whole_chain(mini_chain: Path) -> None:
    out = mini_chain  # seqat run MINI --ortho --ortho-options --report (exit 0: checked)
    for name in ("eop.csv", "mosaic.tif", "cameras.gpkg", "report.html", "report.json"):
        assert (out / name).stat().st_size > 0, name
    assert len(list((out / "ortho").glob("*.tif"))) == 18
    report = json.loads((out / "report.json").read_text())
    assert report["methods"] == ["direct", "seq-r"]
    run = read_run(out)
    assert report["tie_points"]["count"] == len(run.points)
    ortho = json.loads((out / "ortho.json").read_text())
    assert ortho["pixel_m"] == MINI_ORTHO_PIXEL_M  # the --ortho-options file was read
    live = ortho["live"]  # the ortho ran image by image
    assert live["surface_from_image"] is not None  # no lidar: flat plane after the first GPs
    stages = {s["stage"]: s for s in report["latency"]["stages"]}
    assert report["latency"]["ortho"] == "live"
    assert stages["end to end"]["median_ms"] > stages["AT update"]["median_ms"] > 0
    assert stages["ortho: AT update -> mosaic"]["images"] == 18
    # the EXIF camera was self-calibrated; run.json, the report and later stages say so
    est = run.record["camera_estimate"]
    assert "k1" in est["free"] and run.camera.model == "OPENCV"  # type: ignore[index,operator]
    assert run.camera.k1 == est["values"]["k1"] != run.camera_prior.k1  # type: ignore[index]
    assert "self-calibrated: " in report["flight_summary"]["camera_estimate"]
    assert "k1 " in (out / "report.html").read_text()


def test_images_of_another_size_are_named_once_per_size(tmp_path: Path) -> None:
    """Images of another size than the camera's (the first image's) with its aspect ratio are
    resampled to it and named in one warning per size; one image alone in its own line."""
    folder = tmp_path / "mini"
    shutil.copytree(MINI, folder)
    images = sorted((folder / "images").glob("*.jpg"))
    resize_images(images[1:5], [(900, 675)] * 3 + [(800, 600)])
    flight = read_flight(folder)
    cam = flight.camera_config
    assert (cam.width_px, cam.height_px) == (1000, 750)
    assert cam.fx_px == pytest.approx(MINI_F_PX, rel=1e-9)
    assert len(flight.nav) == 18 and not flight.skipped
    assert [w for w in flight.warnings if "resampled" in w] == [
        "3 images of 900 x 675 px (IMG_0461.jpg, IMG_0462.jpg, IMG_0463.jpg) differ from the "
        "camera's 1000 x 750 px; resampled to it (same aspect ratio)",
        "IMG_0464.jpg: size 800 x 600 px differs from the camera's 1000 x 750 px; resampled "
        "to it (same aspect ratio)"]
    assert np.isfinite(flight.nav.eop[:, 3:]).all()  # the resized files kept their XMP


def test_too_few_usable_images_names_the_first_reasons_and_counts_the_rest(
        tmp_path: Path) -> None:
    """Every image but one of another aspect ratio: one line that gives the first reasons
    (as the navigation's own "too few usable images" error does) and counts the rest, not
    every reason of a long flight joined into one line."""
    paths = _copy_images(tmp_path, 6)
    resize_images(paths[1:], [(1000, 600)] * 5)
    with pytest.raises(InputDataError) as err:
        read_flight(tmp_path)
    msg = str(err.value)
    assert "\n" not in msg and ": 1 usable image(s); at least 2 are needed (skipped: " in msg
    named = [p.name for p in paths[1:4]]
    assert msg.endswith("another aspect ratio than the camera's 1000 x 750 px; and 2 more)")
    assert all(f"{n}: size 1000 x 600 px" in msg for n in named)
    assert paths[4].name not in msg and paths[5].name not in msg


@pytest.mark.parametrize(("items", "limit", "sep", "expected"), [
    (["a", "b"], 5, ", ", "a, b"),
    (["a", "b", "c"], 2, ", ", "a, b and 1 more"),
    (["a: x, y", "b: z", "c"], 1, "; ", "a: x, y; and 2 more"),
    (["a"] * 3, 3, "; ", "a; a; a"),
    ([], 3, ", ", ""),
])
def test_first_few_names_the_first_items_and_counts_the_rest(
        items: list[str], limit: int, sep: str, expected: str) -> None:
    assert first_few(items, limit, sep) == expected
