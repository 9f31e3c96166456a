"""``seqat bench dask``: the ortho and mosaic stages of a campaign on Dask (issue 18).

Several rendered flights (``configs/autzen_sample.yaml`` with other seeds, shifted by
:data:`OFFSETS_M` so neighbouring flights overlap and the campaign mosaic has seams between
flights) are simulated and run once (``seqat run``, as campaign tasks); then the ortho stage
(prepare, one ortho per image, flight tiles and mosaics, campaign tiles and mosaic) is timed on
a LocalCluster of 1 and of 2 single-threaded workers (``cv2.setNumThreads(1)`` in each),
interleaved, ``--repeats`` times each, with the 1-minute load average before each run. Every
run's rasters (orthos, flight mosaics, campaign tiles and mosaic) must be identical, pixel for
pixel, to the first run's and to the single-process path (``seqat ortho``'s
``orthorectify_run`` per flight; one :class:`MosaicBuilder` fed every flight in order for the
campaign mosaic). Last, a 2-worker run in which one worker is killed with SIGKILL half-way
must complete with the same outputs.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import shutil
import signal
import statistics
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import rasterio

from pipeline.bench.common import load_average, machine
from pipeline.campaign.flights import CampaignFlight
from pipeline.campaign.job import CAMPAIGN_DIR, CampaignOptions, campaign_client, process_campaign
from pipeline.common.atomic import atomic_write_text
from pipeline.run.store import to_jsonable

#: Shift of flight i's centre from the sample's, metres (east, north): overlapping flights.
OFFSETS_M = ((0.0, 0.0), (90.0, 0.0), (0.0, 60.0), (90.0, 60.0), (45.0, 30.0), (-45.0, 30.0),
             (45.0, -30.0), (-45.0, -30.0))
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "autzen_sample.yaml"


def render_flight(config_path: Path, index: int, out_dir: Path) -> Path:
    """Flight ``index``: the config's plan shifted by ``OFFSETS_M[index]``, seed ``index + 1``."""
    from pipeline.simulate.config import load_simulate_config
    from pipeline.simulate.rendered import render_to_folder

    if (out_dir / "flight.yaml").is_file():
        return out_dir
    config = load_simulate_config(config_path)
    plan = config.plan
    assert plan.center_m is not None
    dx, dy = OFFSETS_M[index % len(OFFSETS_M)]
    config = dataclasses.replace(config, plan=dataclasses.replace(
        plan, center_m=(plan.center_m[0] + dx, plan.center_m[1] + dy)))
    render_to_folder(config, config_path.parent, out_dir, index + 1)
    return out_dir


def _single_threaded() -> int:
    """In a worker: OpenCV on one thread (the worker is one core's worth of work); the pid."""
    import cv2

    import pipeline.campaign.tasks  # noqa: F401 - imported before the clock starts

    cv2.setNumThreads(1)
    return os.getpid()


def _cpu_s() -> float:
    """In a worker: the CPU seconds of its process so far (all threads)."""
    times = os.times()
    return times.user + times.system


def raster_digests(out: Path) -> dict[str, str]:
    """sha256 of the pixels and geotransform of every raster the ortho stage writes."""
    digests = {}
    files = sorted([*out.glob("*/ortho/*.tif"), *out.glob("*/mosaic.tif"),
                    *(out / CAMPAIGN_DIR).rglob("*.tif")])
    for path in files:
        with rasterio.open(path) as src:
            h = hashlib.sha256(src.read().tobytes())
            h.update(repr((tuple(src.transform)[:6], src.crs.to_wkt())).encode())
        digests[str(path.relative_to(out))] = h.hexdigest()
    return digests


def timed_ortho(flights: Sequence[CampaignFlight], out: Path, workers: int,
                kill_after_s: float | None = None) -> dict[str, object]:
    """One timed ortho stage on a fresh LocalCluster (start-up and imports not timed)."""
    from distributed import get_task_stream

    with campaign_client(None, workers) as client:
        pids = client.run(_single_threaded)
        killed: list[str] = []

        def kill() -> None:
            address, pid = sorted(pids.items())[-1]
            os.kill(pid, signal.SIGKILL)
            killed.append(address)

        timer = threading.Timer(kill_after_s, kill) if kill_after_s is not None else None
        load = load_average()
        t0 = time.perf_counter()
        if timer is not None:
            timer.start()
        cpu0 = sum(client.run(_cpu_s).values())
        with get_task_stream(client) as stream:
            summary = process_campaign(flights, out, client=client, progress=False,
                                       options=CampaignOptions(stages=("ortho",), ortho=True))
        wall = time.perf_counter() - t0
        cpu = sum(client.run(_cpu_s).values()) - cpu0  # a killed worker's CPU is lost
        if timer is not None:
            timer.cancel()
    computing = [ss["stop"] - ss["start"] for task in stream.data
                 for ss in task.get("startstops", ()) if ss.get("action") == "compute"]
    return {"workers": workers, "wall_s": wall, "load_1m_before": load,
            "load_1m_after": load_average(), "tasks": summary.tasks,
            "failed": [f.name for f in summary.failed], "killed": killed,
            "killed_at_s": kill_after_s if killed else None,
            # sum of the tasks' compute times / wall: how many workers were busy on average
            "task_s": sum(computing), "mean_busy_workers": sum(computing) / wall,
            "workers_cpu_s": cpu}


def single_process(flights: Sequence[CampaignFlight], out: Path, work: Path,
                   pixel_m: float) -> dict[str, object]:
    """The single-process path on copies of the run folders: ``orthorectify_run`` per flight,
    one MosaicBuilder over every flight's orthos in order; digests of the mosaics."""
    from pipeline.ortho.base import OrthoOptions
    from pipeline.ortho.mosaic import MosaicBuilder
    from pipeline.ortho.orthorectifier import Orthorectifier
    from pipeline.ortho.stage import choose_dsm, orthorectify_run, read_image
    from pipeline.run.store import read_run

    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    digests = {}
    for f in flights:
        copy = work / f.name
        shutil.copytree(out / f.name, copy, ignore=shutil.ignore_patterns(
            "ortho", "mosaic.tif", "ortho.json", "cameras.gpkg"))
        orthorectify_run(copy, options=OrthoOptions(pixel_m=pixel_m), progress=False)
        digests[f"{f.name}/mosaic.tif"] = raster_digests(work)[f"{f.name}/mosaic.tif"]
    flights_s = time.perf_counter() - t0
    builder = None
    for f in flights:
        run = read_run(work / f.name)
        dsm, _ = choose_dsm(work / f.name, run.crs, None, run.flight_dir, run.eop,
                            run.points.xyz_m[:, 2])
        builder = builder or MosaicBuilder(work / CAMPAIGN_DIR / "mosaic.tif", run.crs)
        with Orthorectifier(dsm, run.camera, run.crs, None,
                            OrthoOptions(pixel_m=pixel_m, write_images=False)) as ortho:
            for image_id, eop in zip(run.eop.image_ids, run.eop.eop, strict=True):
                path = run.images_dir / f"{image_id}.jpg" if run.images_dir else None
                builder.add(ortho.add_image(image_id, read_image(path), eop))
    assert builder is not None
    builder.finish()
    digests[f"{CAMPAIGN_DIR}/mosaic.tif"] = raster_digests(work)[f"{CAMPAIGN_DIR}/mosaic.tif"]
    return {"digests": digests, "flights_ortho_s": flights_s}


def run_campaign_bench(out: Path, n_flights: int, repeats: int, kill: bool) -> dict[str, object]:
    load_start = load_average()
    flights_dir, campaign_out = out / "flights", out / "campaign_out"
    with campaign_client(None, 2) as client:
        paths = client.gather([client.submit(render_flight, CONFIG, i, flights_dir / f"f{i}",
                                             pure=False) for i in range(n_flights)])
    flights = [CampaignFlight(name=p.name, folder=p) for p in paths]
    if not all((campaign_out / f.name / "run.json").is_file() for f in flights):
        with campaign_client(None, 2) as client:
            summary = process_campaign(flights, campaign_out, client=client, progress=False,
                                       options=CampaignOptions(stages=("run",)))
        assert not summary.failed, summary.failed
    images = sum(len(list((f.folder / "images").glob("*.jpg"))) for f in flights)
    if not all((campaign_out / f.name / "dsm.tif").is_file() for f in flights):
        warm_up = timed_ortho(flights, campaign_out, 2)  # grids each dsm.tif (not timed)
        assert not warm_up["failed"], warm_up
    runs: list[dict[str, object]] = []
    reference: dict[str, str] | None = None
    for r in range(repeats):
        for workers in ((1, 2) if r % 2 == 0 else (2, 1)):
            row = timed_ortho(flights, campaign_out, workers)
            digests = raster_digests(campaign_out)
            reference = reference or digests
            row["identical_to_first"] = digests == reference
            runs.append(row)
            print(json.dumps(row), flush=True)
    assert reference is not None
    campaign = json.loads((campaign_out / "campaign.json").read_text())
    single = single_process(flights, campaign_out, out / "single_process", campaign["pixel_m"])
    single_equal = {k: reference.get(k) == v for k, v in single["digests"].items()}  # type: ignore[union-attr]
    killed = None
    if kill:
        two = [float(x["wall_s"]) for x in runs if x["workers"] == 2]  # type: ignore[arg-type]
        killed = timed_ortho(flights, campaign_out, 2, kill_after_s=0.5 * statistics.median(two))
        killed["identical_to_first"] = raster_digests(campaign_out) == reference
        leftovers = [str(p) for p in campaign_out.rglob(".*") if p.name not in (
            ".seqat-run", ".seqat-campaign")]
        killed["leftover_files"] = leftovers
        print(json.dumps(killed), flush=True)
    t1 = [float(x["wall_s"]) for x in runs if x["workers"] == 1]  # type: ignore[arg-type]
    t2 = [float(x["wall_s"]) for x in runs if x["workers"] == 2]  # type: ignore[arg-type]
    result = {
        "machine": to_jsonable(machine(load_start)), "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "flights": n_flights, "images": images, "rasters_compared": len(reference),
        "pixel_m": campaign["pixel_m"], "campaign_tiles": campaign["tiles"], "runs": runs,
        "median_1_worker_s": statistics.median(t1), "median_2_workers_s": statistics.median(t2),
        "speedup_medians": statistics.median(t1) / statistics.median(t2),
        "speedup_pairs": [a / b for a, b in zip(t1, t2, strict=True)],
        "single_process_flights_ortho_s": single["flights_ortho_s"],
        "single_process_equal": single_equal, "killed_run": killed,
    }
    atomic_write_text(out / "bench_dask.json", json.dumps(result, indent=1) + "\n")
    return result


def main(argv: Sequence[str] | None = None) -> None:
    """``seqat bench dask --out DIR [--flights N] [--repeats R] [--no-kill]``."""
    parser = argparse.ArgumentParser(prog=None if argv is None else "seqat bench dask",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--flights", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-kill", action="store_true")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    result = run_campaign_bench(args.out, args.flights, args.repeats, not args.no_kill)
    print(json.dumps({k: v for k, v in result.items() if k not in ("runs", "machine")},
                     indent=1, default=str))


if __name__ == "__main__":
    main()
