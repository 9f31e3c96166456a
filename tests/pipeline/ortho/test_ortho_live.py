"""Live ortho of ``seqat run --ortho``: equals the post-run ortho, re-ortho rule, fallbacks."""

from __future__ import annotations

import json
import os
import shutil
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import rasterio
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.dsm import read_dsm
from pipeline.ortho.live import LiveOrtho, LiveOrthoOptions
from pipeline.ortho.stage import image_files, orthorectify_run
from pipeline.run.store import read_run
from seqat.errors import ConfigError
from seqat.types import EopEstimate, PointEstimate, Solution

from .test_ortho_run import Z_PLANE_M, mosaic_matches_texture, write_run, write_scene_dsm

#: Ortho pixel of these tests (the scene's GSD is 0.1 m): the strip spans several tiles.
PIXEL_M = 0.05


def _copy_run(out: Path, to: Path) -> Path:
    """The run's own files only (no ortho products): a fresh folder for ``seqat ortho``."""
    to.mkdir()
    for name in ("eop.csv", "points.csv", "run.json", "nav.csv", "observations.csv"):
        shutil.copy(out / name, to / name)
    return to


def _live(out: Path, dsm_path: Path | None, **options: object) -> LiveOrtho:
    run = read_run(out)
    assert run.images_dir is not None
    return LiveOrtho(out, crs=run.crs, camera=run.camera, images=image_files(run.images_dir),
                     nav=run.nav, dsm=read_dsm(dsm_path, run.crs) if dsm_path else None,
                     ortho_options=OrthoOptions(pixel_m=PIXEL_M),
                     options=LiveOrthoOptions(**options))  # type: ignore[arg-type]


def _feed(live: LiveOrtho, solution: Solution, live_eops: dict[str, np.ndarray],
          estimator: object = None) -> None:
    """Drive the listener as the runner does: one update per image, then the end."""
    for k, est in enumerate(solution.eops):
        update = SimpleNamespace(eop=EopEstimate(image_id=est.image_id,
                                                 eop=live_eops[est.image_id], sigma=est.sigma),
                                 n_points_total=len(solution.points) if k else 0)
        live.on_image(SimpleNamespace(image_id=est.image_id), update, estimator)  # type: ignore[arg-type]
    live.on_finish(solution)


def _solution(out: Path) -> Solution:
    run = read_run(out)
    return Solution(
        eops=tuple(EopEstimate(image_id=i, eop=e, sigma=s) for i, e, s in
                   zip(run.eop.image_ids, run.eop.eop, run.eop.sigma, strict=True)),
        points=tuple(PointEstimate(point_id=p, xyz_m=x, sigma_m=np.full(3, 0.02), n_obs=3)
                     for p, x in zip(run.points.point_ids, run.points.xyz_m, strict=True)),
        sigma0=1.0, redundancy=1)


def _mosaic(path: Path) -> tuple[np.ndarray, object]:
    with rasterio.open(path) as src:
        return src.read(), src.transform


@pytest.fixture(scope="module")
def post_mosaic(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, object]:
    """Pixels and transform of the post-run mosaic (``seqat ortho``) of ``write_run``'s run
    on the scene DSM: what the live mosaic must equal when it ends on the same EOPs."""
    root = tmp_path_factory.mktemp("post")
    out = write_run(root)
    post = orthorectify_run(_copy_run(out, root / "post"),
                            dsm_path=write_scene_dsm(root / "dsm.tif"),
                            options=OrthoOptions(pixel_m=PIXEL_M), progress=False)
    return _mosaic(post.mosaic)


@pytest.mark.parametrize("background", [True, False])
def test_live_mosaic_equals_the_post_run_one_when_eops_do_not_move(
        tmp_path: Path, post_mosaic: tuple[np.ndarray, object], background: bool) -> None:
    out = write_run(tmp_path)
    dsm = write_scene_dsm(tmp_path / "dsm.tif")
    solution = _solution(out)
    with _live(out, dsm, background=background) as live:
        _feed(live, solution, {e.image_id: e.eop for e in solution.eops})
    summary = live.result()
    live_pixels, live_transform = _mosaic(out / "mosaic.tif")
    post_pixels, post_transform = post_mosaic
    assert live_transform == post_transform
    np.testing.assert_array_equal(live_pixels, post_pixels)
    mosaic_matches_texture(out / "mosaic.tif")
    assert summary.live is not None and summary.live.images_reorthorectified == ()
    assert summary.live.tiles_rebuilt == 0 and summary.live.background is background
    doc = json.loads((out / "ortho.json").read_text())
    assert doc["eop_source"] == "live"
    for image in doc["images"]:
        assert image["eop"] == "live" and image["shift_px"] == 0.0
        for key in ("read_ms", "compute_ms", "mosaic_ms", "queue_ms", "latency_ms"):
            assert image[key] >= 0.0, key
        assert image["latency_ms"] >= image["compute_ms"] + image["mosaic_ms"]
    for key in ("listener_ms", "queue_ms", "latency_ms"):
        assert doc["live"][key]["median_ms"] >= 0.0
    assert (out / "cameras.gpkg").is_file() and len(list((out / "ortho").glob("*.tif"))) == 3
    assert not list(out.glob(".mosaic.tif.tiles"))  # tile store removed


def test_reortho_rule_and_rebuilt_mosaic(tmp_path: Path,
                                        post_mosaic: tuple[np.ndarray, object]) -> None:
    out = write_run(tmp_path)
    dsm = write_scene_dsm(tmp_path / "dsm.tif")
    solution = _solution(out)
    # live EOPs off by a pure translation: 0.01 m (0.2 px) for img_0000, 0.15 m (3 px) for
    # img_0001; img_0002 exact. A translation moves the footprint by exactly that much.
    offsets = {"img_0000": 0.01, "img_0001": 0.15, "img_0002": 0.0}
    live_eops = {e.image_id: e.eop + np.array([offsets[e.image_id], 0, 0, 0, 0, 0])
                 for e in solution.eops}
    with _live(out, dsm) as live:
        _feed(live, solution, live_eops)
    summary = live.result()
    assert summary.live is not None
    assert summary.live.images_reorthorectified == ("img_0001",)
    assert summary.live.tiles_rebuilt > 0
    shifts = {r.image: r.shift_px for r in summary.images}
    assert shifts == pytest.approx({i: d / PIXEL_M for i, d in offsets.items()}, abs=1e-6)
    assert [r.eop for r in summary.images] == ["live", "final", "live"]
    # Rule 0: every image that moved at all is done again, and the rebuilt tiles give
    # exactly the mosaic of the post-run ortho with the final EOPs.
    out0 = write_run(tmp_path / "zero")
    with _live(out0, dsm, reortho_shift_px=0.0) as live:
        _feed(live, solution, live_eops)
    assert live.result().live.images_reorthorectified == ("img_0000", "img_0001")  # type: ignore[union-attr]
    np.testing.assert_array_equal(_mosaic(out0 / "mosaic.tif")[0], post_mosaic[0])


def test_flat_fallback_waits_for_the_first_ground_points(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    solution = _solution(out)
    estimator = SimpleNamespace(window_solution=lambda: solution)
    with _live(out, None) as live:
        _feed(live, solution, {e.image_id: e.eop for e in solution.eops}, estimator)
    summary = live.result()
    assert summary.live is not None
    assert summary.live.surface_from_image == "img_0001"  # the first update with points
    assert [r.image for r in summary.images] == ["img_0000", "img_0001", "img_0002"]
    assert any("flat plane" in w and f"{Z_PLANE_M:.2f}" in w for w in summary.warnings)
    mosaic_matches_texture(out / "mosaic.tif")


def test_live_ortho_in_another_crs(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    run = read_run(out)
    solution = _solution(out)
    assert run.images_dir is not None
    with LiveOrtho(out, crs=run.crs, camera=run.camera, images=image_files(run.images_dir),
                   nav=run.nav, dsm=read_dsm(write_scene_dsm(tmp_path / "dsm.tif"), run.crs),
                   ortho_options=OrthoOptions(pixel_m=0.2), out_crs="EPSG:4326") as live:
        _feed(live, solution, {e.image_id: e.eop for e in solution.eops})
    summary = live.result()
    assert summary.crs == "WGS 84" and len(summary.images) == 3
    for record in summary.images:
        with rasterio.open(record.path or "") as src:
            assert src.crs.to_epsg() == 4326


def test_live_errors_are_kept_until_the_run_is_published(tmp_path: Path) -> None:
    out = write_run(tmp_path)
    solution = _solution(out)
    far = {e.image_id: e.eop + np.array([5000.0, 0, 0, 0, 0, 0]) for e in solution.eops}
    with _live(out, write_scene_dsm(tmp_path / "dsm.tif")) as live:
        _feed(live, Solution(eops=tuple(EopEstimate(image_id=e.image_id, eop=far[e.image_id],
                                                    sigma=e.sigma) for e in solution.eops),
                             points=solution.points, sigma0=1.0, redundancy=1), far)
    with pytest.raises(Exception, match="no image could be orthorectified"):
        live.result()
    assert not (out / "mosaic.tif").exists() and not list(out.glob(".mosaic.tif.tiles"))


def test_cli_run_ortho_flags(tmp_path: Path, small_sim_dir: Path) -> None:
    bad = CliRunner().invoke(app, ["run", str(small_sim_dir), "--out", str(tmp_path / "a"),
                                   "--dsm", "x.tif"])
    assert bad.exit_code == 2 and "--ortho" in bad.output
    bad = CliRunner().invoke(app, ["run", str(small_sim_dir), "--out", str(tmp_path / "b"),
                                   "--ortho"])
    assert bad.exit_code == 2 and "image flight" in bad.output
    assert len(bad.output.strip().splitlines()) == 1 and not (tmp_path / "b").exists()
    options = tmp_path / "live.yaml"
    options.write_text("live:\n  reortho_shift_px: -1\n")
    bad = CliRunner().invoke(app, ["run", str(small_sim_dir), "--out", str(tmp_path / "c"),
                                   "--ortho", "--ortho-options", str(options)])
    assert bad.exit_code == 2 and "reortho_shift_px" in bad.output
    # The dsm: section grids the flight's LiDAR (issue 14), so it is read and checked.
    options.write_text("dsm:\n  cell_m: -1\n")
    bad = CliRunner().invoke(app, ["run", str(small_sim_dir), "--out", str(tmp_path / "c"),
                                   "--ortho", "--ortho-options", str(options)])
    assert bad.exit_code == 2 and "cell_m: expected a positive number" in bad.output
    options.write_text("dsm:\n  min_points_per_cell: 2\n")  # removed with the gap filling
    bad = CliRunner().invoke(app, ["run", str(small_sim_dir), "--out", str(tmp_path / "c"),
                                   "--ortho", "--ortho-options", str(options)])
    assert bad.exit_code == 2 and "dsm.min_points_per_cell: unknown key" in bad.output
    assert not (tmp_path / "c").exists()


@pytest.mark.skipif(not hasattr(os, "setpriority"), reason="per-thread priority: Linux")
def test_the_worker_thread_runs_nicer_than_the_at_loop() -> None:
    from pipeline.ortho.live import _lower_priority

    seen: list[int] = []

    def worker() -> None:
        _lower_priority(5)
        tid = threading.get_native_id()
        inner = threading.Thread(target=lambda: seen.append(
            os.getpriority(os.PRIO_PROCESS, threading.get_native_id())))
        inner.start()
        inner.join()  # threads it starts inherit the priority
        seen.append(os.getpriority(os.PRIO_PROCESS, tid))

    main = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen == [min(main + 5, 19)] * 2
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main
    with pytest.raises(ConfigError, match="worker_nice"):
        LiveOrthoOptions(worker_nice=25)


def test_per_image_cogs_are_written_once_at_the_end(tmp_path: Path) -> None:
    """No per-image COG while the flight goes on (most are redone with the final EOP, and a
    COG costs more CPU than its ortho); at the end each image's COG equals ``seqat ortho``'s
    with the EOP it is kept with."""
    out = write_run(tmp_path / "live")
    dsm = write_scene_dsm(tmp_path / "dsm.tif")
    solution = _solution(out)
    with _live(out, dsm, background=False) as live:
        for k, est in enumerate(solution.eops):
            update = SimpleNamespace(eop=est, n_points_total=len(solution.points) if k else 0)
            live.on_image(SimpleNamespace(image_id=est.image_id), update, None)  # type: ignore[arg-type]
        assert not list((out / "ortho").glob("*.tif"))  # every image orthorectified, no COG
        live.on_finish(solution)
    post = orthorectify_run(_copy_run(write_run(tmp_path / "post_run"), tmp_path / "post"),
                            dsm_path=dsm, options=OrthoOptions(pixel_m=PIXEL_M), progress=False)
    doc = json.loads((out / "ortho.json").read_text())
    assert [r["eop"] for r in doc["images"]] == ["live"] * 3
    for record in doc["images"]:
        ours = Path(record["path"])
        assert ours.parent == out / "ortho" and ours.is_file()
        theirs = post.mosaic.parent / "ortho" / ours.name
        with rasterio.open(ours) as a, rasterio.open(theirs) as b:
            assert a.transform == b.transform
            np.testing.assert_array_equal(a.read(), b.read())
