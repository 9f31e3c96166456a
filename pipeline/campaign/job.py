"""A campaign on Dask: ``seqat process FLIGHT... --out OUT`` (issue 18).

The driver (this process) submits tasks to a ``dask.distributed`` cluster as their inputs
become known and reacts to each as it completes (``as_completed``)::

    per flight:  run ─┬─► prepare ─► ortho (per image) ─► flight tile (per tile) ─► finish ─┐
                      └─► reference ─────────────────────────────────────────────────────┴► report
    campaign:    every flight's orthos ─► campaign tile (one per tile, COG) ─► campaign mosaic

The run of a flight is one task (one sequential stream); orthos, tiles and flights spread over
the workers. Task bodies are :mod:`pipeline.campaign.tasks`. Every flight's orthos share one
global grid: the CRS and pixel size of the first flight (in the order given) that has orthos,
so the campaign mosaic needs no resampling; a flight in another working CRS keeps its own
products and stays out of the campaign mosaic (a warning). A task that fails marks its flight
failed (reported in ``OUT/campaign.json`` and on the console) and the other flights go on.

A worker that dies is Dask's to handle: the tasks it held run again elsewhere; each writes its
files atomically and the same way twice, so the outputs are the same as without the loss.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import re
import shutil
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from pipeline.campaign import tasks
from pipeline.campaign.flights import CampaignFlight
from pipeline.common.atomic import atomic_write_text
from pipeline.common.outdir import claim_output_folder
from pipeline.ortho.base import OrthoOptions
from pipeline.ortho.dsm import DsmOptions
from pipeline.ortho.mosaic import FEATHER_PX
from pipeline.ortho.raster import COG_THREADS_ENV
from pipeline.ortho.stage import MOSAIC_FILE
from seqat.errors import InputDataError, SeqatError

#: Marker of a campaign output folder (its flights' run folders carry the run marker).
CAMPAIGN_MARKER = ".seqat-campaign"
CAMPAIGN_DIR = "campaign"
CAMPAIGN_JSON = "campaign.json"
WORK_DIR = ".campaign-work"
#: Stages a campaign can run (the benchmark runs ``ortho`` alone on finished runs).
STAGES = ("run", "ortho", "reference", "report")
#: Temporary files of atomic writes (``.<name>.<mkstemp's 8 characters><suffix>``, and the
#: ``.ovr.tmp`` GDAL's COG driver writes beside one) a killed worker can leave behind; swept
#: when the job ends.
#: Environment of a LocalCluster's worker processes (single-threaded workers).
SINGLE_THREADED_ENV = {COG_THREADS_ENV: "1", "OPENCV_FOR_THREADS_NUM": "1"}
_TEMPORARY = re.compile(r"^\..+\.[A-Za-z0-9_]{8}(\.tif|\.tmp)(\.ovr\.tmp)?$")


@dataclass(frozen=True, kw_only=True)
class CampaignOptions:
    """What a campaign runs.

    ``ortho``: None = a flight with ``lidar:`` (as ``seqat process``), True = every flight with
    images (a flat plane without a surface), False = none. ``ortho_options.pixel_m`` fixes the
    campaign grid (default: the GSD of the first flight's first image).
    """

    method: str = "seq-r"
    stages: tuple[str, ...] = STAGES
    ortho: bool | None = None
    reference: bool = True
    report: bool = True
    ortho_options: OrthoOptions = field(default_factory=OrthoOptions)
    feather_px: int = FEATHER_PX
    dsm_options: DsmOptions | None = None


@dataclass(frozen=True, kw_only=True)
class FlightOutcome:
    name: str
    folder: str
    run_dir: str
    stages: tuple[str, ...]
    error: str | None
    images: int | None = None
    orthos: int | None = None
    skipped: tuple[str, ...] = ()
    in_campaign_mosaic: bool = False


@dataclass(frozen=True, kw_only=True)
class CampaignSummary:
    """What :func:`process_campaign` did (also ``OUT/campaign.json``)."""

    out_dir: str
    scheduler: str
    workers: int
    flights: tuple[FlightOutcome, ...]
    mosaic: str | None
    tiles: int
    pixel_m: float
    crs: str | None
    tasks: int
    wall_s: float
    warnings: tuple[str, ...]

    @property
    def failed(self) -> tuple[FlightOutcome, ...]:
        return tuple(f for f in self.flights if f.error is not None)


@dataclass(eq=False)
class _Flight:
    flight: CampaignFlight
    run_dir: Path
    ortho: bool
    error: str | None = None
    stages_done: list[str] = field(default_factory=list)
    images: int | None = None
    prepared: Any = None  # the prepare task's future (its result ships to the ortho tasks)
    plan: tasks.FlightOrtho | None = None
    orthos_submitted: bool = False
    orthos: dict[str, tasks.OrthoDone] = field(default_factory=dict)
    pending: int = 0
    tiles: list[tasks.TileDone] = field(default_factory=list)
    ortho_done: bool = False
    reference_done: bool = False
    report_submitted: bool = False
    in_campaign: bool = False
    t_ortho: float = math.nan

    @property
    def settled(self) -> bool:
        """Its orthos are final (done, failed, or none to make)."""
        return self.error is not None or not self.ortho or self.ortho_done


def open_client(scheduler: str | None, workers: int | None, *, processes: bool = True) -> (
        tuple[Any, Any]):
    """A ``distributed.Client`` on ``scheduler``, or on a new LocalCluster of ``workers``
    single-threaded workers (default: one per CPU); also the cluster to close (or None)."""
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            return Client(scheduler, timeout="20s"), None
        except (OSError, TimeoutError) as err:
            raise InputDataError(f"--scheduler {scheduler}: cannot connect: {err}") from err
    n = workers or os.cpu_count() or 1
    # One core per worker: OpenCV and GDAL's COG compression on one thread too (Dask already
    # sets OMP/MKL/OpenBLAS to 1), so n workers do not fight over n cores.
    kwargs = {"env": SINGLE_THREADED_ENV} if processes else {}
    # ":0": any free port (the scheduler serves HTTP anyway; 8787 may be another cluster's)
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=processes,
                           dashboard_address=":0", silence_logs=40, **kwargs)
    return Client(cluster), cluster


@contextlib.contextmanager
def campaign_client(scheduler: str | None, workers: int | None,
                    processes: bool = True) -> Iterator[Any]:
    client, cluster = open_client(scheduler, workers, processes=processes)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def process_campaign(flights: Sequence[CampaignFlight], out: Path, *, client: Any,
                     options: CampaignOptions | None = None, progress: bool = True,
                     console: Console | None = None) -> CampaignSummary:
    """Run the campaign's tasks on ``client`` and write ``OUT/campaign.json``.

    Raises
    ------
    InputDataError
        OUT is not a campaign folder seqat may write (nothing is written then).
    """
    options = options or CampaignOptions()
    console = console or Console(stderr=True, soft_wrap=True)
    t0 = time.perf_counter()
    claim_output_folder(out, [f.folder for f in flights], marker=CAMPAIGN_MARKER,
                        what="campaign folder")
    # Absolute paths: a worker of a cluster runs in another working directory (same mounts).
    out = Path(os.path.abspath(out))
    flights = [replace(f, folder=Path(os.path.abspath(f.folder))) for f in flights]
    work = out / WORK_DIR
    job = _Job(client, flights, out, options, console)
    if "dashboard" in client.scheduler_info().get("services", {}):
        import importlib.util

        note = ("" if importlib.util.find_spec("bokeh") is not None
                else " (its pages need bokeh on the scheduler: pip install '.[dashboard]')")
        console.print(f"Dask dashboard: {client.dashboard_link}{note}", highlight=False,
                      markup=False)
    with Progress(TextColumn("[bold]campaign"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console,
                  transient=True, disable=not (progress and console.is_terminal)) as bar:
        job.bar, job.bar_task = bar, bar.add_task("tasks", total=0, info="")
        job.run()
    shutil.rmtree(work, ignore_errors=True)
    _sweep_temporaries(out)
    summary = job.summary(time.perf_counter() - t0)
    atomic_write_text(out / CAMPAIGN_JSON, json.dumps(_jsonable(summary), indent=1,
                                                      allow_nan=False) + "\n")
    return summary


class _Job:
    """The driver's state: which task belongs to which flight, what to submit next."""

    def __init__(self, client: Any, flights: Sequence[CampaignFlight], out: Path,
                 options: CampaignOptions, console: Console) -> None:
        from distributed import as_completed

        self.client, self.out, self.options, self.console = client, out, options, console
        self.work = out / WORK_DIR
        self.flights = [_Flight(flight=f, run_dir=out / f.name,
                                ortho="ortho" in options.stages and options.ortho is not False)
                        for f in flights]
        self.token = uuid.uuid4().hex[:8]
        self.pending: dict[str, tuple[str, _Flight | None, Any]] = {}
        self.queue = as_completed()
        self.count = 0
        self.bar: Progress | None = None
        self.bar_task: Any = None
        self.pixel_m = options.ortho_options.pixel_m
        self.grid_crs: Any = None
        self.campaign_tiles: list[tasks.TileDone] = []
        self.campaign_stage = "waiting"
        self.campaign_pending = 0
        self.campaign_images = 0
        self.mosaic: str | None = None
        self.warnings: list[str] = []

    # --- submission ---------------------------------------------------------------------------

    def submit(self, kind: str, flight: _Flight | None, extra: Any, fn: Any, *args: Any,
               priority: int = 0) -> Any:
        name = flight.flight.name if flight else CAMPAIGN_DIR
        key = f"{kind}-{name}-{self.count}-{self.token}"
        self.count += 1
        future = self.client.submit(fn, *args, key=key, pure=False, priority=priority)
        self.pending[future.key] = (kind, flight, extra)
        self.queue.add(future)
        if self.bar is not None:
            self.bar.update(self.bar_task, total=self.count)
        return future

    def run(self) -> None:
        for fl in self.flights:
            self._start(fl)
        self._campaign_if_settled()
        for future in self.queue:
            kind, fl, extra = self.pending.pop(future.key)
            if self.bar is not None:
                self.bar.update(self.bar_task, advance=1,
                                info=f"{kind} {fl.flight.name if fl else ''}")
            if future.status == "error":
                self._failed(kind, fl, future.exception())
            elif future.status != "finished":  # cancelled: the scheduler gave the task up
                self._failed(kind, fl, RuntimeError(f"task {future.key} {future.status}"))
            elif isinstance(refused := future.result(), tasks.Refused):
                self._failed(kind, fl, InputDataError(refused.message))
            else:
                getattr(self, f"_on_{kind}")(fl, extra, future)
            self._campaign_if_settled()

    def _start(self, fl: _Flight) -> None:
        stages = self.options.stages
        if "run" in stages:
            self.submit("run", fl, None, tasks.run_task, fl.flight.folder, fl.run_dir,
                        self.options.method, priority=10)
        else:
            self._after_run(fl)

    def _after_run(self, fl: _Flight) -> None:
        stages = self.options.stages
        if fl.ortho and self.options.ortho is None:
            from pipeline.ortho.stage import flight_lidar

            try:
                fl.ortho = bool(flight_lidar(fl.flight.folder))
            except SeqatError as err:
                self._failed("ortho", fl, err)
                return
        if fl.ortho:
            fl.prepared = self.submit("prepare", fl, None, tasks.prepare_task, fl.flight.name,
                                      fl.run_dir, self.options.dsm_options, priority=5)
            fl.t_ortho = time.perf_counter()
        if "reference" in stages and self.options.reference:
            self.submit("reference", fl, None, tasks.reference_task, fl.run_dir)
        else:
            fl.reference_done = True
        self._report_if_ready(fl)

    # --- completions ----------------------------------------------------------------------------

    def _on_run(self, fl: _Flight, _: Any, future: Any) -> None:
        fl.images = future.result()
        fl.stages_done.append("run")
        self._after_run(fl)

    def _on_prepare(self, fl: _Flight, _: Any, future: Any) -> None:
        fl.plan = future.result()
        self.warnings.extend(f"{fl.flight.name}: {w}" for w in fl.plan.warnings)
        self._submit_orthos()

    def _submit_orthos(self) -> None:
        """Orthos of every prepared flight, once the campaign's pixel size is known."""
        if self.pixel_m is None:
            for fl in self.flights:
                if fl.error is not None or not fl.ortho:
                    continue
                if fl.plan is None:
                    return  # an earlier flight decides
                if math.isfinite(fl.plan.pixel_m):
                    self.pixel_m = fl.plan.pixel_m
                    break
            else:
                return
        for fl in self.flights:
            if fl.plan is None or fl.orthos_submitted or fl.error is not None:
                continue
            fl.orthos_submitted = True
            opts = replace(self.options.ortho_options, pixel_m=self.pixel_m, threads=1,
                           background_writes=False)
            work = self.work / fl.flight.name / "orthos"
            fl.pending = len(fl.plan.eops.image_ids)
            for image_id in fl.plan.eops.image_ids:
                self.submit("ortho", fl, image_id, tasks.ortho_task, fl.prepared, image_id,
                            opts, work, priority=1)

    def _on_ortho(self, fl: _Flight, image_id: str, future: Any) -> None:
        done: tasks.OrthoDone = future.result()
        fl.orthos[image_id] = done
        fl.pending -= 1
        if fl.pending or fl.error is not None:
            return
        assert fl.plan is not None
        fl.prepared = None  # every ortho has its plan: the workers may drop it
        ok = [fl.orthos[i] for i in fl.plan.eops.image_ids if fl.orthos[i].record is not None]
        if not ok:
            errors = [d.error for d in fl.orthos.values() if d.error]
            self._failed("ortho", fl, InputDataError(
                f"{fl.run_dir}: no image could be orthorectified"
                + (f" ({errors[-1]})" if errors else "")))
            return
        by_tile = rasters_by_tile(ok)
        fl.pending = len(by_tile)
        work = self.work / fl.flight.name / "tiles"
        for key, files in by_tile.items():
            self.submit("flight_tile", fl, key, tasks.flight_tile_task, key, files,
                        self.options.feather_px, work, priority=2)

    def _on_flight_tile(self, fl: _Flight, _: Any, future: Any) -> None:
        fl.tiles.append(future.result())
        fl.pending -= 1
        if fl.pending or fl.error is not None:
            return
        assert fl.plan is not None and self.pixel_m is not None
        job = tasks.FlightMosaic(flight=fl.plan, done=tuple(fl.orthos[i] for i in
                                                            fl.plan.eops.image_ids),
                                 pixel_m=self.pixel_m,
                                 elapsed_s=time.perf_counter() - fl.t_ortho)
        self.submit("finish", fl, None, tasks.finish_flight_task, job, fl.tiles,
                    self.work / fl.flight.name, priority=3)

    def _on_finish(self, fl: _Flight, _: Any, future: Any) -> None:
        future.result()
        fl.ortho_done = True
        fl.stages_done.append("ortho")
        self._report_if_ready(fl)

    def _on_reference(self, fl: _Flight, _: Any, future: Any) -> None:
        future.result()
        fl.reference_done = True
        fl.stages_done.append("reference")
        self._report_if_ready(fl)

    def _report_if_ready(self, fl: _Flight) -> None:
        if (fl.error is None and fl.reference_done and (fl.ortho_done or not fl.ortho)
                and "report" in self.options.stages and self.options.report
                and not fl.report_submitted):
            fl.report_submitted = True
            self.submit("report", fl, None, tasks.report_task, fl.run_dir)

    def _on_report(self, fl: _Flight, _: Any, future: Any) -> None:
        future.result()
        fl.stages_done.append("report")

    # --- the campaign mosaic --------------------------------------------------------------------

    def _campaign_if_settled(self) -> None:
        if self.campaign_stage != "waiting" or not all(fl.settled for fl in self.flights):
            return
        self.campaign_stage = "tiles"
        members: list[tasks.OrthoDone] = []
        for fl in self.flights:
            if fl.error is not None or not fl.ortho or fl.plan is None:
                continue
            if self.grid_crs is None:
                self.grid_crs = fl.plan.crs
            elif not fl.plan.crs.equals(self.grid_crs, ignore_axis_order=True):
                self.warnings.append(f"{fl.flight.name}: working CRS {fl.plan.crs.name} differs "
                                     f"from the campaign's ({self.grid_crs.name}): left out of "
                                     "the campaign mosaic (its own mosaic.tif is complete)")
                continue
            members += [fl.orthos[i] for i in fl.plan.eops.image_ids
                        if fl.orthos[i].record is not None]
            fl.in_campaign = True
        if not members:
            self.campaign_stage = "done"
            return
        by_tile = rasters_by_tile(members)
        self.campaign_pending = len(by_tile)
        tiles_dir = self.out / CAMPAIGN_DIR / "tiles"
        for key, files in by_tile.items():
            self.submit("campaign_tile", None, key, tasks.campaign_tile_task, key, files,
                        self.options.feather_px, tiles_dir, self.pixel_m, self.grid_crs)
        self.campaign_images = len(members)

    def _on_campaign_tile(self, _: None, __: Any, future: Any) -> None:
        self.campaign_tiles.append(future.result())
        self.campaign_pending -= 1
        if self.campaign_pending:
            return
        self.campaign_stage = "mosaic"
        self.submit("campaign_mosaic", None, None, tasks.mosaic_task,
                    self.out / CAMPAIGN_DIR / MOSAIC_FILE, self.campaign_tiles,
                    self.grid_crs, self.pixel_m, self.campaign_images, self.work / CAMPAIGN_DIR)

    def _on_campaign_mosaic(self, _: None, __: Any, future: Any) -> None:
        self.mosaic = str(future.result().path)
        self.campaign_stage = "done"

    # --- failures and the summary -----------------------------------------------------------------

    def _failed(self, kind: str, fl: _Flight | None, err: BaseException | None) -> None:
        what = (str(err) if isinstance(err, SeqatError)
                else f"{type(err).__name__}: {err}")
        if fl is None:
            self.campaign_stage = "done"
            self.warnings.append(f"campaign mosaic: {kind}: {what}")
            self.console.print(f"[red]campaign mosaic failed[/red] ({kind}): {what}",
                               highlight=False)
            return
        if fl.error is None:
            fl.error = f"{kind}: {what}"
            self.console.print(f"[red]flight {fl.flight.name} failed[/red] ({kind}): {what}; "
                               "the other flights go on", highlight=False)
        self._submit_orthos()  # a failed first flight no longer decides the pixel size

    def summary(self, wall_s: float) -> CampaignSummary:
        info = self.client.scheduler_info()
        flights = tuple(FlightOutcome(
            name=fl.flight.name, folder=str(fl.flight.folder), run_dir=str(fl.run_dir),
            stages=tuple(fl.stages_done), error=fl.error, images=fl.images,
            orthos=sum(d.record is not None for d in fl.orthos.values()) if fl.orthos else None,
            skipped=tuple(i for i, d in fl.orthos.items() if d.record is None),
            in_campaign_mosaic=fl.in_campaign and self.mosaic is not None)
            for fl in self.flights)
        return CampaignSummary(
            out_dir=str(self.out), scheduler=str(info.get("address", "")),
            workers=len(info.get("workers", {})), flights=flights, mosaic=self.mosaic,
            tiles=sum(t.extent is not None for t in self.campaign_tiles),
            pixel_m=float(self.pixel_m) if self.pixel_m is not None else math.nan,
            crs=self.grid_crs.name if self.grid_crs is not None else None, tasks=self.count,
            wall_s=wall_s, warnings=tuple(self.warnings))


def rasters_by_tile(orthos: Sequence[tasks.OrthoDone]) -> dict[tuple[int, int], list[Path]]:
    """The raster files touching each tile, in the given order (acquisition, flights in
    campaign order): the order the blend depends on."""
    by_tile: dict[tuple[int, int], list[Path]] = {}
    for done in orthos:
        assert done.raster_file is not None
        for key in done.tiles:
            by_tile.setdefault(key, []).append(done.raster_file)
    return dict(sorted(by_tile.items(), key=lambda kv: (kv[0][1], kv[0][0])))


def _sweep_temporaries(out: Path) -> None:
    """Remove what atomic writes of killed workers left (never a published file)."""
    for folder in itertools.chain([out, out / CAMPAIGN_DIR, out / CAMPAIGN_DIR / "tiles"],
                                  *((p, p / "ortho") for p in out.iterdir() if p.is_dir())):
        if folder.is_dir():
            for path in folder.iterdir():
                if path.is_file() and _TEMPORARY.match(path.name):
                    path.unlink(missing_ok=True)


def _jsonable(value: Any) -> Any:
    if hasattr(value, "__dataclass_fields__"):
        return {k: _jsonable(getattr(value, k)) for k in value.__dataclass_fields__}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
