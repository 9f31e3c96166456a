"""``seqat run``, ``seqat watch`` and ``seqat feed``."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from pipeline.cli.common import choice, console, guarded, run_rows, table

if TYPE_CHECKING:
    from pipeline.run.runner import Method, RunSummary


app = typer.Typer()

MethodOption = Annotated[str, typer.Option(
    "--method", help="seq-r, seq-f or sim (any case).")]
ThresholdOption = Annotated[float | None, typer.Option(
    "--threshold", help="seq-r: EOP correlation threshold in [0, 1].")]
InitialImagesOption = Annotated[int | None, typer.Option(
    "--initial-images", help="Images of the initial simultaneous stage.")]
EstimatorOptionsFile = Annotated[Path | None, typer.Option(
    "--options", help="Estimator options YAML (sections sequential:, sim:).")]
GcpOption = Annotated[Path | None, typer.Option(
    "--gcp", help="Ground control points: an ODM gcp_list.txt or a Metashape markers XML "
    "(default: flight.yaml gcp:, else gcp_list.txt in the flight folder).")]
GcpSigmaOption = Annotated[str | None, typer.Option(
    "--gcp-sigma-m", help="Default GCP sigma 'H,V' in metres, horizontal and vertical "
    "(default: flight.yaml gcp:, else 0.02,0.03).")]
BudgetOption = Annotated[float | None, typer.Option(
    "--budget-ms", help="seq-r: processing budget per image (tracking + update), ms; over it "
    "the window threshold tightens.")]


@app.command()
@guarded
def run(
    flight: Annotated[Path, typer.Argument(help="Flight folder.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    method: MethodOption = "seq-r",
    final_only: Annotated[bool, typer.Option(
        "--final-only", help="sim: adjust once after the last image.")] = False,
    threshold: ThresholdOption = None,
    initial_images: InitialImagesOption = None,
    options: EstimatorOptionsFile = None,
    progress: Annotated[bool, typer.Option(
        "--progress/--no-progress", help="Progress bar on a terminal.")] = True,
    observations: Annotated[Path | None, typer.Option(
        "--observations", help="Image points to use instead of the flight's own or of "
        "tracking (e.g. OUT/observations.csv of an earlier run).")] = None,
    ortho: Annotated[bool, typer.Option(
        "--ortho", help="Orthorectify each image as soon as it is georeferenced and build "
        "the mosaic live (ortho/, mosaic.tif, cameras.gpkg, ortho.json).")] = False,
    dsm: Annotated[Path | None, typer.Option(
        "--dsm", help="--ortho: DSM GeoTIFF (default: OUT/dsm.tif, the flight's lidar, else a "
        "flat plane).")] = None,
    ortho_options: Annotated[Path | None, typer.Option(
        "--ortho-options", help="--ortho: options YAML (sections ortho:, mosaic:, live:).")]
    = None,
    report: Annotated[bool, typer.Option(
        "--report", help="Then write OUT/report.html and report.json (as seqat report).")]
    = False,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue an interrupted run from OUT/journal/ (same results as an "
        "uninterrupted run).")] = False,
    budget_ms: BudgetOption = None,
    self_calibration: Annotated[bool | None, typer.Option(
        "--self-calibration/--fixed-camera", help="Estimate the camera's interior parameters "
        "with the EOPs, or keep the camera fixed (default: flight.yaml self_calibration:, on "
        "for a camera from EXIF).", show_default=False)] = None,
    gcp: GcpOption = None,
    gcp_sigma_m: GcpSigmaOption = None,
) -> None:
    """Adjust a flight folder and write eop.csv, points.csv, run.json, nav.csv and
    observations.csv."""
    summary = adjust_flight(flight, out, method=method, final_only=final_only,
                            threshold=threshold, initial_images=initial_images,
                            options=options, progress=progress, observations=observations,
                            ortho=ortho, dsm=dsm, ortho_options=ortho_options, resume=resume,
                            budget_ms=budget_ms, self_calibration=self_calibration,
                            gcp=gcp, gcp_sigma_m=gcp_sigma_m)
    if report:
        from pipeline.report.stage import make_report

        r = make_report(summary.out_dir)
        console().print("report: " + ", ".join(str(f) for f in r.files))


def adjust_flight(flight: Path, out: Path, *, method: str = "seq-r", final_only: bool = False,
                  threshold: float | None = None, initial_images: int | None = None,
                  options: Path | None = None, progress: bool = True,
                  observations: Path | None = None, ortho: bool = False,
                  dsm: Path | None = None, ortho_options: Path | None = None,
                  resume: bool = False, budget_ms: float | None = None,
                  self_calibration: bool | None = None, gcp: Path | None = None,
                  gcp_sigma_m: str | None = None) -> RunSummary:
    """What ``seqat run`` does and prints (``seqat process`` runs it as its first stage).

    With ``ortho``, OUT is claimed before the live ortho grids a DSM into it, and released
    again when the run fails before publishing anything.

    Returns
    -------
    RunSummary

    Raises
    ------
    ConfigError, InputDataError
        Bad options or input (nothing is written).
    """
    from pipeline.run.runner import run_flight
    from seqat.errors import ConfigError

    if not ortho and (dsm is not None or ortho_options is not None):
        raise ConfigError("--dsm and --ortho-options go with --ortho")
    sigma = parse_gcp_sigma(gcp_sigma_m)
    live = None
    created: list[Path] = []
    if ortho:
        from pipeline.common.outdir import claim_output_folder
        from pipeline.ortho.live import open_live_ortho

        # the live ortho writes into OUT (dsm.tif) before the run starts: claim it first
        created = claim_output_folder(out, [flight, dsm, ortho_options, options, observations,
                                            gcp])
    try:
        if ortho:
            live = open_live_ortho(flight, out, dsm_path=dsm, options_path=ortho_options)
        how = parse_method(method)
        with live if live is not None else contextlib.nullcontext():
            summary = run_flight(flight, out, method=how, final_only=final_only,
                                 options_path=options, threshold=threshold,
                                 initial_images=initial_images, progress=progress,
                                 observations=observations, resume=resume,
                                 budget_ms=budget_ms, self_calibration=self_calibration,
                                 gcp=gcp, gcp_sigma_m=sigma,
                                 listeners=(live,) if live is not None else ())
    except BaseException:
        from pipeline.common.outdir import release_output_folder

        release_output_folder(out, created)
        raise
    console().print(table(f"seqat run {summary.flight_dir}", run_rows(summary, final_only)))
    if live is not None:
        o = live.result()
        assert o.live is not None
        console().print(
            f"orthos and mosaic (live): {o.mosaic} ({len(o.images)} images, "
            f"{len(o.live.images_reorthorectified)} orthorectified again at the end; "
            f"surface: {o.dsm_source}); ortho ms median {o.compute_ms.median_ms:.0f}, "
            f"image to mosaic latency ms median / max {o.live.latency_ms.median_ms:.0f} / "
            f"{o.live.latency_ms.max_ms:.0f}")
    return summary


def parse_gcp_sigma(text: str | None) -> tuple[float, float] | None:
    """``--gcp-sigma-m H,V`` (metres, both in [1e-4, 1e5]; one value for both)."""
    from pipeline.flight.schema import MAX_SIGMA_POSITION_M, MIN_SIGMA_POSITION_M
    from seqat.errors import ConfigError

    if text is None:
        return None
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) == 1:
        values *= 2
    if len(values) != 2 or not all(MIN_SIGMA_POSITION_M <= v <= MAX_SIGMA_POSITION_M
                                   for v in values):
        raise ConfigError(f"--gcp-sigma-m: expected 'H,V' in metres within "
                          f"[{MIN_SIGMA_POSITION_M:g}, {MAX_SIGMA_POSITION_M:g}], got {text!r}")
    return values[0], values[1]


def parse_method(method: str) -> Method:
    """``--method`` in any case (``SEQ-R``, ``Sim``)."""
    from pipeline.run.runner import Method

    return Method(choice("--method", method, (m.value for m in Method)))


def parse_budget(value: str) -> float | str | None:
    """``seqat watch --budget-ms``: ``keep-up``, ``off`` (None) or a number of ms > 0."""
    from pipeline.run.runner import KEEP_UP
    from seqat.errors import ConfigError

    text = value.strip().lower()
    if text in (KEEP_UP, "off"):
        return None if text == "off" else KEEP_UP
    try:
        ms = float(text)
    except ValueError:
        ms = float("nan")
    if not (ms > 0 and ms < float("inf")):
        raise ConfigError(f"--budget-ms: expected keep-up, off or a number of ms > 0, "
                          f"got {value!r}")
    return ms


@app.command()
@guarded
def watch(
    flight: Annotated[Path, typer.Argument(help="Flight folder being written (flight.yaml "
                                           "present).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder.")],
    method: MethodOption = "seq-r",
    threshold: ThresholdOption = None,
    initial_images: InitialImagesOption = None,
    options: EstimatorOptionsFile = None,
    budget_ms: Annotated[str, typer.Option(
        "--budget-ms", help="seq-r: processing budget per image (reading and tracking + "
        "update): N ms; keep-up (default): the interval at which the images arrive, and no "
        "backlog; off. Over it the window threshold tightens and the tracker detects fewer "
        "features.")] = "keep-up",
    idle_timeout_s: Annotated[float | None, typer.Option(
        "--idle-timeout-s", "--idle-timeout", help="Stop after this many seconds without new "
        "input (default: until Ctrl-C).")] = None,
    wait_timeout_s: Annotated[float, typer.Option(
        "--wait-timeout-s", help="Seconds an image waits for its nav row (or a nav row for "
        "its image) before it is skipped.")] = 10.0,
    poll_s: Annotated[float, typer.Option("--poll-s", help="Seconds between polls.")] = 0.05,
    resume: Annotated[bool, typer.Option(
        "--resume", help="Continue from OUT/journal/ (after a crash or an earlier stop).")]
    = False,
    ortho: Annotated[bool, typer.Option(
        "--ortho", help="Orthorectify each image as soon as it is georeferenced; the growing "
        "mosaic is published in OUT/live/ during the flight, mosaic.tif at the end.")] = False,
    dsm: Annotated[Path | None, typer.Option(
        "--dsm", help="--ortho: DSM GeoTIFF (default: OUT/dsm.tif, the flight's lidar, else a "
        "flat plane).")] = None,
    ortho_options: Annotated[Path | None, typer.Option(
        "--ortho-options", help="--ortho: options YAML (sections ortho:, mosaic:, live:, "
        "dsm:).")] = None,
    serve: Annotated[int | None, typer.Option(
        "--serve", help="Also serve the run folder's web map (as seqat serve) on this TCP port "
        "while the watch goes on (0: any free port).", min=0, max=65535, show_default=False)]
    = None,
    host: Annotated[str, typer.Option(
        "--host", help="--serve: address to listen on (127.0.0.1 unless given).")]
    = "127.0.0.1",
    serve_in: Annotated[str, typer.Option(
        "--serve-in", help="--serve: run the server in a child process (default: the AT loop "
        "keeps its core and the GIL) or in a thread of the watch.")] = "process",
    stop_sigma_cm: Annotated[float | None, typer.Option(
        "--stop-sigma-cm", help="Stop criterion shown on the map: every ground point's σ "
        "(each axis) at most this many cm; coverage done / not yet done and a count in "
        "status.json.", show_default=False)] = None,
) -> None:
    """Georeference images as they appear in a growing flight folder; one line per image.
    Ctrl-C or --idle-timeout-s stops and publishes the results (as seqat run)."""
    import math

    from pipeline.run.watch import WatchOptions, watch_flight
    from seqat.errors import ConfigError

    if not ortho and (dsm is not None or ortho_options is not None):
        raise ConfigError("--dsm and --ortho-options go with --ortho")
    if serve is None and host != "127.0.0.1":
        raise ConfigError("--host goes with --serve")
    serve_in = choice("--serve-in", serve_in, ("process", "thread"))
    if stop_sigma_cm is not None and not (math.isfinite(stop_sigma_cm) and stop_sigma_cm > 0):
        raise ConfigError(f"--stop-sigma-cm: expected a number > 0, got {stop_sigma_cm!r}")
    how = parse_method(method)
    budget = parse_budget(budget_ms)
    make_listeners = None
    if ortho:
        from pipeline.ortho.live import watch_ortho_factory

        make_listeners = watch_ortho_factory(out, dsm_path=dsm, options_path=ortho_options)
    with watch_server(serve, host, serve_in) as on_claimed:
        summary = watch_flight(flight, out, method=how, options_path=options,
                               threshold=threshold, initial_images=initial_images,
                               budget_ms=budget, resume=resume,
                               watch=WatchOptions(idle_timeout_s=idle_timeout_s,
                                                  wait_timeout_s=wait_timeout_s, poll_s=poll_s),
                               make_listeners=make_listeners, on_claimed=on_claimed,
                               stop_sigma_m=None if stop_sigma_cm is None
                               else stop_sigma_cm / 100.0)
    rows = [("stopped", summary.stopped), *run_rows(summary)]
    console().print(table(f"seqat watch {summary.flight_dir}", rows))


@contextlib.contextmanager
def watch_server(port: int | None, host: str,
                  where: str = "process") -> Iterator[Callable[[Path], None] | None]:
    """``--serve PORT``: the socket is bound now (a busy port fails before the watch starts);
    the server starts on OUT once the watch has claimed it, niced below the live ortho's worker
    (the AT loop first), in a child process (``where``; or a thread of the watch), and stops
    when the watch has published its results."""
    if port is None:
        yield None
        return
    from pipeline.serve import app as serve_app

    nice = serve_app.WATCH_SERVE_NICE
    sock = serve_app.bind(host, port)
    stops: list[Callable[[], None]] = []

    def start(out: Path) -> None:
        if where == "thread":
            served = serve_app.server_on(out, sock, host, nice=nice)
            thread = serve_app.start_thread(served, nice=nice)
            stops.append(lambda: serve_app.stop_thread(served, thread))
        else:
            child = serve_app.start_process(out, sock, host, nice=nice)
            stops.append(lambda: serve_app.stop_process(child))
        shown = f"[{host}]" if ":" in host else host
        typer.echo(f"seqat watch: map at http://{shown}:{sock.getsockname()[1]}/", err=True)

    try:
        yield start
    finally:
        for stop in stops:
            stop()
        sock.close()


@app.command()
@guarded
def feed(
    src: Annotated[Path, typer.Argument(help="Flight folder to replay.")],
    old_dst: Annotated[Path | None, typer.Argument(
        metavar="DST", help="Deprecated: the folder to write as a second argument (seqat "
        "feed SRC DST); use --out.", show_default=False)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", help="Flight folder to write (absent or empty).", show_default=False)] = None,
    rate: Annotated[float, typer.Option("--rate", help="Images per second.")] = 2.0,
    limit: Annotated[int | None, typer.Option("--limit", help="Only the first N images.")]
    = None,
    delay_s: Annotated[float, typer.Option(
        "--delay-s", help="Seconds between writing flight.yaml and the first image.")] = 0.0,
) -> None:
    """Copy a flight into a folder image by image at the camera's rate (for seqat watch),
    with the partial-file convention (name.jpg.part, then renamed)."""
    from pipeline.run.feed import feed_flight

    dst = feed_destination(old_dst, out)
    s = feed_flight(src, dst, rate_hz=rate, limit=limit, delay_s=delay_s)
    console().print(f"fed {s.images} images in {s.duration_s:.1f} s (at most "
                     f"{s.late_s * 1e3:.0f} ms late)")


def feed_destination(old_dst: Path | None, out: Path | None) -> Path:
    """``seqat feed``'s folder to write: ``--out DST``, or the deprecated second argument (with
    a note on stderr).

    Raises
    ------
    ConfigError
        Neither or both.
    """
    from seqat.errors import ConfigError

    if old_dst is not None and out is not None:
        raise ConfigError(f"give the folder to write once: --out {out} (the second argument "
                          f"{old_dst} is the deprecated form)")
    if out is not None:
        return out
    if old_dst is None:
        raise ConfigError("--out: missing (the flight folder to write: seqat feed SRC --out DST)")
    typer.echo(f"seqat: note: `seqat feed SRC DST` is deprecated; use `seqat feed SRC --out "
               f"{old_dst}`", err=True)
    return old_dst
