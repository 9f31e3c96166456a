"""Campaigns on Dask (issue 18): the distributed mosaic equals MosaicBuilder's pixel for
pixel, tasks run twice write the same files, a failing flight is reported while the others
finish. An in-process LocalCluster (threads, ``processes=False``): no worker start-up cost."""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio

from pipeline.campaign import tasks
from pipeline.campaign.flights import find_flights
from pipeline.campaign.job import (
    CampaignOptions,
    campaign_client,
    process_campaign,
    rasters_by_tile,
)
from pipeline.common.tables import EopTable
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.mosaic import MosaicBuilder
from pipeline.ortho.orthorectifier import Orthorectifier
from pipeline.ortho.stage import read_image
from seqat.errors import InputDataError

from ..synthetic_ortho import CRS, E0_M, N0_M, Scene, render, small_camera

PIXEL_M = 0.1
FEATHER_PX = 6
#: Two strips of four images, 15 m apart along and 20 m across (overlapping 40 m footprints).
NADIR_M = [(-22.5 + 15.0 * i, 10.0 * s) for s in (-1, 1) for i in range(4)]


@pytest.fixture(scope="module")
def client() -> Iterator[object]:
    with campaign_client(None, 2, processes=False) as c:
        yield c


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tasks.FlightOrtho:
    """Eight rendered images of a sloped plane and their plan, as a prepare task returns it."""
    folder = tmp_path_factory.mktemp("campaign")
    cam, scene = small_camera(), Scene(a=12.0, b=0.05, c=-0.03)
    ids, eops, files = [], [], {}
    for i, (de, dn) in enumerate(NADIR_M):
        eop = np.array([E0_M + de, N0_M + dn, 52.0, 0.01 * i, -0.01, np.radians(90.0)])
        image = (render(scene, cam, eop) // 256).astype(np.uint8)
        files[f"img_{i}"] = folder / f"img_{i}.png"
        cv2.imwrite(str(files[f"img_{i}"]), image)
        ids.append(f"img_{i}")
        eops.append(eop)
    return tasks.FlightOrtho(
        name="f", run_dir=folder / "run", crs=CRS, camera=cam,
        eops=EopTable(image_ids=tuple(ids), eop=np.array(eops), sigma=np.full((8, 6), np.nan)),
        files=files, surface=scene.dsm(), dsm_source="scene", eop_source="seq-r",
        pixel_m=PIXEL_M, warnings=())


def _read(path: Path) -> tuple[np.ndarray, tuple[float, ...]]:
    with rasterio.open(path) as src:
        return src.read(), tuple(src.transform)[:6]


def test_distributed_mosaic_equals_the_single_process_one_and_tasks_are_idempotent(
        client: object, flight: tasks.FlightOrtho, tmp_path: Path) -> None:
    options = OrthoOptions(pixel_m=PIXEL_M, threads=1, background_writes=False)
    work = tmp_path / "work"
    done = client.gather([client.submit(tasks.ortho_task, flight, i, options, work / "orthos",
                                        pure=False) for i in flight.eops.image_ids])
    assert all(d.record is not None for d in done)
    by_tile = rasters_by_tile(done)
    assert len(by_tile) > 1
    flight_tiles = client.gather([client.submit(tasks.flight_tile_task, key, files, FEATHER_PX,
                                                work / "tiles", pure=False)
                                  for key, files in by_tile.items()])
    camp_tiles = client.gather([client.submit(tasks.campaign_tile_task, key, files, FEATHER_PX,
                                              tmp_path / "tiles", PIXEL_M, CRS, pure=False)
                                for key, files in by_tile.items()])
    distributed = tasks.write_mosaic(tmp_path / "flight.tif", flight_tiles, CRS, PIXEL_M, 8,
                                     work)
    campaign = client.submit(tasks.mosaic_task, tmp_path / "campaign.tif", camp_tiles, CRS,
                             PIXEL_M, 8, work, pure=False).result()

    # The single-process path: Orthorectifier + MosaicBuilder, as seqat ortho streams them.
    builder = MosaicBuilder(tmp_path / "single.tif", CRS, feather_px=FEATHER_PX)
    with Orthorectifier(flight.surface, flight.camera, CRS, tmp_path / "single_orthos",
                        OrthoOptions(pixel_m=PIXEL_M)) as ortho:
        for image_id, eop in zip(flight.eops.image_ids, flight.eops.eop, strict=True):
            builder.add(ortho.add_image(image_id, read_image(flight.files[image_id]), eop))
    single = builder.finish()
    reference = _read(single.path)
    assert _read(distributed.path)[1] == reference[1] == _read(campaign.path)[1]
    assert np.array_equal(_read(distributed.path)[0], reference[0])
    assert np.array_equal(_read(campaign.path)[0], reference[0])
    for image_id in flight.eops.image_ids:  # the per-image orthos too
        a = _read(flight.run_dir / "ortho" / f"{image_id}.tif")
        b = _read(tmp_path / "single_orthos" / f"{image_id}.tif")
        assert a[1] == b[1] and np.array_equal(a[0], b[0])

    # Idempotent: a task run again (a worker lost after writing) writes the same bytes.
    first = {p: p.read_bytes() for p in [flight.run_dir / "ortho" / "img_0.tif",
                                         work / "orthos" / "img_0.npz", camp_tiles[0].path,
                                         campaign.path]}
    again = client.submit(tasks.ortho_task, flight, "img_0", options, work / "orthos",
                          pure=False).result()
    assert again.tiles == done[0].tiles and again.raster_file == done[0].raster_file
    key, files = next(iter(by_tile.items()))
    assert client.submit(tasks.campaign_tile_task, key, files, FEATHER_PX, tmp_path / "tiles",
                         PIXEL_M, CRS, pure=False).result() == camp_tiles[0]
    tasks.write_mosaic(tmp_path / "campaign.tif", camp_tiles, CRS, PIXEL_M, 8, work)
    assert {p: p.read_bytes() for p in first} == first
    assert not [p for p in (tmp_path / "tiles").iterdir() if p.name.startswith(".")]


def test_bad_input_in_a_task_is_refused_not_raised(flight: tasks.FlightOrtho,
                                                   tmp_path: Path) -> None:
    refused = tasks.mosaic_task(tmp_path / "m.tif", [], CRS, PIXEL_M, 0, tmp_path)
    assert isinstance(refused, tasks.Refused) and "no ortho" in refused.message
    no_file = replace(flight, files={})  # an image without its file is skipped, not fatal
    skipped = tasks.ortho_task(no_file, "img_0", OrthoOptions(pixel_m=PIXEL_M, threads=1),
                               tmp_path)
    assert skipped.record is None and "no image img_0.jpg" in str(skipped.error)


def test_a_failing_flight_is_reported_and_the_others_finish(
        client: object, small_sim_dir: Path, tmp_path: Path) -> None:
    campaign = tmp_path / "flights"
    shutil.copytree(small_sim_dir, campaign / "a_good")
    shutil.copytree(small_sim_dir, campaign / "b_bad")
    with (campaign / "b_bad" / "flight.yaml").open("a", encoding="utf-8") as handle:
        handle.write("bogus: 1\n")
    flights = find_flights([campaign])
    assert [f.name for f in flights] == ["a_good", "b_bad"]
    out = tmp_path / "out"
    summary = process_campaign(flights, out, client=client, progress=False,
                               options=CampaignOptions(reference=False, report=False))
    good, bad = summary.flights
    assert good.error is None and good.stages == ("run",)
    assert (out / "a_good" / "eop.csv").is_file()
    assert bad.error is not None and "bogus: unknown key" in bad.error
    assert summary.mosaic is None  # observations only: nothing to orthorectify
    written = json.loads((out / "campaign.json").read_text())
    assert [f["error"] is None for f in written["flights"]] == [True, False]
    assert not (out / ".campaign-work").exists()


def test_flights_and_campaign_folders_are_found_and_names_must_differ(
        small_sim_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(InputDataError, match="no such flight folder"):
        find_flights([tmp_path / "missing"])
    with pytest.raises(InputDataError, match="nor a campaign folder"):
        find_flights([tmp_path])
    shutil.copytree(small_sim_dir, tmp_path / "x" / "f")
    shutil.copytree(small_sim_dir, tmp_path / "y" / "f")
    with pytest.raises(InputDataError, match="a second flight named 'f'"):
        find_flights([tmp_path / "x", tmp_path / "y" / "f"])


def test_single_flight_options_are_refused_with_several_flights(small_sim_dir: Path,
                                                                tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pipeline.cli import app

    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["process", str(small_sim_dir), str(small_sim_dir),
                                      "--out", str(out), "--observations", "x.csv"])
    assert result.exit_code == 2
    assert result.stderr == ("seqat: error: --observations: only with one flight (not with "
                             "several flights, a campaign folder, --scheduler or --workers)\n")
    result = CliRunner().invoke(app, ["process", str(small_sim_dir), "--out", str(out),
                                      "--workers", "0"])
    assert result.exit_code == 2 and "--workers: expected >= 1" in result.stderr
    assert not out.exists()
